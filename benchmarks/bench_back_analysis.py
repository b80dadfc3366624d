"""Back-analysis against the field's own methods: p = 2, 4, 6 parameters, 5 starts each.

Identical-twin problem: the small jointed tunnel of the tests (two joint sets,
gravity in-situ stress with K0, support pressure), excavated in two stages
(a top heading, then the bench). The "measurements" are the convergences of
three sections and the crown's ux, uy at the end of both stages (10 values),
with 5% Gaussian noise (seed 0) and a 5% standard deviation. Fitted:

- p = 2: kn, ks of joint set 1;
- p = 4: and kn, ks of joint set 2;
- p = 6: and the friction angle of set 2 and the in-situ K0.

All methods work in the same bounded coordinates (stiffnesses log-scaled within
a factor 10 of the truth, friction 20-40 deg, K0 0.4-1.6) and start from the
same 5 random points (uniform in those coordinates, 10%-90% of each range):

- ``Gauss-Newton``: ``inverse.back_analyse`` with its default optimiser
  (Levenberg-Marquardt on the Jacobian that each solve with sensitivities gives) and
  its default iteration limit (50 per local fit, ``--gn-iterations``), tolerance 1e-10;
- ``L-BFGS``: ``back_analyse(optimizer="lbfgs")`` (optax, same gradients);
- ``LM, FD``: SciPy's Levenberg-Marquardt (``least_squares(method="lm")``) with
  its own forward-difference Jacobian (p + 1 plain solves each), relative step
  ``FD_STEP`` = 1e-3 (SciPy's default, 1.5e-8, is close to the solver's own noise: the
  solves converge to 1e-9). At a start without equilibrium its residuals are the
  placeholder 1e6, the difference Jacobian is zero and MINPACK stops after p + 1 solves;
  Gauss-Newton first moves such a start towards the centre of the bounds;
- ``Nelder-Mead``: SciPy's simplex on the misfit;
- ``DE``: SciPy's ``differential_evolution`` (population 15 p, seed = start no.).

Each is charged in forward-solve equivalents: a plain solve counts 1, a solve with
sensitivities its cost in plain solves (median of 9 pairs, measured at the start of
each p; ``--ratio R`` fixes it instead, for runs on a loaded machine). The counts of
plain solves and of solves with sensitivities are printed too, so that the figures can
be priced again at any ratio.

Two views of "the same misfit", both from the same runs (each solve's misfit, counts
and wall time are recorded, so a run is charged what it had spent when its misfit first
met a target):

- ``same misfit``: the lowest misfit any Gauss-Newton run reached, plus 1e-3 of it (and
  1e-6); every method must reach it from every start;
- ``per start``: from each start, the misfit Gauss-Newton ended at from that start, plus
  1e-3 of it. Where the misfit has more than one minimum (p = 6: set 2's friction at
  its upper bound, where no joint of the set slips, against about 30 deg, where some
  do), this asks each method for what Gauss-Newton delivered from the same start.

Gauss-Newton runs once from each start, to its own stop. The other methods stop as
soon as they meet the ``same misfit`` target (after any ``per start`` one, which is
never lower), or at their budget (``--budget`` forward-solve equivalents; the figure is
then a lower bound on what the method needs, reported as "> N"). Nelder-Mead and DE
also stop once they have spent ``--decide-at`` times Gauss-Newton's median without
reaching the target (one value for both, or two: Nelder-Mead's, then DE's; default
120; the larger of Gauss-Newton's medians in the views where it is not a bound): the
ratio against Gauss-Newton is then known to exceed that (the targets are 20x and 100x),
and solving on would only cost time. ``--de-starts N`` runs DE from the first N starts
only; the starts not run count as 0 in the median (a lower bound), so when DE reaches
the target from none of N > starts / 2 runs, the median over all starts still exceeds
the smallest of what those runs spent. ``--de-only K [K ...]`` runs DE from those starts
only (numbered from 0), so that a long run can be finished in another process; its
counts are deterministic (seeded), so rows from such runs with the same ``--ratio``
join into one table. A median that the runs do not decide is printed as the range it
lies in: "lo to hi", ">lo" (no upper bound), or "undecided" (too few starts run).

    python benchmarks/bench_back_analysis.py [--params 2 4 6] [--starts 5] [--budget 1500]
        [--decide-at 120 | --decide-at NM DE] [--methods ...] [--ratio R]
        [--gn-iterations 50] [--de-starts N | --de-only K ...] [--price-only]
"""

