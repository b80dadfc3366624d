"""Back-analysis (``inverse/``) and ``jaxdem back-analyse``.

The forward models are analytic stand-ins for ``jaxdem.differentiable``, passed with
``forward=(f, theta0)``: a "tunnel" whose sections converge by c_i = a_i / kn + b_i / ks
(m; kn, ks in kPa/m, a_i, b_i in kN/m) and whose crown moves by [ux, uy]. Variants add
a parameter that no output depends on, a unit weight that only enters as unit_weight / kn,
a region of no equilibrium (NaN) and per-stage values. The observed monitors and stages
are checked against a real scene that has those monitors and stages.

``test_cli_back_analyse_end_to_end`` alone runs the real solver through
``jaxdem.differentiable`` on ``tests/data/back_analysis_stack.toml``.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from scenes import stack

import jaxdem
from inverse import BackAnalysis, Observation, back_analyse, read_observations
from inverse.observations import default_std
from inverse.plots import write_figures
from jaxdem.cli import main
from jaxdem.scene import SceneError, parse_scene

DATA = Path(__file__).parent / "data"
STACK = DATA / "back_analysis_stack.toml"

KN, KS = "joints.j.kn", "joints.j.ks"
TRUE = np.array([2.0e6, 1.0e6])  # kn, ks (kPa/m)
START = np.array([1.0e6, 2.0e6])
# Closure of section i per unit compliance (kN/m): a_i / kn + b_i / ks, 1-4 mm here.
A = np.array([2.0e3, 1.0e3, 3.0e3, 0.5e3])
B = np.array([0.5e3, 2.0e3, 1.0e3, 3.0e3])
SECTIONS = ("s1", "s2", "s3", "s4")
STAGES = ("excavate", "support")
EXCAVATE_FRACTION = 0.6  # of the final values reached at the end of "excavate"


@pytest.fixture(scope="module")
def scene():
    """A scene with the stand-ins' monitors (sections s1-s4, point crown) and stages."""
    data = stack(3)
    data["monitors"] = [{"name": s, "from": [0.5, -0.5], "to": [0.5, 0.5 * k + 0.5]}
                        for k, s in enumerate(SECTIONS, start=1)]
    data["monitors"].append({"name": "crown", "point": [0.5, 2.5]})
    data["stages"] = [{"name": s} for s in STAGES]
    return parse_scene(data)


def tunnel_values(kn, ks, weight=1.0):
    """Monitors at the end of the analysis: section convergences and the crown [ux, uy]."""
    out = {s: weight * a / kn + b / ks for s, a, b in zip(SECTIONS, A, B, strict=True)}
    out["crown"] = jnp.stack([400.0 / ks, -(weight * 1500.0 / kn + 800.0 / ks)])
    return out


def tunnel(theta):
    """theta = [kn, ks]."""
    return tunnel_values(theta[0], theta[1])


def staged(f):
    """f with per-stage output, as jaxdem.differentiable(..., stages=STAGES) gives it."""

    def g(theta):
        final = f(theta)
        return {"excavate": {k: EXCAVATE_FRACTION * v for k, v in final.items()},
                "support": final}

    return g


def unused_friction(theta):
    """theta = [kn, ks, friction_deg]: nothing depends on the friction."""
    return tunnel_values(theta[0], theta[1])


def weight_over_kn(theta):
    """theta = [kn, ks, unit_weight]: the weight only enters as unit_weight / kn."""
    return tunnel_values(theta[0], theta[1], weight=theta[2] / 25.0)


def mechanism_below(kn_min):
    """The tunnel, with no equilibrium (NaN) where kn < kn_min."""

    def f(theta):
        return {k: jnp.where(theta[0] < kn_min, jnp.nan, v) for k, v in tunnel(theta).items()}

    return f


def exact_observations(f, theta, *, stages=False):
    """Every monitor value of f(theta) as an Observation (point monitors: ux and uy)."""
    out = f(jnp.asarray(theta))
    blocks = out.items() if stages else [(None, out)]
    obs = []
    for stage, block in blocks:
        for name, value in block.items():
            value = np.asarray(value)
            if value.shape == (2,):
                obs += [Observation(name, float(value[k]), stage=stage, component=c)
                        for k, c in enumerate(("ux", "uy"))]
            else:
                obs.append(Observation(name, float(value), stage=stage))
    return obs


def fit(scene, observed, paths=(KN, KS), start=START, f=tunnel, **kwargs) -> BackAnalysis:
    return back_analyse(scene, observed, list(paths), forward=(f, jnp.asarray(start)), **kwargs)


