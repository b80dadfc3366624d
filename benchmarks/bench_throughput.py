"""Throughput of a sweep: batched (vmap) solves against a Python loop of single solves.

The scene is the standing tunnel of ``bench_scaling.py`` (a 6 m tunnel in a
30 m square cut by two joint sets with cohesion, gravity in-situ stress), with
the joint spacing set for about 50 or about 500 blocks. Each sample draws the
first set's kn and the second set's friction angle (uniform, 1e6-4e6 kPa/m
and 25-40 degrees; seed 0), so the samples need different numbers of
iterations, as in a real sweep.

For each size and sample count, in one process and after compilation:
samples per second of ``jaxdem.solve_batch`` (all samples, chunked as it
chooses) and of a loop of ``jaxdem.solve`` over the first ``--loop`` samples
(the loop's rate does not depend on how many samples it is given), their
ratio, and the accuracy: the largest difference of the batch's monitors from
the loop's, relative to the largest monitor value. Medians of ``--repeats``.

    python benchmarks/bench_throughput.py                          # 50 and 500 blocks, 64 and 1,024
    python benchmarks/bench_throughput.py --spacings 3.5 --samples 64 --loop 16
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

PARAMS = ["joints.set1.kn", "joints.set2.friction_deg"]


def samples(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(1e6, 4e6, n), rng.uniform(25.0, 40.0, n)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", type=float, nargs="+", default=[7.0, 1.5],
                    help="joint spacings (m): 7.0 gives 52 blocks, 1.5 gives 492")
    ap.add_argument("--samples", type=int, nargs="+", default=[64, 1024])
    ap.add_argument("--loop", type=int, default=16, help="samples solved by the loop")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--chunk", type=int, default=None)
    args = ap.parse_args()

    import jax
    from bench_scaling import scene as standing_tunnel

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.core import model as model_mod
    from jaxdem.scene import parse_scene

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} "
          f"({jax.default_backend()}: {jax.devices()[0].device_kind}), repeats {args.repeats}")
    head = (f"{'blocks':>6} {'solver':>6} {'samples':>7} {'chunk':>5} {'compile s':>9} "
            f"{'batch /s':>9} {'loop /s':>8} {'ratio':>6} {'its mean/max':>12} {'rel. diff':>9}")
    print(head)
    for spacing in args.spacings:
        scene = parse_scene(standing_tunnel(spacing, "auto"))
        theta_all = samples(max(args.samples))
        # The loop: single solves (compiled once by a first solve).
        jaxdem.solve(scene)
        loop_rates, loop_mon = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            mon = []
            for row in theta_all[:args.loop]:
                r = jaxdem.solve(scene, set=dict(zip(PARAMS, row, strict=True)))
                mon.append(r.monitors["vertical"]["convergence"] if r.converged else np.nan)
            loop_rates.append(args.loop / (time.perf_counter() - t0))
            loop_mon = np.array(mon)
        loop_rate = statistics.median(loop_rates)
        for S in args.samples:
            theta = theta_all[:S]
            first = jaxdem.solve_batch(scene, PARAMS, theta, chunk=args.chunk)
            rates = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                res = jaxdem.solve_batch(scene, PARAMS, theta, chunk=args.chunk)
                rates.append(S / (time.perf_counter() - t0))
            rate = statistics.median(rates)
            m = res.monitors["vertical"][:args.loop]
            n = min(len(m), len(loop_mon))
            diff = np.nanmax(np.abs(m[:n] - loop_mon[:n])) / np.nanmax(np.abs(loop_mon[:n]))
            blocks = model_mod.build(scene)[2].n_rock
            solver = model_mod.build(scene)[0].linear_solver
            print(f"{blocks:>6} {solver:>6} {S:>7} {res.timing['chunk']:>5} "
                  f"{first.timing['compile_s']:>9.1f} {rate:>9.2f} {loop_rate:>8.2f} "
                  f"{rate / loop_rate:>6.2f} "
                  f"{res.iterations.mean():>6.1f}/{res.iterations.max():<5d} "
                  f"{diff:>9.1e}", flush=True)


if __name__ == "__main__":
    main()
