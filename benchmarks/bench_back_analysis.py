"""Back-analysis three ways: implicit gradients, Nelder-Mead, finite-difference gradients.

The same identical-twin problem (the small jointed tunnel of the tests, whose
convergences and crown displacement at known joint stiffnesses are the
"measurements", 5% standard deviation) is fitted from the same start:

- ``L-BFGS, grad``: ``inverse.back_analyse`` (optax L-BFGS; derivatives from one
  solve with sensitivities, ``jaxdem.differentiable``);
- ``Gauss-Newton``: the same, ``optimizer="gauss-newton"`` (Levenberg-Marquardt on
  the Jacobian that every solve with sensitivities gives);
- ``L-BFGS, FD``: L-BFGS with the Jacobian from central differences (2 p extra
  solves per gradient);
- ``nelder-mead``: SciPy's Nelder-Mead on the same misfit, in log(theta).

Each is charged in forward-solve equivalents: a solve with sensitivities counts
as its measured cost relative to a plain solve (``gradient/forward``), a plain
solve as one. The table gives what each needed to bring the misfit (chi^2 / 2)
below the target, and the wall time to get there.

    python benchmarks/bench_back_analysis.py [--scene tunnel|example2] [--target 1e-4]
"""

from __future__ import annotations

import argparse
import functools
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np
import scipy.optimize

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from scenes import jointed_tunnel  # noqa: E402

import jaxdem  # noqa: E402
from inverse import Observation, back_analyse  # noqa: E402
from jaxdem.differentiable import Problem  # noqa: E402
from jaxdem.scene import parse_scene  # noqa: E402

# Fitted parameters per scene and p: {path: (truth, start)}.
CASES = {
    "tunnel": {
        2: {"joints.set1.kn": (2.0e6, 4.0e6), "joints.set1.ks": (5.0e5, 2.5e5)},
        4: {"joints.set1.kn": (2.0e6, 4.0e6), "joints.set1.ks": (5.0e5, 2.5e5),
            "joints.set2.kn": (1.0e6, 0.6e6), "joints.set2.ks": (4.0e5, 8.0e5)},
    },
    "example2": {
        2: {"joints.foliation.kn": (1.36e6, 0.68e6), "joints.foliation.ks": (1.36e5, 2.72e5)},
        4: {"joints.foliation.kn": (1.36e6, 0.68e6), "joints.foliation.ks": (1.36e5, 2.72e5),
            "materials.rock.E": (6.89e6, 1.4e7), "materials.shear_zone.E": (3.45e6, 2.0e6)},
    },
}
METHODS = (("L-BFGS, grad", "lbfgs"), ("Gauss-Newton", "gauss-newton"),
           ("L-BFGS, FD", "lbfgs"))
EXAMPLE2 = Path(__file__).resolve().parents[1] / "examples" / "seed_example2_tunnel.toml"


def scene(values, name="tunnel"):
    """The benchmark scene with ``values`` set: the tests' 75-block jointed tunnel with
    three sections, or seed example 2 with rigid blocks (no intact mesh: 72 blocks)."""
    if name == "tunnel":
        d = jointed_tunnel(water=False, bolts=False)
        d["monitors"] += [{"name": "height", "from": [0.0, 2.05], "to": [0.0, -2.05]},
                          {"name": "diag", "from": [-2.05, -1.5], "to": [1.5, 2.05]}]
    else:
        d = jaxdem.load_scene(EXAMPLE2).data
        d = dict(d, domain={k: v for k, v in d["domain"].items() if k != "mesh_size"})
    return parse_scene(d).with_overrides(values)


def observations(truth, name="tunnel"):
    """The solve's sections and the crown's ux, uy at the truth, each with a 5% std."""
    r = jaxdem.solve(scene(truth, name))
    vals = [(k, m["convergence"], None) for k, m in r.monitors.items() if "convergence" in m]
    ux, uy = r.monitors["crown"]["displacement"]
    vals += [("crown", ux, "ux"), ("crown", uy, "uy")]
    return [Observation(n, v, max(0.05 * abs(v), 1e-5), component=c) for n, v, c in vals]


def _vector(problem, obs):
    """Indices of the observations in the problem's flat monitor vector."""
    keys = [(None, o.monitor, o.component) for o in obs]
    return np.array([problem.keys.index(k) for k in keys])


def gradient_cost(problem, theta, repeats=21):
    """Median times (s) of a plain solve and of a solve with sensitivities, at fresh points."""
    plain, sens = [], []
    for k in range(repeats):
        th = theta * (1.0 + 1e-3 * (k + 1))
        t0 = time.perf_counter()
        problem.evaluate(th, jacobian=False)
        plain.append(time.perf_counter() - t0)
        th = theta * (1.0 - 1e-3 * (k + 1))
        t0 = time.perf_counter()
        problem.evaluate(th, jacobian=True)
        sens.append(time.perf_counter() - t0)
    return float(np.median(plain)), float(np.median(sens))


