"""The Newton loop's ``loop`` (jaxdem.core._substep._newton): a sub-step run with a loop
that hands each iteration to the host (benchmarks/newton_trace.py's) is the sub-step of
the default ``jax.lax.while_loop``, and keeps one record an iteration, the last the
iteration that ended it; each record names the slot whose closing bounded its step."""

from __future__ import annotations

import functools
import importlib.util
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scenes import jointed_tunnel, slide_and_stop

from jaxdem.core import model as model_mod
from jaxdem.core._substep import substep
from jaxdem.core.kinematics import block_travel
from jaxdem.core.loads import make_loads
from jaxdem.core.state import OPEN
from jaxdem.scene import parse_scene

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "benchmarks" / "newton_trace.py"


def _tool():
    """benchmarks/newton_trace.py as a module (not on the import path)."""
    spec = importlib.util.spec_from_file_location("newton_trace", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_recording_loop_gives_the_substep_and_one_record_an_iteration():
    recording_loop = _tool().recording_loop
    # A jointed tunnel with its bolts, loaded by its weight from rest: a first sub-step of
    # several iterations in which the slip tangent is tried (the bolts yield).
    model, state, _ = model_mod.build(parse_scene(jointed_tunnel(water=False)))
    loads = make_loads(model, model.f_ext)
    warm = jnp.array(False)
    plain = jax.jit(substep)(model, state, loads, warm)
    records = []
    kept = jax.jit(functools.partial(substep, loop=recording_loop(records)))(
        model, state, loads, warm)
    jax.block_until_ready(kept)
    newton = plain[2]
    assert int(newton.it) >= 3 and any(bool(r.trying) for r in records)
    assert [int(r.it) for r in records] == list(range(1, int(newton.it) + 1))
    assert bool(records[-1].done) and not any(bool(r.done) for r in records[:-1])
    # The same program but for the callback: the same iterates to round-off.
    np.testing.assert_allclose(np.asarray(records[-1].du), np.asarray(newton.du), rtol=0,
                               atol=1e-12 * float(np.max(np.abs(np.asarray(newton.du)))))
    np.testing.assert_array_equal(np.asarray(records[-1].st), np.asarray(newton.st))
    np.testing.assert_allclose(np.asarray(kept[0].centroid), np.asarray(plain[0].centroid),
                               rtol=0, atol=1e-12)


def test_the_step_that_lands_a_sliding_block_is_cut_by_the_slot_it_closes():
    # Seed example 1 with a gap of 2 cm: the block slides down its 30 degree slope
    # (friction 15 degrees), a mechanism that the iteration follows by a step beyond
    # Newton's, until the block meets the fixed block below it. That step is cut where
    # the slot between the two closes: open at the evaluation it was taken from, with the
    # gap between their faces (2 cm, the slope's direction is normal to the stop's face),
    # closed at the next, the block moved by that gap.
    tool, gap = _tool(), 0.02
    model, state, _ = model_mod.build(parse_scene(slide_and_stop(gap=gap)))
    loads = make_loads(model, model.f_ext)
    records = []
    jax.jit(functools.partial(substep, loop=tool.recording_loop(records)))(
        model, state, loads, jnp.array(False))
    cut = [i for i, r in enumerate(records) if int(r.cut_by) >= 0]
    assert len(cut) == 1 and cut[0] + 1 < len(records)
    i = cut[0]
    k = int(records[i].cut_by)
    # The step was taken from the iterate before it (from rest in the first iteration).
    before = np.asarray(records[i - 1].du) if i else np.zeros_like(np.asarray(records[i].du))
    slots = tool.slots_of(model, state, loads)
    a, b = int(slots["a"][k]), int(slots["b"][k])
    assert {a, b} == {1, 2}  # the sliding block and the stop
    at = slots["gap"][k] + slots["Bn"][k] @ np.concatenate([before[a], before[b]])
    assert int(records[i].st[k]) == OPEN and abs(at - gap) <= 0.01 * gap
    assert int(records[i + 1].st[k]) != OPEN and 0.0 < float(records[i].scale) < 1.0
    moved = np.asarray(block_travel(model, jnp.asarray(records[i].du - before)))[1]
    assert abs(moved - gap) <= 0.01 * gap


def test_the_trace_command_lists_the_increments_and_traces_a_substep():
    out = subprocess.run(
        [sys.executable, str(TOOL),
         str(ROOT / "examples" / "block_on_incline.toml"), "--increment", "0", "--substep", "0"],
        capture_output=True, text=True, timeout=600, check=True).stdout
    assert "increment   0" in out and "converged" in out
    # The sub-step's line and one line an iteration of its trace, the last within tolerance.
    its = int(out.split("\n   0 ", 1)[1].split()[0])
    table = out.split("kn x gap kN/m\n", 1)[1].splitlines()[:its]
    assert [int(line.split()[0]) for line in table] == list(range(its))
    assert float(table[-1].split()[1]) <= 1.0
