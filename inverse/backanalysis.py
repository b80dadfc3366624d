"""Back-analysis: fit scene parameters to measured monitor values (SPEC section 5).

The forward model is :func:`jaxdem.differentiable`: ``f(theta)`` gives every
monitor at the end of the last stage (or of named stages) as a pure JAX function
of the fitted parameters ``theta`` (file units). :func:`back_analyse` minimises

    misfit(theta) = 1/2 sum_i ((y_i(theta) - observed_i) / std_i)^2

over the observations i, then describes the estimate by Gauss-Newton: with
``J_w = diag(1/std) dy/dtheta`` the covariance is ``(J_w^T J_w)^-1``.

Parameters are optimised in an unconstrained space z. A parameter whose bounds
are both positive is log-scaled (stiffnesses and moduli span decades):
``theta = exp(log lo + (log hi - log lo) sigmoid(z))``; any other is linear:
``theta = lo + (hi - lo) sigmoid(z)``. Default bounds for a positive starting
value are ``[theta0 / 100, theta0 * 100]``; a zero or negative starting value
needs explicit bounds.

Example::

    import jaxdem
    from inverse import Observation, back_analyse

    scene = jaxdem.load_scene("tunnel.toml")
    fit = back_analyse(
        scene,
        [Observation("section 1-1", 0.0123, std=0.0005),
         Observation("crown", -0.0081, std=0.0005, component="uy", stage="excavate")],
        fit=["joints.set1.kn", "joints.set1.ks"],
    )
    fit.params, fit.std, fit.warnings

The package, by concept (data flows down this list, nothing imports upwards):

- :mod:`inverse.observations`: what was measured (CSV, checks, default stds) and how
  each observation maps onto the model's monitors;
- :mod:`inverse.fit`: bounded coordinates, the counted objective, the optimisers;
- :mod:`inverse.statistics`: standard deviations, correlations, identifiability;
- :mod:`inverse.report`: :class:`BackAnalysis` and its JSON;
- this module: :func:`back_analyse`, which checks the input, runs the fit and builds
  the report; :mod:`inverse.plots` draws it.

Host code: NumPy and Python around the jitted forward model and its Jacobian.
"""


from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from inverse.fit import (
    ADAM_LEARNING_RATE,
    CONVERGED,
    DEFAULT_TOLERANCE,
    LM_MAX_STEP,
    NO_EQUILIBRIUM_AT_START,
    OPTIMIZERS,
    RESTARTS,
    Objective,
    Run,
    Transform,
    check_bounds,
    check_fit,
    finite_entry,
    logit,
    make_transform,
    restart_points,
    restore,
    run_adam,
    run_gauss_newton,
    run_lbfgs,
    scales,
    start_z,
)
from inverse.observations import (
    Observation,
    as_observations,
    checked_observations,
    observed_model,
    read_observations,
    resolve_stages,
)
from inverse.report import BackAnalysis
from inverse.statistics import (
    REJECT_QUANTILE,
    bound_warnings,
    fit_warnings,
    gauss_newton_statistics,
    misfit_limit,
    precision_warnings,
)
from jaxdem.config import float64
from jaxdem.scene import Scene

__all__ = ["BackAnalysis", "Observation", "back_analyse", "read_observations"]