def relative_error(result, truth, paths=(KN, KS)):
    return np.array([result.params[p] / t - 1.0 for p, t in zip(paths, truth, strict=True)])


# --------------------------------------------------------------------------- recovery


def test_recovers_parameters_from_several_monitors_and_stages(scene):
    f = staged(tunnel)
    observed = exact_observations(f, TRUE, stages=True)
    result = fit(scene, observed, f=f)
    assert result.converged, result.message
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)
    assert result.identifiable == {KN: True, KS: True}
    assert result.warnings == []
    assert all(np.isfinite(list(result.std.values())))
    assert result.history[0] > 1.0 > 1e-4 > result.history[-1]
    assert len(result.history) == result.iterations + 1
    # The line search gets values and gradients from one jacfwd solve per trial point:
    # nothing is solved for values alone.
    assert result.evaluations["forward"] == 0
    assert 0 < result.evaluations["gradient"] <= 3 * result.iterations + 2
    np.testing.assert_allclose(result.fitted, [o.value for o in observed], rtol=1e-3)


def test_sensitivity_is_the_jacobian_at_the_estimate(scene):
    observed = exact_observations(tunnel, TRUE)
    result = fit(scene, observed)
    kn, ks = result.params[KN], result.params[KS]
    # Section s1: c = a/kn + b/ks, so dc/dkn = -a/kn^2 and dc/dks = -b/ks^2.
    row = [o.monitor for o in result.observations].index("s1")
    np.testing.assert_allclose(result.sensitivity["jacobian"][row],
                               [-A[0] / kn**2, -B[0] / ks**2], rtol=1e-9)
    std = result.observations[row].std
    np.testing.assert_allclose(result.sensitivity["dimensionless"][row],
                               [-A[0] / kn / std, -B[0] / ks / std], rtol=1e-9)


def test_standard_deviations_of_a_linear_model_are_the_closed_form(scene):
    # y = J theta: the Gauss-Newton covariance (J_w^T J_w)^-1 is exact, whatever theta.
    jac = np.array([[1.0, 2.0], [3.0, -1.0], [0.5, 0.5], [-2.0, 1.0]]) * 1e-9  # m per kPa/m
    std = np.array([1e-4, 2e-4, 1e-4, 3e-4])

    def f(theta):
        y = jnp.asarray(jac) @ theta
        return {s: y[i] for i, s in enumerate(SECTIONS)}

    observed = [Observation(o.monitor, o.value, std=sd)
                for o, sd in zip(exact_observations(f, TRUE), std, strict=True)]
    result = fit(scene, observed, f=f)
    weighted = jac / std[:, None]
    covariance = np.linalg.inv(weighted.T @ weighted)
    np.testing.assert_allclose([result.std[KN], result.std[KS]], np.sqrt(np.diag(covariance)),
                               rtol=1e-6)
    r = covariance[0, 1] / np.sqrt(covariance[0, 0] * covariance[1, 1])
    assert result.correlation[0, 1] == pytest.approx(r, abs=1e-9)
    np.testing.assert_allclose(result.sensitivity["jacobian"], jac, rtol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_with_five_percent_noise_the_truth_is_within_two_std(scene, seed):
    # 12 observations (4 sections and the crown's ux, uy at two stages) for 2 parameters,
    # each with 5 % Gaussian noise and the default 5 % std: the estimates are close to
    # normal around the truth, so each lies within 2 std with ~95 % probability (40 of
    # 40 seeds did for both parameters when this test was written).
    rng = np.random.default_rng(seed)
    f = staged(tunnel)
    observed = [Observation(o.monitor, o.value * (1.0 + 0.05 * rng.standard_normal()),
                            stage=o.stage, component=o.component)
                for o in exact_observations(f, TRUE, stages=True)]
    result = fit(scene, observed, f=f)
    assert result.converged, result.message
    for path, truth in zip((KN, KS), TRUE, strict=True):
        assert result.identifiable[path]
        assert 0.0 < result.std[path] < 0.2 * truth
        assert abs(result.params[path] - truth) < 2.0 * result.std[path]
    assert result.observations[0].std == pytest.approx(default_std(observed[0].value))


def test_dict_of_section_values_with_and_without_std(scene):
    final = tunnel(jnp.asarray(TRUE))
    observed = {"s1": float(final["s1"]), "s2": (float(final["s2"]), 1e-4),
                "s3": float(final["s3"]), "s4": (float(final["s4"]), 2e-4)}
    result = fit(scene, observed)
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)
    assert [o.std for o in result.observations][1::2] == [1e-4, 2e-4]


