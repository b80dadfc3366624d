"""The fit: bounded coordinates, the counted objective and the three optimisers.

Owns the parameter transform (bounds, log scaling, z = logit of the fraction of the
range), :class:`Objective` (misfit and Jacobian of the observed model, with cached
and counted solves; a solve without equilibrium, without derivative or that raises is
a point to step back from), the start's restoration (``restore``), the points a rejected
fit restarts from (``restart_points``) and the optimisers: Gauss-Newton /
Levenberg-Marquardt (the default), optax L-BFGS and Adam. Data flows
one way: the vector model of :mod:`inverse.observations` -> Objective -> a
:class:`Run` (the point reached, history, status), which :mod:`inverse.backanalysis`
turns into a result with :mod:`inverse.statistics`. Host code around the jitted
model and its jacfwd.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from inverse.observations import finite_number
from jaxdem.scene import Scene, SceneError, apply_overrides

DEFAULT_BOUND_FACTOR = 100.0
"""Default bounds of a positive parameter: [theta0 / 100, theta0 * 100]."""

DEFAULT_TOLERANCE = 1.0e-6
"""Stopping tolerance: the misfit is in units of chi^2 / 2, so a change below 1e-6 moves
the parameters by about a thousandth of their standard deviation."""

ADAM_LEARNING_RATE = 0.05
"""Adam's step in z-space. Adam moves each z by at most about its learning rate per
iteration, and d sigmoid / dz <= 1/4, so 0.05 moves a parameter by at most ~1/80 of its
(log-)range: a factor 10^(4/80) = 1.12 within the default bounds. Steady, and fine enough
to end within ~0.1 % of the optimum."""
ADAM_PATIENCE = 30
"""Adam stops when its best misfit has not improved by tolerance * (1 + misfit) in this
many iterations: its momentum carries it past the minimum and back for a while, so one
small change means little. Expect a few hundred iterations (L-BFGS: about ten)."""
START_INSIDE = 1.0e-2
"""A starting value on a bound starts this fraction of the (log-)range inside it, where
sigmoid(z) still has a usable slope (0.0099)."""

RESTORE_STEPS = (0.25, 0.5, 0.75, 1.0)
"""Where the model has no equilibrium at the start, the points tried on the straight
line (in u, see ``run_gauss_newton``) from the start (0) to the centre of the bounds
(1); the fit starts from the first with equilibrium and derivatives. With default bounds
the start is the centre, so only explicit bounds give it room to move."""

RESTARTS = 4
"""Most restarts of the local fit (``back_analyse(restarts=...)``, ``--restarts``). The
fit restarts only when its misfit is statistically rejected (``REJECT_QUANTILE`` in
:mod:`inverse.statistics`), from the points of :func:`restart_points` in turn, and stops
at the first accepted fit: an accepted first fit costs nothing more, a model that fits
nowhere (stds too small, a mechanism missing from the model) pays for every restart."""

CACHE_SIZE = 8
"""Forward evaluations (values and Jacobians) remembered by theta: the line search asks
again for points it has seen, and the final analysis asks for the accepted one."""
OPTIMIZERS = ("gauss-newton", "lbfgs", "adam")

# Statuses of a fit; ``BackAnalysis.converged`` is True for the first only.
CONVERGED = "converged"
MAX_ITERATIONS = "max_iterations"
LINE_SEARCH_FAILED = "line_search_failed"
NO_EQUILIBRIUM_AT_START = "no_equilibrium_at_start"


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Transform:
    """theta (file units) <-> z (unconstrained), per parameter, on the host.

    ``log[j]``: theta_j = exp(a_j + (b_j - a_j) sigmoid(z_j)) with a, b = log lo, log hi;
    otherwise theta_j = a_j + (b_j - a_j) sigmoid(z_j) with a, b = lo, hi.
    """

    lo: np.ndarray
    hi: np.ndarray
    log: np.ndarray

    @property
    def _ends(self) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.where(self.log, np.log(np.abs(self.lo)), self.lo)
            b = np.where(self.log, np.log(np.abs(self.hi)), self.hi)
        return a, b

    def fraction(self, z: np.ndarray) -> np.ndarray:
        """sigmoid(z): where theta sits between its bounds (0-1, in log for log-scaled)."""
        return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(z, dtype=np.float64)))

    def theta(self, z: np.ndarray) -> np.ndarray:
        a, b = self._ends
        t = a + (b - a) * self.fraction(z)
        # Clipped: exp(log hi) may round a hair above hi.
        return np.clip(np.where(self.log, np.exp(t), t), self.lo, self.hi)

    def dtheta_dz(self, z: np.ndarray) -> np.ndarray:
        a, b = self._ends
        u = self.fraction(z)
        slope = (b - a) * u * (1.0 - u)
        return np.where(self.log, self.theta(z) * slope, slope)


def check_fit(fit: Any, scene: Scene | None) -> list[str]:
    if isinstance(fit, str) or not isinstance(fit, Sequence) or not fit:
        raise SceneError("fit", f"expected a list of parameter paths (got {fit!r})")
    paths = []
    for path in fit:
        if not isinstance(path, str) or not path:
            raise SceneError("fit", "parameter paths are strings like joints.set1.kn "
                                    f"(got {path!r})")
        if path in paths:
            raise SceneError(f"fit {path}", "listed twice")
        paths.append(path)
    if scene is not None:
        # The scene's own override walk knows which paths are numeric parameters; the
        # value written is irrelevant (the copy is thrown away, nothing is validated).
        for path in paths:
            try:
                apply_overrides(scene.data, {path: 1.0})
            except SceneError as err:
                raise SceneError(path, err.problem, prefix="fit ") from None
    return paths


def check_bounds(bounds: Mapping | None, paths: list[str]) -> dict[str, tuple[float, float]]:
    """Explicit bounds, checked before any solve: fitted paths, finite, lo < hi."""
    if bounds is None:
        return {}
    if not isinstance(bounds, Mapping):
        raise SceneError("bounds", f"expected {{path: (lo, hi)}} (got {bounds!r})")
    out = {}
    for path, entry in bounds.items():
        where = f"bounds {path}"
        if path not in paths:
            raise SceneError(where, f"not a fitted parameter (fit: {', '.join(paths)})")
        if isinstance(entry, (str, bytes)) or not isinstance(entry, Sequence) or len(entry) != 2:
            raise SceneError(where, f"expected (lo, hi) (got {entry!r})")
        lo, hi = finite_number(entry[0], where), finite_number(entry[1], where)
        if not lo < hi:
            raise SceneError(where, f"lo must be < hi (got {lo:g}, {hi:g})")
        out[path] = (lo, hi)
    return out


def make_transform(paths: list[str], theta0: np.ndarray,
               bounds: dict[str, tuple[float, float]]) -> Transform:
    """Bounds of every parameter (explicit, or the default for a positive start) and
    whether it is log-scaled."""
    lo, hi = np.empty(len(paths)), np.empty(len(paths))
    for j, path in enumerate(paths):
        start = float(theta0[j])
        if not math.isfinite(start):
            raise SceneError(path, f"starting value is not finite ({start})", prefix="fit ")
        if path in bounds:
            lo[j], hi[j] = bounds[path]
        elif start > 0.0:
            lo[j], hi[j] = start / DEFAULT_BOUND_FACTOR, start * DEFAULT_BOUND_FACTOR
        else:
            raise SceneError(path, f"starting value {start:g} is not positive, so it has no "
                                   "default bounds: give them (bounds={path: (lo, hi)}, or "
                                   "--bounds PATH=LO:HI)", prefix="fit ")
        if not lo[j] <= start <= hi[j]:
            raise SceneError(f"bounds {path}", f"the starting value {start:g} lies outside "
                                               f"[{lo[j]:g}, {hi[j]:g}]")
    return Transform(lo=lo, hi=hi, log=(lo > 0.0) & (hi > 0.0))


def logit(u: np.ndarray) -> np.ndarray:
    """z of a fraction u of the range: the inverse of :meth:`Transform.fraction`."""
    return np.log(u) - np.log1p(-u)


def start_z(theta0: np.ndarray, transform: Transform) -> np.ndarray:
    """z of the starting values; one on a bound (a cohesion starting at its lower bound 0)
    starts START_INSIDE of the range inside it, where sigmoid(z) still has a slope."""
    a, b = transform._ends
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(transform.log, np.log(np.abs(theta0)), theta0)
    return logit(np.clip((t - a) / (b - a), START_INSIDE, 1.0 - START_INSIDE))


def scales(theta: np.ndarray, transform: Transform) -> np.ndarray:
    """Scale of each parameter for dimensionless sensitivities: |theta|, or the width of
    its bounds where theta = 0."""
    width = transform.hi - transform.lo
    return np.where(np.abs(theta) > 0.0, np.abs(theta), width)


# --------------------------------------------------------------------------- objective


class Objective:
    """The misfit as a function of z, on the host, with counted and cached solves.

    ``evaluate(theta, derivatives)`` returns the observed model values y (n,) and,
    when asked, dy/dtheta (n, p) from one ``jax.jacfwd`` solve. The last
    ``CACHE_SIZE`` points are remembered, so a value asked where the Jacobian was just
    computed costs nothing. A point without equilibrium (NaN) has misfit +inf and
    a zero gradient: optax's line search reads inf as "outside the domain" and steps
    back. So has a point whose values are finite but whose derivatives are not ("no
    derivative": the held-state tangent could not be factorised, counted as
    ``no_derivative``), and one whose solve raised (the reason kept in ``failures``).
    """

    def __init__(self, model: Callable, transform: Transform, observed: np.ndarray,
                 std: np.ndarray):
        self.transform = transform
        self.observed = observed
        self.std = std
        self.evaluations = {"forward": 0, "gradient": 0, "no_equilibrium": 0,
                            "no_derivative": 0}
        self.failures: list[str] = []  # solves that raised: read as no equilibrium
        self._values = jax.jit(model)

        def both(theta):
            y = model(theta)
            return y, y

        # jacfwd: one forward pass per parameter column, all observations at once.
        self._jacobian = jax.jit(jax.jacfwd(both, has_aux=True))
        self._cache: OrderedDict[bytes, tuple[np.ndarray, np.ndarray | None]] = OrderedDict()

    def evaluate(self, theta: np.ndarray, derivatives: bool) -> tuple[np.ndarray, Any]:
        theta = np.asarray(theta, dtype=np.float64)
        key = theta.tobytes()
        hit = self._cache.get(key)
        if hit is not None and (hit[1] is not None or not derivatives):
            self._cache.move_to_end(key)
            return hit
        # The optimiser loop runs under jax.disable_jit (see run_lbfgs); the model is
        # compiled and run as usual.
        with jax.disable_jit(False):
            try:
                if derivatives:
                    jac, y = self._jacobian(jnp.asarray(theta))
                    entry = (np.asarray(y, dtype=np.float64), np.asarray(jac, dtype=np.float64))
                else:
                    entry = (np.asarray(self._values(jnp.asarray(theta)), dtype=np.float64),
                             None)
            except SceneError:
                raise
            except Exception as err:  # noqa: BLE001 - a solve that fails is a point to step back from
                entry = (np.full(self.observed.shape, np.nan),
                         np.full(self.observed.shape + theta.shape, np.nan)
                         if derivatives else None)
                lines = str(err).strip().splitlines() or [""]
                self.failures.append(f"at theta = {theta.tolist()}: {type(err).__name__}: "
                                     f"{lines[-1]}")
            self.evaluations["gradient" if derivatives else "forward"] += 1
        if not np.all(np.isfinite(entry[0])):
            self.evaluations["no_equilibrium"] += 1
        elif not finite_entry(entry):
            self.evaluations["no_derivative"] += 1
        self._cache[key] = entry
        while len(self._cache) > CACHE_SIZE:
            self._cache.popitem(last=False)
        return entry

    def misfit(self, z: np.ndarray) -> float:
        y, _ = self.evaluate(self.transform.theta(z), derivatives=False)
        r = (y - self.observed) / self.std
        value = 0.5 * float(r @ r)
        return value if math.isfinite(value) else math.inf

    def misfit_and_grad(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        z = np.asarray(z, dtype=np.float64)
        y, jac = self.evaluate(self.transform.theta(z), derivatives=True)
        if not finite_entry((y, jac)):
            return math.inf, np.zeros_like(z)
        r = (y - self.observed) / self.std
        grad = ((r / self.std) @ jac) * self.transform.dtheta_dz(z)
        return 0.5 * float(r @ r), grad

    def as_jax(self) -> Callable:
        """The misfit as a JAX-differentiable function of z, for optax's line search.

        A custom VJP hands JAX the gradient computed on the host. The optimiser runs
        it eagerly (under jax.disable_jit), so z arrives concrete; no callback
        re-enters JAX from inside compiled code.
        """

        @jax.custom_vjp
        def misfit(z):
            return jnp.asarray(self.misfit(np.asarray(z)))

        def forward(z):
            value, grad = self.misfit_and_grad(np.asarray(z))
            return jnp.asarray(value), jnp.asarray(grad)

        def backward(grad, cotangent):
            return (cotangent * grad,)

        misfit.defvjp(forward, backward)
        return misfit


def finite_entry(entry: tuple[np.ndarray, Any]) -> bool:
    y, jac = entry
    return bool(np.all(np.isfinite(y)) and (jac is None or np.all(np.isfinite(jac))))


# --------------------------------------------------------------------------- optimisers


@dataclass
class Run:
    z: np.ndarray
    history: list[float]
    iterations: int
    status: str
    message: str


def _settled(previous: float, value: float, grad_norm: float, tolerance: float) -> str | None:
    """The stopping rule shared by both optimisers; None to go on."""
    scale = tolerance * (1.0 + value)
    if grad_norm <= scale:
        return (f"the gradient norm in z-space ({grad_norm:.2e}) fell below "
                f"tolerance x (1 + misfit) = {scale:.2e}")
    if 0.0 <= previous - value <= scale and grad_norm <= math.sqrt(tolerance) * (1.0 + value):
        return (f"the last iteration lowered the misfit by {previous - value:.2e}, "
                f"less than tolerance x (1 + misfit) = {scale:.2e}")
    return None


def run_lbfgs(objective: Objective, z0: np.ndarray, max_iterations: int, tolerance: float,
               report: Callable) -> Run:
    """optax L-BFGS with its zoom line search, as optax documents the loop."""
    solver = optax.lbfgs()
    value_fn = objective.as_jax()
    value_and_grad = optax.value_and_grad_from_state(value_fn)
    z = jnp.asarray(z0)
    state = solver.init(z)
    # Eager: optax's line search is a lax.while_loop, which would otherwise trace
    # value_fn once and never come back to the host for the trial points.
    with jax.disable_jit():
        value, grad = value_and_grad(z, state=state)
        value = float(value)
        history = [value]
        report(0, z, value, grad)
        if not math.isfinite(value):
            return Run(np.asarray(z), history, 0, NO_EQUILIBRIUM_AT_START, _NO_START)
        status, message = MAX_ITERATIONS, _limit_message(max_iterations)
        best_z, best, k = z, value, 0
        for k in range(1, max_iterations + 1):
            updates, state = solver.update(grad, state, z, value=value, grad=grad,
                                           value_fn=value_fn)
            z_new = optax.apply_updates(z, updates)
            if np.array_equal(np.asarray(z_new), np.asarray(z)):
                status, message, k = LINE_SEARCH_FAILED, _STUCK, k - 1
                break
            z = z_new
            value, grad = value_and_grad(z, state=state)
            value = float(value)
            history.append(value)
            report(k, z, value, grad)
            if value < best:  # the zoom line search may accept an "unsafe" step that does not
                best_z, best = z, value  # lower the misfit: keep the best point
            done = _settled(history[-2], value, float(jnp.linalg.norm(grad)), tolerance)
            if done:
                status, message = CONVERGED, done
                break
    return Run(np.asarray(best_z), history, k, status, message)


def run_adam(objective: Objective, z0: np.ndarray, max_iterations: int, tolerance: float,
              learning_rate: float, report: Callable) -> Run:
    """optax Adam on the host gradient; returns the best point seen (Adam's misfit is
    not monotone). A point without equilibrium sends it back to the best point with
    half the learning rate."""
    z = np.asarray(z0, dtype=np.float64)
    value, grad = objective.misfit_and_grad(z)
    history = [value]
    report(0, z, value, grad)
    if not math.isfinite(value):
        return Run(z, history, 0, NO_EQUILIBRIUM_AT_START, _NO_START)
    solver = optax.adam(learning_rate)
    state = solver.init(jnp.asarray(z))
    best_z, best, best_grad, best_at = z, value, grad, 0
    status, message = MAX_ITERATIONS, _limit_message(max_iterations)
    k = 0
    for k in range(1, max_iterations + 1):
        updates, state = solver.update(jnp.asarray(grad), state)
        z = np.asarray(optax.apply_updates(jnp.asarray(z), updates))
        value, grad = objective.misfit_and_grad(z)
        history.append(value)
        report(k, z, value, grad)
        if not math.isfinite(value):
            learning_rate *= 0.5
            solver = optax.adam(learning_rate)
            z, value, grad = best_z, best, best_grad
            state = solver.init(jnp.asarray(z))
            continue
        if value < best - tolerance * (1.0 + value):
            best_at = k
        if value < best:
            best_z, best, best_grad = z, value, grad
        grad_norm = float(np.linalg.norm(grad))
        if grad_norm <= tolerance * (1.0 + value):
            status, message = CONVERGED, _settled(math.inf, value, grad_norm, tolerance)
            break
        if k - best_at >= ADAM_PATIENCE:
            status = CONVERGED
            message = (f"the best misfit improved by less than tolerance x "
                       f"(1 + misfit) in the last {ADAM_PATIENCE} iterations")
            break
    return Run(best_z, history, k, status, message)


LM_DAMPING = 1.0e-3
"""Starting Levenberg-Marquardt damping (relative to the diagonal of J^T J); divided by
3 after a step that lowers the misfit, multiplied by 10 after one that does not."""
LM_MAX_STEP = 0.125
"""Largest Levenberg-Marquardt step of one parameter, as a fraction of its (log-)range (a
factor 3.2 within the default bounds): a trust region, so that a step from far away
cannot jump from bound to bound, nor try a point where the model is a mechanism (whose
solve may take many times as long)."""
LM_BLOCKED = 2
"""Trial points without equilibrium in one iteration after which the step is sought one
parameter at a time (``along_axes`` in :func:`run_gauss_newton`): next to a region where
the model is a mechanism, a step that moves every parameter at once may enter it at any
length, while one along a single parameter (stiffening one set) need not."""
U_EDGE = 1.0e-15
"""A Gauss-Newton estimate on a bound is handed back as z = logit(U_EDGE) (or of 1 - U_EDGE)."""


def run_gauss_newton(objective: Objective, z0: np.ndarray, max_iterations: int,
                      tolerance: float, report: Callable) -> Run:
    """Projected Levenberg-Marquardt on the weighted residuals r = (y - observed) / std.

    Every solve gives the whole Jacobian of the observations (forward-mode
    sensitivities), so the misfit's Gauss-Newton model is free: the step solves
    (J^T J + lambda diag(J^T J)) du = -J^T r. It works in u = sigmoid(z), where each
    parameter sits between its bounds (0-1, in log for log-scaled ones), not in z:
    in z a step of a few units saturates the sigmoid, the gradient vanishes there and
    the fit stops on a bound as if converged. In u a bound is a box face: the step is
    clipped to the box (and to ``LM_MAX_STEP``), a parameter on a bound whose gradient
    pushes outwards is held there, and convergence is read on the projected gradient.
    Each trial point costs one solve with sensitivities; a trial that does not lower
    the misfit (or has no equilibrium, or no derivative) is refused and the damping
    raised. After ``LM_BLOCKED`` trials without equilibrium, or before giving up, it
    tries steps of one parameter at a time. Not optax: the least-squares structure is what
    makes it converge in a handful of solves.
    """
    tr = objective.transform
    a, b = tr._ends

    def theta_of(u):
        t = a + (b - a) * u
        return np.clip(np.where(tr.log, np.exp(t), t), tr.lo, tr.hi)

    def weighted(u):
        theta = theta_of(u)
        y, jac = objective.evaluate(theta, derivatives=True)
        if not finite_entry((y, jac)):
            return None, None
        r = (y - objective.observed) / objective.std
        dtheta_du = (b - a) * np.where(tr.log, theta, 1.0)
        return r, (jac / objective.std[:, None]) * dtheta_du

    def z_of(u):
        return logit(np.clip(u, U_EDGE, 1.0 - U_EDGE))

    def held(u, g):
        """Parameters on a bound that the gradient pushes further out."""
        return ((u <= 0.0) & (g > 0.0)) | ((u >= 1.0) & (g < 0.0))

    def projected(u, g):
        return np.where(held(u, g), 0.0, g)

    def along_axes(u, g, A, free, value):
        """The Gauss-Newton step of one parameter at a time, the largest expected
        decrease g_j^2 / A_jj first, whole or halved: (u, r, J) of the first that lowers
        the misfit, or None."""
        gain = np.where(free, g**2 / np.maximum(np.diag(A), 1e-30), -1.0)
        for j in np.argsort(-gain)[:int(free.sum())]:
            s = float(np.clip(-g[j] / max(A[j, j], 1e-30), -LM_MAX_STEP, LM_MAX_STEP))
            for _ in range(2):
                u_try = u.copy()
                u_try[j] = min(max(u[j] + s, 0.0), 1.0)
                if u_try[j] == u[j]:
                    break
                r_try, J_try = weighted(u_try)
                if r_try is not None and 0.5 * float(r_try @ r_try) < value:
                    return u_try, r_try, J_try
                s *= 0.5
        return None

    u = tr.fraction(np.asarray(z0, dtype=np.float64))
    r, Ju = weighted(u)
    if r is None:
        report(0, z_of(u), math.inf, np.zeros_like(u))
        return Run(z_of(u), [math.inf], 0, NO_EQUILIBRIUM_AT_START, _NO_START)
    value = 0.5 * float(r @ r)
    history = [value]
    report(0, z_of(u), value, Ju.T @ r * u * (1.0 - u))
    damping = LM_DAMPING
    status, message = MAX_ITERATIONS, _limit_message(max_iterations)
    k = 0
    for k in range(1, max_iterations + 1):
        g = Ju.T @ r
        free = ~held(u, g)
        A = Ju.T @ Ju
        blocked, axes_tried = 0, False
        while True:
            step = np.zeros_like(u)
            Af = A[np.ix_(free, free)]
            step[free] = np.linalg.solve(
                Af + damping * np.diag(np.maximum(np.diag(Af), 1e-30)), -g[free])
            biggest = float(np.max(np.abs(step), initial=0.0))
            if biggest > LM_MAX_STEP:
                step *= LM_MAX_STEP / biggest
            u_new = np.clip(u + step, 0.0, 1.0)
            if np.array_equal(u_new, u):
                return Run(z_of(u), history, k - 1, LINE_SEARCH_FAILED, _STUCK)
            r_new, J_new = weighted(u_new)
            if r_new is not None and 0.5 * float(r_new @ r_new) < value:
                break
            blocked += r_new is None
            if not axes_tried and (blocked >= LM_BLOCKED or damping * 10.0 > 1e12):
                axes_tried = True
                found = along_axes(u, g, A, free, value)
                if found is not None:
                    u_new, r_new, J_new = found
                    break
            damping *= 10.0
            if damping > 1e12:
                return Run(z_of(u), history, k - 1, LINE_SEARCH_FAILED, _STUCK)
        previous, u, r, Ju = value, u_new, r_new, J_new
        value = 0.5 * float(r @ r)
        damping = max(damping / 3.0, 1e-12)
        history.append(value)
        g = Ju.T @ r
        report(k, z_of(u), value, g * u * (1.0 - u))
        done = _settled(previous, value, float(np.linalg.norm(projected(u, g))), tolerance)
        if done:
            status, message = CONVERGED, done.replace("in z-space", "(projected, in u-space)")
            break
    return Run(z_of(u), history, k, status, message)


_NO_START = ("the model has no equilibrium at the starting parameters (the forward solve "
             "returned NaN): start from values at which `jaxdem run` converges")
_STUCK = ("the line search found no step that lowers the misfit (every trial point was worse "
          "or had no equilibrium); the estimate is the best point found")


def _limit_message(max_iterations: int) -> str:
    return (f"stopped at the iteration limit ({max_iterations}) before the misfit settled; "
            "a larger max_iterations may lower it further")


def restore(objective: Objective, z0: np.ndarray, paths: list[str]) -> tuple[np.ndarray, str]:
    """A start where the model has equilibrium: z0 itself, or the first of the
    ``RESTORE_STEPS`` towards the centre of the bounds that has one (the sentence
    saying so as the second value). Where none has, z0: the optimiser then reports
    ``no_equilibrium_at_start``."""
    tr = objective.transform
    if finite_entry(objective.evaluate(tr.theta(z0), derivatives=True)):
        return z0, ""
    u0 = tr.fraction(z0)
    for t in RESTORE_STEPS:
        u = u0 + t * (0.5 - u0)
        z = logit(u)
        theta = tr.theta(z)
        if finite_entry(objective.evaluate(theta, derivatives=True)):
            moved = ", ".join(f"{p} = {v:.4g}" for p, v in zip(paths, theta, strict=True))
            return z, (f"the model has no equilibrium (or no derivative) at the starting "
                       f"values; the fit started from {moved}, {t:.0%} of the way (in "
                       f"log-scaled coordinates) to the centre of the bounds")
    return z0, ""


def restart_points(p: int) -> Iterator[np.ndarray]:
    """Where to restart a rejected fit, in u (each parameter's fraction of its
    (log-)range): the centre of the bounds, then the Halton sequence (bases 2, 3, 5, ...,
    one per parameter; Halton 1960), which fills the box evenly and deterministically:
    each new point lands in the largest gap the earlier ones left.

    Example::

        from itertools import islice
        list(islice(restart_points(2), 3))  # [0.5, 0.5], [0.5, 0.333], [0.25, 0.667]
    """
    yield np.full(p, 0.5)
    bases = _primes(p)
    k = 1
    while True:
        yield np.array([_radical_inverse(k, base) for base in bases])
        k += 1


def _radical_inverse(k: int, base: int) -> float:
    """k's digits in ``base`` mirrored about the point: 1 -> 1/b, 2 -> 2/b, b -> 1/b^2."""
    x, f = 0.0, 1.0
    while k:
        f /= base
        x += f * (k % base)
        k //= base
    return x


def _primes(count: int) -> list[int]:
    out: list[int] = []
    n = 2
    while len(out) < count:
        if all(n % q for q in out):
            out.append(n)
        n += 1
    return out
