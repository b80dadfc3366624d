"""Model only what a scene needs: the cost of the bolt and water kernels in a scene without them.

A scene without bolts or a water table compiles an increment with no bolt rows
and no pore-pressure term (``Model.n_bolts`` and ``Model.has_water`` are static
fields: the kernels are left out of the program, not masked). This benchmark
measures what that saves: the standing tunnel of ``bench_scaling.py`` (about
50 and 500 blocks), as it is, and with the kernels forced in by entries that
change nothing: a water table far below the model (no pore pressure anywhere)
and a bolt of negligible stiffness (1e-9 kN/m). For each: compile time of the
increment, solve time after compilation (median of repeats), the size of the
compiled program (HLO instructions) and the difference of the vertical
convergence from the scene without the kernels (relative).

    python benchmarks/bench_kernels.py
    python benchmarks/bench_kernels.py --spacings 7.0 --repeats 5
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def variants(base: dict) -> dict:
    water = {"table": [[-15.0, -1000.0], [15.0, -1000.0]]}
    bolt = {"from": [0.0, 3.1], "to": [0.0, 7.0], "stiffness": 1e-9, "yield_force": 1e3,
            "anchor_capacity": 1e3}
    out = {"none (as the scene is)": base}
    for name, extra in (("water kernel", {"water": water}), ("bolt kernel", {"bolts": [bolt]}),
                        ("both", {"water": water, "bolts": [bolt]})):
        d = copy.deepcopy(base)
        d.update(copy.deepcopy(extra))
        out[name] = d
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", type=float, nargs="+", default=[7.0, 1.5])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    import jax
    from bench_scaling import scene as standing_tunnel

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.core import compile_cache
    from jaxdem.core import model as model_mod
    from jaxdem.core.increment import increment
    from jaxdem.core.loads import make_loads
    from jaxdem.scene import parse_scene

    jaxdem.config.compilation_cache(False)  # measure compilation, not the cache
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} "
          f"({jax.default_backend()}), repeats {args.repeats}")
    print(f"{'blocks':>6} {'kernels':<24} {'compile s':>9} {'solve s':>8} {'solve ratio':>11} "
          f"{'HLO ops':>8} {'rel. diff':>9}")
    for spacing in args.spacings:
        rows = {}
        for name, d in variants(standing_tunnel(spacing, "auto")).items():
            scene = parse_scene(d)
            compile_cache._COMPILED.clear()
            first = jaxdem.solve(scene)
            times = [jaxdem.solve(scene).timing["solve_s"] for _ in range(args.repeats)]
            m, s, _ = model_mod.build(scene)
            loads = make_loads(m, jax.numpy.zeros((m.n_blocks, m.ndof)))
            text = increment.lower(m, s, loads).compile().as_text()
            ops = sum(1 for line in text.splitlines() if " = " in line and "%" in line)
            conv = first.monitors["vertical"]["convergence"]
            rows[name] = (len(first.blocks), first.timing["compile_s"], statistics.median(times),
                          ops, conv)
        base = rows["none (as the scene is)"]
        for name, (n, comp, solve_s, ops, conv) in rows.items():
            print(f"{n:>6} {name:<24} {comp:>9.2f} {solve_s:>8.3f} {solve_s / base[2]:>11.2f} "
                  f"{ops:>8d} {abs(conv - base[4]) / abs(base[4]):>9.1e}", flush=True)


if __name__ == "__main__":
    main()
