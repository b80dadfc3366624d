"""What the command line prints: the scene's one-line summary (blocks, joints, ...), its
name with the ``--set`` overrides, and the summaries after a run (status, stability,
monitors table, contacts, timings), a sweep, and each back-analysis iteration and fit.

Takes a Scene or a result object and returns text (``print_iteration`` prints it); the
rock mass of a ``[domain]`` and the solver's stage plan are imported inside the functions
that need them. Used by :mod:`jaxdem.cli._commands`.
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path
from typing import Any


def _count(scene: Any, name: str) -> int:
    try:
        return len(getattr(scene, name, None) or ())
    except TypeError:
        return 0


def scene_name(scene: Any, path: Path, overrides: dict[str, Any] | None = None) -> str:
    """The scene's name, with the ``--set`` overrides it was solved with."""
    name = str(getattr(scene, "name", None) or path.stem)
    if overrides:
        name += " (--set " + " ".join(f"{k}={v}" if isinstance(v, str) else f"{k}={v:g}"
                                      for k, v in overrides.items()) + ")"
    return name


def stage_count(scene: Any) -> int:
    """Stages the progress line numbers: the stages run after the initial state
    (``[[stages]]``, or the one the solver makes for excavations and supports); the
    initial state (loading or in-situ) is named, not counted."""
    from jaxdem.solver import stage_plan

    return len(stage_plan(scene))


def scene_summary(scene: Any) -> str:
    """'496 blocks (496 generated), 2 joints, 3 discontinuities, ...' for the parts the
    scene has; a [domain]'s rock mass is generated (host NumPy, fast) to count its blocks."""
    explicit = _count(scene, "blocks")
    generated = 0
    if getattr(scene, "domain", None) is not None:
        from jaxdem.rockmass import generate

        generated = len(generate(scene).pieces)
    n = explicit + generated
    blocks = plural(n, "block")
    if generated:
        blocks += f" ({generated:,} generated" + (f", {explicit} explicit)" if explicit else ")")
    parts = [blocks, plural(_count(scene, "joints"), "joint")]
    for name in ("discontinuities", "boundaries", "bolts", "monitors", "stages"):
        n = _count(scene, name)
        if n:
            parts.append(f"{n} {name}" if n != 1 else f"1 {_singular(name)}")
    return ", ".join(parts)


def plural(n: int, word: str) -> str:
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def _singular(name: str) -> str:
    return {"discontinuities": "discontinuity", "boundaries": "boundary"}.get(name, name[:-1])


def result_summary(result: Any) -> str:
    """Status, stability, monitors table and timings, as printed after a run."""
    lines = [f"status: {result.status}: {result.message}"]
    if result.stable and result.converged:
        lines.append("stable: yes")
    elif result.stable:
        # No mechanism was found, but no admissible equilibrium either (the iteration
        # limit, an overflow, a state that breaks the law): whether the rock stands is
        # not known, and "stable: yes" would say it does.
        lines.append(f"stable: not known (no admissible equilibrium: {result.status})")
    else:
        ids = [str(i) for i in result.moving_blocks]
        moving = ", ".join(ids[:20])
        more = f" (+{len(ids) - 20} more)" if len(ids) > 20 else ""
        lines.append(f"stable: NO, moving blocks: {moving}{more}" if moving else "stable: NO")
    lines += [f"warning: {w}" for w in getattr(result, "warnings", None) or []]
    lines += _monitor_table(result.monitors or {})
    lines += _bolt_summary(getattr(result, "bolts", None) or [])
    contacts = result.contacts or {}
    if contacts:
        lines.append(
            f"contacts: {contacts.get('total', 0)} total, {contacts.get('open', 0)} open, "
            f"{contacts.get('slipping', 0)} slipping"
        )
    timing = result.timing or {}
    lines.append(
        "time: "
        + ", ".join(
            f"{k} {float(timing.get(f'{k}_s', 0.0)):.2f} s" for k in ("build", "compile", "solve")
        )
    )
    return "\n".join(lines)


def _bolt_summary(bolts: list[dict[str, Any]]) -> list[str]:
    """'bolts: 2 yielded, 1 not installed; largest force 20 kN (bolt 0)': the bolts by
    state, and the largest force of those installed (a bolt whose stage never ran
    carries nothing, and is not counted as an elastic bolt at 0 kN)."""
    if not bolts:
        return []
    states: dict[str, int] = {}
    for bolt in bolts:
        state = str(bolt.get("state", ""))
        states[state] = states.get(state, 0) + 1
    line = "bolts: " + ", ".join(f"{n} {state}" for state, n in states.items())
    installed = [b for b in bolts if b.get("state") != "not installed"]
    if installed:
        top = max(installed, key=lambda b: abs(float(b.get("force", 0.0))))
        line += f"; largest force {float(top.get('force', 0.0)):.4g} kN (bolt {top.get('id')})"
    if len(installed) < len(bolts):
        line += "; not installed: the analysis stopped before their stage"
    return [line]