def test_without_a_scene_the_model_output_is_checked():
    f = staged(tunnel)
    observed = exact_observations(f, TRUE, stages=True)
    result = back_analyse(None, observed, [KN, KS], forward=(f, jnp.asarray(START)),
                          stages=list(STAGES))
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)
    with pytest.raises(SceneError, match="the model gives no monitor named 'tunnel crown'"):
        back_analyse(None, [Observation("tunnel crown", 0.001)], [KN, KS],
                     forward=(tunnel, jnp.asarray(START)))
    with pytest.raises(SceneError, match="'crown' is a point monitor"):
        back_analyse(None, [Observation("crown", 0.001)], [KN, KS],
                     forward=(tunnel, jnp.asarray(START)))


def test_adam_reaches_the_lbfgs_estimate(scene):
    # Adam moves at most ~learning_rate in z per iteration and needs a few hundred
    # iterations; it stops within ~0.1 % of the optimum here, so 1 % is the tolerance.
    observed = exact_observations(tunnel, TRUE)
    lbfgs = fit(scene, observed, optimizer="lbfgs")
    adam = fit(scene, observed, optimizer="adam", max_iterations=1000)
    assert adam.converged, adam.message
    assert adam.optimizer == "adam"
    for path in (KN, KS):
        assert adam.params[path] == pytest.approx(lbfgs.params[path], rel=0.01)
    assert adam.evaluations["gradient"] > lbfgs.evaluations["gradient"]


def test_gauss_newton_reaches_the_lbfgs_estimate_in_fewer_solves(scene):
    observed = exact_observations(tunnel, TRUE)
    lbfgs = fit(scene, observed, optimizer="lbfgs")
    gn = fit(scene, observed)  # the default
    assert gn.converged, gn.message
    for path in (KN, KS):
        assert gn.params[path] == pytest.approx(lbfgs.params[path], rel=1e-4)
    assert gn.evaluations["gradient"] < lbfgs.evaluations["gradient"]


def test_gauss_newton_refuses_steps_into_points_without_equilibrium(scene):
    result = fit(scene, exact_observations(tunnel, TRUE), f=mechanism_below(1.6e6),
                 start=[2e7, 1e6], optimizer="gauss-newton")
    assert result.converged, result.message
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)


def test_progress_is_called_at_the_start_and_after_each_iteration(scene):
    events = []
    result = fit(scene, exact_observations(tunnel, TRUE), progress=events.append)
    assert [e["iteration"] for e in events] == list(range(result.iterations + 1))
    assert [e["misfit"] for e in events] == result.history
    assert set(events[0]) >= {"iteration", "misfit", "params", "gradient_norm"}
    assert events[0]["params"] == pytest.approx({KN: START[0], KS: START[1]})


# --------------------------------------------------------------------------- identifiability


def test_a_parameter_nothing_depends_on_is_not_identifiable(scene):
    paths = (KN, KS, "joints.j.friction_deg")
    result = fit(scene, exact_observations(tunnel, TRUE), paths=paths, f=unused_friction,
                 start=[*START, 30.0])
    assert result.identifiable == {KN: True, KS: True, "joints.j.friction_deg": False}
    assert result.std["joints.j.friction_deg"] == np.inf
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)
    assert np.isfinite(result.std[KN]) and np.isfinite(result.std[KS])
    assert any("joints.j.friction_deg is not identifiable" in w and "no monitor is sensitive" in w
               for w in result.warnings)
    data = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert data["std"]["joints.j.friction_deg"] is None
    assert data["correlation"][0][2] is None  # undefined: nothing measures the friction


def test_parameters_that_only_enter_as_a_ratio_are_reported_as_a_pair(scene):
    weight = "materials.rock.unit_weight"
    truth = [*TRUE, 25.0]
    result = fit(scene, exact_observations(weight_over_kn, truth), paths=(KN, KS, weight),
                 f=weight_over_kn, start=[*START, 20.0])
    assert result.identifiable == {KN: False, KS: True, weight: False}
    assert result.std[KN] == np.inf and result.std[weight] == np.inf
    assert result.params[KS] == pytest.approx(TRUE[1], rel=0.01)
    # The data fix unit_weight / kn only.
    assert result.params[weight] / result.params[KN] == pytest.approx(25.0 / TRUE[0], rel=0.01)
    i, j = result.paths.index(KN), result.paths.index(weight)
    assert result.correlation[i, j] == pytest.approx(1.0, abs=1e-6)
    assert any("nearly perfectly correlated (r = 1.0000)" in w and KN in w and weight in w
               for w in result.warnings)