from __future__ import annotations

import argparse
import logging
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
from jaxdem.scene import parse_scene

STAGES = ("heading", "bench")
SECTIONS = ("span", "height", "bench span")
# {path: (truth, lo, hi, log)}: the six parameters, in the order p = 2, 4, 6 takes them.
PARAMS = {
    "joints.set1.kn": (2.0e6, 2.0e5, 2.0e7, True),
    "joints.set1.ks": (5.0e5, 5.0e4, 5.0e6, True),
    "joints.set2.kn": (1.0e6, 1.0e5, 1.0e7, True),
    "joints.set2.ks": (4.0e5, 4.0e4, 4.0e6, True),
    "joints.set2.friction_deg": (30.0, 20.0, 40.0, False),
    "in_situ.k0": (0.8, 0.4, 1.6, False),
}
FD_STEP = 1e-3  # LM, FD: relative difference step in the logit coordinates


def scene(values=None):
    """The 2-stage jointed tunnel with ``values`` set (file units)."""
    d = jointed_tunnel(water=False, bolts=False)
    d["excavations"] = [
        {"name": "heading", "shape": "polygon",
         "vertices": [[-2.0, -0.5], [2.0, -0.5], [2.0, 1.0], [1.0, 2.0], [-1.0, 2.0], [-2.0, 1.0]]},
        {"name": "bench", "shape": "polygon", "stage": "bench",
         "vertices": [[-2.0, -2.5], [2.0, -2.5], [2.0, -0.5], [-2.0, -0.5]]},
    ]
    d["supports"] = [{"excavation": "heading", "pressure": 100.0}]
    d["stages"] = [{"name": "heading"}, {"name": "bench"}]
    d["monitors"] = [{"name": "crown", "point": [0.0, 2.05]},
                     {"name": "span", "from": [-2.05, 0.5], "to": [2.05, 0.5]},
                     {"name": "height", "from": [0.0, 2.05], "to": [0.0, -2.6]},
                     {"name": "bench span", "from": [-2.05, -1.5], "to": [2.05, -1.5]}]
    return parse_scene(d).with_overrides(values or {})


def observations(truth):
    """Sections and crown ux, uy at the end of both stages, 5% noise and std (seed 0)."""
    problem = Problem(scene(truth), list(truth), stages=list(STAGES))
    y, _ = problem.evaluate(problem.theta0)
    rng = np.random.default_rng(0)
    obs = []
    for (stage, name, comp), v in zip(problem.keys, y, strict=True):
        if name not in SECTIONS and name != "crown":
            continue
        std = max(0.05 * abs(v), 1e-5)
        obs.append(Observation(name, float(v + std * rng.standard_normal()), std, stage=stage,
                               component=comp))
    return obs


class Transform:
    """theta <-> u in [0, 1]^p (log for stiffnesses) <-> z in R^p (u = sigmoid(z))."""

    def __init__(self, paths):
        spec = np.array([PARAMS[k][1:3] for k in paths], float)
        self.log = np.array([PARAMS[k][3] for k in paths])
        self.lo = np.where(self.log, np.log(spec[:, 0]), spec[:, 0])
        self.hi = np.where(self.log, np.log(spec[:, 1]), spec[:, 1])

    def theta(self, u):
        x = self.lo + (self.hi - self.lo) * np.asarray(u)
        return np.where(self.log, np.exp(x), x)

    def theta_z(self, z):
        return self.theta(1.0 / (1.0 + np.exp(-np.asarray(z))))