def _monitor_table(monitors: dict[str, dict[str, Any]]) -> list[str]:
    """Rows in mm: point (ux, uy, |u|) or section (convergence, along)."""
    if not monitors:
        return []
    width = max(8, *(len(name) for name in monitors))
    rows = [
        f"{'monitor':<{width}}  {'ux (mm)':>10} {'uy (mm)':>10} {'|u| (mm)':>10} {'conv. (mm)':>11}"
    ]
    blank = ""
    for name, entry in monitors.items():
        if "displacement" in entry:
            ux, uy = (1e3 * float(v) for v in entry["displacement"][:2])
            rows.append(
                f"{name:<{width}}  {ux:>10.4g} {uy:>10.4g} {(ux**2 + uy**2) ** 0.5:>10.4g}"
                f" {blank:>11}"
            )
        elif "convergence" in entry:
            c = 1e3 * float(entry["convergence"])
            rows.append(f"{name:<{width}}  {blank:>10} {blank:>10} {blank:>10} {c:>11.4g}")
        else:
            rows.append(f"{name:<{width}}  {entry}")
    return rows


def print_iteration(event: dict[str, Any]) -> None:
    """One line per back-analysis iteration, on stderr like the solver's progress."""
    params = "  ".join(f"{path}={value:.5g}" for path, value in event["params"].items())
    if event.get("start") and event["iteration"] == 0:
        print(f"restart {event['start']}: the misfit so far is more than the stds explain",
              file=sys.stderr, flush=True)
    print(
        f"it {event['iteration']:>3}  misfit {event['misfit']:.4e}  "
        f"|grad| {event['gradient_norm']:.2e}  {params}",
        file=sys.stderr,
        flush=True,
    )


def sweep_summary(result: Any) -> str:
    b, pr = result.batch, result.probability
    t = b.timing
    lines = [f"{len(b.stable)} samples: {int(b.converged.sum())} in equilibrium, "
             f"{pr['unstable']} mechanisms, {pr['undecided']} without an answer "
             f"({result.mode}: {t['solve_s']:.2f} s solving, {t['compile_s']:.1f} s compiling, "
             f"{t['chunk']} samples per batch, {t.get('workers', 1)} at a time)"]
    stops = collections.defaultdict(list)  # stage -> load factors of the samples that stopped
    for status, stop in zip(b.status, b.stopped or [None] * len(b.status), strict=True):
        if stop is not None and status != "mechanism":
            stops[stop["stage"]].append(stop["load_factor"])
    for stage, at in stops.items():
        span = (f"{min(at):.3g}" if min(at) == max(at) else f"{min(at):.3g} to {max(at):.3g}")
        lines.append(f"{len(at)} without an answer stopped in stage {stage} at load factor "
                     f"{span} (sweep.csv: stopped_stage, stopped_load_factor)")
    if pr["decided"]:
        lo, hi = pr["ci95"]
        lines.append(f"probability of instability {pr['p_unstable']:.3f} "
                     f"(95% interval {lo:.3f} to {hi:.3f}, {pr['decided']} samples)")
    loose = sum(1 for ids in (b.loose_blocks or []) if ids)
    if loose:
        lines.append(f"{loose} samples removed loose blocks that fell free and ran the stage "
                     f"again without them, as a single run does (sweep.csv: loose_blocks)")
    if pr.get("small"):
        lines.append(f"{pr['small']} of the {pr['unstable']} mechanisms are small: their moving "
                     f"blocks together no larger than solver.max_loose_volume, pieces working "
                     f"loose rather than a collapse (sweep.csv: moving_volume, "
                     f"small_mechanism)")
    for name, bars in result.tornado.items():
        top = ", ".join(f"{bar['path']} {bar['swing'] * 1e3:+.3g} mm" for bar in bars[:3])
        lines.append(f"tornado {name}: {top}")
    return "\n".join(lines)


def back_analysis_summary(result: Any) -> str:
    """Estimates with standard deviations, the misfit, warnings and status."""
    width = max(9, *(len(p) for p in result.paths))
    lines = [f"{'parameter':<{width}}  {'start':>11} {'estimate':>11} {'std':>10} {'std/est':>8}"]
    for path in result.paths:
        start, estimate, std = result.start[path], result.params[path], result.std[path]
        row = f"{path:<{width}}  {start:>11.5g} {estimate:>11.5g}"
        if not result.identifiable[path]:
            row += "  not identifiable"
        else:
            relative = f"{100 * std / abs(estimate):.2g}%" if estimate else ""
            row += f" {std:>10.3g} {relative:>8}"
        lines.append(row)
    evaluations = result.evaluations
    lines.append(
        f"misfit {result.misfit:.4g} (start {result.history[0]:.4g}) for "
        f"{len(result.observations)} observations after {result.iterations} iterations; "
        f"solves: {evaluations.get('gradient', 0)} with derivatives, "
        f"{evaluations.get('forward', 0)} values only"
    )
    if result.warnings:
        lines.append("warnings:")
        lines += [f"  - {warning}" for warning in result.warnings]
    lines.append(f"status: {result.status}: {result.message}")
    return "\n".join(lines)
