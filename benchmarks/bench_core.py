"""Core engine benchmark: contact detection and one increment on jointed assemblies.

A regular jointed rock mass: rows of rectangular blocks (bedding joints) with
vertical cross joints staggered by half a block (a brick pattern), in a box
with a fixed base and roller sides, loaded by self-weight in one increment.
For each size and dtype, in a fresh process (so that peak memory is its own):
build time, compile time of detection and of the increment, median time of
contact detection (broad + narrow phase) and of one increment's solve, and the
accuracy of the answer: the settlement of the top row against the closed form
of a column of springs in series (eqs. 6-7 with Le), and the global force
imbalance.

    python benchmarks/bench_core.py            # 100, 1,000, 10,000 blocks
    python benchmarks/bench_core.py --sizes 100 1000 --repeats 5
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
import time


def assembly(n_target: int, dtype: str) -> dict:
    """Brick-pattern block assembly of about n_target blocks (2 m x 1 m bricks)."""
    rows = max(2, int(round((n_target / 2) ** 0.5)))
    cols = max(2, int(round(n_target / rows)))
    w, h = 2.0, 1.0
    width = cols * w
    blocks = []
    for r in range(rows):
        y0, y1 = r * h, (r + 1) * h
        if r % 2:  # staggered row: half bricks at both ends
            edges = [0.0] + [w / 2 + c * w for c in range(cols)] + [width]
        else:
            edges = [c * w for c in range(cols + 1)]
        for x0, x1 in zip(edges[:-1], edges[1:], strict=True):
            blocks.append({"vertices": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]],
                           "material": "rock"})
    top_y = rows * h
    return {
        "scene": {"name": f"brick assembly {len(blocks)}"},
        "solver": {"load_steps": 1, "dtype": dtype},
        "materials": {"rock": {"E": 1e7, "nu": 0.25, "unit_weight": 25.0}},
        "joints": {"j": {"kn": 1e6, "ks": 5e5, "friction_deg": 35.0, "cohesion": 50.0}},
        "blocks": blocks,
        "boundaries": [{"side": "bottom", "condition": "fixed"},
                       {"side": "left", "condition": "roller"},
                       {"side": "right", "condition": "roller"}],
        "monitors": [{"name": "top", "point": [width / 2, top_y - h / 2]}],
        "_rows": rows,
    }


def closed_form_settlement(rows: int, h=1.0, E=1e7, nu=0.25, kn0=1e6, gamma=25.0) -> float:
    """Top-row settlement of a laterally confined column of rows (springs in series).

    Each bedding joint carries the weight of the rows above it per metre,
    gamma * h * (rows - k); its stiffness per unit length is
    1 / (h/2 / kn_i * 2 + 1/kn0) (eq. 7); the base contact with the rigid
    wall is kn_i / (h/2) (no joint term).
    """
    kn_i = E / (1 - nu**2)
    k_joint = 1.0 / (h / kn_i + 1.0 / kn0)
    k_base = kn_i / (h / 2)
    settle = gamma * h * rows / k_base
    for k in range(1, rows):
        settle += gamma * h * (rows - k) / k_joint
    return settle


def run_one(n: int, dtype: str, repeats: int) -> dict:
    import jax

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem import solver
    from jaxdem.core import model as model_mod
    from jaxdem.core._contact import broad_phase, narrow_phase
    from jaxdem.core.loads import make_loads
    from jaxdem.core.status import Status, global_imbalance
    from jaxdem.scene import parse_scene

    d = assembly(n, dtype)
    rows = d.pop("_rows")
    t0 = time.perf_counter()
    scene = parse_scene(d)
    model, state, layout = model_mod.build(scene)
    jax.block_until_ready(state.verts)
    build_s = time.perf_counter() - t0

    def detect(model, verts, centroid, capacity):
        pairs, count, full = broad_phase(model, verts, capacity, state.alive)
        geo, _ = narrow_phase(model, verts, centroid, pairs)
        return pairs, count, full, geo.gap

    det = jax.jit(detect, static_argnums=3)
    t0 = time.perf_counter()
    det_c = det.lower(model, state.verts, state.centroid, state.capacity).compile()
    detect_compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = det_c(model, state.verts, state.centroid)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    detect_s = statistics.median(times)
    n_pairs = int(out[1])

    lam = make_loads(model, model.f_ext)  # all of the self-weight in one increment
    # First call: compile (and grow capacity if needed).
    t0 = time.perf_counter()
    model, new, info, compile_s = solver.run_increment(model, state, lam)
    jax.block_until_ready(new.verts)
    if new.capacity != state.capacity:
        state = jax.tree.map(lambda x: x, state)
        from jaxdem.core.state import grow_capacity
        state = grow_capacity(state, new.capacity)
    times = []
    for _ in range(max(1, repeats // 2)):
        t0 = time.perf_counter()
        _, new, info, dt = solver.run_increment(model, state, lam)
        jax.block_until_ready(new.verts)
        times.append(time.perf_counter() - t0 - dt)
    solve_s = statistics.median(times)
    status = Status.of(info.status).label
    from jaxdem.results import monitor_values

    uy = -monitor_values(layout, new)["top"]["displacement"][1]
    ref = closed_form_settlement(rows)
    imbalance = global_imbalance(info.balance)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return dict(blocks=layout.n_rock, dtype=dtype, solver=model.linear_solver,
                pairs=n_pairs, build_s=build_s, detect_compile_s=detect_compile_s,
                detect_s=detect_s, increment_compile_s=compile_s, increment_s=solve_s,
                iterations=int(info.iterations), status=status,
                settlement_err=abs(uy - ref) / ref, imbalance=imbalance, peak_mb=peak_mb)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 10000])
    ap.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(int(args.one[0]), args.one[1], args.repeats)))
        return
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}")
    import jax

    print(f"jax {jax.__version__}, device {jax.devices()[0].platform}; medians of {args.repeats} "
          "detections and {0} increments, each size in a fresh process".format(
              max(1, args.repeats // 2)))
    head = (f"{'blocks':>7} {'dtype':>7} {'solver':>6} {'pairs':>7} {'build s':>8} "
            f"{'det. comp s':>11} {'detect ms':>10} {'incr. comp s':>12} {'increment s':>11} "
            f"{'its':>4} {'status':>10} {'settle err':>10} {'imbalance':>9} {'peak MB':>8}")
    print(head)
    for n in args.sizes:
        for dt in args.dtypes:
            out = subprocess.run([sys.executable, __file__, "--one", str(n), dt,
                                  "--repeats", str(args.repeats)],
                                 capture_output=True, text=True)
            if out.returncode:
                print(f"{n:>7} {dt:>7} failed: {out.stderr.strip().splitlines()[-1]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"{r['blocks']:>7} {r['dtype']:>7} {r['solver']:>6} {r['pairs']:>7} "
                  f"{r['build_s']:>8.2f} {r['detect_compile_s']:>11.2f} "
                  f"{1e3 * r['detect_s']:>10.2f} {r['increment_compile_s']:>12.2f} "
                  f"{r['increment_s']:>11.3f} {r['iterations']:>4} {r['status']:>10} "
                  f"{r['settlement_err']:>10.2e} {r['imbalance']:>9.1e} {r['peak_mb']:>8.0f}",
                  flush=True)


if __name__ == "__main__":
    main()
