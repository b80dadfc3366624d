"""Where one increment's Newton iterations go: its sub-steps replayed one by one, and the
iterations of the long ones one by one (a diagnostic, not a benchmark: it measures no
error).

The scene is solved as ``jaxdem.solve`` solves it up to the increment asked for (numbered
from 0 in the order they run, the in-situ or loading state's first); that increment's
inputs are kept, and it is replayed sub-step by sub-step through the jitted
``jaxdem.core._substep.substep``, as ``jaxdem.core.increment`` chains them (``warm`` after a
balanced sub-step). Each sub-step that took at least ``--trace-from`` iterations (or the
one ``--substep`` names) is run again with each Newton iteration handed to the host
(``_newton``'s ``loop``: a ``while_loop`` whose body also calls back with its carry), and
each iteration printed: the residual (the largest free block's, in tolerances), the
slots whose state changed and those slipping, the slip tangent tried / used, the stall
count, the slots held frozen, how far the step moved the blocks (the largest travel of
the step, m), the block furthest out of balance, the share of Newton's step taken and,
where a closing slot bounded it, that slot: its two blocks, its state at the iteration's
evaluation (open, stick, slip), its gap there (m) and its normal spring's force over that
gap, kn x gap (kN/m: how far from closing it was, in force).

    PYTHONPATH=. python benchmarks/newton_trace.py SCENE                 # list the increments
    PYTHONPATH=. python benchmarks/newton_trace.py SCENE --increment 3   # replay the 4th
    PYTHONPATH=. python benchmarks/newton_trace.py SCENE --increment 3 --substep 14 --set k=v

The replay runs other programs than the increment's (each sub-step compiled on its own),
whose arithmetic agrees with it to round-off: where the iteration is chaotic (seed example
3's failing load step) the replay parts from the run's path after a few sub-steps, and its
figures describe the kind of work, not the run's own sub-steps.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdem import config  # noqa: E402

config.configure()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxdem  # noqa: E402
import jaxdem.solver as solver_mod  # noqa: E402
from jaxdem.core import _substep  # noqa: E402
from jaxdem.core.kinematics import block_travel  # noqa: E402
from jaxdem.core.state import OPEN, SLIP, STICK  # noqa: E402
from jaxdem.core.status import Status  # noqa: E402
from jaxdem.scene import parse_set_arguments  # noqa: E402


class _Kept(Exception):
    """Ends the solve once the increment asked for has run."""


def capture(scene, overrides: dict, index: int | None):
    """Solve ``scene`` to increment ``index`` (all of it where None), printing each
    increment's record; returns (that increment's (model, state, loads, report) or None,
    how many increments ran)."""
    kept, records, printed = {}, [], [0]
    original = solver_mod.run_increment

    def run_increment(model, state, loads, tangents=None, quick=False):
        out = original(model, state, loads, tangents, quick)
        records.append(out[2])
        if len(records) - 1 == index:
            kept.update(model=model, state=state, loads=loads, info=out[2])
        return out

    def progress(event):
        if len(records) == printed[0]:  # an event of the stage, not of a new increment
            return
        printed[0] = len(records)
        info = records[-1]
        print(f"increment {len(records) - 1:3d}  {event['stage']:>12} step {event['step']}/"
              f"{event['n_steps']}  {Status.of(info.status).label:>16}  iterations "
              f"{int(info.iterations):5d}  sub-steps {int(info.substeps):3d}", flush=True)
        if kept:
            raise _Kept

    solver_mod.run_increment = run_increment
    try:
        jaxdem.solve(scene, set=overrides or None, progress=progress)
    except _Kept:
        pass
    finally:
        solver_mod.run_increment = original
    if not kept:
        return None, len(records)
    return (kept["model"], kept["state"], kept["loads"], kept["info"]), len(records)


def recording_loop(records: list):
    """A ``loop`` for ``_newton``: :func:`jax.lax.while_loop` whose body also hands each
    iteration's :class:`jaxdem.core._substep.Iterate` to the host, appended to ``records``
    (a ``jax.debug.callback``: the sub-step stays one compiled program)."""
    def keep(c):
        jax.debug.callback(records.append, c)
        return c

    def loop(cond, body, init):
        return jax.lax.while_loop(cond, lambda c: keep(body(c)), init)

    return loop


STATES = {OPEN: "open", STICK: "stick", SLIP: "slip"}


def slots_of(model, state, loads):
    """The slots a sub-step's Newton iteration works on at ``state`` (as
    ``jaxdem.core._substep.newton_and_commit`` packs them): their blocks ``a``, ``b``,
    rows ``Bn``, gaps at the sub-step's start and normal stiffness ``kn``, as NumPy."""
    @jax.jit
    def packed(model, state, loads):
        mdl, sub, st0, _, _ = _substep.prepare_substep(model, state, loads, rows=False)
        p = _substep.pack_slots(mdl, sub, st0, state.centroid)[0]
        return dict(a=p.geo.a, b=p.geo.b, Bn=p.Bn, gap=p.geo.gap, kn=p.prop.kn)

    return {k: np.asarray(v) for k, v in packed(model, state, loads).items()}


