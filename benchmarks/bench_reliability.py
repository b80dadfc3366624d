"""FORM with the model's gradients against Monte Carlo: solves and wall time at p = 2, 4, 6.

The scene is the benchmark tunnel (``benchmarks/scenes/tunnel.toml``: a 6 m circular
tunnel in a 30 m square cut by two cohesive joint sets 1.35 m apart, 596 blocks, gravity
in-situ stress, excavated in 2 load steps); the limit state is its vertical convergence
(crown to invert), ``vertical <= X``. Random variables (independent), the first p of:

    joints.set1.kn, joints.set2.kn   lognormal, mean 2e6 kPa/m, CoV 30%
    joints.set1.ks, joints.set2.ks   lognormal, mean 5e5 kPa/m, CoV 30%
    in_situ.k0                       lognormal, mean 1.0, CoV 15%
    materials.rock.E                 lognormal, mean 2e7 kPa, CoV 20%

For each p:

1. The limit X is chosen so that the probability of failure is near 1e-3: one solve
   with sensitivities at the medians gives the convergence m0 and its gradient in
   standard normal space, and X0 = m0 + 3.09 |grad| (first order: beta = 3.09). The
   convergence is convex in the lognormal stiffnesses (about 1 / kn), so P is higher
   there; a first FORM run at X0 gives beta0, and X = X0 + (3.09 - beta0) |grad g*|
   (d beta / d X = 1 / |grad g| at the design point). These runs, 2 warm-up solves and
   3 pairs of solves that measure the cost of sensitivities are reported apart
   ("calibration"), not charged to FORM.
2. FORM (``jaxdem.reliability``, improved HL-RF, exact gradients) at X, timed after a
   warm-up solve (compilation apart).
3. Monte Carlo at equal accuracy: a coefficient of variation of 10% on the
   probability needs N = (1 - P) / (P 0.1^2) samples (about 1e5 at P = 1e-3). N is
   computed from FORM's P, not run: its wall time is N times the time per sample of a
   smaller batched Monte Carlo run (``--mc`` samples, ``jaxdem.solve_batch``, after
   compilation) or of a single plain solve, whichever is less. That smaller run checks
   FORM at a moderate limit X_mod = m0 + 1.645 |grad| (P of several percent, where
   ``--mc`` samples see enough failures), where FORM is run again; at X it sees only a
   few failures (they are counted, not compared).
4. Importance sampling centred at FORM's design point z* (``--mc`` samples of
   N(z*, I), weights phi(z) / phi(z - z*) = exp(-z . z* + |z*|^2 / 2)) checks FORM's P
   at X itself: unbiased whatever the design point, and precise when z* is right.

Solves are counted as they are (a solve with sensitivities counts 1) and also in
forward-solve equivalents (a solve with sensitivities priced at its measured cost in
plain solves, median of 3 pairs at the medians).

    PYTHONPATH=. python benchmarks/bench_reliability.py                  # p = 2, 4, 6; --mc 256
    PYTHONPATH=. python benchmarks/bench_reliability.py --p 4 --mc 1000
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

SCENE = Path(__file__).resolve().parent / "scenes" / "tunnel.toml"
VARIABLES = ["joints.set1.kn=lognormal:2e6:6e5", "joints.set2.kn=lognormal:2e6:6e5",
             "joints.set1.ks=lognormal:5e5:1.5e5", "joints.set2.ks=lognormal:5e5:1.5e5",
             "in_situ.k0=lognormal:1.0:0.15", "materials.rock.E=lognormal:2e7:4e6"]
MONITOR = "vertical"
COV = 0.1


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95% Wilson score interval of a proportion k / n."""
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, c - h), min(1.0, c + h)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--p", type=int, nargs="+", default=[2, 4, 6])
    ap.add_argument("--mc", type=int, default=256, help="Monte Carlo samples actually run")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import jax

    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache
    from jaxdem.batch import solve_batch
    from jaxdem.differentiable import Problem
    from jaxdem.reliability import samples_for_cov, transform
    from jaxdem.sweep import Variable

    scene = jaxdem.load_scene(SCENE)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} "
          f"({jax.default_backend()}), scene {SCENE.name} ({scene.name}), limit "
          f"'{MONITOR} <= X', Monte Carlo run: {args.mc} samples, seed {args.seed}")
    rows = []
    for p in args.p:
        variables = [Variable.parse(v) for v in VARIABLES[:p]]
        paths = [v.path for v in variables]
        median, dxdy = transform(variables, np.zeros(p))
        # 1. Calibration: the limit for P near 1e-3 (and a moderate one), from one solve
        # with sensitivities at the medians; the plain/sensitivity cost ratio.
        problem = Problem(scene, paths)
        k = [i for i, key in enumerate(problem.keys) if key[1] == MONITOR][0]
        problem.evaluate(median * 1.001, jacobian=True)          # compile both programs
        problem.evaluate(median * 1.002, jacobian=False)
        plain, sens = [], []
        for j in range(3):
            x = median * (1 + 1e-4 * (j + 1))
            t0 = time.perf_counter()
            problem.evaluate(x, jacobian=False)
            plain.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            problem.evaluate(x * (1 + 1e-6), jacobian=True)
            sens.append(time.perf_counter() - t0)
        ratio = statistics.median(sens) / statistics.median(plain)
        y, J = problem.evaluate(median, jacobian=True)
        m0, grad = float(y[k]), J[k] * dxdy
        X_mod = m0 + 1.645 * float(np.linalg.norm(grad))
        # The convergence is convex in the lognormal stiffnesses, so the first-order X
        # gives P well above 1e-3: one FORM run there, then X moved by
        # (3.09 - beta) |grad g| at its design point (d beta / d X = 1 / |grad g|).
        X0 = m0 + 3.09 * float(np.linalg.norm(grad))
        first = jaxdem.reliability(scene, variables, f"{MONITOR} <= {X0!r}")
        X = X0 + (3.09 - first.beta) * first.history[-1]["gradient_norm"]
        # 2. FORM at X (timed; its programs are compiled by now) and at X_mod.
        t0 = time.perf_counter()
        form = jaxdem.reliability(scene, variables, f"{MONITOR} <= {X!r}")
        form_s = time.perf_counter() - t0
        form_mod = jaxdem.reliability(scene, variables, f"{MONITOR} <= {X_mod!r}")
        n_form = form.solves["plain"] + form.solves["with_sensitivities"]
        eq_form = form.solves["plain"] + ratio * form.solves["with_sensitivities"]
        # 3. Monte Carlo: a smaller batched run (after a compiling batch), for the time per
        # sample and the agreement; N for CoV 10% from FORM's P.
        rng = np.random.default_rng(args.seed)
        theta, _ = transform(variables, rng.standard_normal((args.mc, p)))
        solve_batch(scene, paths, theta[:16])
        t0 = time.perf_counter()
        b = solve_batch(scene, paths, theta)
        mc_s = time.perf_counter() - t0
        conv = b.monitors[MONITOR]
        decided = b.converged | ~b.stable
        n_dec = int(decided.sum())
        fails = [int(np.sum(decided & ((~b.stable) | (conv > lim)))) for lim in (X, X_mod)]
        N = samples_for_cov(form.probability, COV)
        # Monte Carlo at its fastest: batched, or single plain solves if those are faster.
        per_sample = min(mc_s / args.mc, statistics.median(plain))
        # 4. Importance sampling centred at FORM's design point: P at X checked with as
        # many solves as the Monte Carlo run.
        zstar = np.array([form.design_point_u[q] for q in paths])
        zi = rng.standard_normal((args.mc, p)) + zstar
        b_is = solve_batch(scene, paths, transform(variables, zi)[0])
        dec = b_is.converged | ~b_is.stable
        with np.errstate(invalid="ignore"):
            fail = dec & (~b_is.stable | (b_is.monitors[MONITOR] > X))
        w = np.where(fail, np.exp(-zi @ zstar + 0.5 * zstar @ zstar), 0.0)[dec]
        P_is, se_is = float(w.mean()), float(w.std(ddof=1) / math.sqrt(len(w)))
        rows.append(dict(
            p=p, X=X, X_mod=X_mod, beta=form.beta, P=form.probability, status=form.status,
            iterations=form.iterations, sens=form.solves["with_sensitivities"],
            plain=form.solves["plain"], n_form=n_form, eq_form=eq_form, ratio=ratio,
            form_s=form_s, N=N, mc_time=N * per_sample, per_sample=per_sample,
            batch_sample=mc_s / args.mc, single=statistics.median(plain),
            calibration=first.solves["with_sensitivities"] + 9, X0=X0, beta0=first.beta,
            count_ratio=N / n_form, eq_ratio=N / eq_form, time_ratio=N * per_sample / form_s,
            mc_n=n_dec, mc_fail=fails[0],
            is_n=len(w), is_fail=int(fail.sum()), is_P=P_is,
            is_ci=(max(0.0, P_is - 1.959964 * se_is), P_is + 1.959964 * se_is),
            mod_P=form_mod.probability, mod_beta=form_mod.beta,
            mod_solves=form_mod.solves["with_sensitivities"] + form_mod.solves["plain"],
            mod_fail=fails[1], mod_ci=wilson(fails[1], n_dec),
            importance=form.importance,
            undecided=int(args.mc - n_dec) + int(args.mc - len(w))))
        r = rows[-1]
        print(f"p = {p}: m0 = {1e3 * m0:.4f} mm, X0 = {1e3 * X0:.4f} mm (beta0 "
              f"{first.beta:.3f}), X = {1e3 * X:.4f} mm, beta {r['beta']:.3f} "
              f"({r['status']}, {r['iterations']} it.), calibration solves "
              f"{r['calibration']}, s/sample batched {r['batch_sample']:.3f}, single plain "
              f"{r['single']:.3f}; importance "
              + ", ".join(f"{q.split('.')[-2]}.{q.split('.')[-1]} {100 * v:.0f}%"
                          for q, v in form.importance.items()), flush=True)

    print()
    print(f"{'p':>2} {'X mm':>8} {'beta':>6} {'P FORM':>9} {'FORM solves':>11} "
          f"{'(sens+plain)':>12} {'equiv.':>6} {'FORM s':>7} {'MC N (CoV 10%)':>14} "
          f"{'MC s (est.)':>11} {'solves x':>8} {'equiv. x':>8} {'time x':>7}")
    for r in rows:
        print(f"{r['p']:>2} {1e3 * r['X']:>8.4f} {r['beta']:>6.3f} {r['P']:>9.3e} "
              f"{r['n_form']:>11} {r['sens']:>6}+{r['plain']:<5} {r['eq_form']:>6.1f} "
              f"{r['form_s']:>7.1f} {r['N']:>14,.0f} {r['mc_time']:>11,.0f} "
              f"{r['count_ratio']:>8,.0f} {r['eq_ratio']:>8,.0f} {r['time_ratio']:>7,.0f}")
    print()
    print("Agreement: at X, importance sampling centred at FORM's design point (95%: +-1.96 "
          "standard errors); at X_mod, the plain Monte Carlo run (95% Wilson interval)")
    print(f"{'p':>2} {'IS n':>5} {'fails':>5} {'IS P':>9} {'IS 95%':>19} {'FORM P':>9} {'ok':>3} "
          f"{'MC n':>5} {'fails at X':>10} {'fails at X_mod':>14} {'MC P':>7} {'MC 95%':>15} "
          f"{'FORM P':>7} {'ok':>3} {'s/sample':>8} {'sens/plain':>10}")
    for r in rows:
        ok = r["is_ci"][0] <= r["P"] <= r["is_ci"][1]
        ok_mod = r["mod_ci"][0] <= r["mod_P"] <= r["mod_ci"][1]
        print(f"{r['p']:>2} {r['is_n']:>5} {r['is_fail']:>5} {r['is_P']:>9.3e} "
              f"{r['is_ci'][0]:>9.3e}-{r['is_ci'][1]:<9.3e} {r['P']:>9.3e} "
              f"{'yes' if ok else 'NO':>3} {r['mc_n']:>5} {r['mc_fail']:>10} "
              f"{r['mod_fail']:>14} {r['mod_fail'] / r['mc_n']:>7.4f} "
              f"{r['mod_ci'][0]:>7.4f}-{r['mod_ci'][1]:<7.4f} {r['mod_P']:>7.4f} "
              f"{'yes' if ok_mod else 'NO':>3} {r['per_sample']:>8.3f} {r['ratio']:>10.2f}")
    if any(r["undecided"] for r in rows):
        print("undecided Monte Carlo samples (left out): "
              + ", ".join(f"p = {r['p']}: {r['undecided']}" for r in rows))


if __name__ == "__main__":
    main()
