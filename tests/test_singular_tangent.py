"""Sensitivities where the held-state tangent is singular (issue 17).

A free block with a neutral direction in the held contact states (all its contacts
open, or none at all, or a rotation about its one contact point) makes the tangent
K = -dR/d(du) singular. The forward solve carries a pseudo-mass and converges; the
sensitivity solve used to factorise K itself and raised ("Factor is exactly
singular", sparse path) or returned NaN (dense path). It now factorises K + eps M
and refines on K: exact where K is regular, zero along a neutral direction.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import stack

import jaxdem
from jaxdem.cli import main
from jaxdem.differentiable import Problem
from jaxdem.scene import load_scene, parse_scene

PARAMS = ["joints.j.kn", "joints.j.ks"]


def _stack_with_a_loose_block(solver: str):
    """Two blocks on a fixed base, and a weightless free block touching nothing."""
    d = stack(2)
    d["materials"]["light"] = {"E": 1.0e7, "nu": 0.25, "unit_weight": 0.0}
    d["blocks"].append({"vertices": [[2.0, 0.5], [2.5, 0.5], [2.5, 1.0], [2.0, 1.0]],
                        "material": "light"})
    d["monitors"].append({"name": "loose", "point": [2.25, 0.75]})
    d["solver"]["linear_solver"] = solver
    return d


def _central(problem, theta, j, rel=1e-5):
    h = rel * theta[j]
    e = np.zeros_like(theta)
    e[j] = h
    return (problem.evaluate(theta + e)[0] - problem.evaluate(theta - e)[0]) / (2 * h)


@pytest.mark.parametrize("solver", ["sparse", "dense"])
def test_a_block_touching_nothing_has_zero_derivatives_and_the_rest_exact(solver):
    scene = parse_scene(_stack_with_a_loose_block(solver))
    assert jaxdem.solve(scene).converged
    problem = Problem(scene, PARAMS)
    theta = np.asarray(problem.theta0, float)
    y, J = problem.evaluate(theta, jacobian=True)  # raised (sparse) / NaN (dense) before
    assert np.all(np.isfinite(J))
    loose = [i for i, key in enumerate(problem.keys) if key[1] == "loose"]
    np.testing.assert_array_equal(J[loose], 0.0)
    top_uy = problem.keys.index((None, "top", "uy"))
    assert abs(J[top_uy, 0]) > 0  # the stack's settlement does depend on kn
    for j in range(len(PARAMS)):
        fd = _central(problem, theta, j)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-6, atol=1e-9 * np.abs(J).max())


def test_jacfwd_on_the_slope_example_where_it_raised():
    # Issue 17: jax.jacfwd(f) raised "Factor is exactly singular" at these values
    # (a block with a neutral rotation in the held states).
    scene = load_scene("examples/seed_example4_slope_dry.toml")
    paths = ["joints.set1.kn", "joints.set2.kn"]
    theta = np.array([1.034e6, 2.90e5])
    problem = Problem(scene, paths)
    f = problem.function()
    J = jax.jacfwd(lambda t: jnp.stack([f(t)["section 1-1"], f(t)["section 2-2"]]))(
        jnp.asarray(theta))
    J = np.asarray(J)
    assert np.all(np.isfinite(J)) and np.all(J != 0.0)
    i = [problem.keys.index((None, name, None)) for name in ("section 1-1", "section 2-2")]
    # Set 2's column (the one whose rotation-neutral block made K singular), against
    # central differences over 1e-4 theta (measured 2e-5 apart). Not over 1e-5 theta: the
    # solve at theta_2 (1 - 1e-5) takes another path (339 Newton iterations where its
    # neighbours at -2e-5, 0, +1e-5 and +2e-5 take 273-293 on one path), which puts
    # section 2-2 4e-8 m off the line through the others; a friction answer is
    # path-dependent, and the derivative is that of the path the solve takes.
    fd = _central(problem, theta, 1, rel=1e-4)[i]
    np.testing.assert_allclose(J[:, 1], fd, rtol=1e-3)


LOOSE_TOML = """
[scene]
name = "stack with a loose block"
[solver]
load_steps = 1
[materials.rock]
E = 1.0e7
nu = 0.25
unit_weight = 25.0
[materials.light]
E = 1.0e7
nu = 0.25
unit_weight = 0.0
[joints.j]
kn = 1.0e6
ks = 1.0e6
friction_deg = 35.0
[[blocks]]
vertices = [[-2, -1], [3, -1], [3, 0], [-2, 0]]
material = "rock"
fixed = true
[[blocks]]
vertices = [[0, 0], [1, 0], [1, 1], [0, 1]]
material = "rock"
[[blocks]]
vertices = [[0, 1], [1, 1], [1, 2], [0, 2]]
material = "rock"
[[blocks]]
vertices = [[2.0, 0.5], [2.5, 0.5], [2.5, 1.0], [2.0, 1.0]]
material = "light"
[[monitors]]
name = "top"
point = [0.5, 1.5]
[[monitors]]
name = "loose"
point = [2.25, 0.75]
"""


def _write_observations(path, values):
    path.write_text("monitor,component,value,std\n" + "".join(
        f"{m},{c},{v!r},1e-5\n" for m, c, v in values))


def test_cli_back_analyse_of_the_loose_block_scene_exits_0(tmp_path, capsys):
    # The command of issue 17 crashed with a traceback (exit 1) on such a scene.
    scene_file = tmp_path / "loose.toml"
    scene_file.write_text(LOOSE_TOML)
    truth = jaxdem.solve(load_scene(scene_file, set={"joints.j.kn": 2.0e6}))
    obs = tmp_path / "obs.csv"
    _write_observations(obs, [("top", "uy", truth.monitors["top"]["displacement"][1]),
                              ("loose", "uy", 0.0)])
    status = main(["back-analyse", str(scene_file), "--observed", str(obs), "--fit",
                   "joints.j.kn", "--out", str(tmp_path / "out")])
    out = capsys.readouterr()
    assert status == 0, out.err
    assert "gauss-newton" in out.out
    data = json.loads((tmp_path / "out" / "back_analysis.json").read_text())
    assert data["optimizer"] == "gauss-newton"
    assert data["params"]["joints.j.kn"] == pytest.approx(2.0e6, rel=1e-3)


def test_cli_turns_a_solve_that_raises_into_exit_3(tmp_path, capsys, monkeypatch):
    import inverse

    def boom(*args, **kwargs):
        raise RuntimeError("Factor is exactly singular")

    monkeypatch.setattr(inverse, "back_analyse", boom)
    scene_file = tmp_path / "loose.toml"
    scene_file.write_text(LOOSE_TOML)
    obs = tmp_path / "obs.csv"
    _write_observations(obs, [("top", "uy", -1e-4)])
    status = main(["back-analyse", str(scene_file), "--observed", str(obs), "--fit",
                   "joints.j.kn", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 3
    assert "Factor is exactly singular" in err and "Traceback" not in err


def test_a_solve_that_raises_is_read_as_no_equilibrium_with_its_reason():
    from inverse import Observation, back_analyse

    def f(theta):
        raise RuntimeError("Factor is exactly singular")

    result = back_analyse(None, [Observation("m", 4.0, std=0.01)], ["x"],
                          forward=(f, jnp.array([1.0])))
    assert result.status == "no_equilibrium_at_start"
    assert result.evaluations["no_equilibrium"] >= 1
    assert any("RuntimeError: Factor is exactly singular" in w for w in result.warnings)