class Counter:
    """A Problem whose every solve is charged and whose misfit is tracked."""

    class Reached(Exception):
        pass

    def __init__(self, problem, obs, ratio, target, budget):
        keys = [(o.stage, o.monitor, o.component) for o in obs]
        self.idx = np.array([problem.keys.index(k) for k in keys])
        self.observed = np.array([o.value for o in obs])
        self.std = np.array([o.std for o in obs])
        self.problem, self.ratio, self.target, self.budget = problem, ratio, target, budget
        self.solves = [0, 0]  # plain solves, solves with sensitivities
        self.best = np.inf
        self.hit = None  # (solves, wall time) when the misfit first met the target
        self.history = []  # (solves, wall time, misfit) after every new solve
        self.outcome = ""  # how back_analyse ended (Gauss-Newton and L-BFGS)
        self.local_fits = 0  # back_analyse's local fits (more than 1 after a restart)
        self.t0 = time.perf_counter()
        self._evaluate = problem.evaluate
        problem.evaluate = self.evaluate

    def misfit_of(self, y):
        r = (y[self.idx] - self.observed) / self.std
        return 0.5 * float(r @ r) if np.all(np.isfinite(r)) else np.inf

    def evaluate(self, theta, jacobian=False):
        if self.equiv >= self.budget:
            raise Counter.Reached
        cached = self.problem._cache.get(np.asarray(theta, float).tobytes())
        y, J = self._evaluate(theta, jacobian)
        m = self.misfit_of(y)
        if cached is None or (jacobian and cached[1] is None):
            self.solves[int(jacobian)] += 1
            self.history.append((tuple(self.solves), time.perf_counter() - self.t0, m))
        self.best = min(self.best, m)
        if self.hit is None and m <= self.target:
            self.hit = (tuple(self.solves), time.perf_counter() - self.t0)
        return y, J

    def equiv_of(self, solves):
        """Forward-solve equivalents of (plain solves, solves with sensitivities)."""
        return solves[0] + self.ratio * solves[1]

    @property
    def equiv(self):
        return self.equiv_of(self.solves)

    def first_hit(self, target):
        """(solves, wall time) when the recorded misfit first met ``target``; None if never."""
        return next(((n, t) for n, t, m in self.history if m <= target), None)

    def misfit(self, theta):
        m = self.misfit_of(self.evaluate(theta)[0])
        if self.hit is not None:
            raise Counter.Reached
        return m

    def residuals(self, theta):
        y, _ = self.evaluate(theta)
        if self.hit is not None:
            raise Counter.Reached
        r = (y[self.idx] - self.observed) / self.std
        return np.where(np.isfinite(r), r, 1e6)


def fresh(paths, start):
    problem = Problem(scene(start), paths, stages=list(STAGES))
    problem.evaluate(problem.theta0 * 1.001, jacobian=True)  # compile both programs
    problem.evaluate(problem.theta0 * 1.002)
    problem._cache.clear()
    return problem


def gradient_cost(problem, pairs=9):
    plain, sens = [], []
    for k in range(pairs):
        for jac, out, f in ((False, plain, 1 + 1e-3 * (k + 1)), (True, sens, 1 - 1e-3 * (k + 1))):
            t0 = time.perf_counter()
            problem.evaluate(problem.theta0 * f, jacobian=jac)
            out.append(time.perf_counter() - t0)
    problem._cache.clear()
    return float(np.median(plain)), float(np.median(sens))


def run(method, paths, start_u, seed, obs, ratio, target, budget, gn_iterations=50):
    tr = Transform(paths)
    theta0 = tr.theta(start_u)
    start = dict(zip(paths, theta0, strict=True))
    problem = fresh(paths, start)
    c = Counter(problem, obs, ratio, target, budget)
    bounds = {k: (PARAMS[k][1], PARAMS[k][2]) for k in paths}
    z0 = np.log(start_u / (1.0 - start_u))
    try:
        if method in ("Gauss-Newton", "L-BFGS"):
            opt = "gauss-newton" if method == "Gauss-Newton" else "lbfgs"
            fit = back_analyse(scene(start), obs, paths, forward=(problem.function(), theta0),
                               bounds=bounds, optimizer=opt, max_iterations=gn_iterations,
                               tolerance=1e-10)
            c.outcome = f"{fit.status}: {fit.message}"
            c.local_fits = len(fit.starts)
        elif method == "LM, FD":
            scipy.optimize.least_squares(lambda z: c.residuals(tr.theta_z(z)), z0, method="lm",
                                         max_nfev=int(budget), xtol=1e-12, ftol=1e-12,
                                         diff_step=FD_STEP)
        elif method == "Nelder-Mead":
            scipy.optimize.minimize(lambda z: c.misfit(tr.theta_z(z)), z0, method="Nelder-Mead",
                                    options=dict(maxfev=int(budget), xatol=1e-10, fatol=1e-12))
        else:
            scipy.optimize.differential_evolution(
                lambda u: c.misfit(tr.theta(u)), [(0.0, 1.0)] * len(paths), seed=seed,
                maxiter=int(budget), polish=False, tol=0.0, x0=start_u)
    except Counter.Reached:
        pass
    c.t_end = time.perf_counter()
    return c


