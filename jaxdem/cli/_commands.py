"""The subcommands of ``jaxdem`` (``demo``, ``run``, ``check``, ``sweep``, ``fos``,
``grc``, ``back-analyse``) and the steps they share: load the scene with its ``--set`` overrides,
refuse an unusable ``--out`` before any computation, solve, write JSON and figures, and
turn the outcome into an exit status (``EXIT_OK``, ``EXIT_INVALID_INPUT``,
``EXIT_NOT_CONVERGED``).

Each ``cmd_*`` takes the parsed ``argparse.Namespace`` (from :mod:`jaxdem.cli._parser`) and
returns the exit status; invalid input raises ``InputError`` or ``SceneError`` for
:func:`jaxdem.cli.main` to print as one line. JAX, the solver and matplotlib are imported
inside the commands, so that ``jaxdem --help`` answers at once.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from jaxdem.cli._progress import ProgressBar, SampleBar
from jaxdem.cli._summaries import (
    back_analysis_summary,
    plural,
    print_iteration,
    result_summary,
    scene_name,
    scene_summary,
    stage_count,
    sweep_summary,
)

EXIT_OK = 0
EXIT_INVALID_INPUT = 2
EXIT_NOT_CONVERGED = 3

#: Statuses that count as an answer (exit 0); every other status exits 3.
SOLVED_STATUSES = ("converged", "mechanism")

MAX_TRIALS = 1024
"""Most ``fos --trials`` (factors solved together in one batch per round)."""
MAX_FIT_ITERATIONS = 10_000
"""Most ``back-analyse --max-iterations`` (each iteration solves the scene at least once)."""
MAX_FIT_RESTARTS = 100
"""Most ``back-analyse --restarts`` (each restart is a whole local fit)."""


class InputError(Exception):
    """Invalid input found by the command line itself (exit status 2)."""


# Wall-clock marks of a command's phases (time.time(), s), written as JSON to
# $JAXDEM_PHASES when that is set (benchmarks/bench_time_to_answer.py reads them).
_PHASES: dict[str, float] = {}


def _mark(name: str) -> None:
    import time

    _PHASES[name] = time.time()


def _write_phases(extra: dict[str, Any] | None = None) -> None:
    target = os.environ.get("JAXDEM_PHASES")
    if target:
        Path(target).write_text(json.dumps({**_PHASES, **(extra or {})}))


def cmd_demo(args: argparse.Namespace) -> int:
    """Solve the bundled demo scene ``jaxdem/data/demo.toml``."""
    from importlib import resources

    resource = resources.files("jaxdem").joinpath("data", "demo.toml")
    if not resource.is_file():
        raise InputError("the bundled demo scene jaxdem/data/demo.toml is missing")
    view = _check_view(args)
    with resources.as_file(resource) as path:
        return _solve_and_report(path, Path(args.out), overrides={}, vtk=args.vtk,
                                 figures=not args.no_figures, view=view)


def cmd_run(args: argparse.Namespace) -> int:
    """Solve a scene file with ``--set`` overrides and write results and figures."""
    path = Path(args.scene)
    out = Path(args.out) if args.out else Path("out") / path.stem
    overrides = _set_overrides(args)
    view = _check_view(args)
    return _solve_and_report(path, out, overrides=overrides, vtk=args.vtk,
                             figures=not args.no_figures, view=view)


def _check_view(args: argparse.Namespace) -> tuple[float, ...] | None:
    """``--view X0 X1 Y0 Y1`` (m), checked before any computation; None without it."""
    view = getattr(args, "view", None)
    if view is None:
        return None
    x0, x1, y0, y1 = view
    if not (all(math.isfinite(v) for v in view) and x0 < x1 and y0 < y1):
        raise InputError(f"--view must be X0 X1 Y0 Y1 (m) with X0 < X1 and Y0 < Y1 "
                         f"(got {' '.join(f'{v:g}' for v in view)})")
    return tuple(view)


def cmd_check(args: argparse.Namespace) -> int:
    """Validate a scene file and draw its blocks to ``DIR/check.png``."""
    from jaxdem.plots import plot_scene_check

    path = Path(args.scene)
    out = Path(args.out) if args.out else Path("out") / path.stem
    scene = _load(path, overrides={})
    _check_out(out)
    print(f"OK: {scene_summary(scene)}")
    figure = plot_scene_check(scene, out / "check.png")
    print(f"wrote {figure}")
    return EXIT_OK


def cmd_back_analyse(args: argparse.Namespace) -> int:
    """Fit scene parameters to measured monitor values; write back_analysis.json and figures."""
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _set_overrides(args)
    bounds = _parse_bounds([item for group in args.bounds or [] for item in group])
    if not 0 <= args.max_iterations <= MAX_FIT_ITERATIONS:
        what = ">= 0" if args.max_iterations < 0 else f"<= {MAX_FIT_ITERATIONS:,}"
        raise InputError(f"--max-iterations must be {what} (got {args.max_iterations})")
    if args.restarts is not None and not 0 <= args.restarts <= MAX_FIT_RESTARTS:
        what = ">= 0" if args.restarts < 0 else f"<= {MAX_FIT_RESTARTS}"
        raise InputError(f"--restarts must be {what} (got {args.restarts})")
    scene = _load(path, overrides)
    _check_out(out)

    from inverse import back_analyse, read_observations
    from inverse.backanalysis import NO_EQUILIBRIUM_AT_START
    from inverse.plots import write_figures
    from jaxdem.scene import SceneError

    observations = read_observations(args.observed)
    print(f"{scene_name(scene, path, overrides)}: {scene_summary(scene)}")
    print(f"fitting {', '.join(args.fit)} to {len(observations)} observations "
          f"({args.optimizer}, at most {args.max_iterations} iterations)")
    try:
        result = back_analyse(
            scene,
            observations,
            args.fit,
            bounds=bounds,
            optimizer=args.optimizer,
            max_iterations=args.max_iterations,
            **({} if args.restarts is None else {"restarts": args.restarts}),
            progress=print_iteration,
        )
    except SceneError:
        raise
    except Exception as err:  # noqa: BLE001 - exit codes are 0, 2 and 3 only
        return _failed("back-analyse", err)
    written = [_write_json(result.to_dict(), out / "back_analysis.json")]
    if result.status != NO_EQUILIBRIUM_AT_START:
        written += write_figures(result, out)
    print(back_analysis_summary(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_NOT_CONVERGED if result.status == NO_EQUILIBRIUM_AT_START else EXIT_OK


def cmd_sweep(args: argparse.Namespace) -> int:
    """Solve a scene over sampled parameters (batched); write sweep.csv, sweep.json, tornado.png."""
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _set_overrides(args)
    _check_chunk(args)
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0 (got {args.seed})")
    scene = _load(path, overrides)
    _check_out(out)

    from jaxdem.plots import plot_tornado
    from jaxdem.sweep import Variable, draw, sweep, tornado_solves

    variables = [Variable.parse(v) for group in args.vary for v in group]
    method = args.method or ("grid" if all(v.kind == "range" for v in variables) else "lhs")
    theta = draw(variables, args.samples, method, args.seed)
    n = theta.shape[0]
    p = len(variables)
    points, new = 1 + 2 * p, tornado_solves(variables, theta)
    shared = "" if new == points else f" ({points - new} of its {points} points are samples)"
    print(f"{scene_name(scene, path, overrides)}: {scene_summary(scene)}")
    if method == "grid":
        how = (f"grid: {args.samples} levels x {plural(p, 'parameter')} = {n:,} solves "
               "(--samples is the levels per parameter)")
    else:
        how = f"{method}: {n:,} samples (seed {args.seed})"
    print(f"sweep {how}, plus {new} for the tornado{shared}; "
          + "; ".join(f"{v.path} {v.describe()}" for v in variables), flush=True)
    bar = SampleBar()
    from jaxdem.scene import SceneError

    try:
        with bar:
            result = sweep(scene, variables, args.samples, method=method, seed=args.seed,
                           chunk=args.chunk, workers=args.workers, progress=bar)
    except SceneError:
        raise
    except Exception as err:  # noqa: BLE001 - exit codes are 0, 2 and 3 only
        return _failed("sweep", err)
    written = [result.to_csv(out / "sweep.csv"), _write_json(result.to_dict(), out / "sweep.json")]
    if result.tornado:
        written.append(plot_tornado(result.tornado, out / "tornado.png"))
    print(sweep_summary(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def cmd_fos(args: argparse.Namespace) -> int:
    """Factor of safety by strength reduction; write fos.json, mechanism.png and fos.png."""
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _set_overrides(args)
    if not 2 <= args.trials <= MAX_TRIALS:
        raise InputError(f"--trials must be an integer from 2 to {MAX_TRIALS} "
                         f"(got {args.trials})")
    if not 0 < args.tolerance < float("inf"):
        raise InputError(f"--tolerance must be a number > 0 (got {args.tolerance})")
    scene = _load(path, overrides)
    _check_out(out)

    from jaxdem.fos import factor_of_safety, write_outputs

    def report(r: dict[str, Any]) -> None:
        trials = ", ".join(f"{f:.4g} {s if s != 'converged' else 'stable'}"
                           for f, s in zip(r["factors"], r["outcomes"], strict=True))
        lo, hi = (("-" if x is None else f"{x:.5g}") for x in r["bracket"])
        print(f"round {r['round']}: {trials} -> bracket [{lo}, {hi}]", file=sys.stderr,
              flush=True)

    print(f"{scene_name(scene, path, overrides)}: {scene_summary(scene)}")
    result = factor_of_safety(scene, intact=args.intact, tensile=args.tensile,
                              trials=args.trials, rtol=args.tolerance, progress=report)
    written = write_outputs(result, scene, out)
    print(result.message)
    if result.mechanism is not None:
        m = result.mechanism
        moving = ", ".join(str(i) for i in m["moving_blocks"][:20])
        print(f"at F = {m['factor']:.5g}: {m['status']}"
              + (f", moving blocks: {moving}" if moving else ""))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK if result.decided else EXIT_NOT_CONVERGED


# --- jaxdem grc: the ground reaction curve (jaxdem.grc) ---------------------------------

#: ground_reaction's argument names -> the grc command's options (for messages).
GRC_OPTIONS = {"excavation": "--excavation", "levels": "--levels", "p0": "--p0",
               "start": "--from", "monitor": "--monitor",
               "support.stiffness": "--support-stiffness",
               "support.capacity": "--support-capacity",
               "support.installed_at": "--install-convergence"}


def cmd_grc(args: argparse.Namespace) -> int:
    """Ground reaction curve of an excavation in one batch; write grc.json and grc.png."""
    from jaxdem.scene import SceneError

    path = Path(args.scene)
    out = Path(args.out)
    overrides = _set_overrides(args)
    _check_chunk(args)
    line = [args.support_stiffness, args.support_capacity]
    if any(x is not None for x in line) or args.install_convergence is not None:
        missing = [o for o, x in zip(("--support-stiffness", "--support-capacity"), line,
                                     strict=True) if x is None]
        if missing:
            raise InputError(f"{missing[0]}: required with the other support line options")
    scene = _load(path, overrides)
    _check_out(out)
    excavation = args.excavation
    if excavation is None:
        names = [e.name for e in scene.excavations]
        if len(names) != 1:
            listed = ", ".join(repr(n) for n in names) or "none"
            raise InputError(f"--excavation: required, the scene has {len(names)} excavations "
                             f"({listed})")
        excavation = names[0]
    support = None if line[0] is None else dict(
        stiffness=line[0], capacity=line[1], installed_at=args.install_convergence or 0.0)

    from jaxdem.grc import check_inputs, ground_reaction, write_outputs

    options = dict(p0=args.p0, start=args.start, support=support, monitor=args.monitor)
    try:
        checked = check_inputs(scene, excavation, args.levels, **options)
    except SceneError as err:
        if err.path in GRC_OPTIONS:
            raise InputError(f"{GRC_OPTIONS[err.path]}: {err.problem}") from None
        raise
    print(f"{scene_name(scene, path, overrides)}: {scene_summary(scene)}")
    how = "given" if checked["p0_from"] == "given" else "mean in-situ normal stress at the face"
    print(f"ground reaction curve of {excavation!r}: {plural(args.levels, 'level')} from "
          f"{checked['start']:.4g} to 0 kPa in one batch (p0 = {checked['p0']:.4g} kPa, {how})",
          flush=True)
    # matplotlib's import and fonts beside the solve, which runs without Python's lock.
    threading.Thread(target=_prepare_figures, daemon=True, name="jaxdem-figures").start()
    bar = SampleBar()
    try:
        with bar:
            curve = ground_reaction(scene, excavation, args.levels, chunk=args.chunk,
                                    workers=args.workers, progress=bar, **options)
    except SceneError:
        raise
    except Exception as err:  # noqa: BLE001 - exit codes are 0, 2 and 3 only
        return _failed("grc", err)
    written = write_outputs(curve, out)
    names = list(curve.monitors)
    print(f"{'p kPa':>10} {'status':>16} " + " ".join(f"{n[:14]:>14}" for n in names))
    for i, p in enumerate(curve.pressure):
        values = " ".join(f"{curve.monitors[n][i]:>14.6g}" for n in names)
        print(f"{p:>10.4g} {curve.status[i]:>16} {values}")
    print("(m: a section's convergence, a point's displacement towards the opening)")
    print(curve.message)
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_NOT_CONVERGED if curve.undecided else EXIT_OK


# --- end of jaxdem grc -------------------------------------------------------------------


def _prepare_figures() -> None:
    """Import matplotlib and load its fonts (while the solver's programs compile)."""
    from jaxdem.plots import warm_up

    warm_up()


def _solve_and_report(path: Path, out: Path, overrides: dict[str, Any],
                      vtk: bool = False, figures: bool = True,
                      view: tuple[float, ...] | None = None) -> int:
    _mark("start")
    from jaxdem.core import compile_cache

    fingerprint = _fingerprint(path, overrides)
    if fingerprint is not None:
        compile_cache.warm_start(fingerprint)
    scene = _load(path, overrides)
    _check_out(out)
    print(f"{scene_name(scene, path, overrides)}: {scene_summary(scene)}")
    _mark("loaded")

    from jaxdem import solver

    if figures:
        compile_cache.while_compiling(_prepare_figures)
    _mark("imported")
    bar = ProgressBar(n_stages=stage_count(scene))
    with bar:
        result = solver.solve(scene, progress=bar)
    _mark("solved")
    compile_cache.remember_run()

    data = result.to_dict()
    if overrides:
        # result.json keeps the file's scene name and says what --set changed; the
        # figures' titles carry both.
        data["overrides"] = dict(overrides)
        result = dataclasses.replace(result, scene=scene_name(scene, path, overrides))
    out.mkdir(parents=True, exist_ok=True)
    (out / "result.json").write_text(json.dumps(data, indent=2))
    # The answer first: the summary and result.json do not wait for the figures.
    print(result_summary(result), flush=True)
    _mark("answered")
    written = [out / "result.json"]
    if figures:
        from jaxdem.plots import write_figures

        written += write_figures(result, out, **({"view": view} if view else {}))
    _mark("figures")
    if vtk:
        from jaxdem.vtk import write_vtk

        written += write_vtk(result, out)

    print("wrote " + ", ".join(str(p) for p in written))
    _mark("end")
    _write_phases({"timing": dict(getattr(result, "timing", None) or {}),
                   "increment": dict(getattr(solver, "COMPILE_TIMES", {}))})
    return EXIT_OK if result.status in SOLVED_STATUSES else EXIT_NOT_CONVERGED


def _fingerprint(path: Path, overrides: dict[str, Any]) -> str | None:
    """What decides a run's programs, known before the scene is built: the scene file's
    bytes and the ``--set`` values (:func:`jaxdem.core.compile_cache.warm_start`); None
    for a file that cannot be read (``_load`` says why)."""
    try:
        text = path.read_bytes()
    except OSError:
        return None
    return hashlib.sha256(text + repr(sorted(overrides.items())).encode()).hexdigest()


def _load(path: Path, overrides: dict[str, Any]) -> Any:
    """Load and validate a scene; every problem (unreadable file included) is a SceneError.

    Its plausibility warnings (values most likely in the wrong unit) are printed on
    stderr, ``warning: materials.rock.E: ...``, before anything is solved."""
    from jaxdem.scene import load_scene

    scene = load_scene(path, set=overrides or None)
    for warning in getattr(scene, "warnings", ()):
        print(f"warning: {warning}", file=sys.stderr, flush=True)
    return scene


def _check_out(out: Path) -> None:
    """Refuse, before any computation, an output folder that cannot be made or written:
    a file in its place or on its path, or a folder without write permission."""
    for folder in (out, *out.parents):
        if folder.exists() or folder.is_symlink():
            if not folder.is_dir():
                raise InputError(f"--out {out}: {folder} exists and is not a folder")
            if not os.access(folder, os.W_OK | os.X_OK):
                raise InputError(f"--out {out}: cannot write in {folder} (permission denied)")
            return


def _set_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The command's ``--set`` groups (``args.set``, a list of lists or None) as a dict."""
    return _parse_overrides([item for group in args.set or [] for item in group])


def _check_chunk(args: argparse.Namespace) -> None:
    """Refuse a ``--chunk`` or ``--workers`` below 1 (exit 2)."""
    if args.chunk is not None and args.chunk < 1:
        raise InputError(f"--chunk must be >= 1 (got {args.chunk})")
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be >= 1 (got {workers})")


def _parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``--set PATH=VALUE`` arguments to a dict; bad syntax raises SceneError (exit 2)."""
    if not items:
        return {}
    from jaxdem.scene import parse_set_arguments

    return dict(parse_set_arguments(list(items)))


def _parse_bounds(items: Sequence[str]) -> dict[str, tuple[float, float]]:
    """``--bounds PATH=LO:HI`` arguments to ``{PATH: (LO, HI)}``; bad syntax raises
    SceneError (exit 2). Whether LO < HI and the path is fitted is checked by the fit."""
    from jaxdem.scene import SceneError

    out: dict[str, tuple[float, float]] = {}
    for item in items:
        path, equals, text = item.partition("=")
        lo_text, colon, hi_text = text.partition(":")
        path = path.strip()
        if not equals or not colon or not path:
            raise SceneError("--bounds", f"expected PATH=LO:HI, e.g. joints.set1.kn=1e5:1e8 "
                                         f"(got {item!r})")
        try:
            lo, hi = float(lo_text), float(hi_text)
        except ValueError:
            raise SceneError("--bounds", f"bounds of {path} must be numbers LO:HI "
                                         f"(got {text!r})") from None
        out[path] = (lo, hi)
    return out


def _write_json(data: dict[str, Any], path: Path) -> Path:
    from jaxdem.results import write_json

    return write_json(data, path)


def _failed(command: str, err: Exception) -> int:
    """A solve that raised inside ``command``: one line on stderr, exit status 3."""
    lines = str(err).strip().splitlines() or [""]
    print_error(f"{command}: the solver failed ({type(err).__name__}: {lines[-1]})")
    return EXIT_NOT_CONVERGED


def print_error(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)


# ---------------------------------------------------------------------------
# reliability (issue 31)


def cmd_reliability(args: argparse.Namespace) -> int:
    """FORM reliability index (issue 31); write reliability.json and reliability.png.

    Exit 0 when FORM ran (converged or not: its warnings say so), 2 on invalid input,
    3 when g has no value at the medians (no equilibrium: FORM cannot start) or a solve
    raised.
    """
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _set_overrides(args)
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0 (got {args.seed})")
    if not 1 <= args.max_iterations <= MAX_FIT_ITERATIONS:
        raise InputError(f"--max-iterations must be from 1 to {MAX_FIT_ITERATIONS:,} "
                         f"(got {args.max_iterations})")
    _check_chunk(args)
    scene = _load(path, overrides)
    _check_out(out)

    from jaxdem.reliability import (
        NO_ANSWER_AT_START,
        Limit,
        check_variables,
        correlation_matrix,
        parse_check,
        reliability,
        write_outputs,
    )
    from jaxdem.scene import SceneError
    from jaxdem.sweep import Variable

    variables = [Variable.parse(v) for group in args.vary for v in group]
    check_variables(variables)
    limit = Limit.parse(args.limit, scene)
    correlation = _parse_correlation([c for group in args.correlation or [] for c in group])
    correlation_matrix(variables, correlation)
    samples = parse_check(args.check)

    def report(r: dict[str, Any]) -> None:
        print(f"iteration {r['iteration']}: beta {r['beta']:.5g}, g {r['g']:.5g}"
              + ("" if r["step"] is None else f", step {r['step']:g}"), file=sys.stderr,
              flush=True)

    print(f"{scene_name(scene, path, overrides)}: {scene_summary(scene)}")
    print(f"FORM, {limit.describe()}; " + "; ".join(f"{v.path} {v.describe()}"
                                                     for v in variables), flush=True)
    try:
        result = reliability(scene, variables, limit, correlation=correlation,
                             check=samples, seed=args.seed, max_iterations=args.max_iterations,
                             intact=args.intact, chunk=args.chunk, progress=report)
    except SceneError:
        raise
    except Exception as err:  # noqa: BLE001 - exit codes are 0, 2 and 3 only
        return _failed("reliability", err)
    written = write_outputs(result, out)
    print(result.message())
    print("design point: " + ", ".join(f"{k} = {v:.5g}" for k, v in result.design_point.items()))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_NOT_CONVERGED if result.status == NO_ANSWER_AT_START else EXIT_OK


def _parse_correlation(items: Sequence[str]) -> dict[tuple[str, str], float] | None:
    """``--correlation PATH_A,PATH_B=RHO`` arguments to {(a, b): rho}; bad syntax raises
    SceneError (exit 2). Whether the pairs make a correlation matrix is checked later."""
    if not items:
        return None
    from jaxdem.scene import SceneError

    out: dict[tuple[str, str], float] = {}
    for item in items:
        pair, equals, text = item.partition("=")
        a, comma, b = pair.partition(",")
        if not equals or not comma or not a.strip() or not b.strip():
            raise SceneError("--correlation", f"expected PATH_A,PATH_B=RHO (got {item!r})")
        try:
            out[(a.strip(), b.strip())] = float(text)
        except ValueError:
            raise SceneError("--correlation", f"RHO of {pair} must be a number "
                                              f"(got {text!r})") from None
    return out
