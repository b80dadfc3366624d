"""Build of large scenes (issue 30): the host side before the first increment, by phase.

Each scene is read, validated, generated and laid out as device arrays, as
``jaxdem run`` does before it compiles and solves, ``--repeats`` times in one
process (JAX initialised first by a small build); the table gives the median
of each phase (s):

- read: the TOML file (``tomllib``); none for a scene given as a dict;
- validate: :func:`jaxdem.scene.parse_scene`, every check of the scene;
- generate: :func:`jaxdem.rockmass.generate`, the cutting of a ``[domain]``
  (part of build: timed apart in a separate call);
- build: :func:`jaxdem.core.model.build` (generation included): areas,
  centroids, moments, walls, joints, loads, bolts, monitors, the contact
  capacity, the transfer to the device;
- data: :func:`jaxdem.solver.scene_data`, the driver's loads;
- host: read + validate + build + data, all the host does before the first
  increment compiles and runs.

Correctness: the largest difference of the model's areas, centroids and
r_g^2 = J / A (polar moment about the centroid over the area, from the
pseudo-mass) from the scalar reference functions, evaluated block by block:
:func:`jaxdem.geometry.signed_area`, :func:`jaxdem.geometry.centroid` and the
shoelace sum of J / A about that centroid in plain Python here (relative to the
block's area, size sqrt(area) and r_g^2).

Scenes: grid100, grid70 (benchmarks/bench_time_to_answer.py's grid of 1 m
blocks on a base, 10,001 and 4,901 blocks, as explicit ``[[blocks]]`` in a
TOML file), tunnel10k (bench_scaling.py's jointed tunnel at spacing 0.3 m,
10,464 generated blocks, a dict), ex2 and ex4wet (seed examples 2 and 4 as
shipped) and demo (``jaxdem demo``'s scene).

    PYTHONPATH=. python benchmarks/bench_build.py                    # all, 3 repeats
    PYTHONPATH=. python benchmarks/bench_build.py --cases grid100 demo --repeats 5
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11, as jaxdem.scene reads files
    import tomli as tomllib

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

PHASES = ("read", "validate", "generate", "build", "data", "host")


def scenes() -> dict:
    """name -> a TOML path or a scene dict."""
    from bench_scaling import scene as scaling_scene
    from bench_time_to_answer import grid_scene, to_toml

    out: dict = {}
    folder = Path(tempfile.mkdtemp(prefix="bench-build-"))
    for n in (100, 70):
        path = folder / f"grid{n}.toml"
        path.write_text(to_toml(grid_scene(n)))
        out[f"grid{n}"] = path
    out["tunnel10k"] = scaling_scene(0.3, "auto")
    out["ex2"] = HERE.parent / "examples" / "seed_example2_tunnel.toml"
    out["ex4wet"] = HERE.parent / "examples" / "seed_example4_slope_wet.toml"
    out["demo"] = HERE.parent / "jaxdem" / "data" / "demo.toml"
    return out


def _rg2(v: np.ndarray, c: np.ndarray) -> float:
    """J / A of one polygon about point ``c`` (m2), by the shoelace formulas summed vertex by
    vertex (the scalar definition)."""
    pts = [(float(x) - c[0], float(y) - c[1]) for x, y in v]
    n = len(pts)
    a = j = 0.0
    for k in range(n):
        (x0, y0), (x1, y1) = pts[k], pts[(k + 1) % n]
        w = x0 * y1 - x1 * y0
        a += 0.5 * w
        j += w * (x0 * x0 + x0 * x1 + x1 * x1 + y0 * y0 + y0 * y1 + y1 * y1) / 12.0
    return j / a


def model_error(model, state, layout) -> float:
    """Largest relative difference of the model's areas, centroids and r_g^2 from the scalar
    references (:func:`jaxdem.geometry.signed_area`, :func:`jaxdem.geometry.centroid`,
    :func:`_rg2`) over the rock blocks."""
    from jaxdem import geometry

    n = layout.n_rock
    area = np.asarray(model.area)[:n]
    cent = np.asarray(state.centroid)[:n]
    pm = np.asarray(model.pseudo_mass)
    rg2 = pm[:n, 2] / pm[:n, 0]
    worst = 0.0
    for i, v in enumerate(layout.polygons):
        a, c = geometry.signed_area(v), geometry.centroid(v)
        r = _rg2(v, c)
        worst = max(worst, abs(area[i] - a) / a,
                    float(np.hypot(*(cent[i] - c))) / np.sqrt(a), abs(rg2[i] - r) / r)
    return worst


def run_case(source, repeats: int) -> dict:
    import jax

    from jaxdem import rockmass, solver
    from jaxdem.core import model as model_mod
    from jaxdem.scene import parse_scene

    rows = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        if isinstance(source, dict):
            data, name = source, "<dict>"
        else:
            data, name = tomllib.loads(Path(source).read_text()), str(source)
        t1 = time.perf_counter()
        scene = parse_scene(data, source=name)
        t2 = time.perf_counter()
        model, state, layout = model_mod.build(scene)
        jax.block_until_ready(state.verts)
        t3 = time.perf_counter()
        solver.scene_data(scene, layout)
        t4 = time.perf_counter()
        rockmass.generate(scene)
        t5 = time.perf_counter()
        rows.append(dict(read=t1 - t0, validate=t2 - t1, build=t3 - t2, data=t4 - t3,
                         generate=t5 - t4, host=t4 - t0))
    med = {k: statistics.median(r[k] for r in rows) for k in PHASES}
    med["blocks"] = layout.n_rock
    med["error"] = model_error(model, state, layout)
    return med


def main() -> None:
    import jaxdem.config

    jaxdem.config.configure()
    cases = scenes()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(cases), choices=list(cases))
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    import jax

    run_case(cases["ex4wet"], 1)  # JAX's start and first transfers, outside the table
    print(f"# {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}, "
          f"python {platform.python_version()}; medians of {args.repeats} builds (s)")
    print(f"{'scene':>10} {'blocks':>6} " + " ".join(f"{p:>8}" for p in PHASES)
          + f" {'max rel. diff.':>14}")
    for case in args.cases:
        r = run_case(cases[case], args.repeats)
        print(f"{case:>10} {r['blocks']:>6} " + " ".join(f"{r[p]:>8.3f}" for p in PHASES)
              + f" {r['error']:>14.1e}", flush=True)


if __name__ == "__main__":
    main()