METHODS = ("Gauss-Newton", "L-BFGS", "LM, FD", "Nelder-Mead", "DE")


def main(argv=None):
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--budget", type=float, default=1500,
                        help="most forward-solve equivalents per run (default 1500)")
    parser.add_argument("--decide-at", type=float, nargs="+", default=[120.0],
                        help="stop Nelder-Mead and DE at this multiple of Gauss-Newton's "
                             "median fwd-equiv: one value for both, or Nelder-Mead's then "
                             "DE's (default 120)")
    parser.add_argument("--de-starts", type=int, default=None,
                        help="run DE from the first N starts only (when N > starts / 2 and "
                             "none reaches the target, the median over all starts is decided)")
    parser.add_argument("--de-only", type=int, nargs="+", default=None,
                        help="run DE from these starts only (numbered from 0)")
    parser.add_argument("--gn-iterations", type=int, default=50,
                        help="Gauss-Newton and L-BFGS: iterations per local fit "
                             "(default 50, back_analyse's)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--price-only", action="store_true",
                        help="only measure the price of a solve with sensitivities, for "
                             "each p of --params")
    parser.add_argument("--ratio", type=float, default=None,
                        help="cost of a solve with sensitivities in plain solves (default: "
                             "measured, median of 9 pairs)")
    args = parser.parse_args(argv)
    if not all(1 <= q <= len(PARAMS) for q in args.params):
        parser.error(f"--params: each p runs from 1 to {len(PARAMS)} (got {args.params})")
    if args.de_only is not None and not all(0 <= k < args.starts for k in args.de_only):
        parser.error(f"--de-only: start numbers run from 0 to {args.starts - 1} "
                     f"(got {args.de_only})")
    # A run is stopped by raising Counter.Reached inside the solve; under L-BFGS that is
    # inside a jax.pure_callback, which logs every such raise with its traceback.
    logging.getLogger("jax._src.callback").setLevel(logging.CRITICAL)
    decide_at = dict(zip(("Nelder-Mead", "DE"), args.decide_at * 2 if len(args.decide_at) == 1
                         else args.decide_at, strict=True))
    print(f"machine: {platform.machine()}, {jax.devices()[0].device_kind}, "
          f"jax {jax.__version__}, numpy {np.__version__}")
    truth_all = {k: v[0] for k, v in PARAMS.items()}
    rng = np.random.default_rng(1)
    for p in args.params:
        paths = list(PARAMS)[:p]
        truth = {k: truth_all[k] for k in paths}
        obs = observations(truth)
        starts = 0.1 + 0.8 * rng.random((args.starts, p))
        ref = fresh(paths, truth)
        t_plain, t_sens = gradient_cost(ref)
        ratio = t_sens / t_plain if args.ratio is None else args.ratio
        print(f"\np = {p} ({', '.join(paths)}); {len(obs)} observations; plain solve "
              f"{t_plain:.3f} s, with sensitivities {t_sens:.3f} s = {t_sens / t_plain:.2f} "
              f"plain; charged {ratio:.2f}{'' if args.ratio is None else ' (--ratio)'}")
        if args.price_only:
            continue
        # The target: the best misfit Gauss-Newton reaches from any start; and, per
        # start, the misfit Gauss-Newton ends at from that start (a local minimum of its
        # own where it is higher). Gauss-Newton is charged what it had spent when its
        # misfit first met either.
        gn = [run("Gauss-Newton", paths, s, k, obs, ratio, -1.0, np.inf, args.gn_iterations)
              for k, s in enumerate(starts)]
        best = min(c.best for c in gn)
        target = best * (1 + 1e-3) + 1e-6
        own = [c.best * (1 + 1e-3) + 1e-6 for c in gn]
        for c in gn:
            c.hit = c.first_hit(target)
        print(f"target misfit {target:.6g} (best Gauss-Newton {best:.6g}); per start, "
              f"Gauss-Newton's own end: {', '.join(f'{c.best:.6g}' for c in gn)}")
        views = {"same misfit": [target] * len(gn), "per start": own}
        medians = {view: {} for view in views}
        for method in args.methods:
            budget = args.budget
            if method in ("Nelder-Mead", "DE"):
                # Decided in every view with a measured Gauss-Newton median (the larger
                # one); its whole runs when it was not reported.
                gn_meds = [m["Gauss-Newton"][0] for m in medians.values()
                           if "Gauss-Newton" in m and m["Gauss-Newton"][0] == m["Gauss-Newton"][1]]
                gn_median = max(gn_meds) if gn_meds else float(np.median([c.equiv for c in gn]))
                budget = min(budget, decide_at[method] * gn_median)
            ran = list(range(len(starts)))  # the starts this method runs from
            if method == "DE" and args.de_only is not None:
                ran = list(args.de_only)
            elif method == "DE" and args.de_starts is not None:
                ran = ran[:args.de_starts]
            if method == "Gauss-Newton":
                runs = gn
            else:
                runs = []
                for k in ran:
                    runs.append(run(method, paths, starts[k], k, obs, ratio, target, budget,
                                    args.gn_iterations))
                    c = runs[-1]  # as it ends: a long run can be read before the table
                    print(f"    {method} start {k}: solves {tuple(c.solves)}, best misfit "
                          f"{c.best:.6g}, {c.t_end - c.t0:.0f} s", flush=True)
            for view, targets in views.items():
                hits = [c.first_hit(targets[k]) for c, k in zip(runs, ran, strict=True)]
                medians[view][method] = report(p, method, view, runs, hits, len(starts))
            for k, c in enumerate(runs):
                if c.hit is None and c.outcome:
                    print(f"    start {k} did not reach the same misfit: {c.outcome}",
                          flush=True)
            if any(c.local_fits > 1 for c in runs):
                print(f"    local fits per start (restarts after a rejected fit): "
                      f"{[c.local_fits for c in runs]}", flush=True)
        for view, meds in medians.items():
            if "Gauss-Newton" not in meds:
                continue
            gn_lo, gn_hi = meds["Gauss-Newton"]
            for method, (lo, hi) in meds.items():
                if method == "Gauss-Newton":
                    continue
                ratio_text = "undetermined (Gauss-Newton's median is a lower bound)" \
                    if gn_hi > gn_lo else describe(lo / gn_lo, hi / gn_lo, "x")
                print(f"p={p} [{view}] {method} / Gauss-Newton (median fwd-equiv): "
                      f"{ratio_text}", flush=True)