def iteration_table(model, records, slots) -> None:
    """One line an iteration of a sub-step replayed with :func:`recording_loop`; the states
    that changed are counted from the first iteration's (those of its evaluation). A step
    that a closing slot bounded names it (``slots``: :func:`slots_of`), with its state and
    gap at the evaluation the step was taken from."""
    print(f"{'it':>4} {'residual/tol':>13} {'changed':>7} {'slip':>5} {'try':>3} "
          f"{'tan':>3} {'stall':>5} {'frozen':>6} {'step travel m':>13} {'worst':>6} "
          f"{'scale':>8}  cut by a closing slot: blocks, state, gap m, kn x gap kN/m")
    before_st, before_du = np.asarray(records[0].st), np.zeros_like(np.asarray(records[0].du))
    for c in records:
        st = np.asarray(c.st)
        moved = float(np.max(np.asarray(block_travel(model, jnp.asarray(c.du - before_du)))))
        cut = ""
        k = int(c.cut_by)
        if k >= 0:
            a, b = int(slots["a"][k]), int(slots["b"][k])
            gap = slots["gap"][k] + slots["Bn"][k] @ np.concatenate([before_du[a], before_du[b]])
            cut = (f"{a}-{b} {STATES.get(int(st[k]), int(st[k]))} {gap:.3g} "
                   f"{slots['kn'][k] * gap:.3g}")
        print(f"{int(c.it) - 1:4d} {float(c.rprev):13.4g} {int(np.sum(st != before_st)):7d} "
              f"{int(np.sum(st == SLIP)):5d} {int(c.trying):3d} "
              f"{int(c.tangent):3d} {int(c.stall):5d} {int(np.sum(c.frozen)):6d} "
              f"{moved:13.3g} {int(c.unbalanced.ids[0]):6d} {float(c.scale):8.3g}  {cut}")
        before_st, before_du = st, np.asarray(c.du)


def replay(model, state, loads, substeps: int, trace_from: int, only: int | None) -> None:
    """The increment's sub-steps one by one; the Newton iterations of the long ones."""
    one = jax.jit(_substep.substep)
    residual, total, t0 = np.inf, 0, time.perf_counter()
    print(f"{'sub':>4} {'its':>4} {'conv':>4} {'clip':>4} {'residual':>9} {'travel m':>9} "
          f"{'(block)':>7} {'new failures':>12} {'frozen':>6}  worst blocks")
    for k in range(substeps):
        warm = jnp.array(k > 0 and residual <= model.tol)
        new, du, c, need, _, _ = one(model, state, loads, warm)
        travel = np.asarray(block_travel(model, du))
        residual, total = float(c.rnorm), total + int(c.it)
        if bool(need.overflowed(model, state)):
            print(f"sub-step {k}: a capacity overflowed (the run grew it and did the increment "
                  "again): not replayed further")
            break
        print(f"{k:4d} {int(c.it):4d} {int(c.converged):4d} {int(c.clipped):4d} "
              f"{residual:9.2e} {travel.max():9.2e} {int(travel.argmax()):7d} "
              f"{str(bool(need.new_failures)):>12} {int(np.sum(c.frozen)):6d}  "
              f"{np.asarray(c.unbalanced.ids)[:3].tolist()}", flush=True)
        if (only is None and int(c.it) >= trace_from) or only == k:
            records = []
            traced = jax.jit(functools.partial(_substep.substep, loop=recording_loop(records)))
            jax.block_until_ready(traced(model, state, loads, warm))
            iteration_table(model, records, slots_of(model, state, loads))
        state = new
        if bool(c.converged) and travel.max() <= model.touch_tol and not bool(need.new_failures):
            break
    print(f"replayed {k + 1} sub-steps, {total} iterations, {time.perf_counter() - t0:.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--increment", type=int, help="replay this one (0 = the first to run)")
    ap.add_argument("--substeps", type=int, help="at most this many (default: the run's)")
    ap.add_argument("--trace-from", type=int, default=100,
                    help="trace each sub-step that took at least this many iterations")
    ap.add_argument("--substep", type=int, help="trace this sub-step alone")
    ap.add_argument("--set", nargs="+", default=[], metavar="PATH=VALUE")
    args = ap.parse_args()
    scene = jaxdem.load_scene(args.scene)
    kept, count = capture(scene, parse_set_arguments(args.set), args.increment)
    if kept is None:
        if args.increment is not None:
            sys.exit(f"no increment {args.increment}: the scene ran increments 0 to "
                     f"{count - 1}")
        return
    model, state, loads, info = kept
    print(f"\nincrement {args.increment} again, sub-step by sub-step:")
    replay(model, state, loads, args.substeps or int(info.substeps), args.trace_from, args.substep)


if __name__ == "__main__":
    main()