def test_nearly_collinear_sensitivities_are_reported_as_correlated(scene):
    # Sections whose kn and ks weights differ by a few percent: r = -0.9993 (> 0.99).
    a = np.array([1e3, 2e3, 3e3, 4e3])
    b = a * np.array([1.0, 1.05, 0.95, 1.0])

    def f(theta):
        return {s: ai / theta[0] + bi / theta[1] for s, ai, bi in zip(SECTIONS, a, b, strict=True)}

    result = fit(scene, exact_observations(f, TRUE), f=f)
    assert result.identifiable == {KN: False, KS: False}
    assert result.correlation[0, 1] == pytest.approx(-0.9993, abs=1e-4)
    assert result.warnings == [f"{KN} and {KS} are nearly perfectly correlated (r = -0.9993): "
                               "only their combination is determined"]


# --------------------------------------------------------------------------- bounds and NaN


def test_bounds_are_respected_and_reported(scene):
    result = fit(scene, exact_observations(tunnel, TRUE), bounds={KN: (2e5, 1.5e6)})
    assert 2e5 <= result.params[KN] <= 1.5e6
    assert result.params[KN] == pytest.approx(1.5e6, rel=0.01)
    assert result.bounds[KN] == (2e5, 1.5e6)
    assert result.bounds[KS] == (START[1] / 100, START[1] * 100)  # the default
    assert any(w.startswith(f"{KN} ended at its upper bound") for w in result.warnings)


def test_linear_bounds_for_a_parameter_starting_at_zero(scene):
    cohesion = "joints.j.cohesion"

    def f(theta):  # cohesion (kPa) holds sections s1 and s3 back by 0.01 mm per kPa
        out = tunnel(theta)
        return {k: v - 1e-5 * theta[2] if k in ("s1", "s3") else v for k, v in out.items()}

    observed = exact_observations(f, [*TRUE, 20.0])
    with pytest.raises(SceneError, match="fit joints.j.cohesion: starting value 0 is not "
                                         "positive.*give them"):
        fit(scene, observed, paths=(KN, KS, cohesion), f=f, start=[*START, 0.0])
    result = fit(scene, observed, paths=(KN, KS, cohesion), f=f, start=[*START, 0.0],
                 bounds={cohesion: (0.0, 100.0)})
    assert result.converged, result.message
    assert result.params[cohesion] == pytest.approx(20.0, rel=0.01)
    assert result.start[cohesion] == 0.0


def test_line_search_backs_off_from_points_without_equilibrium(scene):
    # No equilibrium for kn < 1.6e6, just below the truth (2e6); from kn = 2e7 the first
    # steps overshoot into that region, and the fit must still get there.
    f = mechanism_below(1.6e6)
    result = fit(scene, exact_observations(tunnel, TRUE), f=f, start=[2e7, 1e6],
                 optimizer="lbfgs")
    assert result.evaluations["no_equilibrium"] > 0
    assert result.converged, result.message
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)
    assert all(np.isfinite(result.history))


def test_adam_backs_off_from_points_without_equilibrium(scene):
    f = mechanism_below(1.6e6)
    result = fit(scene, exact_observations(tunnel, TRUE), f=f, start=[2e7, 1e6],
                 optimizer="adam", max_iterations=1000, learning_rate=0.2)
    assert result.evaluations["no_equilibrium"] > 0
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)


def test_no_equilibrium_at_the_start(scene):
    result = fit(scene, exact_observations(tunnel, TRUE), f=mechanism_below(1.6e6))
    assert result.status == "no_equilibrium_at_start"
    assert not result.converged
    assert "no equilibrium at the starting parameters" in result.message
    assert result.std == {KN: np.inf, KS: np.inf}
    assert result.identifiable == {KN: False, KS: False}
    json.dumps(result.to_dict(), allow_nan=False)


def test_a_start_without_equilibrium_moves_towards_the_centre_of_explicit_bounds(scene):
    # kn = 1e6 has no equilibrium (kn < 1.6e6); the centre of the kn bounds (in log) is
    # 2e6. The steps of RESTORE_STEPS reach kn = 1.19e6, 1.41e6 (still none) and
    # 1.68e6 (equilibrium): the fit starts there and goes on to the truth.
    bounds = {KN: (1e5, 4e7), KS: (1e4, 1e8)}
    result = fit(scene, exact_observations(tunnel, TRUE), f=mechanism_below(1.6e6),
                 bounds=bounds)
    assert result.converged, result.message
    assert np.all(np.abs(relative_error(result, TRUE)) < 0.01)
    assert result.start == {KN: START[0], KS: START[1]}
    assert result.evaluations["no_equilibrium"] == 3
    note = [w for w in result.warnings if "no equilibrium" in w]
    assert len(note) == 1 and "75% of the way" in note[0], result.warnings
    assert f"{KN} = 1.682e+06" in note[0]


