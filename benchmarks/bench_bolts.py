"""Bolted scenes: error against statics, Newton iterations and solve time.

The scenes of tests/verification/test_bolts.py: a roof wedge (key block) hung on 1, 2
and 3 vertical bolts, and a block on an incline held by an inclined bolt at limit
equilibrium. For each: the status, the largest error of the bolt forces against the
closed form (statics of the rigid block; Hoek & Bray's bolted plane slide), the Newton
iterations of the whole solve, and the solve time (median of --repeat warm runs,
compilation apart).

    python benchmarks/bench_bolts.py [--repeat 5]

Run with PYTHONPATH pointing at another checkout to compare versions (the scenes come
from this checkout's tests).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent / "tests"), str(HERE.parent / "tests" / "verification")]

import numpy as np  # noqa: E402
import test_bolts as tb  # noqa: E402

import jaxdem  # noqa: E402
from jaxdem.scene import parse_scene  # noqa: E402


def cases():
    """(name, scene dict, expected bolt forces (kN/m))."""
    out = []
    for label, apex, xs in [("wedge, 1 bolt (centroid)", (0.0, 1.5), [0.0]),
                            ("asym. wedge, 1 bolt", (0.4, 1.5), [0.4 / 3.0]),
                            ("asym. wedge, 2 bolts", (0.4, 1.5), [-0.5, 0.5]),
                            ("wedge, 3 bolts", (0.0, 1.5), [-0.6, 0.1, 0.55])]:
        for in_situ in (False, True):
            d = tb.key_block([((x, 0.15), (x, 2.6)) for x in xs], apex, in_situ=in_situ)
            out.append((f"{label}{', in-situ 0' if in_situ else ''}", d,
                        tb._vertical_bolt_forces(xs, apex)))
    for alpha, phi, beta in [(35, 25, 30), (40, 30, 60)]:
        d = tb.incline_with_bolt(alpha, phi, beta)
        out.append((f"incline {alpha}/{phi}, bolt at {beta}", d,
                    np.array([tb._incline_tension(alpha, phi, beta)])))
    return out


def main() -> None:
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"jaxdem {jaxdem.__file__}")
    print(f"machine: {platform.machine()}, {platform.processor() or '?'}, jax {jax.__version__}")
    print(f"{'scene':<34} {'status':<10} {'force err':>10} {'Newton it':>10} {'solve s':>9}")
    for name, d, expected in cases():
        scene = parse_scene(d)
        times = []
        for _ in range(args.repeat + 1):
            t0 = time.perf_counter()
            r = jaxdem.solve(scene)
            times.append(time.perf_counter() - t0 - r.timing["compile_s"])
        forces = np.array([b["force"] for b in r.bolts])
        err = float(np.max(np.abs(forces - expected) / np.abs(expected)))
        its = sum(sum(s["iterations"]) for s in r.stages)
        print(f"{name:<34} {r.status:<10} {err:>10.2e} {its:>10d} "
              f"{statistics.median(times[1:]):>9.3f}")


if __name__ == "__main__":
    main()
