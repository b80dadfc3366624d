"""The ``jaxdem`` command line (SPEC section 3).

::

    jaxdem demo  [--out DIR] [--vtk] [--no-figures]            # bundled demo scene
    jaxdem run   SCENE.toml [--out DIR] [--set PATH=VALUE ...] [--vtk] [--no-figures]
    jaxdem check SCENE.toml [--out DIR]                         # validate, draw blocks
    jaxdem sweep SCENE.toml --vary PATH=LOW:HIGH[:log] [--vary PATH=DIST:ARGS ...] --samples N
           [--method grid|lhs|mc] [--seed S] [--chunk C] [--workers W]
           [--out DIR] [--set PATH=VALUE ...]
    jaxdem fos SCENE.toml [--out DIR] [--intact] [--tensile] [--trials N] [--tolerance R]
           [--set PATH=VALUE ...]                               # factor of safety
    jaxdem grc SCENE.toml [--excavation NAME] [--levels K] [--p0 KPA] [--from KPA]
           [--monitor NAME] [--support-stiffness KPA_PER_M --support-capacity KPA
           [--install-convergence M]] [--chunk C] [--workers W] [--out DIR]
           [--set PATH=VALUE ...]
                                                                # ground reaction curve
    jaxdem back-analyse SCENE.toml --observed FILE.csv --fit PATH [--fit PATH ...]
           [--bounds PATH=LO:HI ...] [--optimizer gauss-newton|lbfgs|adam] [--max-iterations N]
           [--restarts N] [--out DIR] [--set PATH=VALUE ...]    # fit parameters to measurements
    jaxdem reliability SCENE.toml --vary PATH=DIST:ARGS [...] --limit LIMIT [--check mc:N]
           [--correlation A,B=RHO ...] [--out DIR] [--set PATH=VALUE ...]   # FORM

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
``grc`` exits 0 when every level of the curve converged or found a mechanism, 3 when
a level did neither; it writes ``grc.json`` and ``grc.png`` in both cases.

``--vtk`` (run, demo) also writes ``blocks.vtk``, ``contacts.vtk`` and ``bolts.vtk``
(legacy VTK, ASCII) of the final state, and every stage's files with ``.pvd``
collections (:mod:`jaxdem.vtk`), for ParaView; ``jaxdem --version`` prints the version.

JAX, the solver and matplotlib are imported inside the commands, so that
``jaxdem --help`` answers at once. A command first makes the process-wide settings of
:func:`jaxdem.config.configure` (float64, one OpenBLAS thread, the compilation cache).

Where it lives (this module is the entry point, ``jaxdem = "jaxdem.cli:entry"`` and
``python -m jaxdem``; each module imports only those above it):

- :mod:`jaxdem.cli._progress`: progress bars on stderr;
- :mod:`jaxdem.cli._summaries`: the text printed about a scene, a run, a sweep, a fit;
- :mod:`jaxdem.cli._commands`: the subcommands, exit statuses and ``InputError``;
- :mod:`jaxdem.cli._parser`: the argument parser.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from jaxdem.cli._commands import (
    EXIT_INVALID_INPUT,
    EXIT_NOT_CONVERGED,
    EXIT_OK,
    SOLVED_STATUSES,
    InputError,
    print_error,
)
from jaxdem.cli._parser import make_parser
from jaxdem.cli._progress import ProgressBar, SampleBar

__all__ = [
    "EXIT_INVALID_INPUT",
    "EXIT_NOT_CONVERGED",
    "EXIT_OK",
    "SOLVED_STATUSES",
    "InputError",
    "ProgressBar",
    "SampleBar",
    "main",
]


GC_YOUNG = 50_000
"""Objects allocated (less those freed) between two collections of the youngest
generation in a ``jaxdem`` process (Python's default is 700): :func:`entry`."""


def entry() -> None:
    """The ``jaxdem`` command: :func:`main`, then the process ends at once.

    Once the answer, the files and the output streams are written, nothing is left
    to do: Python's own shutdown (JAX's runtime and thread pools, the collection
    of every module) took 0.25 s of a 1.5 s run (more on a loaded machine), and
    is skipped with ``os._exit``. Files are closed where they are written; the
    streams are flushed here. :func:`main` itself returns, for callers in Python.

    Python's cyclic garbage collector runs its youngest generation every
    :data:`GC_YOUNG` objects allocated (less those freed), not every 700: JAX's
    import and the tracing of a solve's programs allocate millions of objects that
    live on, and the collector, walking them again and again, took 0.47 s of the
    demo's cold run and 0.14 s of its warm one (``gc.callbacks``; 0.23 and 0.06 s with
    this; seed example 2's cold run 0.54 -> 0.18 s; the 100 x 100 grid's peak memory
    the same, 796 MB). Cycles are still collected, later. A process's setting, not a
    library's: made here, not in :func:`main`.
    """
    import gc
    import logging

    gc.set_threshold(GC_YOUNG, 10, 10)
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(code)


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
    parser = make_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exit_:  # --help or --version (0)
        return int(exit_.code or 0)
    except InputError as err:  # a usage error
        print_error(str(err))
        return EXIT_INVALID_INPUT
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_INVALID_INPUT
    # The command line is a whole process: float64, one OpenBLAS thread and the
    # persistent compilation cache, before anything loads JAX's LAPACK (jaxdem.config).
    from jaxdem import config
    from jaxdem.scene import SceneError

    config.configure()
    try:
        return int(args.func(args))
    except (SceneError, InputError) as err:
        print_error(str(err))
        return EXIT_INVALID_INPUT