def test_gauss_newton_steps_along_one_parameter_beside_a_region_without_equilibrium():
    # Monitors linear in (log kn, log ks), truth (2e6, 1e6), start (4e7, 2e6); no
    # equilibrium where kn > 1e7 and ks < 1.98e6, so that every step that moves both
    # parameters towards the truth from the start enters that region, at any length
    # above 1% of ks. Before the axis steps (LM_BLOCKED) the fit crept along the
    # region's edge and stopped there (line_search_failed after 59 solves, kn 3.9e7);
    # softening kn alone leaves the region behind, and then the fit goes straight on.
    def clean(theta):
        a, b = jnp.log(theta[0] / 2e6), jnp.log(theta[1] / 1e6)
        return {"s1": 0.01 * (1.0 + a + b), "s2": 0.01 * (1.0 + a - 0.5 * b)}

    def f(theta):
        none = (theta[0] > 1e7) & (theta[1] < 0.99 * 2e6)
        return {k: jnp.where(none, jnp.nan, v) for k, v in clean(theta).items()}

    observed = [Observation(k, float(v), 1e-4) for k, v in clean(jnp.array([2e6, 1e6])).items()]
    result = back_analyse(None, observed, ["kn", "ks"], forward=(f, jnp.array([4e7, 2e6])),
                          bounds={"kn": (2e4, 2e8), "ks": (1e4, 1e8)})
    assert result.converged, result.message
    assert result.evaluations["no_equilibrium"] > 0
    assert abs(result.params["kn"] / 2e6 - 1.0) < 1e-6
    assert abs(result.params["ks"] / 1e6 - 1.0) < 1e-6
    assert result.evaluations["gradient"] <= 12


def two_valleys(theta):
    """Monitors whose misfit has two valleys in x = log(kn / 1e6): s1 sees only x^2, and
    only the slight slope of s2 (0.001 x) tells x = +log 2 (the truth, kn = 2e6) from
    x = -log 2. The valley at kn = 5e5 is a local minimum whose misfit (48 with stds of
    1e-4) is far above what noise explains, like the slope's beside its mechanism."""
    x, w = jnp.log(theta[0] / 1e6), jnp.log(theta[1] / 1e6)
    return {"s1": 0.01 * x**2, "s2": 0.001 * x + 0.01 * w, "s3": 0.01 * (1.0 + w)}


TWO_VALLEYS_TRUTH = np.array([2e6, 1e6])


def two_valley_fit(start, **kwargs):
    observed = [Observation(k, float(v), 1e-4)
                for k, v in two_valleys(jnp.asarray(TWO_VALLEYS_TRUTH)).items()]
    return back_analyse(None, observed, ["kn", "ks"], forward=(two_valleys, jnp.array(start)),
                        **kwargs)


def test_a_rejected_fit_restarts_and_reaches_the_truth():
    from inverse.statistics import misfit_limit

    bounds = {"kn": (1e4, 1e8), "ks": (1e4, 1e8)}
    alone = two_valley_fit([3e5, 3e5], bounds=bounds, restarts=0)
    assert alone.converged and abs(alone.params["kn"] / 5e5 - 1.0) < 0.01  # the wrong valley
    assert alone.misfit > misfit_limit(3, 2)
    assert len(alone.starts) == 1

    result = two_valley_fit([3e5, 3e5], bounds=bounds)
    assert result.converged, result.message
    assert abs(result.params["kn"] / 2e6 - 1.0) < 1e-6
    assert abs(result.params["ks"] / 1e6 - 1.0) < 1e-6
    # The first local fit is the one without restarts, rejected; the first restart (from
    # the centre of the bounds, kn = ks = 1e6) is accepted, and the fit stops there.
    assert [s["misfit"] for s in result.starts][0] == pytest.approx(alone.misfit)
    assert len(result.starts) == 2
    assert result.starts[1]["start"] == pytest.approx({"kn": 1e6, "ks": 1e6})
    assert result.starts[1]["misfit"] < 1e-10
    assert result.evaluations["gradient"] == sum(s["solves"] for s in result.starts)
    assert any("restarted 1 time from other points" in w for w in result.warnings)
    json.dumps(result.to_dict(), allow_nan=False)