@float64
def back_analyse(
    scene: Scene | None,
    observed: Mapping[str, Any] | Sequence[Observation],
    fit: Sequence[str],
    *,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    optimizer: str = "gauss-newton",
    max_iterations: int = 50,
    tolerance: float = DEFAULT_TOLERANCE,
    learning_rate: float = ADAM_LEARNING_RATE,
    restarts: int = RESTARTS,
    stages: Sequence[str] | None = None,
    forward: tuple[Callable, Any] | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> BackAnalysis:
    """Fit scene parameters to measured monitor values; estimates with Gauss-Newton stds.

    Minimises 1/2 sum_i ((y_i(theta) - observed_i) / std_i)^2 in the bounded,
    log-scaled z-space (module docstring), then computes at the estimate the
    Jacobian, the covariance (J_w^T J_w)^-1 and which parameters the observations
    determine (``identifiable``; see ``RELATIVE_SENSITIVITY_MIN``,
    ``SINGULAR_RATIO`` and ``CORRELATION_MAX``).

    Stopping rule: after an iteration with misfit m (in units of chi^2 / 2), stop
    when the gradient norm in z-space is <= tolerance * (1 + m); or, L-BFGS, when
    that iteration lowered the misfit by no more than tolerance * (1 + m) while the
    gradient norm is <= sqrt(tolerance) * (1 + m) (a slow crawl along a valley is
    not convergence); or, Adam, when its best misfit has not improved by
    tolerance * (1 + m) in ``ADAM_PATIENCE`` iterations; or after ``max_iterations``.
    L-BFGS also stops when its line search finds no lower point. Both return the
    best point seen. A trial point
    where the model has no equilibrium (NaN) counts as misfit +inf: the line search
    steps back from it; Adam returns to its best point with half the learning rate.
    A start without equilibrium moves towards the centre of the bounds first
    (``RESTORE_STEPS``; ``warnings`` says where the fit started).

    Restarts: a local fit whose misfit noise cannot explain (2 x misfit above the
    ``REJECT_QUANTILE`` = 99.9 % quantile of chi^2 with n - p degrees of freedom,
    :func:`inverse.statistics.misfit_limit`) has stopped in a local minimum, or the
    model or the stds are wrong. The fit then starts again, at most ``restarts`` times,
    from the centre of the bounds and then the Halton points of
    :func:`inverse.fit.restart_points` (a point within one trust-region step,
    ``LM_MAX_STEP``, of the given start is skipped), stops at the first accepted fit
    and keeps the lowest misfit. A fit accepted from the given start does no restart
    and costs nothing more; ``starts`` in the result lists every local fit and
    ``warnings`` says when there were restarts. No restart follows a start without
    equilibrium (``no_equilibrium_at_start``) or ``max_iterations = 0``.

    Args:
      scene: the scene (``jaxdem.load_scene``); observed monitors, stages and fitted
        paths are checked against it before any solve. May be None with ``forward``.
      observed: {monitor: value} or {monitor: (value, std)} for sections, or a list
        of :class:`Observation` (needed for point monitors, which take a component,
        and for values at the end of a named stage). Values and stds in m.
      fit: dotted paths of the parameters to fit (``"joints.set1.kn"``).
      bounds: {path: (lo, hi)} in file units; default [theta0 / 100, theta0 * 100]
        for a positive theta0, required otherwise.
      optimizer: "gauss-newton" (the default: Levenberg-Marquardt on the observations'
        Jacobian, fewest solves and robust from any start within the bounds), "lbfgs"
        (optax L-BFGS, zoom line search) or "adam" (optax).
      max_iterations: most optimiser iterations of each local fit (0: analyse the
        starting point).
      tolerance: of the stopping rule above.
      learning_rate: Adam's step in z-space (``ADAM_LEARNING_RATE``); unused by L-BFGS.
      restarts: most restarts after a rejected fit (above; default ``RESTARTS`` = 4;
        0: one local fit from the given start).
      stages: the stage names the model reports (``jaxdem.differentiable``'s
        ``stages``); None: the stages the observations name, plus the last one if
        some observation names none; no stages at all when none does.
      forward: ``(f, theta0)`` to use instead of ``jaxdem.differentiable(scene, fit,
        stages=...)``; ``f`` must follow its contract (dict of monitors, or of stages
        of monitors when ``stages`` is not None).
      progress: called at the start and after each iteration with a dict:
        ``iteration``, ``misfit``, ``params`` ({path: value}), ``gradient_norm``
        (in z-space), ``evaluations`` (all solves so far), ``start`` (0 for the fit
        from the given start, k for the k-th restart).

    Returns:
      a :class:`BackAnalysis`; its ``status`` says whether the fit converged, and is
      ``"no_equilibrium_at_start"`` when the model has none at theta0.

    Raises:
      SceneError: an unknown monitor, stage or parameter path, a point observation
        without component, bad bounds or std; the message names the field.
      ValueError: an unknown optimizer, max_iterations < 0, restarts < 0, tolerance <= 0,
        or a ``theta0`` whose length is not that of ``fit``.

    Example::

        scene = jaxdem.load_scene("tunnel.toml")
        fit = back_analyse(scene, {"section 1-1": (0.0123, 0.0005)},
                           fit=["joints.set1.kn"], bounds={"joints.set1.kn": (1e5, 1e8)})
        print(fit.params["joints.set1.kn"], fit.std["joints.set1.kn"], fit.warnings)
    """
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)} (got {optimizer!r})")
    if int(max_iterations) != max_iterations or max_iterations < 0:
        raise ValueError(f"max_iterations must be a whole number >= 0 (got {max_iterations!r})")
    if int(restarts) != restarts or restarts < 0:
        raise ValueError(f"restarts must be a whole number >= 0 (got {restarts!r})")
    if not tolerance > 0.0:
        raise ValueError(f"tolerance must be > 0 (got {tolerance!r})")
    if scene is None and forward is None:
        raise ValueError("give the scene, or forward=(f, theta0)")

    paths = check_fit(fit, scene)
    bounds = check_bounds(bounds, paths)
    observations = checked_observations(as_observations(observed), scene)
    stage_list, last_stage = resolve_stages(observations, scene, stages)
    if forward is None:
        import jaxdem

        forward = jaxdem.differentiable(scene, params=paths, stages=stage_list)
    f, theta0 = forward
    theta0 = np.asarray(theta0, dtype=np.float64).reshape(-1)
    if theta0.shape != (len(paths),):
        raise ValueError(f"theta0 has {theta0.size} values for {len(paths)} fitted parameters")
    transform = make_transform(paths, theta0, bounds)

    observed_values = np.array([obs.value for obs in observations])
    std = np.array([obs.std for obs in observations])
    model = observed_model(f, observations, stage_list, last_stage)
    objective = Objective(model, transform, observed_values, std)

    current = 0  # which local fit is reporting: 0 from the given start, k the k-th restart

    def report(iteration: int, z: Any, value: float, grad: Any) -> None:
        if progress is None:
            return
        theta = transform.theta(np.asarray(z))
        progress({
            "iteration": iteration,
            "misfit": float(value),
            "params": dict(zip(paths, map(float, theta), strict=True)),
            "gradient_norm": float(np.linalg.norm(np.asarray(grad))),
            "evaluations": dict(objective.evaluations),
            "start": current,
        })

    def local_fit(z_start: np.ndarray) -> tuple[Run, dict[str, Any], str]:
        """One run of the optimiser from z_start (restored: ``restore``), its line in
        ``starts`` and the restoration's sentence."""
        before = objective.evaluations["gradient"] + objective.evaluations["forward"]
        z_start, restored = restore(objective, z_start, paths)
        if optimizer == "lbfgs":
            run = run_lbfgs(objective, z_start, int(max_iterations), tolerance, report)
        elif optimizer == "gauss-newton":
            run = run_gauss_newton(objective, z_start, int(max_iterations), tolerance, report)
        else:
            run = run_adam(objective, z_start, int(max_iterations), tolerance, learning_rate,
                           report)
        finite = [v for v in run.history if math.isfinite(v)]
        line = {
            "start": dict(zip(paths, map(float, transform.theta(z_start)), strict=True)),
            "params": dict(zip(paths, map(float, transform.theta(run.z)), strict=True)),
            "misfit": min(finite) if finite else math.inf,
            "status": run.status,
            "iterations": run.iterations,
            "solves": objective.evaluations["gradient"] + objective.evaluations["forward"]
                      - before,
        }
        return run, line, restored

    run, line, restored = local_fit(start_z(theta0, transform))
    runs, starts = [run], [line]
    limit = misfit_limit(len(observations), len(paths))
    if max_iterations > 0 and run.status != NO_EQUILIBRIUM_AT_START:
        u_given = transform.fraction(start_z(theta0, transform))
        candidates = (u for u in restart_points(len(paths))
                      if np.max(np.abs(u - u_given)) >= LM_MAX_STEP)
        while len(runs) <= restarts and not min(s["misfit"] for s in starts) <= limit:
            current += 1
            u = next(candidates)
            run, line, _ = local_fit(logit(u))
            runs.append(run)
            starts.append(line)
    best = min(range(len(runs)), key=lambda k: starts[k]["misfit"])
    warnings = [restored] if restored else []
    if len(runs) > 1:
        warnings.append(_restart_sentence(starts, best, limit, len(observations), len(paths)))
    return _analyse(runs[best], theta0, objective, transform, paths, observations, optimizer,
                    warnings, starts)