def run_case(name, p, target, max_solves):
    case = CASES[name][p]
    paths = list(case)
    truth = {k: v[0] for k, v in case.items()}
    start = {k: v[1] for k, v in case.items()}
    obs = observations(truth, name)
    observed = np.array([o.value for o in obs])
    std = np.array([o.std for o in obs])
    rows = []

    # One problem per method, so that each counts its own solves (and none
    # profits from another's cache); the compile is done before timing.
    def fresh():
        problem = Problem(scene(start, name), paths)
        problem.evaluate(problem.theta0 * 1.01, jacobian=True)
        problem.evaluate(problem.theta0 * 1.02)
        problem.solves.clear()
        problem._cache.clear()
        return problem

    ref = fresh()
    t_plain, t_sens = gradient_cost(ref, ref.theta0)
    ratio = t_sens / t_plain

    # Implicit gradients with L-BFGS and with Gauss-Newton (Levenberg-Marquardt);
    # L-BFGS with central finite differences. A short warm-up run first, so that
    # the optimisers' own first-call compilation is not timed.
    for label, optimizer in METHODS:
        problem = fresh()
        jac = functools.partial(_finite_differences, problem) if "FD" in label else None
        forward = (problem.function(jac), problem.theta0)
        back_analyse(scene(start, name), obs, fit=paths, forward=forward, optimizer=optimizer,
                     max_iterations=1)
        problem.solves.clear()
        problem._cache.clear()
        hit, progress = _tracker(problem, target)
        fit = back_analyse(scene(start, name), obs, fit=paths, forward=forward,
                           optimizer=optimizer, progress=progress, max_iterations=100,
                           tolerance=1e-10)
        rows.append((label, hit, fit, problem, ratio))

    # 3. Nelder-Mead on log(theta).
    problem = fresh()
    idx = _vector(problem, obs)
    hit = {}
    best = [np.inf]
    t0 = time.perf_counter()

    def misfit(z):
        y, _ = problem.evaluate(problem.theta0 * np.exp(z))
        r = (y[idx] - observed) / std
        m = 0.5 * float(r @ r) if np.all(np.isfinite(r)) else np.inf
        best[0] = min(best[0], m)
        if "solves" not in hit and m <= target:
            hit.update(solves=dict(problem.solves), time=time.perf_counter() - t0, misfit=m)
        return m

    scipy.optimize.minimize(misfit, np.zeros(p), method="Nelder-Mead",
                            options=dict(maxfev=max_solves, xatol=1e-8, fatol=1e-12,
                                         initial_simplex=_simplex(p)))
    rows.append(("nelder-mead", hit, best[0], problem, ratio))
    return rows, t_plain, t_sens


def _simplex(p):
    """Start simplex in log(theta): the start and a 20% step along each parameter."""
    return np.vstack([np.zeros(p), 0.2 * np.eye(p)])


def _tracker(problem, target):
    """(record, progress callback): the solves and time when the misfit first met the target."""
    hit = {}
    t0 = time.perf_counter()

    def progress(event):
        if "solves" not in hit and event["misfit"] <= target:  # noqa: B023
            hit.update(solves=dict(problem.solves), time=time.perf_counter() - t0,
                       misfit=event["misfit"])

    return hit, progress


def _finite_differences(problem, theta, rel=1e-4):
    """Values and Jacobian from central differences of plain solves (2 p solves)."""
    y, _ = problem.evaluate(theta)
    J = np.empty((y.size, theta.size))
    for i in range(theta.size):
        e = np.zeros(theta.size)
        e[i] = rel * abs(theta[i])
        J[:, i] = (problem.evaluate(theta + e)[0] - problem.evaluate(theta - e)[0]) / (2 * e[i])
    return y, J


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", type=float, default=1e-4,
                        help="misfit (chi^2 / 2) to reach (default 1e-4)")
    parser.add_argument("--max-solves", type=int, default=400)
    parser.add_argument("--params", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--scene", choices=list(CASES), default="tunnel",
                        help="tunnel: 75-block jointed tunnel; example2: seed example 2, rigid")
    args = parser.parse_args(argv)
    print(f"machine: {platform.machine()} {platform.processor() or ''}, "
          f"{jax.devices()[0].device_kind}, jax {jax.__version__}")
    print(f"scene {args.scene}; target misfit {args.target:g} (chi^2/2, std 5%)")
    print(f"{'p':>2} {'method':<12} {'plain':>6} {'w/ sens':>8} {'fwd-equiv':>10} "
          f"{'wall s':>7} {'misfit':>10}  final estimate error")
    for p in args.params:
        rows, t_plain, t_sens = run_case(args.scene, p, args.target, args.max_solves)
        print(f"{p:>2} one solve {t_plain:.3f} s, with sensitivities {t_sens:.3f} s: "
              f"gradient = {t_sens / t_plain:.2f} forward solves")
        case = CASES[args.scene][p]
        truth = np.array([v[0] for v in case.values()])
        for name, hit, fit, problem, ratio in rows:
            if hit:
                s = hit["solves"]
                equiv = s.get("value", 0) + ratio * s.get("jacobian", 0)
                solves = f"{s.get('value', 0)}+{s.get('jacobian', 0)}s"
                tail = f"{equiv:>10.1f} {hit['time']:>7.1f} {hit['misfit']:>10.2e}"
            else:
                solves = f"{problem.solves.get('value', 0)}+{problem.solves.get('jacobian', 0)}s"
                tail = f"{'not reached':>10} {'':>7} {'':>10}"
            if isinstance(fit, float):
                err = f"(min misfit {fit:.2e})"
            else:
                est = np.array([fit.params[k] for k in case])
                err = f"max |rel err| {float(np.max(np.abs(est / truth - 1))):.1e}"
            print(f"{p:>2} {name:<13} {solves:>15} {tail}  {err}")


if __name__ == "__main__":
    main()