def test_restarts_skip_the_centre_when_the_fit_started_there():
    # Default bounds: the start is their centre, so the restarts come from the Halton
    # points, (0.5, 1/3), (1/4, 2/3), (3/4, 1/9) of each (log-)range: the first two lie
    # on the start's side of the kn valleys, the third (kn = 3e6) on the truth's.
    result = two_valley_fit([3e5, 3e5])
    assert abs(result.params["kn"] / 2e6 - 1.0) < 1e-6
    assert [s["start"]["kn"] for s in result.starts] == pytest.approx([3e5, 3e5, 3e4, 3e6])
    assert [s["misfit"] > 1.0 for s in result.starts] == [True, True, True, False]


def test_an_accepted_fit_does_not_restart():
    first = two_valley_fit([6e6, 3e5])
    alone = two_valley_fit([6e6, 3e5], restarts=0)
    assert abs(first.params["kn"] / 2e6 - 1.0) < 1e-6
    assert len(first.starts) == 1
    assert first.evaluations == alone.evaluations
    assert not any("restarted" in w for w in first.warnings)


def test_restarts_are_capped_when_no_fit_can_be_accepted():
    # Every value 1.5 times the model's at the truth: no (kn, ks) fits them within their
    # stds, every local fit is rejected, and the fit stops after `restarts` restarts with
    # the lowest misfit.
    observed = [Observation(k, float(v) * 1.5, 1e-4)
                for k, v in two_valleys(jnp.asarray(TWO_VALLEYS_TRUTH)).items()]
    result = back_analyse(None, observed, ["kn", "ks"],
                          forward=(two_valleys, jnp.array([6e6, 3e5])), restarts=2)
    assert len(result.starts) == 3
    assert result.misfit == pytest.approx(min(s["misfit"] for s in result.starts))
    assert any("none reached a misfit that noise explains" in w for w in result.warnings)


def test_to_dict_is_json_without_nan(scene):
    result = fit(scene, exact_observations(staged(tunnel), TRUE, stages=True), f=staged(tunnel))
    data = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert set(data) >= {"params", "std", "identifiable", "correlation", "history",
                         "evaluations", "warnings", "observations", "sensitivity",
                         "converged", "message"}
    row = data["observations"][0]
    assert set(row) == {"monitor", "component", "stage", "observed", "std", "fitted",
                        "residual", "normalized_residual"}
    assert np.array(data["sensitivity"]["dimensionless"]).shape == (len(result.observations), 2)


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "observation, field, message",
    [
        (Observation("nowhere", 0.001), "observed.0.monitor", "no monitor named 'nowhere'"),
        (Observation("crown", 0.001), "observed.0.component", "point monitor"),
        (Observation("s1", 0.001, component="ux"), "observed.0.component", "is a section"),
        (Observation("s1", 0.001, component="uz"), "observed.0.component", "must be ux or uy"),
        (Observation("s1", 0.001, stage="grout"), "observed.0.stage", "no stage named 'grout'"),
        (Observation("s1", 0.001, std=0.0), "observed.0.std", "must be > 0"),
        (Observation("s1", float("nan")), "observed.0.value", "must be finite"),
    ],
)
def test_observations_are_checked_against_the_scene(scene, observation, field, message):
    with pytest.raises(SceneError, match=message) as info:
        fit(scene, [observation])
    assert info.value.path == field


def test_csv_observations_name_their_row_in_messages(scene, tmp_path):
    csv = tmp_path / "obs.csv"
    csv.write_text("monitor,value\ns1,0.001\ntunnel crown,0.002\n")
    with pytest.raises(SceneError, match="no monitor named 'tunnel crown'") as info:
        fit(scene, read_observations(csv))
    assert info.value.path == f"{csv}, row 3, monitor"


@pytest.mark.parametrize(
    "paths, bounds, field, message",
    [
        ((KN, "joints.j.kx"), None, "joints.j.kx", "no such parameter"),
        ((KN, KN), None, f"fit {KN}", "listed twice"),
        ((KN, KS), {"joints.j.friction_deg": (10, 40)}, "bounds joints.j.friction_deg",
         "not a fitted parameter"),
        ((KN, KS), {KN: (1e7, 1e5)}, f"bounds {KN}", "lo must be < hi"),
        ((KN, KS), {KN: (3e6, 1e7)}, f"bounds {KN}", "starting value 1e\\+06 lies outside"),
    ],
)
def test_fit_paths_and_bounds_are_checked(scene, paths, bounds, field, message):
    with pytest.raises(SceneError, match=message) as info:
        fit(scene, exact_observations(tunnel, TRUE), paths=paths, bounds=bounds)
    assert info.value.path == field