def describe(lo, hi, unit=""):
    """A median known to lie in [lo, hi]: "x", ">lo", "lo to hi", or "undecided"."""
    if hi == lo:
        return f"{lo:.1f}{unit}"
    if lo == 0.0:
        return "undecided"
    return f">{lo:.1f}{unit}" if hi == np.inf else f"{lo:.1f} to {hi:.1f}{unit}"


def report(p, method, view, runs, hits, n_starts):
    """Print one method's figures against one view's targets; return the bounds (lo, hi)
    of its median over all starts (equal where the runs decide it).

    A run that did not reach its target counts what it spent (a lower bound). With
    fewer runs than starts (``--de-starts``, ``--de-only``), the median is a lower bound
    unless the runs made decide it.
    """
    solves = [h[0] if h else tuple(c.solves) for c, h in zip(runs, hits, strict=True)]
    equiv = [c.equiv_of(n) for c, n in zip(runs, solves, strict=True)]
    wall = [h[1] if h else c.t_end - c.t0 for c, h in zip(runs, hits, strict=True)]
    reached = sum(h is not None for h in hits)
    # The median over all starts lies between these two: a run that did not reach its
    # target at what it spent or at infinity, a start not run at 0 or at infinity.
    missing = [0.0] * (n_starts - len(runs))
    lo = float(np.median(equiv + missing))
    hi = float(np.median([e if h else np.inf for e, h in zip(equiv, hits, strict=True)]
                         + [np.inf] * len(missing)))
    cells = " ".join(f"{e:>7.1f}" if h else f"{'>' + format(e, '.1f'):>7}"
                     for e, h in zip(equiv, hits, strict=True))
    print(f"p={p} [{view}] {method:<13} reached {reached}/{n_starts}  median fwd-equiv "
          f"{describe(lo, hi)}  median wall {'>' if hi > lo else ''}"
          f"{float(np.median(wall)):.1f} s  per start: {cells}", flush=True)
    print(f"    solves per start (plain, with sensitivities): {solves}", flush=True)
    return lo, hi


if __name__ == "__main__":
    main()