def _restart_sentence(starts: list[dict[str, Any]], best: int, limit: float, n: int,
                      p: int) -> str:
    """Why the fit restarted, from where, and which local fit gave the estimate."""
    misfits = ", ".join(f"{s['misfit']:.4g}" for s in starts[1:])
    if starts[best]["misfit"] <= limit:
        outcome = (f"restart {best} reached misfit {starts[best]['misfit']:.4g}, which noise "
                   "explains")
    else:
        kept = f"restart {best}'s" if best else "the first fit's"
        outcome = (f"none reached a misfit that noise explains, and the estimate is {kept}, "
                   "the lowest: the model or the stds may be wrong, which no restart mends")
    dof, k = max(n - p, 1), len(starts) - 1
    return (f"the fit from the start ended at misfit {starts[0]['misfit']:.4g}, more than noise "
            f"explains (above {limit:.4g}, the {REJECT_QUANTILE:.1%} quantile of chi^2 / 2 with "
            f"{dof} degree{'s' * (dof > 1)} of freedom): a local minimum, or a model that cannot "
            f"fit; it restarted {k} time{'s' * (k > 1)} from other points (the centre of the "
            f"bounds, then Halton points; misfits {misfits}): {outcome}")


def _analyse(run: Run, theta0: np.ndarray, objective: Objective, transform: Transform,
             paths: list[str], observations: list[Observation], optimizer: str,
             warnings: list[str], starts: list[dict[str, Any]]) -> BackAnalysis:
    theta = transform.theta(run.z)
    y, jac = objective.evaluate(theta, derivatives=True)
    r = (y - objective.observed) / objective.std
    misfit = 0.5 * float(r @ r)
    if run.status == NO_EQUILIBRIUM_AT_START or not finite_entry((y, jac)):
        if run.status != NO_EQUILIBRIUM_AT_START:
            warnings.append("the model's values or derivatives at the estimate are not finite: "
                            "no standard deviations")
        p = len(paths)
        stds, identifiable = np.full(p, np.inf), np.zeros(p, dtype=bool)
        correlation = np.where(np.eye(p, dtype=bool), 1.0, np.nan)
        scaled = np.full_like(jac, np.nan)
    else:
        scale = scales(theta, transform)
        scaled = jac / objective.std[:, None] * scale[None, :]
        stds, identifiable, correlation = gauss_newton_statistics(scaled, scale, paths, warnings)
        warnings += bound_warnings(transform.fraction(run.z), theta, transform.lo, transform.hi,
                                   paths)
        warnings += precision_warnings(theta, stds, identifiable, paths)
        warnings += fit_warnings(misfit, len(observations), len(paths))
    if objective.evaluations["no_derivative"]:
        warnings.append(f"{objective.evaluations['no_derivative']} solves had finite values but "
                        "no derivative (a singular held-state tangent); the optimiser stepped "
                        "back from them")
    if objective.failures:
        warnings.append(f"{len(objective.failures)} solves raised and were read as points "
                        f"without equilibrium; the first {objective.failures[0]}")
    return BackAnalysis(
        paths=list(paths),
        params=dict(zip(paths, map(float, theta), strict=True)),
        std=dict(zip(paths, map(float, stds), strict=True)),
        identifiable=dict(zip(paths, map(bool, identifiable), strict=True)),
        correlation=correlation,
        start=dict(zip(paths, map(float, theta0), strict=True)),
        bounds={p: (float(lo), float(hi))
                for p, lo, hi in zip(paths, transform.lo, transform.hi, strict=True)},
        observations=list(observations),
        fitted=y,
        sensitivity={"jacobian": jac, "dimensionless": scaled},
        misfit=misfit if math.isfinite(misfit) else math.inf,
        history=run.history,
        iterations=run.iterations,
        evaluations=dict(objective.evaluations),
        converged=run.status == CONVERGED,
        status=run.status,
        message=run.message,
        warnings=warnings,
        optimizer=optimizer,
        starts=starts,
    )