# --------------------------------------------------------------------------- CSV


def test_read_observations(tmp_path):
    path = tmp_path / "obs.csv"
    # A byte-order mark and capitalised header, as spreadsheets write them; a blank line.
    path.write_text(
        "\ufeffMonitor,Value,Std,Stage,Component\n"
        "s1,0.0012,0.0001,,\n"
        "\n"
        "crown,-0.0031,,excavate,uy\n"
        "crown, 0.0004 ,2e-4,,UX\n",
        encoding="utf-8",
    )
    observations = read_observations(path)
    assert observations == [
        Observation("s1", 0.0012, 0.0001),
        Observation("crown", -0.0031, None, stage="excavate", component="uy"),
        Observation("crown", 0.0004, 2e-4, component="ux"),
    ]
    assert observations[1].source == f"{path}, row 4"


def test_read_observations_without_std_column(tmp_path):
    path = tmp_path / "obs.csv"
    path.write_text("monitor,value\ns1,0.01\ns2,0.00001\n")
    observations = read_observations(path)
    assert [o.std for o in observations] == [None, None]
    assert default_std(0.01) == pytest.approx(5e-4)  # 5 %
    assert default_std(0.00001) == 1e-4  # the floor, 0.1 mm


@pytest.mark.parametrize(
    "text, field, message",
    [
        ("", "", "empty file"),
        ("monitor,value,std\n", "", "no observations"),
        ("monitor,std\ns1,0.001\n", ", row 1 (header)", "missing column 'value'"),
        ("monitor,value,stdev\ns1,0.001,0.1\n", ", row 1 (header)", "unknown column 'stdev'"),
        ("monitor,value,std\ns1,0.001,0.0001\ns2,abc,0.0001\n", ", row 3, value",
         "must be a number \\(got 'abc'\\)"),
        ("monitor,value,std\ns1,nan,0.0001\n", ", row 2, value", "must be finite"),
        ("monitor,value,std\ns1,0.001,-0.0001\n", ", row 2, std", "must be > 0"),
        ("monitor,value,std\ns1,0.001,0\n", ", row 2, std", "must be > 0"),
        ("monitor,value,component\ncrown,0.001,uz\n", ", row 2, component", "must be ux or uy"),
        ("monitor,value\n,0.001\n", ", row 2, monitor", "empty"),
        ("monitor,value\ns1,\n", ", row 2, value", "empty"),
        ("monitor,value\ns1,0.001,7\n", ", row 2", "3 cells but the header has 2"),
    ],
)
def test_bad_observation_files(tmp_path, text, field, message):
    path = tmp_path / "obs.csv"
    path.write_text(text)
    with pytest.raises(SceneError, match=message) as info:
        read_observations(path)
    assert info.value.path == f"{path}{field}"


def test_missing_observation_file(tmp_path):
    with pytest.raises(SceneError, match="cannot read the observations file"):
        read_observations(tmp_path / "missing.csv")


# --------------------------------------------------------------------------- figures


def test_figures_are_written(scene, tmp_path):
    paths = (KN, KS, "joints.j.friction_deg")
    result = fit(scene, exact_observations(staged(tunnel), TRUE, stages=True),
                 paths=paths, f=staged(unused_friction), start=[*START, 30.0])
    written = write_figures(result, tmp_path / "figures")
    assert [p.name for p in written] == ["misfit.png", "fit.png", "sensitivity.png"]
    for p in written:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert p.stat().st_size > 10_000


# --------------------------------------------------------------------------- command line


def stack_forward(kn_min=0.0):
    """A stand-in for jaxdem.differentiable on the stack scene: the column shortens by
    150 kN/m / kn (m), the top settles by as much; NaN where kn < kn_min."""

    def differentiable(scene, params, stages=None):
        def f(theta):
            kn = theta[params.index(KN)]
            c = jnp.where(kn < kn_min, jnp.nan, 150.0 / kn)
            return {"column": c, "top": jnp.stack([0.0 * c, -c])}

        theta0 = jnp.array([getattr(scene.joints["j"], p.split(".")[-1]) for p in params])
        return f, theta0

    return differentiable


def write_stack_observations(path, convergence):
    path.write_text("monitor,value,std,component\n"
                    f"column,{convergence!r},1e-4,\n"
                    f"top,{-convergence!r},1e-4,uy\n")
    return path


