"""Ground reaction curve of the demo tunnel: one batch against a loop of single solves.

``jaxdem.ground_reaction`` solves the K support pressures of the curve as one
``jaxdem.solve_batch`` (issue 31: at least 4 times faster than K single runs).
The same K pressures are then solved one after another with ``jaxdem.solve`` on
the same scene (the demo with its support's pressure as the parameter). Both are
timed warm, after a first call that compiles their programs (its time is printed
apart); the batch without the extra solve that names a mechanism's blocks. The
error is the largest difference between the batch's monitors and the single
solves', over every level that converged and every monitor, relative to the
largest monitor value; the statuses must agree level by level.

    python benchmarks/bench_grc.py [--levels 16] [--chunk C] [--scene jaxdem/data/demo.toml]
    python benchmarks/bench_grc.py --commands [--repeats 3]

``--commands`` times what a user types instead (issue 31's comparison): ``python -m
jaxdem grc SCENE --levels K`` (its grc.json and grc.png) against K ``python -m jaxdem run
SCENE --set supports.I.pressure=P`` at the curve's pressures, each with its figures (the
default) and with ``--no-figures``; all warm (one run of each first), medians of
``--repeats``, in one process so that the ratios come from the same minutes. The grc
command is also timed with ``--workers 1`` (one level after another, as before the
levels were solved several at a time).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "jaxdem" / "data" / "demo.toml"))
    ap.add_argument("--excavation", default="tunnel")
    ap.add_argument("--levels", type=int, default=16)
    ap.add_argument("--chunk", type=int, default=None, help="levels per batch (default: "
                    "solve_batch's)")
    ap.add_argument("--commands", action="store_true",
                    help="time the grc command against K run commands (see the docstring)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if args.commands:
        commands(args)
        return
    import numpy as np

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.grc import grc_scene

    scene = jaxdem.load_scene(args.scene)
    solved, _, note, _ = grc_scene(scene, args.excavation)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()}; "
          f"jax {__import__('jax').__version__}; load average at start "
          f"{os.getloadavg()[0]:.1f}")
    print(f"scene: {scene.name}; {note}")

    def curve():
        t = time.perf_counter()
        c = jaxdem.ground_reaction(scene, args.excavation, args.levels, name_blocks=False,
                                   chunk=args.chunk)
        return c, time.perf_counter() - t

    first, t_first = curve()
    c, t_batch = curve()
    path, pressure = c.parameter, c.pressure

    def singles():
        t = time.perf_counter()
        out = [jaxdem.solve(solved, set={path: float(p)}) for p in pressure]
        return out, time.perf_counter() - t

    t = time.perf_counter()
    jaxdem.solve(solved, set={path: float(pressure[0])})    # compiles the single solve
    t_single_first = time.perf_counter() - t
    runs, t_loop = singles()

    # Error of the batch against the single solves.
    same = [r.status == s for r, s in zip(runs, c.status, strict=True)]
    worst, scale = 0.0, 0.0
    for name, values in c.monitors.items():
        for i, r in enumerate(runs):
            if not r.converged:
                continue
            m = r.monitors[name]
            if "convergence" in m:
                single = np.array([m["convergence"]])
                batch = np.array([values[i]])
            else:
                single = np.array(m["displacement"])
                batch = np.asarray(c.displacements[name][i])
            worst = max(worst, float(np.abs(batch - single).max()))
            scale = max(scale, float(np.abs(single).max()))
    iters = [sum(sum(s["iterations"]) for s in r.stages) for r in runs]
    print(f"levels: {args.levels} from {pressure[0]:.1f} to 0 kPa (p0 {c.p0:.1f} kPa); "
          f"statuses: {', '.join(f'{p:.0f} {s}' for p, s in zip(pressure, c.status, strict=True))}")
    print(f"Newton iterations of the single solves: {iters} (sum {sum(iters)})")
    print(f"batch chunk {c.timing['chunk']}, first call (compiles) {t_first:.1f} s; single "
          f"solve first call {t_single_first:.1f} s")
    print(f"load average at end {os.getloadavg()[0]:.1f}")
    print()
    print(f"| levels | batch s | batch: build / compile / solve s | {args.levels} single solves s "
          f"| single / batch | statuses agree | largest difference (m) | relative |")
    print("|---:|---:|---|---:|---:|---|---:|---:|")
    tm = c.timing
    print(f"| {args.levels} | {t_batch:.1f} | {tm['build_s']:.1f} / {tm['compile_s']:.1f} / "
          f"{tm['solve_s']:.1f} | {t_loop:.1f} | **{t_loop / t_batch:.2f}** | "
          f"{sum(same)}/{len(same)} | {worst:.2e} | {worst / scale:.1e} |")


def commands(args) -> None:
    """The grc command against K single run commands, warm (see the module docstring)."""
    import json
    import statistics
    import subprocess
    import sys
    import tempfile

    out = Path(tempfile.mkdtemp(prefix="bench-grc-"))
    jaxdem = [sys.executable, "-m", "jaxdem"]
    grc = [*jaxdem, "grc", args.scene, "--excavation", args.excavation, "--levels",
           str(args.levels), "--out", str(out / "grc")]

    def timed(cmd) -> float:
        t = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT)
        return time.perf_counter() - t

    timed(grc)  # warm-up: stores its programs
    curve = json.loads((out / "grc" / "grc.json").read_text())
    path, pressures = curve["parameter"], curve["pressure"]

    def singles(figures: bool) -> float:
        extra = [] if figures else ["--no-figures"]
        return sum(timed([*jaxdem, "run", args.scene, "--set", f"{path}={p!r}", "--out",
                          str(out / f"run{i}"), *extra]) for i, p in enumerate(pressures))

    timed([*jaxdem, "run", args.scene, "--set", f"{path}={pressures[0]!r}", "--out",
           str(out / "run0")])  # warm-up
    rows = {"grc": [], "grc --workers 1": [], "runs": [], "runs, --no-figures": []}
    for _ in range(args.repeats):
        rows["grc"].append(timed(grc))
        rows["grc --workers 1"].append(timed([*grc, "--workers", "1"]))
        rows["runs"].append(singles(True))
        rows["runs, --no-figures"].append(singles(False))
    g = statistics.median(rows["grc"])
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; load average "
          f"{os.getloadavg()[0]:.1f}; {args.levels} levels of {args.scene}, warm, medians of "
          f"{args.repeats}")
    print()
    print("| command | wall s (median) | this / grc |")
    print("|---|---:|---:|")
    print(f"| `jaxdem grc --levels {args.levels}` | {g:.1f} | |")
    one = statistics.median(rows["grc --workers 1"])
    print(f"| `jaxdem grc --levels {args.levels} --workers 1` | {one:.1f} | {one / g:.2f} |")
    for name in ("runs", "runs, --no-figures"):
        m = statistics.median(rows[name])
        print(f"| {args.levels} x `jaxdem run --set {path}=P`"
              f"{' --no-figures' if 'no-figures' in name else ''} | {m:.1f} | **{m / g:.2f}** |")


if __name__ == "__main__":
    main()
