"""The argument parser of ``jaxdem``: the subcommands, their options and defaults, and
usage errors as one line (``_Parser``) instead of argparse's usage block.

Builds an ``argparse.ArgumentParser`` whose subcommands dispatch (``func``) to the
``cmd_*`` functions of :mod:`jaxdem.cli._commands`; :func:`jaxdem.cli.main` parses with it.
Reads the version from ``jaxdem/__init__.py`` as text, without importing JAX.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from jaxdem.cli._commands import (
    InputError,
    cmd_back_analyse,
    cmd_check,
    cmd_demo,
    cmd_fos,
    cmd_grc,
    cmd_reliability,
    cmd_run,
    cmd_sweep,
)

DEFAULT_DEMO_OUT = "jaxdem-demo"
DEFAULT_BACK_ANALYSIS_OUT = "jaxdem-back-analysis"
DEFAULT_SWEEP_OUT = "jaxdem-sweep"
DEFAULT_FOS_OUT = "jaxdem-fos"
DEFAULT_GRC_OUT = "jaxdem-grc"
DEFAULT_RELIABILITY_OUT = "jaxdem-reliability"

WORKERS_HELP = ("batches solved at the same time, one thread each (default: on a CPU where "
                "each batch holds one sample, as on the sparse path of scenes above 200 "
                "blocks, one per core; else 1); more than 1 on a CPU needs --chunk 1")


def _version() -> str:
    """The package version, without importing JAX (``jaxdem --version`` answers at once)."""
    text = (Path(__file__).resolve().parents[1] / "__init__.py").read_text()
    found = re.search(r'^__version__ = "([^"]+)"', text, re.M)
    return found.group(1) if found else "unknown"


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (``--samples: invalid int value:
    'x'``), printed by :func:`main` like every other invalid input, instead of the usage."""

    def error(self, message: str):  # type: ignore[override]
        named = re.match(r"argument ([^:]+?): (.*)", message)
        if named:
            option = named.group(1).split("/")[-1]  # "-h/--help" -> "--help"
            raise InputError(f"{option}: {named.group(2)} (see {self.prog} --help)")
        raise InputError(f"{self.prog}: {message} (see {self.prog} --help)")


