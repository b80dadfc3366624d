"""Load steps cut where an increment ends at the iteration limit (``solver.max_step_cuts``,
:func:`jaxdem.solver.ramp`, README "Load steps cut").

The staged tunnel (examples/staged_tunnel.toml: heading, then bench) with 10 Newton
iterations per geometry update and one load step per stage: its heading released in one
step runs out of iterations; released in two it converges. The cut analysis must be the
two-step analysis itself (the same increments, the same answer to round-off), and where
even the shortest step fails it stops there, naming the last equilibrium.
"""

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxdem
from jaxdem.cli._progress import ProgressBar
from jaxdem.scene import SceneError, parse_scene

ROOT = Path(__file__).resolve().parents[1]
STAGED = ROOT / "examples" / "staged_tunnel.toml"
TIGHT = {"solver.load_steps": 1, "solver.max_iterations": 10}


def _staged():
    """The staged tunnel with its springs failing as they reach their strength
    (``solver.bond_failure = "substep"``): the cuts below were measured with it. Event by
    event (the default) its heading needs other cuts, and the rules are the same."""
    scene = jaxdem.load_scene(STAGED)
    data = {**scene.data, "solver": {**scene.data["solver"], "bond_failure": "substep"}}
    return parse_scene(data, source=str(STAGED))


def _stage(result, name):
    return next(s for s in result.stages if s["name"] == name)


def test_a_step_too_long_for_the_iteration_is_cut_and_is_then_the_shorter_steps():
    scene = _staged()
    whole = jaxdem.solve(scene, set={**TIGHT, "solver.max_step_cuts": 0})
    assert whole.status == "iteration_limit"
    assert _stage(whole, "heading")["step_cuts"] == 0

    events = []
    cut = jaxdem.solve(scene, set=TIGHT, progress=events.append)  # the default: 3 cuts
    assert cut.status == "converged" and cut.converged, cut.message
    # The progress shows the try that was cut, then the two half steps.
    heading_events = [(e["step"], e["n_steps"], e["status"], e["cut"]) for e in events
                      if e["stage"] == "heading"]
    assert heading_events == [(1, 1, "iteration_limit", True), (1, 2, "converged", False),
                              (2, 2, "converged", False)]
    line = ProgressBar(stream=io.StringIO()).format(events[1])
    assert line.endswith("iteration_limit: the load step cut in two"), line
    heading = _stage(cut, "heading")
    assert heading["load_factor"] == [0.5, 1.0] and heading["step_cuts"] == 1
    assert _stage(cut, "bench")["load_factor"] == [1.0]  # the next stage: its own steps
    assert "the load step of stage heading cut 1 time" in cut.message

    # The same increments asked for: the heading in two load steps, no cut.
    two = jaxdem.solve(scene, set={**TIGHT, "solver.max_step_cuts": 0,
                                   "stages.0.load_steps": 2})
    assert two.converged
    assert _stage(two, "heading")["iterations"] == heading["iterations"]
    for name, values in two.monitors.items():
        for key, value in values.items():
            np.testing.assert_allclose(cut.monitors[name][key], value, rtol=1e-12, atol=1e-15,
                                       err_msg=f"{name} {key}")
    u_cut = np.array([b["u"] for b in cut.blocks])
    u_two = np.array([b["u"] for b in two.blocks])
    np.testing.assert_allclose(u_cut, u_two, rtol=0, atol=1e-12 * np.abs(u_two).max())


def test_where_the_shortest_step_fails_the_analysis_stops_at_the_last_equilibrium():
    """6 iterations a geometry update: the heading's half step converges, its second
    half does not, and one cut is all that is allowed."""
    scene = _staged()
    r = jaxdem.solve(scene, set={**TIGHT, "solver.max_iterations": 6,
                                 "solver.max_step_cuts": 1})
    assert r.status == "iteration_limit" and not r.converged
    heading = _stage(r, "heading")
    assert heading["load_factor"] == [0.5, 1.0] and heading["step_cuts"] == 1
    assert not heading["converged"]
    assert ("Stopped in load step 2 of 2 of stage heading. Its load step was cut 1 time: "
            "the last equilibrium at load factor 0.5, none found at 1.") in r.message
    assert r.unbalanced_blocks  # and where it is out of balance


@pytest.mark.parametrize("value", [-1, 11, 1.5, "2"])
def test_bad_max_step_cuts_is_refused_with_the_field_named(tmp_path, value):
    with pytest.raises(SceneError, match=r"solver\.max_step_cuts"):
        jaxdem.load_scene(STAGED).with_overrides({"solver.max_step_cuts": value})
    text = STAGED.read_text()
    assert "[solver]\n" in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace("[solver]\n", f"[solver]\nmax_step_cuts = {value!r}\n"
                                 .replace("'", '"')))
    proc = subprocess.run([sys.executable, "-m", "jaxdem", "check", str(path),
                           "--out", str(tmp_path / "out")],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "solver.max_step_cuts" in proc.stderr + proc.stdout


def test_derivatives_through_a_cut_are_those_of_the_shorter_steps():
    """The sensitivities are carried through the cut (the failed try is undone with its
    derivatives): the Jacobian of the monitors equals that of the two-step heading."""
    import jax

    params = ["joints.set1.kn", "joints.set2.friction_deg"]
    cut = _staged().with_overrides(TIGHT)
    two = _staged().with_overrides(
        {**TIGHT, "solver.max_step_cuts": 0, "stages.0.load_steps": 2})
    f_cut, theta = jaxdem.differentiable(cut, params)
    f_two, _ = jaxdem.differentiable(two, params)
    j_cut = jax.tree.leaves(jax.jacfwd(f_cut)(theta))
    j_two = jax.tree.leaves(jax.jacfwd(f_two)(theta))
    assert all(np.all(np.isfinite(np.asarray(j))) for j in j_cut)
    assert any(np.any(np.asarray(j) != 0) for j in j_cut)
    for a, b in zip(j_cut, j_two, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-15)
