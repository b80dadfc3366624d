"""The ``jaxdem`` command line (SPEC section 3).

::

    jaxdem demo  [--out DIR] [--vtk] [--no-figures]            # bundled demo scene
    jaxdem run   SCENE.toml [--out DIR] [--set PATH=VALUE ...] [--vtk] [--no-figures]
    jaxdem check SCENE.toml [--out DIR]                         # validate, draw blocks
    jaxdem sweep SCENE.toml --vary PATH=LOW:HIGH[:log] [--vary PATH=DIST:ARGS ...] --samples N
           [--method grid|lhs|mc] [--seed S] [--chunk C] [--out DIR] [--set PATH=VALUE ...]
    jaxdem fos SCENE.toml [--out DIR] [--intact] [--tensile] [--trials N] [--tolerance R]
           [--set PATH=VALUE ...]                               # factor of safety
    jaxdem back-analyse SCENE.toml --observed FILE.csv --fit PATH [--fit PATH ...]
           [--bounds PATH=LO:HI ...] [--optimizer gauss-newton|lbfgs|adam] [--max-iterations N]
           [--out DIR] [--set PATH=VALUE ...]                   # fit parameters to measurements

Exit status: 0 when solved (stable or not: a mechanism is an answer), 2 on
invalid input (one line ``error: <message>`` on stderr naming the field, no
traceback), 3 when the solver did not converge (iteration limit, non-finite
values, contact capacity overflow). ``run`` writes ``result.json`` and the
figures in every case where the solver returned, so that a failed run can be
looked at. ``back-analyse`` exits 0 when the fit ran (converged or not, every
parameter identifiable or not), 3 when the model has no equilibrium at the
starting parameters (``back-analyse`` and ``sweep`` also exit 3, with one line on
stderr, when a solve raised); it writes ``back_analysis.json`` in every case, and the
figures when the fit ran. ``fos`` exits 0 when the factor of safety is
bracketed (or bounded by its limits), 3 when the unstable end of the bracket
is a trial that stopped at the iteration limit or went non-finite rather
than a proven mechanism; it writes ``fos.json`` and its figures in both cases.

``--vtk`` (run, demo) also writes ``blocks.vtk`` and ``contacts.vtk`` (legacy VTK,
ASCII) for ParaView; ``jaxdem --version`` prints the version.

JAX, the solver and matplotlib are imported inside the commands, so that
``jaxdem --help`` answers at once.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
from collections.abc import Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, TextIO

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

EXIT_OK = 0
EXIT_INVALID_INPUT = 2
EXIT_NOT_CONVERGED = 3

#: Statuses that count as an answer (exit 0); every other status exits 3.
SOLVED_STATUSES = ("converged", "mechanism")

DEFAULT_DEMO_OUT = "jaxdem-demo"
DEFAULT_BACK_ANALYSIS_OUT = "jaxdem-back-analysis"
DEFAULT_SWEEP_OUT = "jaxdem-sweep"
DEFAULT_FOS_OUT = "jaxdem-fos"

MAX_TRIALS = 1024
"""Most ``fos --trials`` (factors solved together in one batch per round)."""
MAX_FIT_ITERATIONS = 10_000
"""Most ``back-analyse --max-iterations`` (each iteration solves the scene at least once)."""


def _version() -> str:
    """The package version, without importing JAX (``jaxdem --version`` answers at once)."""
    text = (Path(__file__).resolve().parent / "__init__.py").read_text()
    found = re.search(r'^__version__ = "([^"]+)"', text, re.M)
    return found.group(1) if found else "unknown"


class InputError(Exception):
    """Invalid input found by the command line itself (exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (``--samples: invalid int value:
    'x'``), printed by :func:`main` like every other invalid input, instead of the usage."""

    def error(self, message: str):  # type: ignore[override]
        named = re.match(r"argument ([^:]+?): (.*)", message)
        if named:
            option = named.group(1).split("/")[-1]  # "-h/--help" -> "--help"
            raise InputError(f"{option}: {named.group(2)} (see {self.prog} --help)")
        raise InputError(f"{self.prog}: {message} (see {self.prog} --help)")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``jaxdem`` command line; returns the exit status.

    Args:
      argv: arguments without the program name (default ``sys.argv[1:]``).

    Returns:
      0 solved (stable or not), 2 invalid input, 3 the solver did not converge.

    Example::

        from jaxdem.cli import main
        status = main(["run", "tunnel.toml", "--out", "out/tunnel", "--set", "joints.set1.kn=2e6"])
    """
    parser = _parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exit_:  # --help or --version (0)
        return int(exit_.code or 0)
    except InputError as err:  # a usage error
        _error(str(err))
        return EXIT_INVALID_INPUT
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_INVALID_INPUT
    from jaxdem.scene import SceneError

    try:
        return int(args.func(args))
    except (SceneError, InputError) as err:
        _error(str(err))
        return EXIT_INVALID_INPUT


# ---------------------------------------------------------------------------
# Commands


def cmd_demo(args: argparse.Namespace) -> int:
    """Solve the bundled demo scene ``jaxdem/data/demo.toml``."""
    from importlib import resources

    resource = resources.files("jaxdem").joinpath("data", "demo.toml")
    if not resource.is_file():
        raise InputError("the bundled demo scene jaxdem/data/demo.toml is missing")
    with resources.as_file(resource) as path:
        return _solve_and_report(path, Path(args.out), overrides={}, vtk=args.vtk,
                                 figures=not args.no_figures)


def cmd_run(args: argparse.Namespace) -> int:
    """Solve a scene file with ``--set`` overrides and write results and figures."""
    path = Path(args.scene)
    out = Path(args.out) if args.out else Path("out") / path.stem
    overrides = _parse_overrides([item for group in args.set or [] for item in group])
    return _solve_and_report(path, out, overrides=overrides, vtk=args.vtk,
                             figures=not args.no_figures)


def cmd_check(args: argparse.Namespace) -> int:
    """Validate a scene file and draw its blocks to ``DIR/check.png``."""
    from jaxdem.plots import plot_scene_check

    path = Path(args.scene)
    out = Path(args.out) if args.out else Path("out") / path.stem
    scene = _load(path, overrides={})
    _check_out(out)
    print(f"OK: {_scene_summary(scene)}")
    figure = plot_scene_check(scene, out / "check.png")
    print(f"wrote {figure}")
    return EXIT_OK


def cmd_back_analyse(args: argparse.Namespace) -> int:
    """Fit scene parameters to measured monitor values; write back_analysis.json and figures."""
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _parse_overrides([item for group in args.set or [] for item in group])
    bounds = _parse_bounds([item for group in args.bounds or [] for item in group])
    if not 0 <= args.max_iterations <= MAX_FIT_ITERATIONS:
        what = ">= 0" if args.max_iterations < 0 else f"<= {MAX_FIT_ITERATIONS:,}"
        raise InputError(f"--max-iterations must be {what} (got {args.max_iterations})")
    scene = _load(path, overrides)
    _check_out(out)

    from inverse import back_analyse, read_observations
    from inverse.backanalysis import NO_EQUILIBRIUM_AT_START
    from jaxdem.scene import SceneError
    from inverse.plots import write_figures

    observations = read_observations(args.observed)
    print(f"{_scene_name(scene, path, overrides)}: {_scene_summary(scene)}")
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
            progress=_print_iteration,
        )
    except SceneError:
        raise
    except Exception as err:  # noqa: BLE001 - exit codes are 0, 2 and 3 only
        return _failed("back-analyse", err)
    written = [_write_json(result.to_dict(), out / "back_analysis.json")]
    if result.status != NO_EQUILIBRIUM_AT_START:
        written += write_figures(result, out)
    print(_back_analysis_summary(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_NOT_CONVERGED if result.status == NO_EQUILIBRIUM_AT_START else EXIT_OK


def cmd_sweep(args: argparse.Namespace) -> int:
    """Solve a scene over sampled parameters (batched); write sweep.csv, sweep.json, tornado.png."""
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _parse_overrides([item for group in args.set or [] for item in group])
    if args.chunk is not None and args.chunk < 1:
        raise InputError(f"--chunk must be >= 1 (got {args.chunk})")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0 (got {args.seed})")
    scene = _load(path, overrides)
    _check_out(out)

    from jaxdem.plots import plot_tornado
    from jaxdem.sweep import Variable, draw, sweep

    variables = [Variable.parse(v) for group in args.vary for v in group]
    method = args.method or ("grid" if all(v.kind == "range" for v in variables) else "lhs")
    n = draw(variables, args.samples, method, args.seed).shape[0]
    p = len(variables)
    print(f"{_scene_name(scene, path, overrides)}: {_scene_summary(scene)}")
    if method == "grid":
        how = (f"grid: {args.samples} levels x {_plural(p, 'parameter')} = {n:,} solves "
               "(--samples is the levels per parameter)")
    else:
        how = f"{method}: {n:,} samples (seed {args.seed})"
    print(f"sweep {how}, plus {1 + 2 * p} for the tornado; "
          + "; ".join(f"{v.path} {v.describe()}" for v in variables), flush=True)
    bar = SampleBar()
    from jaxdem.scene import SceneError

    try:
        with bar:
            result = sweep(scene, variables, args.samples, method=method, seed=args.seed,
                           chunk=args.chunk, progress=bar)
    except SceneError:
        raise
    except Exception as err:  # noqa: BLE001 - exit codes are 0, 2 and 3 only
        return _failed("sweep", err)
    written = [result.to_csv(out / "sweep.csv"), _write_json(result.to_dict(), out / "sweep.json")]
    if result.tornado:
        written.append(plot_tornado(result.tornado, out / "tornado.png"))
    print(_sweep_summary(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def cmd_fos(args: argparse.Namespace) -> int:
    """Factor of safety by strength reduction; write fos.json, mechanism.png and fos.png."""
    path = Path(args.scene)
    out = Path(args.out)
    overrides = _parse_overrides([item for group in args.set or [] for item in group])
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

    print(f"{_scene_name(scene, path, overrides)}: {_scene_summary(scene)}")
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


# ---------------------------------------------------------------------------
# Shared steps


def _solve_and_report(path: Path, out: Path, overrides: dict[str, Any],
                      vtk: bool = False, figures: bool = True) -> int:
    _mark("start")
    scene = _load(path, overrides)
    _check_out(out)
    print(f"{_scene_name(scene, path, overrides)}: {_scene_summary(scene)}")
    _mark("loaded")

    from jaxdem import solver

    _mark("imported")
    bar = ProgressBar(n_stages=_stage_count(scene))
    with bar:
        result = solver.solve(scene, progress=bar)
    _mark("solved")

    data = result.to_dict()
    if overrides:
        # result.json keeps the file's scene name and says what --set changed; the
        # figures' titles carry both.
        data["overrides"] = dict(overrides)
        result = dataclasses.replace(result, scene=_scene_name(scene, path, overrides))
    out.mkdir(parents=True, exist_ok=True)
    (out / "result.json").write_text(json.dumps(data, indent=2))
    # The answer first: the summary and result.json do not wait for the figures.
    print(_result_summary(result), flush=True)
    _mark("answered")
    written = [out / "result.json"]
    if figures:
        from jaxdem.plots import write_figures

        written += write_figures(result, out)
    _mark("figures")
    if vtk:
        from jaxdem.vtk import write_vtk

        written += write_vtk(result, out)

    print("wrote " + ", ".join(str(p) for p in written))
    _mark("end")
    _write_phases({"timing": dict(getattr(result, "timing", None) or {}),
                   "increment": dict(getattr(solver, "COMPILE_TIMES", {}))})
    return EXIT_OK if result.status in SOLVED_STATUSES else EXIT_NOT_CONVERGED


def _load(path: Path, overrides: dict[str, Any]) -> Any:
    """Load and validate a scene; every problem (unreadable file included) is a SceneError."""
    from jaxdem.scene import load_scene

    return load_scene(path, set=overrides or None)


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
    _error(f"{command}: the solver failed ({type(err).__name__}: {lines[-1]})")
    return EXIT_NOT_CONVERGED


def _error(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)


# ---------------------------------------------------------------------------
# Progress


class SampleBar(AbstractContextManager):
    """Progress over the samples of a sweep, on stderr: ``samples [####------] 256/1024``."""

    def __init__(self, stream: TextIO | None = None, width: int = 20):
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.tty = self.stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        filled = int(self.width * done / max(total, 1))
        line = f"samples [{'#' * filled}{'-' * (self.width - filled)}] {done}/{total}"
        self.stream.write(("\r" + line) if self.tty else line + "\n")
        self.stream.flush()

    def __exit__(self, *exc: object) -> None:
        if self.tty:
            self.stream.write("\n")


class ProgressBar(AbstractContextManager):
    """Text progress over stages and load increments, on stderr.

    Called by the solver once per increment with a dict: ``stage`` (name),
    ``step`` (1-based), ``n_steps``, ``status``, ``iterations``, ``substeps``,
    ``residual``. On a terminal one line is redrawn in place::

        stage 1/2 excavate [###-------] step 3/10  it 12  res 3.1e-11

    elsewhere (a log file, CI) one line is printed per increment.
    """

    def __init__(self, n_stages: int = 0, stream: TextIO | None = None, width: int = 20):
        self.stream = sys.stderr if stream is None else stream
        self.n_stages = n_stages
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._stages: list[str] = []
        self._open_line = False

    def __call__(self, event: dict[str, Any]) -> None:
        line = self.format(event)
        if self.tty:
            self.stream.write("\r\033[K" + line)
            self._open_line = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def format(self, event: dict[str, Any]) -> str:
        stage = str(event.get("stage", ""))
        if not self._stages or self._stages[-1] != stage:
            self._stages.append(stage)
        index = len(self._stages)
        total = max(self.n_stages, index)
        step = int(event.get("step", 0))
        n_steps = max(int(event.get("n_steps", 0)), 1)
        filled = min(self.width, round(self.width * step / n_steps))
        bar = "#" * filled + "-" * (self.width - filled)
        parts = [f"stage {index}/{total}"]
        if stage:
            parts.append(stage)
        parts.append(f"[{bar}] step {step}/{n_steps}")
        text = " ".join(parts)
        text += f"  it {int(event.get('iterations', 0))}"
        substeps = int(event.get("substeps", 1) or 1)
        if substeps > 1:
            text += f"  sub {substeps}"
        residual = event.get("residual")
        if residual is not None:
            text += f"  res {float(residual):.1e}"
        status = str(event.get("status", ""))
        if status and status != "converged":
            text += f"  {status}"
        return text

    def __exit__(self, *exc: object) -> None:
        if self._open_line:
            self.stream.write("\n")
            self.stream.flush()
            self._open_line = False


# ---------------------------------------------------------------------------
# Summaries


def _count(scene: Any, name: str) -> int:
    try:
        return len(getattr(scene, name, None) or ())
    except TypeError:
        return 0


def _scene_name(scene: Any, path: Path, overrides: dict[str, Any] | None = None) -> str:
    """The scene's name, with the ``--set`` overrides it was solved with."""
    name = str(getattr(scene, "name", None) or path.stem)
    if overrides:
        name += " (--set " + " ".join(f"{k}={v:g}" for k, v in overrides.items()) + ")"
    return name


def _stage_count(scene: Any) -> int:
    """Stages the solver reports progress for: the loading or initial state, then the
    stages it runs (``[[stages]]``, or the one it makes for excavations and supports)."""
    from jaxdem.solver import _stage_plan

    return 1 + len(_stage_plan(scene))


def _scene_summary(scene: Any) -> str:
    """'496 blocks (496 generated), 2 joints, 3 discontinuities, ...' for the parts the
    scene has; a [domain]'s rock mass is generated (host NumPy, fast) to count its blocks."""
    explicit = _count(scene, "blocks")
    generated = 0
    if getattr(scene, "domain", None) is not None:
        from jaxdem.rockmass import generate

        generated = len(generate(scene).pieces)
    n = explicit + generated
    blocks = _plural(n, "block")
    if generated:
        blocks += f" ({generated:,} generated" + (f", {explicit} explicit)" if explicit else ")")
    parts = [blocks, _plural(_count(scene, "joints"), "joint")]
    for name in ("discontinuities", "boundaries", "bolts", "monitors", "stages"):
        n = _count(scene, name)
        if n:
            parts.append(f"{n} {name}" if n != 1 else f"1 {_singular(name)}")
    return ", ".join(parts)


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def _singular(name: str) -> str:
    return {"discontinuities": "discontinuity", "boundaries": "boundary"}.get(name, name[:-1])


def _result_summary(result: Any) -> str:
    """Status, stability, monitors table and timings, as printed after a run."""
    lines = [f"status: {result.status}: {result.message}"]
    if result.stable:
        lines.append("stable: yes")
    else:
        ids = [str(i) for i in result.moving_blocks]
        moving = ", ".join(ids[:20])
        more = f" (+{len(ids) - 20} more)" if len(ids) > 20 else ""
        lines.append(f"stable: NO, moving blocks: {moving}{more}" if moving else "stable: NO")
    lines += [f"warning: {w}" for w in getattr(result, "warnings", None) or []]
    lines += _monitor_table(result.monitors or {})
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


def _print_iteration(event: dict[str, Any]) -> None:
    """One line per back-analysis iteration, on stderr like the solver's progress."""
    params = "  ".join(f"{path}={value:.5g}" for path, value in event["params"].items())
    print(
        f"it {event['iteration']:>3}  misfit {event['misfit']:.4e}  "
        f"|grad| {event['gradient_norm']:.2e}  {params}",
        file=sys.stderr,
        flush=True,
    )


def _sweep_summary(result: Any) -> str:
    b, pr = result.batch, result.probability
    t = b.timing
    lines = [f"{len(b.stable)} samples: {int(b.converged.sum())} in equilibrium, "
             f"{pr['unstable']} mechanisms, {pr['undecided']} without an answer "
             f"({result.mode}: {t['solve_s']:.2f} s solving, {t['compile_s']:.1f} s compiling, "
             f"{t['chunk']} samples per batch)"]
    if pr["decided"]:
        lo, hi = pr["ci95"]
        lines.append(f"probability of instability {pr['p_unstable']:.3f} "
                     f"(95% interval {lo:.3f} to {hi:.3f}, {pr['decided']} samples)")
    for name, bars in result.tornado.items():
        top = ", ".join(f"{bar['path']} {bar['swing'] * 1e3:+.3g} mm" for bar in bars[:3])
        lines.append(f"tornado {name}: {top}")
    return "\n".join(lines)


def _back_analysis_summary(result: Any) -> str:
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


# ---------------------------------------------------------------------------
# Parser


def _add_set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set PATH=VALUE ...`` (repeatable): scene parameter overrides."""
    parser.add_argument("--set", action="append", nargs="+", metavar="PATH=VALUE", help=help)


def _add_figures_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-figures", action="store_true",
                        help="write result.json only, no figures (faster)")


def _add_vtk_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vtk", action="store_true",
                        help="also write blocks.vtk (polygons with displacement, stress, "
                        "state) and contacts.vtk (points with forces) for ParaView")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxdem",
        description="2D block-spring discrete element analysis of tunnels in jointed rock.",
        epilog="Exit status: 0 solved (stable or not), 2 invalid input, 3 solver did not converge.",
    )
    parser.add_argument("--version", action="version", version=f"jaxdem {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    demo = sub.add_parser("demo", help="solve the bundled demo scene")
    demo.add_argument(
        "--out",
        default=DEFAULT_DEMO_OUT,
        metavar="DIR",
        help=f"output folder (default {DEFAULT_DEMO_OUT})",
    )
    _add_vtk_option(demo)
    _add_figures_option(demo)
    demo.set_defaults(func=cmd_demo)

    run = sub.add_parser("run", help="solve a scene, write result.json and figures")
    run.add_argument("scene", metavar="SCENE.toml")
    run.add_argument("--out", metavar="DIR",
                     help="output folder (default out/<file name without .toml>)")
    _add_set_option(run, "override scene parameters, e.g. --set joints.set1.kn=2e6 "
                    "in_situ.k0=1.5 (repeatable)")
    _add_vtk_option(run)
    _add_figures_option(run)
    run.set_defaults(func=cmd_run)

    check = sub.add_parser("check", help="validate a scene and draw its blocks")
    check.add_argument("scene", metavar="SCENE.toml")
    check.add_argument("--out", metavar="DIR",
                       help="output folder (default out/<file name without .toml>)")
    check.set_defaults(func=cmd_check)

    back = sub.add_parser(
        "back-analyse",
        help="fit scene parameters to measured monitor values",
        description="Fit scene parameters to measured monitor values (Gauss-Newton / "
        "Levenberg-Marquardt on the monitors' Jacobian by default); report estimates, Gauss-Newton standard deviations and which "
        "parameters the measurements determine.",
    )
    back.add_argument("scene", metavar="SCENE.toml")
    back.add_argument(
        "--observed",
        required=True,
        metavar="FILE.csv",
        help="measurements: columns monitor,value,std (m) and optionally stage, component "
        "(ux|uy for point monitors); blank std: 5%% of |value|, at least 0.1 mm",
    )
    back.add_argument(
        "--fit",
        action="append",
        required=True,
        metavar="PATH",
        help="parameter to fit, e.g. joints.set1.kn (repeatable)",
    )
    back.add_argument(
        "--bounds",
        action="append",
        nargs="+",
        metavar="PATH=LO:HI",
        help="bounds of a fitted parameter (default theta0/100 to theta0*100 when positive)",
    )
    back.add_argument("--optimizer", choices=("gauss-newton", "lbfgs", "adam"),
                      default="gauss-newton", help="gauss-newton (default: Levenberg-Marquardt "
                      "on the monitors' Jacobian, fewest solves), lbfgs or adam")
    back.add_argument("--max-iterations", type=int, default=50, metavar="N",
                      help="most optimiser iterations (default 50)")
    back.add_argument(
        "--out",
        default=DEFAULT_BACK_ANALYSIS_OUT,
        metavar="DIR",
        help=f"output folder (default {DEFAULT_BACK_ANALYSIS_OUT})",
    )
    _add_set_option(back, "override scene parameters before fitting (repeatable)")
    back.set_defaults(func=cmd_back_analyse)

    sw = sub.add_parser(
        "sweep",
        help="solve a scene over sampled parameters (batched)",
        description="Solve a scene over a grid, Latin hypercube or Monte Carlo sample of its "
        "parameters, all samples in batches (vmap); write sweep.csv (one row per sample), "
        "sweep.json (probability of instability, tornado) and tornado.png.",
    )
    sw.add_argument("scene", metavar="SCENE.toml")
    sw.add_argument(
        "--vary",
        action="append",
        nargs="+",
        required=True,
        metavar="PATH=SPEC",
        help="a parameter and its range or distribution: PATH=LOW:HIGH[:log], "
        "PATH=uniform:LOW:HIGH, PATH=normal:MEAN:SD, PATH=lognormal:MEAN:SD, "
        "PATH=truncnormal:MEAN:SD:LOW:HIGH (repeatable)",
    )
    sw.add_argument("--samples", type=int, required=True, metavar="N",
                    help="grid: levels per parameter (N^p solves for p parameters); lhs, "
                    "mc: the number of draws. The count of solves is printed before any "
                    "starts")
    sw.add_argument("--method", choices=("grid", "lhs", "mc"), default=None,
                    help="grid, lhs (Latin hypercube) or mc (Monte Carlo); default grid when "
                    "every parameter is a range, else lhs")
    sw.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sw.add_argument("--chunk", type=int, default=None, metavar="C",
                    help="samples per batch (default: on a CPU a few, what stays in cache; "
                    "on a GPU as many as fit in memory)")
    sw.add_argument("--out", default=DEFAULT_SWEEP_OUT, metavar="DIR",
                    help=f"output folder (default {DEFAULT_SWEEP_OUT})")
    _add_set_option(sw, "override scene parameters for every sample (repeatable)")
    sw.set_defaults(func=cmd_sweep)

    fos = sub.add_parser(
        "fos",
        help="factor of safety by strength reduction (batched)",
        description="Divide the joints' tan(phi) and cohesion (with --intact also the intact "
        "rock's) by trial factors F, solved in batches, and bracket the largest F that is "
        "still stable; write fos.json, mechanism.png (the solve at the first unstable F) and "
        "fos.png (the trials). Exit 3 when the unstable end of the bracket is a trial that "
        "neither converged nor found a mechanism.",
    )
    fos.add_argument("scene", metavar="SCENE.toml")
    fos.add_argument("--out", default=DEFAULT_FOS_OUT, metavar="DIR",
                     help=f"output folder (default {DEFAULT_FOS_OUT})")
    fos.add_argument("--intact", action="store_true",
                     help="also reduce the intact rock's friction and cohesion (materials)")
    fos.add_argument("--tensile", action="store_true",
                     help="also divide tensile strengths by F (default: unchanged)")
    fos.add_argument("--trials", type=int, default=8, metavar="N",
                     help="factors solved together per round (default 8)")
    fos.add_argument("--tolerance", type=float, default=0.005, metavar="R",
                     help="stop when the bracket's relative width is <= R (default 0.005)")
    _add_set_option(fos, "override scene parameters before the reduction (repeatable)")
    fos.set_defaults(func=cmd_fos)
    return parser