def test_cli_back_analyse_with_a_stand_in_model(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(jaxdem, "differentiable", stack_forward(), raising=False)
    csv = write_stack_observations(tmp_path / "obs.csv", 150.0 / 5e4)
    out = tmp_path / "out"
    status = main(["back-analyse", str(STACK), "--observed", str(csv), "--fit", KN,
                   "--fit", KS, "--bounds", f"{KN}=1e3:1e7", "--out", str(out)])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "it   0  misfit" in captured.err
    assert "not identifiable" in captured.out
    assert f"{KS} is not identifiable" in captured.out
    data = json.loads((out / "back_analysis.json").read_text())
    assert data["params"][KN] == pytest.approx(5e4, rel=0.01)
    assert data["bounds"][KN] == [1e3, 1e7]
    assert data["identifiable"] == {KN: True, KS: False}
    assert len(data["starts"]) == 1  # accepted from the start: no restart
    for name in ("misfit.png", "fit.png", "sensitivity.png"):
        assert (out / name).stat().st_size > 0


def test_cli_back_analyse_exits_3_without_equilibrium_at_the_start(tmp_path, capsys,
                                                                   monkeypatch):
    monkeypatch.setattr(jaxdem, "differentiable", stack_forward(kn_min=2e5), raising=False)
    csv = write_stack_observations(tmp_path / "obs.csv", 150.0 / 5e4)
    out = tmp_path / "out"
    status = main(["back-analyse", str(STACK), "--observed", str(csv), "--fit", KN,
                   "--out", str(out)])
    captured = capsys.readouterr()
    assert status == 3
    assert "no equilibrium at the starting parameters" in captured.out
    assert json.loads((out / "back_analysis.json").read_text())["status"] == \
        "no_equilibrium_at_start"
    assert not (out / "fit.png").exists()


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--observed", "{tmp}/missing.csv", "--fit", KN], "missing.csv: cannot read"),
        (["--observed", "{csv}", "--fit", "joints.j.kx"], "fit joints.j.kx: no such parameter"),
        (["--observed", "{csv}", "--fit", KN, "--bounds", f"{KN}=1e3"],
         "--bounds: expected PATH=LO:HI"),
        (["--observed", "{csv}", "--fit", KN, "--bounds", f"{KN}=a:b"],
         "--bounds: bounds of joints.j.kn must be numbers"),
        (["--observed", "{csv}", "--fit", KN, "--bounds", f"{KN}=1e7:1e3"],
         f"bounds {KN}: lo must be < hi"),
        (["--observed", "{bad}", "--fit", KN], "no monitor named 'crown'"),
        (["--observed", "{csv}", "--fit", KN, "--max-iterations", "-1"],
         "--max-iterations must be >= 0"),
        (["--observed", "{csv}", "--fit", KN, "--restarts", "-1"], "--restarts must be >= 0"),
        (["--observed", "{csv}", "--fit", KN, "--set", "joints.j.kn=-5"], "joints.j.kn"),
    ],
)
def test_cli_back_analyse_invalid_input(tmp_path, capsys, arguments, message):
    csv = write_stack_observations(tmp_path / "obs.csv", 0.003)
    bad = tmp_path / "bad.csv"
    bad.write_text("monitor,value,component\ncrown,0.003,uy\n")
    arguments = [a.format(tmp=tmp_path, csv=csv, bad=bad) for a in arguments]
    status = main(["back-analyse", str(STACK), *arguments, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("error: ") and message in err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_cli_back_analyse_end_to_end(tmp_path, capsys):
    """The real solver through jaxdem.differentiable: fit kn of the stack to the settlement
    it has with kn = 5e4 kPa/m (from 1e5 in the file); ks is not identifiable."""
    scene = jaxdem.load_scene(STACK)
    truth = jaxdem.solve(scene, set={KN: 5.0e4})
    convergence = float(truth.monitors["column"]["convergence"])
    assert convergence > 1e-3  # about 3 mm
    csv = write_stack_observations(tmp_path / "obs.csv", convergence)
    out = tmp_path / "out"
    status = main(["back-analyse", str(STACK), "--observed", str(csv), "--fit", KN,
                   "--fit", KS, "--out", str(out)])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    data = json.loads((out / "back_analysis.json").read_text())
    assert data["params"][KN] == pytest.approx(5.0e4, rel=0.01)
    assert data["identifiable"] == {KN: True, KS: False}
    assert data["std"][KS] is None
    assert data["evaluations"]["gradient"] > 0
    for name in ("misfit.png", "fit.png", "sensitivity.png"):
        assert (out / name).stat().st_size > 0
