"""The parts of FORM (jaxdem.reliability) that need no solve: the map to standard normal
space, the improved HL-RF iteration on limit states with known design points, the
correlation, the limits' syntax and signs. The model's own limit states are checked
against closed forms in tests/verification/test_reliability.py."""

import importlib
import math

import numpy as np
import pytest
from scenes import jointed_tunnel
from scipy.optimize import minimize
from scipy.special import ndtr

import jaxdem
from jaxdem.reliability import (
    CONVERGED,
    LIMIT_NOT_REACHED,
    NO_ANSWER_AT_START,
    NO_GRADIENT,
    Limit,
    correlation_matrix,
    hlrf,
    parse_check,
    samples_for_cov,
    transform,
)
from jaxdem.scene import SceneError, parse_scene
from jaxdem.sweep import Variable

VARIABLES = [Variable.parse(t) for t in ("a=normal:30:3", "b=lognormal:2e6:6e5",
                                         "c=uniform:10:20", "d=truncnormal:5:2:4:9")]


def test_transform_is_each_marginals_quantile_of_phi_y():
    y = np.array([[-2.5, -1.0, 0.0, 0.7, 2.2]]).T @ np.ones((1, 4))
    x, _ = transform(VARIABLES, y)
    for j, v in enumerate(VARIABLES):
        np.testing.assert_allclose(x[:, j], v.quantile(ndtr(y[:, j])), rtol=1e-12)
    # Normal and lognormal in closed form: mean m + s y; median exp(lambda) = m / sqrt(1 + V^2).
    assert x[2, 0] == 30.0 and x[0, 0] == pytest.approx(30.0 - 7.5)
    assert x[2, 1] == pytest.approx(2e6 / math.sqrt(1 + 0.3 ** 2))


def test_transform_derivative_matches_central_differences():
    rng = np.random.default_rng(1)
    y = rng.normal(size=(20, 4)) * 1.5
    _, dx = transform(VARIABLES, y)
    h = 1e-6
    fd = (transform(VARIABLES, y + h)[0] - transform(VARIABLES, y - h)[0]) / (2 * h)
    np.testing.assert_allclose(dx, fd, rtol=1e-6)


def _linear(a0, a):
    a = np.asarray(a, float)
    return lambda z: (a0 + a @ z, a.copy())


def test_hlrf_linear_limit_state_is_exact_in_one_step():
    out = hlrf(_linear(3.0, [-1.0, -2.0]), 2)
    assert out["status"] == CONVERGED
    assert out["beta"] == pytest.approx(3.0 / math.sqrt(5.0), rel=1e-12)
    assert len(out["history"]) == 2        # the start and one step
    np.testing.assert_allclose(out["z"], 3.0 / 5.0 * np.array([1.0, 2.0]), rtol=1e-12)


def test_hlrf_negative_beta_where_the_median_fails():
    out = hlrf(_linear(-1.0, [0.0, -2.0]), 2)
    assert out["status"] == CONVERGED and out["beta"] == pytest.approx(-0.5)


@pytest.mark.parametrize("g, grad", [
    # A parabola touching the circle of radius 2.5 on the diagonal: beta = 2.5
    # (Der Kiureghian's textbook example; the curvature term vanishes there).
    (lambda z: 2.5 - (z[0] + z[1]) / math.sqrt(2) + 0.1 * (z[0] - z[1]) ** 2,
     lambda z: np.array([-1 / math.sqrt(2) + 0.2 * (z[0] - z[1]),
                         -1 / math.sqrt(2) - 0.2 * (z[0] - z[1])])),
    # Strongly curved: the plain HL-RF step overshoots and the line search halves it.
    (lambda z: 3.0 - z[0] - 0.4 * z[1] ** 2 + 0.2 * z[1],
     lambda z: np.array([-1.0, -0.8 * z[1] + 0.2])),
    # Curved the other way, two local minima of |z| (FORM finds the nearer from z = 0).
    (lambda z: np.exp(1.0 - 0.6 * z[0]) - 0.4 - 0.3 * (z[1] - 0.5) ** 2,
     lambda z: np.array([-0.6 * np.exp(1.0 - 0.6 * z[0]), -0.6 * (z[1] - 0.5)])),
])
def test_hlrf_nonlinear_matches_a_direct_minimisation(g, grad):
    out = hlrf(lambda z: (g(z), grad(z)), 2, tolerance=1e-6, max_iterations=100)
    assert out["status"] == CONVERGED
    found = min((minimize(lambda u: u @ u, start, method="SLSQP", options=dict(ftol=1e-14),
                          constraints=[dict(type="eq", fun=g)])
                 for start in ([1.0, 1.0], [1.0, -1.0], [2.0, 2.0], [2.0, -2.0])),
                key=lambda r: r.fun if r.success else np.inf)
    assert out["beta"] == pytest.approx(math.sqrt(found.fun), rel=1e-5)


