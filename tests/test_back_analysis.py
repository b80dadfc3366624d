"""Back-analysis with the real solver: recover joint stiffnesses of a jointed tunnel.

Synthetic "measurements" are the solver's own convergences at known parameters
(the usual identical-twin test of an inverse method); the fit starts elsewhere.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from scenes import jointed_tunnel

import jaxdem
from inverse import Observation, back_analyse
from jaxdem.scene import parse_scene

TRUE = {"joints.set1.kn": 2.0e6, "joints.set1.ks": 5.0e5}
START = {"joints.set1.kn": 4.0e6, "joints.set1.ks": 2.5e5}
SECTIONS = ("span", "height", "diag")


def _scene(values):
    d = jointed_tunnel(water=False, bolts=False)
    # A joint set that no contact uses: no monitor can see its stiffness.
    d["joints"]["unused"] = {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0}
    d["monitors"] += [{"name": "height", "from": [0.0, 2.05], "to": [0.0, -2.05]},
                      {"name": "diag", "from": [-2.05, -1.5], "to": [1.5, 2.05]}]
    return parse_scene(d).with_overrides(values)


@pytest.fixture(scope="module")
def measured():
    """Convergences (m) and the crown's displacement at the true parameters."""
    r = jaxdem.solve(_scene(TRUE))
    assert r.converged
    values = {name: r.monitors[name]["convergence"] for name in SECTIONS}
    values["crown ux"], values["crown uy"] = r.monitors["crown"]["displacement"]
    return values


def _observations(values, noise=None):
    out = []
    for key, v in values.items():
        name, _, comp = key.partition(" ")
        std = 0.05 * abs(v)
        value = v if noise is None else v + std * noise[len(out)]
        out.append(Observation(name, value, std, component=comp or None))
    return out


@pytest.mark.parametrize("optimizer", ["lbfgs", "gauss-newton"])
def test_recovers_joint_stiffness_without_noise(measured, optimizer):
    fit = back_analyse(_scene(START), _observations(measured), fit=list(TRUE),
                       optimizer=optimizer)
    assert fit.converged, fit.message
    for path, true in TRUE.items():
        assert fit.params[path] == pytest.approx(true, rel=0.01)
    assert all(fit.identifiable.values())
    # A gradient-based fit needs tens of solves, not hundreds.
    assert fit.evaluations["gradient"] + fit.evaluations["forward"] <= 60


def test_with_five_percent_noise_the_truth_is_within_two_standard_deviations(measured):
    noise = np.random.default_rng(7).standard_normal(len(measured))
    fit = back_analyse(_scene(START), _observations(measured, noise), fit=list(TRUE))
    assert fit.converged, fit.message
    for path, true in TRUE.items():
        assert np.isfinite(fit.std[path]) and fit.std[path] > 0
        assert abs(fit.params[path] - true) <= 2 * fit.std[path]


def test_a_joint_set_no_monitor_sees_is_reported_not_identifiable(measured):
    fit = back_analyse(_scene(START), _observations(measured),
                       fit=list(TRUE) + ["joints.unused.kn"], max_iterations=30)
    assert fit.identifiable == {"joints.set1.kn": True, "joints.set1.ks": True,
                                "joints.unused.kn": False}
    assert fit.std["joints.unused.kn"] == np.inf
    assert any("joints.unused.kn" in w and "not identifiable" in w for w in fit.warnings)
    assert fit.params["joints.set1.kn"] == pytest.approx(TRUE["joints.set1.kn"], rel=0.01)


def test_the_gauss_newton_jacobian_is_that_of_the_solver(measured):
    fit = back_analyse(_scene(START), _observations(measured), fit=list(TRUE))
    f, _ = jaxdem.differentiable(_scene(START), list(TRUE))
    theta = jnp.array([fit.params[p] for p in TRUE])
    y = f(theta)
    assert float(y["span"]) == pytest.approx(float(fit.fitted[0]), rel=1e-9)


def test_the_default_optimiser_reaches_the_truth_from_random_starts(measured):
    # Issue 17: from any start within the default bounds (a factor 100 either side of
    # the truth), noise-free. Three starts here; benchmarks/robust_back_analysis.py
    # runs twenty on three scenes.
    paths = list(TRUE)
    truth = np.array([TRUE[p] for p in paths])
    bounds = {p: (t / 100.0, t * 100.0) for p, t in TRUE.items()}
    f, _ = jaxdem.differentiable(_scene(TRUE), paths)
    u = np.random.default_rng(17).random((3, len(paths)))
    for start in truth * 100.0 ** (2.0 * u - 1.0):
        fit = back_analyse(_scene(TRUE), _observations(measured), fit=paths, bounds=bounds,
                           forward=(f, start))
        assert fit.optimizer == "gauss-newton"
        assert fit.converged, (start, fit.message)
        for path, true in TRUE.items():
            assert fit.params[path] == pytest.approx(true, rel=0.01), start
