"""The default back-analysis from random starts, and the coverage of its 2-sigma intervals.

1. Robustness: from ``--starts`` random starts (log-uniform within the default
   bounds, a factor 100 either side of the truth) the default optimiser
   (Gauss-Newton / Levenberg-Marquardt) fits noise-free measurements; a start
   succeeds when every parameter ends within 1% of the truth. Each line lists the
   local fits (the restarts after a rejected fit, ``back_analyse``'s ``restarts``) with
   their misfits and solves. Scenes:

   - ``tunnel``: the tests' jointed tunnel (75 blocks), set 1 kn and ks, from three
     section convergences and the crown's ux, uy;
   - ``example2``: seed example 2 with rigid blocks (no intact mesh, 72 blocks),
     foliation kn and ks, from its four sections;
   - ``slope``: seed example 4 (dry), kn of both sets, from its two sections and
     the crown's and crest's ux, uy (the command of issue 17).

   The bounds' centre is the truth, so a restart from it (the first restart point)
   starts at the answer; ``--centre C`` moves the bounds (and the starts' range) to a
   centre C times the truth, which leaves the restarts to the space-filling points.

2. Coverage (``--coverage N``): N replicates of 5% Gaussian noise on the tunnel's
   measurements (std 5%), each fitted from the truth's bounds' start; counts how
   often the truth lies within the reported estimate +- 2 std.

    python benchmarks/robust_back_analysis.py [--scenes tunnel example2 slope] [--starts 20]
        [--coverage 20] [--only 5 6 7] [--centre 3]

Not a test (minutes): the CI runs 3 starts on the tunnel (tests/test_back_analysis.py).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from scenes import jointed_tunnel  # noqa: E402

import jaxdem  # noqa: E402
from inverse import Observation, back_analyse  # noqa: E402
from jaxdem.differentiable import Problem  # noqa: E402
from jaxdem.scene import parse_scene

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
FACTOR = 100.0  # the default bounds: theta0 / 100 to theta0 * 100


def tunnel_scene():
    d = jointed_tunnel(water=False, bolts=False)
    d["monitors"] += [{"name": "height", "from": [0.0, 2.05], "to": [0.0, -2.05]},
                      {"name": "diag", "from": [-2.05, -1.5], "to": [1.5, 2.05]}]
    return parse_scene(d)


def example2_scene():
    d = jaxdem.load_scene(EXAMPLES / "seed_example2_tunnel.toml").data
    d = dict(d, domain={k: v for k, v in d["domain"].items() if k != "mesh_size"})
    return parse_scene(d)


def slope_scene():
    return jaxdem.load_scene(EXAMPLES / "seed_example4_slope_dry.toml")


SCENES = {
    "tunnel": (tunnel_scene, ["joints.set1.kn", "joints.set1.ks"]),
    "example2": (example2_scene, ["joints.foliation.kn", "joints.foliation.ks"]),
    "slope": (slope_scene, ["joints.set1.kn", "joints.set2.kn"]),
}


def measurements(scene, paths, rel_std=0.05, noise=None):
    """Every section's convergence and point's ux, uy at the scene's values, std 5%."""
    problem = Problem(scene, paths)
    y, _ = problem.evaluate(problem.theta0)
    obs = []
    for k, ((_, name, comp), v) in enumerate(zip(problem.keys, y, strict=True)):
        std = max(rel_std * abs(v), 1e-5)
        value = v if noise is None else v + std * noise[k]
        obs.append(Observation(name, float(value), std, component=comp))
    return obs, np.asarray(problem.theta0, float), problem