def test_hlrf_line_search_halves_a_step_that_would_overshoot():
    g = lambda z: 3.0 - z[0] - 0.4 * z[1] ** 2 + 0.2 * z[1]  # noqa: E731
    out = hlrf(lambda z: (g(z), np.array([-1.0, -0.8 * z[1] + 0.2])), 2, tolerance=1e-6)
    assert any(h["step"] is not None and h["step"] < 1 for h in out["history"])


def test_hlrf_stops_and_says_why():
    assert hlrf(_linear(20.0, [-1.0]), 1)["status"] == LIMIT_NOT_REACHED
    assert hlrf(_linear(1.0, [0.0, 0.0]), 2)["status"] == NO_GRADIENT
    assert hlrf(lambda z: (np.nan, np.full(1, np.nan)), 1)["status"] == NO_ANSWER_AT_START
    # g undefined beyond z = -1 (a mechanism): the step is halved until it has a value.
    out = hlrf(lambda z: (3.0 + z[0], np.ones(1)) if z[0] > -1 else
               (np.nan, np.full(1, np.nan)), 1, max_iterations=3)
    assert out["status"] != CONVERGED and out["z"][0] > -1


@pytest.fixture
def linear_state(monkeypatch):
    """A limit state g = a0 + a . x in place of the model's (no solve)."""
    module = importlib.import_module("jaxdem.reliability")

    def install(a0, a):
        class Linear:
            def __init__(self, scene, variables, limit):
                self.variables = variables
                self.notes = []

            def __call__(self, y):
                x, dxdy = transform(self.variables, y)
                return a0 + np.dot(a, x), np.asarray(a, float) * dxdy

            solves = dict(plain=0, with_sensitivities=0, batches=0)

        monkeypatch.setattr(module, "MonitorLimitState", Linear)

    return install


def test_correlated_normals_give_the_closed_form_beta_and_importance(linear_state):
    """g = a0 + a . x with x ~ N(m, S R S): beta = (a0 + a . m) / sqrt((a s)^T R (a s)),
    gamma = -(a s) / |a s|, exact for any correlation R."""
    scene = parse_scene(jointed_tunnel())
    a0, a = 1.2, np.array([-0.05, 0.02, -0.1])
    m, s = np.array([30.0, 20.0, 10.0]), np.array([3.0, 4.0, 1.0])
    R = np.array([[1.0, 0.5, -0.3], [0.5, 1.0, 0.2], [-0.3, 0.2, 1.0]])
    paths = ["joints.set1.friction_deg", "joints.set2.friction_deg", "joints.set1.cohesion"]
    linear_state(a0, a)
    vary = [f"{p}=normal:{mi}:{si}" for p, mi, si in zip(paths, m, s, strict=True)]
    r = jaxdem.reliability(scene, vary, "crown.uy >= -0.01", correlation=R)
    sa = a * s
    assert r.converged
    assert r.beta == pytest.approx((a0 + a @ m) / math.sqrt(sa @ R @ sa), rel=1e-9)
    gamma = -sa / np.linalg.norm(sa)
    np.testing.assert_allclose([r.alpha[p] for p in paths], gamma, rtol=1e-9)
    assert sum(r.importance.values()) == pytest.approx(1.0)
    # The design point lies on g = 0.
    x = np.array([r.design_point[p] for p in paths])
    assert a0 + a @ x == pytest.approx(0.0, abs=1e-9)
    # Pairs by name give the same matrix.
    pairs = {(paths[0], paths[1]): 0.5, (paths[0], paths[2]): -0.3, (paths[1], paths[2]): 0.2}
    r2 = jaxdem.reliability(scene, vary, "crown.uy >= -0.01", correlation=pairs)
    assert r2.beta == pytest.approx(r.beta, rel=1e-12)


