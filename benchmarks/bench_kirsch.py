"""Circular opening in intact elastic rock (mesh_size cells) against the Kirsch solution.

In plane strain, excavating a circular opening of radius a under a vertical
in-situ stress p and a horizontal one K p moves its wall in by
u(theta) = p a / (4 G) [(1 + K) - (1 - K)(3 - 4 nu) cos 2 theta] (theta from the
horizontal; Kirsch 1898; Jaeger, Cook & Zimmerman, Fundamentals of Rock
Mechanics, 8.4), so the horizontal diameter shortens by 2 u(0) and the vertical
one by 2 u(90). K = 1 depends on the shear modulus only; K = 0.5 also on
Poisson's ratio (the factor 3 - 4 nu), which a rigid-cell lattice misses.

The rock is a 64a x 64a square with roller walls (a thick-cylinder estimate puts
their stiffening below 0.3%), cut into deformable constant-strain triangles of
``mesh_size`` h at the opening growing to ``mesh_max_size`` 4a far from it. The
table gives the measured convergences over the closed form and the error of
their mean (K = 1) or the larger of the two errors (K = 0.5).

    python benchmarks/bench_kirsch.py [--sizes 1.0 0.5 0.25 0.125] [--k0 1.0 0.5]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

P, A, E, NU, R, H_MAX = 1000.0, 1.0, 1e7, 0.25, 32.0, 4.0


def scene(h: float, h_max: float | None = H_MAX, k0: float = 1.0, half_width: float = R) -> dict:
    """The Kirsch scene: mesh size h (m) at the opening, K = k0, a square of 2 half_width."""
    R = half_width  # noqa: N806
    return {
        "scene": {"name": f"Kirsch, mesh {h} m"},
        "solver": {"load_steps": 1},
        "materials": {"rock": {"E": E, "nu": NU, "unit_weight": 0.0, "cohesion": 1e5,
                               "tensile_strength": 1e5, "friction_deg": 45.0}},
        "domain": {"outline": [[-R, -R], [R, -R], [R, R], [-R, R]], "material": "rock",
                   "mesh_size": h, **({"mesh_max_size": h_max} if h_max else {})},
        "excavations": [{"name": "hole", "shape": "circle", "center": [0.0, 0.0], "radius": A}],
        "in_situ": {"mode": "uniform", "sigma_xx": k0 * P, "sigma_yy": P, "sigma_xy": 0.0},
        "boundaries": [{"side": s, "condition": "roller"}
                       for s in ("left", "right", "top", "bottom")],
        "monitors": [{"name": "h", "from": [-A, 0.0], "to": [A, 0.0]},
                     {"name": "v", "from": [0.0, -A], "to": [0.0, A]}],
    }


def closed_form(k0: float) -> tuple[float, float]:
    """Horizontal and vertical convergence (m) of the opening, Kirsch."""
    G = E / (2 * (1 + NU))
    f = P * A / (2 * G)
    return f * ((1 + k0) - (1 - k0) * (3 - 4 * NU)), f * ((1 + k0) + (1 - k0) * (3 - 4 * NU))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1.0, 0.5, 0.25, 0.125])
    ap.add_argument("--k0", type=float, nargs="+", default=[1.0, 0.5])
    args = ap.parse_args()
    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.scene import parse_scene

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores")
    print(f"{'K':>4} {'mesh m':>7} {'a/mesh':>7} {'blocks':>7} {'status':>10} {'h/closed':>9} "
          f"{'v/closed':>9} {'error':>7} {'solve s':>8} {'total s':>8}")
    for k0 in args.k0:
        ch, cv = closed_form(k0)
        for h in args.sizes:
            t0 = time.perf_counter()
            r = jaxdem.solve(parse_scene(scene(h, k0=k0)))
            dt = time.perf_counter() - t0
            rh = r.monitors["h"]["convergence"] / ch
            rv = r.monitors["v"]["convergence"] / cv
            err = abs(0.5 * (rh + rv) - 1.0) if k0 == 1.0 else max(abs(rh - 1), abs(rv - 1))
            print(f"{k0:>4} {h:>7} {A / h:>7.1f} {len(r.blocks):>7} {r.status:>10} {rh:>9.3f} "
                  f"{rv:>9.3f} {err:>7.1%} {r.timing['solve_s']:>8.1f} {dt:>8.1f}", flush=True)


if __name__ == "__main__":
    main()
