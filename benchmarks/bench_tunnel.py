"""Tunnel benchmark: a circular tunnel in jointed rock at about 500, 2,000 and 10,000 blocks.

A 30 m x 30 m domain cut by two joint sets (30 and 120 degrees) whose spacing
sets the block count, a 6 m diameter tunnel excavated from a gravity in-situ
state (K0 = 1, 40 m deep) over 2 load steps, roller walls on the sides and
top, a fixed base. For each size, in a fresh process: rock-mass generation and
model build time, compile time, solve time, peak memory, the tunnel's
horizontal and vertical convergence, and the accuracy measures available
without a closed form for jointed rock: the global force imbalance and, for
the converged state, the largest relative residual.

    python benchmarks/bench_tunnel.py                   # ~500, 2,000, 10,000 blocks
    python benchmarks/bench_tunnel.py --spacings 1.35   # one size
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time


def scene(spacing: float) -> dict:
    joint = {"kn": 2.0e6, "ks": 5.0e5, "friction_deg": 30.0, "spacing": spacing}
    return {
        "scene": {"name": f"tunnel, joint spacing {spacing} m"},
        "solver": {"load_steps": 2},
        "materials": {"rock": {"E": 2.0e7, "nu": 0.25, "unit_weight": 26.0, "cohesion": 2000.0,
                               "friction_deg": 45.0, "tensile_strength": 1000.0}},
        "joints": {"set1": dict(joint, dip_deg=30.0), "set2": dict(joint, dip_deg=120.0)},
        "domain": {"outline": [[-15, -15], [15, -15], [15, 15], [-15, 15]], "material": "rock"},
        "excavations": [{"name": "tunnel", "shape": "circle", "center": [0.0, 0.0],
                         "radius": 3.0}],
        "in_situ": {"mode": "gravity", "k0": 1.0, "surface_y": 40.0},
        "boundaries": [{"side": "bottom", "condition": "fixed"}]
        + [{"side": s, "condition": "roller"} for s in ("left", "right", "top")],
        "monitors": [{"name": "horizontal", "from": [-3.05, 0.0], "to": [3.05, 0.0]},
                     {"name": "vertical", "from": [0.0, -3.05], "to": [0.0, 3.05]}],
    }


def run_one(spacing: float) -> dict:
    import jax

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.scene import parse_scene

    t0 = time.perf_counter()
    sc = parse_scene(scene(spacing))
    parse_s = time.perf_counter() - t0
    r = jaxdem.solve(sc)
    jax.block_until_ready(0)
    exc = r.stages[-1]
    return dict(spacing=spacing, blocks=len(r.blocks), status=r.status, parse_s=parse_s,
                build_s=r.timing["build_s"], compile_s=r.timing["compile_s"],
                solve_s=r.timing["solve_s"], iterations=sum(exc["iterations"]),
                horizontal_mm=1e3 * r.monitors["horizontal"]["convergence"],
                vertical_mm=1e3 * r.monitors["vertical"]["convergence"],
                imbalance=r.equilibrium["imbalance"], residual=max(exc["residual"]),
                peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", type=float, nargs="+", default=[1.35, 0.67, 0.3])
    ap.add_argument("--one", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one)))
        return
    import jax

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}, jax {jax.__version__} ({jax.devices()[0].platform})")
    print(f"{'spacing m':>9} {'blocks':>7} {'status':>10} {'parse s':>8} {'build s':>8} "
          f"{'compile s':>9} {'solve s':>8} {'its':>5} {'conv. h mm':>10} {'conv. v mm':>10} "
          f"{'imbalance':>9} {'residual':>9} {'peak MB':>8}")
    for s in args.spacings:
        out = subprocess.run([sys.executable, __file__, "--one", str(s)], capture_output=True,
                             text=True)
        if out.returncode:
            print(f"{s:>9} failed: {out.stderr.strip().splitlines()[-1]}")
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{r['spacing']:>9} {r['blocks']:>7} {r['status']:>10} {r['parse_s']:>8.2f} "
              f"{r['build_s']:>8.2f} {r['compile_s']:>9.2f} {r['solve_s']:>8.2f} "
              f"{r['iterations']:>5} {r['horizontal_mm']:>10.3f} {r['vertical_mm']:>10.3f} "
              f"{r['imbalance']:>9.1e} {r['residual']:>9.1e} {r['peak_mb']:>8.0f}", flush=True)


if __name__ == "__main__":
    main()