def test_correlation_is_checked():
    v = VARIABLES[:2]
    assert np.array_equal(correlation_matrix(v, None), np.eye(2))
    for bad in ([[1, 0.5], [0.4, 1]], [[1, 1.0], [1.0, 1]], [[2, 0], [0, 1]], np.eye(3),
                {("a", "z"): 0.1}, {("a", "a"): 0.1}, {("a", "b"): float("nan")}):
        with pytest.raises(SceneError, match="^--correlation"):
            correlation_matrix(v, bad)
    with pytest.raises(SceneError, match="positive definite"):
        correlation_matrix(VARIABLES[:3], [[1, .9, -.9], [.9, 1, .9], [-.9, .9, 1]])


@pytest.fixture(scope="module")
def tunnel_scene():
    return parse_scene(jointed_tunnel())


@pytest.mark.parametrize("text, monitor, component, operator, value", [
    ("crown.|u| <= 0.02", "crown", "|u|", "<=", 0.02),
    ("crown.uy >= -0.015", "crown", "uy", ">=", -0.015),
    ("crown.ux<1e-3", "crown", "ux", "<=", 1e-3),
    ("span <= 0.03", "span", None, "<=", 0.03),
    ("  span > -.5 ", "span", None, ">=", -0.5),
])
def test_limit_syntax(tunnel_scene, text, monitor, component, operator, value):
    limit = Limit.parse(text, tunnel_scene)
    assert (limit.kind, limit.monitor, limit.component, limit.operator, limit.value) == \
        ("monitor", monitor, component, operator, value)
    assert Limit.parse("Stable", tunnel_scene).ultimate


def test_limit_signs_fail_where_g_is_negative(tunnel_scene):
    u = np.array([0.003, -0.02])                    # ux, uy (m)
    assert Limit.parse("crown.uy >= -0.015", tunnel_scene).g(u[1:]) == pytest.approx(-0.005)
    assert Limit.parse("crown.|u| <= 0.03", tunnel_scene).g(u) == pytest.approx(
        0.03 - np.hypot(*u))
    assert Limit.parse("span <= 0.03", tunnel_scene).g(np.array([0.01])) == pytest.approx(0.02)
    limit = Limit.parse("crown.|u| <= 0.03", tunnel_scene)
    J = np.array([[1.0, 2.0], [3.0, 4.0]])         # d(ux, uy) / d(x1, x2)
    np.testing.assert_allclose(limit.gradient(u, J), -(u @ J) / np.hypot(*u))


@pytest.mark.parametrize("text, message", [
    ("crown <= 0.01", "'crown' is a point"),
    ("span.ux <= 0.01", "'span' is a section"),
    ("crown.uz <= 0.01", "'crown' is a point"),
    ("roof.uy >= -0.01", "no monitor named 'roof'"),
    ("crown.uy == 0.01", "neither 'stable'"),
    ("crown.uy <= abc", "neither 'stable'"),
    ("", "give a limit"),
])
def test_limit_refused_naming_the_field(tunnel_scene, text, message):
    with pytest.raises(SceneError, match=f"^--limit: .*{message}"):
        Limit.parse(text, tunnel_scene)


def test_check_and_samples_for_cov():
    assert parse_check(None) is None and parse_check("mc:2000") == 2000 and parse_check(5) == 5
    for bad in ("mc", "is:100", "mc:x", "mc:0", 0, True):
        with pytest.raises(SceneError, match="^--check"):
            parse_check(bad)
    assert samples_for_cov(1e-3, 0.1) == pytest.approx(99_900)