def _add_set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set PATH=VALUE ...`` (repeatable): scene parameter overrides."""
    parser.add_argument("--set", action="append", nargs="+", metavar="PATH=VALUE", help=help)


def _add_figures_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-figures", action="store_true",
                        help="write result.json only, no figures (faster)")


def _add_view_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--view", nargs=4, type=float, metavar=("X0", "X1", "Y0", "Y1"),
                        help="window (m) of blocks.png's second panel (default: around the "
                        "excavations)")


def _add_vtk_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vtk", action="store_true",
                        help="also write blocks.vtk (polygons with displacement, stress, "
                        "state), contacts.vtk (points with forces), bolts.vtk (lines with "
                        "force and state) and every stage's files with blocks.pvd, "
                        "contacts.pvd, bolts.pvd collections for ParaView")


def make_parser() -> argparse.ArgumentParser:
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
    _add_view_option(demo)
    demo.set_defaults(func=cmd_demo)

    run = sub.add_parser("run", help="solve a scene, write result.json and figures")
    run.add_argument("scene", metavar="SCENE.toml")
    run.add_argument("--out", metavar="DIR",
                     help="output folder (default out/<file name without .toml>)")
    _add_set_option(run, "override scene parameters, e.g. --set joints.set1.kn=2e6 "
                    "in_situ.k0=1.5, or the solver's choices by a word, e.g. "
                    "solver.linear_solver=cg (repeatable)")
    _add_vtk_option(run)
    _add_figures_option(run)
    _add_view_option(run)
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
        "Levenberg-Marquardt on the monitors' Jacobian by default); report estimates, "
        "Gauss-Newton standard deviations and which "
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
                      help="most optimiser iterations of each local fit (default 50)")
    # No default here: back_analyse's (inverse.fit.RESTARTS) holds, and --help stays
    # free of JAX imports.
    back.add_argument("--restarts", type=int, metavar="N",
                      help="most restarts from other points (the centre of the bounds, then "
                      "Halton points) when a fit's misfit is more than the stds explain "
                      "(chi-square test at 99.9%%): a local minimum (default 4; 0: none)")
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
    sw.add_argument("--workers", type=int, default=None, metavar="W",
                    help=WORKERS_HELP)
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
    _add_grc_parser(sub)
    _add_reliability(sub)
    return parser


def _add_grc_parser(sub) -> None:
    """``jaxdem grc``: the ground reaction curve of an excavation (jaxdem.grc)."""
    grc = sub.add_parser(
        "grc",
        help="ground reaction curve of an excavation (batched)",
        description="Ground reaction curve (convergence-confinement method): the excavation "
        "with a support pressure from the in-situ normal stress at its face p0 (or --from) "
        "down to 0 in K levels, all solved in one batch; optionally the support line and "
        "the equilibrium with it. Writes grc.json (pressure, monitors, mechanism, "
        "equilibrium) and grc.png. Exit 3 when a level neither converged nor found a "
        "mechanism.",
    )
    grc.add_argument("scene", metavar="SCENE.toml")
    grc.add_argument("--excavation", metavar="NAME",
                     help="the excavation (default: the scene's only one)")
    grc.add_argument("--levels", type=int, default=16, metavar="K",
                     help="support pressures, evenly spaced down to 0 (default 16)")
    grc.add_argument("--p0", type=float, metavar="KPA",
                     help="in-situ normal stress at the face (default: the mean normal stress "
                     "that [in_situ] puts on the excavation's outline)")
    grc.add_argument("--from", dest="start", type=float, metavar="KPA",
                     help="highest support pressure, at most p0 (default p0)")
    grc.add_argument("--monitor", metavar="NAME",
                     help="the monitor whose value is the convergence of the support line "
                     "(default: the first section, else the first point's |u|)")
    grc.add_argument("--support-stiffness", type=float, metavar="KPA_PER_M",
                     help="support line: kPa of pressure per m of convergence")
    grc.add_argument("--support-capacity", type=float, metavar="KPA",
                     help="support line: the largest pressure it carries (kPa)")
    grc.add_argument("--install-convergence", type=float, metavar="M",
                     help="support line: the convergence when it is installed (m, default 0)")
    grc.add_argument("--chunk", type=int, default=None, metavar="C",
                     help="levels solved together (default: as jaxdem sweep)")
    grc.add_argument("--workers", type=int, default=None, metavar="W",
                     help=WORKERS_HELP)
    grc.add_argument("--out", default=DEFAULT_GRC_OUT, metavar="DIR",
                     help=f"output folder (default {DEFAULT_GRC_OUT})")
    _add_set_option(grc, "override scene parameters before the curve (repeatable)")
    grc.set_defaults(func=cmd_grc)


def _add_reliability(sub) -> None:
    """``jaxdem reliability`` (issue 31): FORM on the model's own gradients."""
    rel = sub.add_parser(
        "reliability",
        help="reliability index by FORM (HL-RF) with the model's gradients",
        description="First-order reliability method: the reliability index beta, the "
        "probability of failure Phi(-beta), the design point and the importance factors of "
        "random scene parameters for a limit state (a monitor against a limit, or the "
        "factor of safety >= 1); write reliability.json and reliability.png.",
    )
    rel.add_argument("scene", metavar="SCENE.toml")
    rel.add_argument(
        "--vary", action="append", nargs="+", required=True, metavar="PATH=DIST",
        help="a random parameter: PATH=normal:MEAN:SD, PATH=lognormal:MEAN:SD, "
        "PATH=uniform:LOW:HIGH, PATH=truncnormal:MEAN:SD:LOW:HIGH (repeatable)")
    rel.add_argument(
        "--limit", required=True, metavar="LIMIT",
        help="failure criterion: 'MONITOR.|u| <= V', 'MONITOR.ux >= V', 'MONITOR.uy >= V' "
        "(a point, m), 'SECTION <= V' (a section's convergence, m), or 'stable' (the "
        "factor of safety F >= 1, g = F - 1)")
    rel.add_argument(
        "--correlation", action="append", nargs="+", metavar="PATH_A,PATH_B=RHO",
        help="correlation of two variables' standard normals (default: independent; "
        "repeatable)")
    rel.add_argument("--check", metavar="mc:N",
                     help="also estimate the probability by N Monte Carlo solves (batched)")
    rel.add_argument("--seed", type=int, default=0, help="Monte Carlo seed (default 0)")
    rel.add_argument("--max-iterations", type=int, default=30, metavar="N",
                     help="most HL-RF iterations (default 30)")
    rel.add_argument("--intact", action="store_true",
                     help="stable: also reduce the intact rock's friction and cohesion")
    rel.add_argument("--chunk", type=int, default=None, metavar="C",
                     help="samples per batch (default: as jaxdem sweep)")
    rel.add_argument("--out", default=DEFAULT_RELIABILITY_OUT, metavar="DIR",
                     help=f"output folder (default {DEFAULT_RELIABILITY_OUT})")
    _add_set_option(rel, "override scene parameters before the analysis (repeatable)")
    rel.set_defaults(func=cmd_reliability)