def robustness(name, starts, seed, max_iterations, only=None, centre=1.0):
    make, paths = SCENES[name]
    scene = make()
    obs, truth, problem = measurements(scene, paths)
    f = problem.function()
    middle = truth * centre  # the bounds' centre (in log), the truth unless --centre
    bounds = {p: (m / FACTOR, m * FACTOR) for p, m in zip(paths, middle, strict=True)}
    rng = np.random.default_rng(seed)
    u = rng.random((starts, len(paths)))
    ok, rows = 0, []
    for k in range(starts):
        if only is not None and k not in only:
            continue
        start = middle * FACTOR ** (2.0 * u[k] - 1.0)
        t0 = time.perf_counter()
        fit = back_analyse(scene, obs, paths, bounds=bounds, forward=(f, start),
                           max_iterations=max_iterations)
        wall = time.perf_counter() - t0
        est = np.array([fit.params[p] for p in paths])
        err = np.abs(est / truth - 1.0)
        good = bool(np.all(err < 0.01))
        ok += good
        solves = fit.evaluations["gradient"] + fit.evaluations["forward"]
        line = (f"{name:<9} start {k:2d} " + " ".join(f"{s:10.3g}" for s in start)
                + f"  max |err| {err.max():8.1e}  {fit.status:<24} {solves:3d} solves "
                f"{wall:6.1f} s  {'ok' if good else 'FAIL'}  local fits {len(fit.starts)}: "
                + ", ".join(f"{s['misfit']:.3g} ({s['solves']} solves, {s['status']})"
                            for s in fit.starts))
        if not good:
            line += f"  ({fit.message}; evaluations {fit.evaluations}; " \
                    f"misfit {fit.misfit:.3g}; estimate {est.tolist()})"
        print(line, flush=True)
        rows.append((good, fit))
    tried = len(rows)
    restarted = sum(len(fit.starts) > 1 for _, fit in rows)
    print(f"{name}: {restarted}/{tried} starts restarted after a rejected fit", flush=True)
    print(f"{name}: {ok}/{tried} starts reached the truth to 1% "
          f"({100.0 * ok / tried:.0f}%)", flush=True)
    return ok, rows


def coverage(replicates, seed):
    make, paths = SCENES["tunnel"]
    scene = make()
    clean, truth, problem = measurements(scene, paths)
    f = problem.function()
    rng = np.random.default_rng(seed)
    inside = total = 0
    z = []
    start = truth * np.array([2.0, 0.5])
    for k in range(replicates):
        noise = rng.standard_normal(len(problem.keys))
        obs, _, _ = measurements(scene, paths, noise=noise)
        fit = back_analyse(scene, obs, paths, forward=(f, start))
        for p, t in zip(paths, truth, strict=True):
            dev = (fit.params[p] - t) / fit.std[p]
            z.append(dev)
            inside += abs(dev) <= 2.0
            total += 1
        print(f"replicate {k:2d}: " + "  ".join(
            f"{p.split('.')[-1]} {fit.params[p]:.4g} +- {fit.std[p]:.3g} "
            f"({(fit.params[p] - t) / fit.std[p]:+.2f} std)"
            for p, t in zip(paths, truth, strict=True)) + f"  misfit {fit.misfit:.2f}",
            flush=True)
    z = np.array(z)
    print(f"coverage: the truth lies within +-2 std in {inside}/{total} estimates "
          f"({100.0 * inside / total:.0f}%); (estimate - truth)/std: mean {z.mean():+.2f}, "
          f"std {z.std():.2f} (1 if calibrated)")
    return inside, total


def main(argv=None):
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--starts", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-iterations", type=int, default=50)
    parser.add_argument("--only", type=int, nargs="*",
                        help="run only these start numbers (the same draws as the full run)")
    parser.add_argument("--centre", type=float, default=1.0,
                        help="centre of the bounds (in log) as a multiple of the truth "
                             "(default 1: the bounds of a fit started at the truth); the "
                             "starts are drawn within these bounds")
    parser.add_argument("--coverage", type=int, default=20,
                        help="noise replicates for the 2-sigma coverage (0: skip)")
    args = parser.parse_args(argv)
    print(f"machine: {platform.machine()}, {jax.devices()[0].device_kind}, jax {jax.__version__}")
    for name in args.scenes:
        robustness(name, args.starts, args.seed, args.max_iterations,
                   None if args.only is None else set(args.only), args.centre)
    if args.coverage:
        coverage(args.coverage, args.seed)


if __name__ == "__main__":
    main()
