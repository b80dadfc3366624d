"""Scaling benchmark: the linear solver paths on a jointed tunnel of ~500 to ~10,000 blocks.

The tunnel of ``bench_tunnel.py`` (30 m square, two joint sets at 30 and 120
degrees whose spacing sets the block count, 6 m circular tunnel, gravity
in-situ stress K0 = 1 at 40 m depth, 2 load steps), with joints given a
cohesion of 1,000 kPa and a tensile strength of 500 kPa so that the
excavation stands (with the friction-only joints of ``bench_tunnel.py`` the
crown unravels at 2,000 blocks and more). Each size and linear solver runs in
a fresh process: build, compile and solve time (median of the repeats; the
first solve compiles), Newton iterations, peak resident memory of the process
(``resource.getrusage``), and the accuracy: the final relative residual, and
the largest difference of a block displacement from the sparse direct
solution, relative to the largest displacement.

Paths: "dense" (Cholesky on the assembled matrix; skipped above
``--dense-up-to`` blocks: at 10,464 blocks the matrix alone is 7.9 GB and
one factorisation about 1e13 flops), "sparse" (SciPy's SuperLU through a host
callback) and "cg" (matrix-free conjugate gradients, block-Jacobi
preconditioned, inexact Newton).

    python benchmarks/bench_scaling.py                     # 596, 2,222, 10,464 blocks
    python benchmarks/bench_scaling.py --spacings 0.67 --solvers sparse cg --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_tunnel import scene as tunnel_scene  # noqa: E402


def scene(spacing: float, linear_solver: str) -> dict:
    """The standing tunnel: ``bench_tunnel.scene`` with cohesive joints."""
    d = tunnel_scene(spacing)
    for j in d["joints"].values():
        j.update(cohesion=1000.0, tensile_strength=500.0)
    d["scene"]["name"] += ", cohesive joints"
    d["solver"]["linear_solver"] = linear_solver
    return d


def run_one(spacing: float, solver: str, repeats: int, out: str) -> dict:
    import jax

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.scene import parse_scene

    sc = parse_scene(scene(spacing, solver))
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = jaxdem.solve(sc)
        jax.block_until_ready(0)
        runs.append((r, time.perf_counter() - t0))
    r = runs[0][0]
    exc = r.stages[-1]
    u = np.array([b["u"] for b in r.blocks])
    np.save(out, u)
    solve = [x.timing["solve_s"] for x, _ in runs]
    return dict(spacing=spacing, solver=solver, blocks=len(r.blocks), status=r.status,
                build_s=statistics.median(x.timing["build_s"] for x, _ in runs),
                compile_s=r.timing["compile_s"], solve_s=statistics.median(solve),
                solve_all=solve, iterations=sum(sum(s["iterations"]) for s in r.stages),
                residual=max(exc["residual"]),
                vertical_mm=1e3 * r.monitors["vertical"]["convergence"],
                peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", type=float, nargs="+", default=[1.35, 0.67, 0.3])
    ap.add_argument("--solvers", nargs="+", default=["dense", "sparse", "cg"])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--dense-up-to", type=int, default=2500, help="blocks")
    ap.add_argument("--one", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        s, solver, repeats, out = args.one
        print(json.dumps(run_one(float(s), solver, int(repeats), out)))
        return
    import jax

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}, jax {jax.__version__} ({jax.devices()[0].platform}), "
          f"repeats {args.repeats}")
    print(f"{'blocks':>7} {'solver':>7} {'status':>10} {'build s':>8} {'compile s':>9} "
          f"{'solve s':>8} {'its':>5} {'peak MB':>8} {'residual':>9} {'du vs sparse':>12} "
          f"{'conv. v mm':>10}")
    solvers = sorted(args.solvers, key=lambda x: x != "sparse")  # the reference first
    tmp = tempfile.mkdtemp()
    for s in args.spacings:
        ref = None
        for solver in solvers:
            path = os.path.join(tmp, f"{s}_{solver}.npy")
            if solver == "dense" and _blocks(s) > args.dense_up_to:
                print(f"{_blocks(s):>7} {solver:>7} skipped: {3 * _blocks(s):,} unknowns, "
                      f"matrix {(3 * _blocks(s)) ** 2 * 8 / 1e9:.1f} GB", flush=True)
                continue
            out = subprocess.run([sys.executable, __file__, "--one", str(s), solver,
                                  str(args.repeats), path], capture_output=True, text=True)
            if out.returncode:
                print(f"{s:>7} {solver:>7} failed: {out.stderr.strip().splitlines()[-1]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            u = np.load(path)[:, :2]
            if solver == "sparse":
                ref = u
            diff = (f"{np.max(np.abs(u - ref)) / np.max(np.abs(ref)):12.1e}"
                    if ref is not None else f"{'-':>12}")
            print(f"{r['blocks']:>7} {solver:>7} {r['status']:>10} {r['build_s']:>8.2f} "
                  f"{r['compile_s']:>9.2f} {r['solve_s']:>8.2f} {r['iterations']:>5} "
                  f"{r['peak_mb']:>8.0f} {r['residual']:>9.1e} {diff} "
                  f"{r['vertical_mm']:>10.4f}", flush=True)


def _blocks(spacing: float) -> int:
    """Rock blocks of the tunnel at this joint spacing (generated, host only)."""
    from jaxdem import rockmass
    from jaxdem.scene import parse_scene

    return len(rockmass.generate(parse_scene(scene(spacing, "auto"))).pieces)


if __name__ == "__main__":
    main()
