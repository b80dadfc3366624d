"""The Newton loop's ``loop`` (jaxdem.core._substep._newton): a sub-step run with a loop
that hands each iteration to the host (benchmarks/newton_trace.py's) is the sub-step of
the default ``jax.lax.while_loop``, and keeps one record an iteration, the last the
iteration that ended it."""

from __future__ import annotations

import functools
import importlib.util
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scenes import jointed_tunnel

from jaxdem.core import model as model_mod
from jaxdem.core._substep import substep
from jaxdem.core.loads import make_loads
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


def test_the_trace_command_lists_the_increments_and_traces_a_substep():
    out = subprocess.run(
        [sys.executable, str(TOOL),
         str(ROOT / "examples" / "block_on_incline.toml"), "--increment", "0", "--substep", "0"],
        capture_output=True, text=True, timeout=600, check=True).stdout
    assert "increment   0" in out and "converged" in out
    # The sub-step's line and one line an iteration of its trace, the last within tolerance.
    its = int(out.split("\n   0 ", 1)[1].split()[0])
    table = out.split("worst block\n", 1)[1].splitlines()[:its]
    assert [int(line.split()[0]) for line in table] == list(range(its))
    assert float(table[-1].split()[1]) <= 1.0
