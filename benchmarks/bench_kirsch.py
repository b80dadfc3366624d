"""Circular opening in intact elastic rock (mesh_size cells) against the Kirsch solution.

Hydrostatic in-situ stress p in plane strain: the wall of a circular opening of
radius a moves in by u = p a (1 + nu) / E (Kirsch 1898; Jaeger, Cook &
Zimmerman, Fundamentals of Rock Mechanics, 8.4), so a diameter shortens by 2u.
The rock is a 16a x 16a square (roller walls, whose confinement changes the
answer by about (a/R)^2 = 1.6%) of rigid square cells bonded by intact-rock
springs (eqs. 3-7), subdivided with domain.mesh_size. The table gives the
measured convergence over the closed form, per mesh size.

    python benchmarks/bench_kirsch.py [--sizes 1.0 0.5 0.25]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

P, A, E, NU, R = 1000.0, 1.0, 1e7, 0.25, 8.0


def scene(h: float) -> dict:
    return {
        "scene": {"name": f"Kirsch, mesh {h} m"},
        "solver": {"load_steps": 1},
        "materials": {"rock": {"E": E, "nu": NU, "unit_weight": 0.0, "cohesion": 1e5,
                               "tensile_strength": 1e5, "friction_deg": 45.0}},
        "domain": {"outline": [[-R, -R], [R, -R], [R, R], [-R, R]], "material": "rock",
                   "mesh_size": h},
        "excavations": [{"name": "hole", "shape": "circle", "center": [0.0, 0.0], "radius": A}],
        "in_situ": {"mode": "uniform", "sigma_xx": P, "sigma_yy": P, "sigma_xy": 0.0},
        "boundaries": [{"side": s, "condition": "roller"}
                       for s in ("left", "right", "top", "bottom")],
        "monitors": [{"name": "h", "from": [-A, 0.0], "to": [A, 0.0]},
                     {"name": "v", "from": [0.0, -A], "to": [0.0, A]}],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1.0, 0.5, 0.25])
    args = ap.parse_args()
    import jaxdem
    from jaxdem.scene import parse_scene

    ref = 2 * P * A * (1 + NU) / E
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; closed form 2u = {ref:.4e} m")
    print(f"{'mesh m':>7} {'a/mesh':>7} {'blocks':>7} {'status':>10} {'h conv/closed':>13} "
          f"{'v conv/closed':>13} {'error':>7} {'time s':>7}")
    for h in args.sizes:
        t0 = time.perf_counter()
        r = jaxdem.solve(parse_scene(scene(h)))
        dt = time.perf_counter() - t0
        ch = r.monitors["h"]["convergence"] / ref
        cv = r.monitors["v"]["convergence"] / ref
        err = abs(0.5 * (ch + cv) - 1.0)
        print(f"{h:>7} {A / h:>7.1f} {len(r.blocks):>7} {r.status:>10} {ch:>13.3f} {cv:>13.3f} "
              f"{err:>7.1%} {dt:>7.1f}", flush=True)


if __name__ == "__main__":
    main()
