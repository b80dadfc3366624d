"""Reliability by FORM, the first-order reliability method, on the model itself
(``jaxdem reliability``).

The random variables X (scene parameters with the sweep's distributions,
:class:`jaxdem.sweep.Variable`) are mapped to independent standard normals z:

    y = L z,    x_i = F_i^-1(Phi(y_i)),

with L the Cholesky factor of the correlation matrix R of the y_i (identity
when the variables are independent). For a normal or lognormal variable the
map is exact and closed (x = m + s y; x = exp(lambda + zeta y)); for a uniform
or truncated normal it goes through Phi(y) and the quantile, with dx/dy from
the densities. R is applied to the y_i directly: exact for normal variables
(and for lognormals, read as the correlation of ln x), an approximation of
Nataf's model otherwise (the correlation of x_i differs slightly from R_ij).

A limit state g(x) is failure where g <= 0:

- serviceability, a monitor against a limit (m): ``"crown.|u| <= 0.02"``
  (g = 0.02 - |u|), ``"crown.uy >= -0.015"`` (g = uy + 0.015), ``"span <= 0.03"``
  (a section's convergence); g and its exact gradient come from one solve with
  sensitivities (:class:`jaxdem.differentiable.Problem`, implicit
  differentiation of every sub-step's equilibrium); a point without
  equilibrium (a mechanism) has no g;
- ultimate, ``"stable"``: g = F - 1 with F the factor of safety by strength
  reduction (:mod:`jaxdem.fos`), bracketed to a relative width ``rtol`` by
  batched solves (every point of an iteration in the same batches). F is not
  a smooth function of one equilibrium: it is where equilibrium ceases to
  exist, and the tangent there is singular, so its gradient is taken by
  central differences of the tightly bracketed F in standard normal space
  (step ``step``), 2p more points per iteration, all bracketed together. With
  rtol = 2e-5 and step = 0.2 the gradient's direction is known to about 3e-4
  (F of the incline is exact to 3e-6 in the model); the design point does not
  depend on that error to first order.

The design point z* is the point of the limit state g = 0 nearest the origin;
beta = alpha . z* (alpha = -grad g / |grad g|, so beta < 0 when the medians
already fail) and the probability of failure is Phi(-beta), exact when g is
linear in z (one variable: whenever g is monotone) and first order otherwise.
It is found by the HL-RF iteration (Hasofer & Lind 1974, Rackwitz & Fiessler
1978) with the step-size rule of Zhang & Der Kiureghian (1995, "Two improved
algorithms for reliability analysis": the improved HL-RF): the HL-RF step d
is scaled by the largest 2^-k that decreases the merit function
m(z) = |z|^2 / 2 + c |g(z)| (Armijo, c = 2 max(|z|, |z + d|) / |grad g|, which
makes d a descent direction). Convergence:
|g| <= tolerance |g(0)| and |z - (alpha . z) alpha| <= tolerance max(1, |z|).

Importance factors are gamma_i^2 with gamma = -grad_y g / |grad_y g| (Der
Kiureghian 2005, "First- and second-order reliability methods", the importance
vector gamma^T = alpha^T L^-1 normalised); without correlation gamma = alpha and
the alpha_i^2 sum to 1. A positive gamma_i marks a load (failure as x_i
grows), a negative one a resistance.

``check="mc:N"`` also estimates the probability by Monte Carlo with the same
variables: N batched solves (:func:`jaxdem.batch.solve_batch`), failure where g
<= 0 or (serviceability and ultimate alike) the scene is a mechanism; samples
that found neither an equilibrium nor a mechanism are counted apart.

Example::

    scene = jaxdem.load_scene("examples/block_on_incline.toml")
    r = jaxdem.reliability(scene, ["joints.base.friction_deg=normal:30:3"], "stable")
    r.beta, r.probability, r.design_point     # 1.667, 0.0478, {"joints...": 25.0}
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxdem.config import float64
from jaxdem.results import jsonable, write_json
from jaxdem.scene import SceneError
from jaxdem.sweep import Variable, check_values, probability_of_instability

#: The distributions a random variable may have (a range LOW:HIGH is not one).
DISTRIBUTIONS = ("normal", "lognormal", "uniform", "truncnormal")
#: Comparisons a serviceability limit may use; g <= 0 is failure.
OPERATORS = ("<=", ">=", "<", ">")
#: Components of a point monitor: its displacement's x and y and its magnitude.
COMPONENTS = ("ux", "uy", "|u|")
#: The ultimate limit state: the factor of safety F >= 1.
STABLE = "stable"
#: Statuses of a FORM analysis.
CONVERGED = "converged"
ITERATION_LIMIT = "iteration_limit"
LINE_SEARCH_FAILED = "line_search_failed"
LIMIT_NOT_REACHED = "limit_not_reached"
NO_GRADIENT = "no_gradient"
NO_ANSWER_AT_START = "no_answer_at_start"
#: Most Monte Carlo samples of a check (--check mc:N).
MAX_CHECK_SAMPLES = 1_000_000
#: Samples of each batched call of the factor-of-safety brackets (padded to it): every
#: call has the same shape, so its program compiles once.
ROWS = 16

_LIMIT = re.compile(r"^\s*(.+?)\s*(<=|>=|<|>)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*$")


# ---------------------------------------------------------------------------
# Limit states


@dataclasses.dataclass(frozen=True)
class Limit:
    """A limit state g(x), failure where g <= 0 (see the module).

    Attributes:
      text: as given.
      kind: ``"monitor"`` (serviceability) or ``"stable"`` (ultimate).
      monitor: the monitor's name (serviceability).
      component: ``"ux"``, ``"uy"`` or ``"|u|"`` for a point monitor, None for a
        section (its convergence).
      operator: ``"<="`` or ``">="`` (``<`` and ``>`` read the same: the boundary
        has probability zero).
      value: the limit (m).
    """

    text: str
    kind: str
    monitor: str | None = None
    component: str | None = None
    operator: str | None = None
    value: float = 0.0

    @classmethod
    def parse(cls, text: str, scene) -> Limit:
        """``"stable"`` or ``"MONITOR[.COMPONENT] OP VALUE"`` against the scene's monitors."""
        if not isinstance(text, str) or not text.strip():
            raise SceneError("--limit", "give a limit: 'stable' or 'MONITOR OP VALUE' "
                             "(e.g. \"crown.|u| <= 0.02\", \"span <= 0.03\")")
        if text.strip().lower() == STABLE:
            return cls(text.strip(), STABLE)
        found = _LIMIT.match(text)
        if not found:
            raise SceneError("--limit", f"{text!r} is neither 'stable' nor 'MONITOR OP VALUE' "
                             "with OP one of <=, >=, <, > and VALUE in m")
        left, operator, value = found.groups()
        monitors = {m.name: m for m in scene.monitors}
        names = ", ".join(monitors) or "none"
        if left in monitors:
            name, component = left, None
        else:
            name, _, component = left.rpartition(".")
            if name not in monitors:
                missing = name if name and component in COMPONENTS else left
                raise SceneError("--limit", f"no monitor named {missing!r} in the scene "
                                 f"(monitors: {names})")
        kind = monitors[name].kind
        if kind == "point" and component not in COMPONENTS:
            raise SceneError("--limit", f"{name!r} is a point: name a component, "
                             f"{', '.join(f'{name}.{c}' for c in COMPONENTS)}")
        if kind != "point" and component is not None:
            raise SceneError("--limit", f"{name!r} is a section: its convergence has no "
                             f"component ({name} <= VALUE)")
        limit = float(value)
        if not math.isfinite(limit):
            raise SceneError("--limit", f"{value!r} is not a finite number")
        return cls(text.strip(), "monitor", name, component, operator[0] + "=", limit)

    @property
    def ultimate(self) -> bool:
        return self.kind == STABLE

    def indices(self, keys) -> list[int]:
        """Positions of the monitor's readings in :attr:`jaxdem.differentiable.Problem.keys`."""
        comps = ("ux", "uy") if self.component == "|u|" else (self.component,)
        return [i for i, (stage, name, comp) in enumerate(keys)
                if stage is None and name == self.monitor and comp in comps]

    def g(self, reading: np.ndarray) -> np.ndarray:
        """g of readings (..., k): the k components of :meth:`indices` (m)."""
        reading = np.asarray(reading, float)
        m = np.linalg.norm(reading, axis=-1) if self.component == "|u|" else reading[..., 0]
        return self.value - m if self.operator == "<=" else m - self.value

    def gradient(self, reading: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
        """dg/dx (p,) from the readings (k,) and their Jacobian (k, p)."""
        reading, jacobian = np.asarray(reading, float), np.asarray(jacobian, float)
        if self.component == "|u|":
            norm = float(np.linalg.norm(reading))
            dm = reading @ jacobian / norm if norm > 0 else np.full(jacobian.shape[1], np.nan)
        else:
            dm = jacobian[0]
        return -dm if self.operator == "<=" else dm

    def describe(self) -> str:
        if self.ultimate:
            return "ultimate: factor of safety F >= 1 (g = F - 1)"
        what = self.monitor if self.component is None else f"{self.monitor}.{self.component}"
        return f"serviceability: {what} {self.operator} {self.value:g} m"


# ---------------------------------------------------------------------------
# Standard normal space


def check_variables(variables: Sequence[Variable]) -> None:
    """Refuse what FORM cannot take: a range instead of a distribution, a path named twice."""
    if not variables:
        raise SceneError("--vary", "give at least one random variable")
    for v in variables:
        if v.kind not in DISTRIBUTIONS:
            raise SceneError(f"--vary {v.path}", "a random variable needs a distribution: "
                             f"{', '.join(f'{d}:...' for d in DISTRIBUTIONS)} (a range "
                             "LOW:HIGH is for sweeps; uniform:LOW:HIGH is its distribution)")
    paths = [v.path for v in variables]
    if len(set(paths)) != len(paths):
        raise SceneError("--vary", "a parameter is named twice")


def transform(variables: Sequence[Variable], y) -> tuple[np.ndarray, np.ndarray]:
    """x_i = F_i^-1(Phi(y_i)) and dx_i/dy_i for standard normal values y (..., p).

    Normal: x = m + s y. Lognormal (mean m, sd s of x): x = exp(lambda + zeta y),
    zeta^2 = ln(1 + (s/m)^2), lambda = ln m - zeta^2 / 2. Uniform on [a, b]:
    x = a + (b - a) Phi(y). Normal (m, s) truncated to [lo, hi]:
    x = m + s Phi^-1(P_lo + Phi(y) (P_hi - P_lo)), dx/dy = s phi(y) (P_hi - P_lo) / phi(t),
    t = (x - m) / s.
    """
    from scipy.special import ndtr, ndtri

    y = np.asarray(y, float)
    x, dx = np.empty_like(y), np.empty_like(y)
    for j, v in enumerate(variables):
        a, yj = v.args, y[..., j]
        if v.kind == "normal":
            x[..., j], dx[..., j] = a[0] + a[1] * yj, a[1]
        elif v.kind == "lognormal":
            zeta = math.sqrt(math.log1p((a[1] / a[0]) ** 2))
            x[..., j] = np.exp(math.log(a[0]) - 0.5 * zeta ** 2 + zeta * yj)
            dx[..., j] = zeta * x[..., j]
        elif v.kind == "uniform":
            x[..., j], dx[..., j] = a[0] + (a[1] - a[0]) * ndtr(yj), (a[1] - a[0]) * _pdf(yj)
        else:
            lo, hi = ndtr((a[2] - a[0]) / a[1]), ndtr((a[3] - a[0]) / a[1])
            t = ndtri(lo + ndtr(yj) * (hi - lo))
            x[..., j] = np.clip(a[0] + a[1] * t, a[2], a[3])
            dx[..., j] = a[1] * _pdf(yj) * (hi - lo) / np.maximum(_pdf(t), 1e-300)
    return x, dx


def _pdf(y):
    return np.exp(-0.5 * np.square(y)) / math.sqrt(2.0 * math.pi)


def correlation_matrix(variables: Sequence[Variable], correlation) -> np.ndarray:
    """The (p, p) correlation matrix R of the standard normals y, checked.

    ``correlation``: None (independent), a (p, p) array in the variables' order, or
    {(path_a, path_b): rho} (pairs not named are uncorrelated).
    """
    p = len(variables)
    if correlation is None:
        return np.eye(p)
    paths = [v.path for v in variables]
    if isinstance(correlation, Mapping):
        R = np.eye(p)
        for pair, rho in correlation.items():
            if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
                raise SceneError("--correlation", f"name a pair of paths, not {pair!r}")
            for path in pair:
                if path not in paths:
                    raise SceneError("--correlation", f"{path!r} is not a random variable "
                                     f"(--vary: {', '.join(paths)})")
            i, j = paths.index(pair[0]), paths.index(pair[1])
            if i == j:
                raise SceneError("--correlation", f"{pair[0]!r} is paired with itself")
            R[i, j] = R[j, i] = float(rho)
    else:
        R = np.array(correlation, float)
        if R.shape != (p, p):
            raise SceneError("--correlation", f"must be {p} x {p} (one row per variable), "
                             f"got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise SceneError("--correlation", "holds a NaN or infinite value")
    if not np.allclose(R, R.T, atol=1e-12) or not np.allclose(np.diag(R), 1.0):
        raise SceneError("--correlation", "must be symmetric with ones on the diagonal")
    off = R[~np.eye(p, dtype=bool)]
    if np.any(np.abs(off) >= 1.0):
        raise SceneError("--correlation", "coefficients must lie strictly between -1 and 1")
    if np.linalg.eigvalsh(R).min() <= 1e-10:
        raise SceneError("--correlation", "is not positive definite (these coefficients "
                         "cannot hold together)")
    return R


# ---------------------------------------------------------------------------
# HL-RF


def hlrf(evaluate: Callable[[np.ndarray], tuple[float, np.ndarray]], p: int, *,
         max_iterations: int = 30, tolerance: float = 1e-3, max_beta: float = 8.0,
         halvings: int = 6, progress: Callable[[dict], None] | None = None) -> dict:
    """The design point of g(z) = 0 nearest the origin by the improved HL-RF iteration.

    Args:
      evaluate: z (p,) -> (g, dg/dz (p,)); NaN where g has no value there.
      p: the number of variables.
      max_iterations: most HL-RF steps.
      tolerance: e in |g| <= e |g(0)| and |z - (alpha . z) alpha| <= e max(1, |z|).
      max_beta: stop when |z| exceeds it (the limit state is not reached nearer).
      halvings: most step halvings of the line search.
      progress: optional callable, called with each iteration's record.
    Returns:
      {"status", "z", "g", "gradient", "beta", "history"}: the last accepted point,
      its g and gradient, beta = alpha . z, and one record per point (``iteration``,
      ``z``, ``g``, ``gradient_norm``, ``beta``, ``step``).

    Example::

        # g = 3 - z1 - z2 (linear): beta = 3 / sqrt(2), found in one step
        out = hlrf(lambda z: (3 - z.sum(), -np.ones(2)), 2)
    """
    z = np.zeros(p)
    G, grad = evaluate(z)
    history: list[dict] = []

    def record(k, step):
        n = float(np.linalg.norm(grad))
        history.append(dict(iteration=k, z=z.tolist(), g=float(G), gradient_norm=n,
                            beta=float(-grad @ z / n) if n > 0 else float("nan"), step=step))
        if progress is not None:
            progress(history[-1])

    if not (np.isfinite(G) and np.all(np.isfinite(grad))):
        return dict(status=NO_ANSWER_AT_START, z=z, g=float(G), gradient=grad,
                    beta=float("nan"), history=history)
    record(0, None)
    scale = abs(G) if G != 0 else 1.0
    status = ITERATION_LIMIT
    for k in range(1, max_iterations + 1):
        n = float(np.linalg.norm(grad))
        if not n > 0:
            status = NO_GRADIENT
            break
        alpha = -grad / n
        along = float(alpha @ z)
        if abs(G) <= tolerance * scale and \
                np.linalg.norm(z - along * alpha) <= tolerance * max(1.0, np.linalg.norm(z)):
            status = CONVERGED
            break
        d = (along + G / n) * alpha - z                  # the HL-RF step
        c = 2.0 * max(np.linalg.norm(z), np.linalg.norm(z + d)) / n
        merit = 0.5 * z @ z + c * abs(G)
        slope = float((z + c * np.sign(G) * grad) @ d)  # < 0: d descends m
        step = 1.0
        for _ in range(halvings + 1):
            zt = z + step * d
            Gt, gt = evaluate(zt)
            if np.isfinite(Gt) and np.all(np.isfinite(gt)) and \
                    0.5 * zt @ zt + c * abs(Gt) <= merit + 0.5 * step * slope:
                break
            step *= 0.5
        else:
            status = LINE_SEARCH_FAILED
            break
        z, G, grad = zt, Gt, gt
        record(k, step)
        if np.linalg.norm(z) > max_beta:
            status = LIMIT_NOT_REACHED
            break
    n = float(np.linalg.norm(grad))
    beta = float(-grad @ z / n) if n > 0 else float(np.linalg.norm(z))
    return dict(status=status, z=z, g=float(G), gradient=grad, beta=beta, history=history)


# ---------------------------------------------------------------------------
# The model's limit states in y (correlated standard normal) space


class MonitorLimitState:
    """g and its exact gradient dg/dy from one solve with sensitivities per point."""

    def __init__(self, scene, variables, limit: Limit):
        from jaxdem.differentiable import Problem

        self.scene, self.variables, self.limit = scene, list(variables), limit
        self.problem = Problem(scene, [v.path for v in variables])
        self.rows = limit.indices(self.problem.keys)
        self.notes: list[str] = []

    def __call__(self, y):
        x, dxdy = transform(self.variables, y)
        p = len(self.variables)
        if not _accepted(self.scene, self.variables, x, self.notes):
            return float("nan"), np.full(p, np.nan)
        values, J = self.problem.evaluate(x, jacobian=True)
        reading, jac = values[self.rows], J[self.rows]
        if not np.all(np.isfinite(reading)):
            self.notes.append(f"no equilibrium at {_point(self.variables, x)} (a mechanism "
                              "or the iteration limit): treated as a step too far")
            return float("nan"), np.full(p, np.nan)
        return float(self.limit.g(reading)), self.limit.gradient(reading, jac) * dxdy

    @property
    def solves(self) -> dict:
        s = self.problem.solves
        return dict(plain=int(s["value"]), with_sensitivities=int(s["jacobian"]), batches=0)


class FactorLimitState:
    """g = F - 1 with F by strength reduction, bracketed by batched solves, and dg/dy by
    central differences of step ``step`` in y (all 2p + 1 points bracketed together)."""

    def __init__(self, scene, variables, *, intact=False, tensile=False, step=0.2,
                 rtol=2e-5, trials=None, limits=(0.01, 100.0), max_rounds=16, chunk=None):
        from jaxdem.fos import strength_parameters

        self.scene, self.variables = scene, list(variables)
        self.step, self.rtol, self.chunk = step, rtol, chunk
        # Trial factors per point and round: the 2p + 1 points' trials fill whole calls.
        points = 2 * len(self.variables) + 1
        calls = -(-2 * points // ROWS)
        self.trials = trials if trials is not None else max(2, calls * ROWS // points)
        self.limits, self.max_rounds = limits, max_rounds
        paths = [v.path for v in self.variables]
        base = strength_parameters(scene, intact=intact, tensile=tensile)
        # A random strength that strength reduction divides is divided even where the
        # scene's own value is zero (a cohesion the file leaves at 0).
        reduced = dict(base)
        for v in self.variables:
            if _is_reduced(v.path, intact, tensile):
                reduced.setdefault(v.path, 0.0)
        if not reduced:
            raise SceneError("--limit", "stable: no strength to reduce: every joint "
                             "friction_deg and cohesion is 0 and none is a random variable")
        self.columns = paths + [q for q in reduced if q not in paths]
        self.reduced = reduced
        self.counts = dict(plain=0, with_sensitivities=0, batches=0)
        self.undecided = 0
        self.notes: list[str] = []
        self._last: tuple | None = None   # (y, F, dF/dy): the guess for the next brackets
        self.wide = 0.02                  # relative half-width of a bracket around a guess

    def __call__(self, y):
        y = np.asarray(y, float)
        p = len(self.variables)
        h = self.step
        Y = np.vstack([y] + [y + s * h * e for e in np.eye(p) for s in (1.0, -1.0)])
        X, _ = transform(self.variables, Y)
        if not all(_accepted(self.scene, self.variables, x, self.notes) for x in X):
            return float("nan"), np.full(p, np.nan)
        guess = None
        if self._last is not None:
            y0, F0, dF0 = self._last
            guess = F0 + (Y - y0) @ dF0
        F = self.factors(X, guess)
        if guess is not None and np.all(np.isfinite(F)):
            # The next brackets start this many times the prediction's error wide.
            self.wide = float(np.clip(4.0 * np.max(np.abs(F - guess) / F), 0.002, 0.05))
        dF = (F[1::2] - F[2::2]) / (2.0 * h)
        if np.all(np.isfinite(F)):
            self._last = (y, F[0], dF)
        return float(F[0] - 1.0), dF

    def factors(self, X: np.ndarray, guess=None) -> np.ndarray:
        """F at each row of X (the variables' values), bracketed to rtol: every row's trial
        factors solved in one batch per round (strengths divided as :mod:`jaxdem.fos`
        divides them). NaN where F lies beyond ``limits``."""
        from jaxdem.batch import solve_batch
        from jaxdem.fos import reduce_strength

        m = X.shape[0]
        outcomes: list[dict[float, bool]] = [{} for _ in range(m)]
        wide = self.wide
        factors = [_geometric(0.25, 8.0, 2 * self.trials) if guess is None or
                   not (np.isfinite(guess[j]) and guess[j] > 0) else
                   _geometric(guess[j] / (1 + wide), guess[j] * (1 + wide), self.trials)
                   for j in range(m)]
        paths = [v.path for v in self.variables]
        for _ in range(self.max_rounds):
            rows, theta = [], []
            for j in range(m):
                values = dict(zip(paths, X[j], strict=True))
                for f in factors[j]:
                    theta.append([reduce_strength(q, values.get(q, self.reduced[q]), f)
                                  if q in self.reduced else values[q] for q in self.columns])
                    rows.append((j, float(f)))
            if not rows:
                break
            status = []
            # Calls of ROWS samples each (the last padded): one shape, one compilation.
            for start in range(0, len(rows), ROWS):
                block = theta[start:start + ROWS]
                block += [block[-1]] * (ROWS - len(block))
                b = solve_batch(self.scene, self.columns, np.array(block), chunk=self.chunk)
                status += b.status[:min(ROWS, len(rows) - start)]
                self.counts["batches"] += 1
            self.counts["plain"] += len(rows)
            for (j, f), s in zip(rows, status, strict=True):
                outcomes[j][f] = s == "converged"
                self.undecided += s not in ("converged", "mechanism")
            factors = [self._next(outcomes[j], factors[j]) for j in range(m)]
        F = np.full(m, np.nan)
        for j in range(m):
            lo, hi = _bracket(outcomes[j])
            if lo is not None and hi is not None:
                F[j] = math.sqrt(lo * hi)
        return F

    def _next(self, outcome: dict[float, bool], last) -> np.ndarray:
        """The next round's factors of one point (empty when its bracket is narrow enough)."""
        lo, hi = _bracket(outcome)
        if len(last) == 0:
            return last
        ratio = max(float(max(last) / min(last)), 1.02) ** 2
        if hi is None:                       # stable at every factor: grow upwards
            if lo >= self.limits[1]:
                return np.array([])
            return _geometric(lo, min(lo * ratio, self.limits[1]), self.trials + 1)[1:]
        if lo is None:                       # unstable at every factor: grow downwards
            if hi <= self.limits[0]:
                return np.array([])
            return _geometric(max(hi / ratio, self.limits[0]), hi, self.trials + 1)[:-1]
        if (hi - lo) / lo <= self.rtol:
            return np.array([])
        return _geometric(lo, hi, self.trials + 2)[1:-1]

    @property
    def solves(self) -> dict:
        return dict(self.counts)


def _geometric(lo: float, hi: float, n: int) -> np.ndarray:
    f = np.exp(np.linspace(math.log(lo), math.log(hi), n))
    f[0], f[-1] = lo, hi
    return f


def _bracket(outcome: dict[float, bool]) -> tuple[float | None, float | None]:
    """[largest stable F below the smallest unstable F, that F]; undecided counts unstable."""
    unstable = [f for f, stable in outcome.items() if not stable]
    hi = min(unstable) if unstable else None
    stable = [f for f, s in outcome.items() if s and (hi is None or f < hi)]
    return (max(stable) if stable else None), hi


def _is_reduced(path: str, intact: bool, tensile: bool) -> bool:
    """Whether strength reduction divides the parameter at ``path`` (see jaxdem.fos)."""
    keys = path.split(".")
    fields = ("friction_deg", "cohesion") + (("tensile_strength",) if tensile else ())
    sections = ("joints", "materials") if intact else ("joints",)
    return len(keys) == 3 and keys[0] in sections and keys[2] in fields


def _accepted(scene, variables, x, notes) -> bool:
    """Whether the scene takes the values x (a normal may reach a negative stiffness)."""
    try:
        scene.with_overrides({v.path: float(xi) for v, xi in zip(variables, x, strict=True)})
    except SceneError as err:
        notes.append(f"{err.path} = {_value(err, variables, x)} is outside what the scene "
                     f"accepts ({err.problem}): treated as a step too far")
        return False
    return True


def _value(err, variables, x):
    for v, xi in zip(variables, x, strict=True):
        if v.path == err.path:
            return f"{xi:.6g}"
    return "?"


def _point(variables, x) -> str:
    return ", ".join(f"{v.path} = {xi:.6g}" for v, xi in zip(variables, x, strict=True))


# ---------------------------------------------------------------------------
# Monte Carlo


def parse_check(check) -> int | None:
    """``"mc:N"`` (or N) -> N; None -> None."""
    if check is None:
        return None
    if isinstance(check, str):
        kind, _, count = check.partition(":")
        if kind.strip().lower() != "mc" or not count.strip():
            raise SceneError("--check", f"expected mc:N (Monte Carlo with N samples), "
                             f"got {check!r}")
        try:
            check = int(count)
        except ValueError:
            raise SceneError("--check", f"N must be a whole number (got {count!r})") from None
    if isinstance(check, bool) or not isinstance(check, (int, np.integer)) or \
            not 1 <= check <= MAX_CHECK_SAMPLES:
        raise SceneError("--check", f"N must be a whole number from 1 to "
                         f"{MAX_CHECK_SAMPLES:,} (got {check!r})")
    return int(check)


def monte_carlo(scene, variables, limit: Limit, R: np.ndarray, samples: int, *,
                seed: int = 0, chunk: int | None = None, progress=None) -> dict:
    """The probability of failure by Monte Carlo: ``samples`` draws of the variables (with
    correlation R of their standard normals), solved in batches.

    Failure: g <= 0 (a serviceability limit) or a mechanism (either limit: a mechanism
    exceeds every displacement, and for ``stable`` it is F < 1). Samples that end at the
    iteration limit (or non-finite) decide nothing: counted as ``undecided``.

    Returns:
      ``samples``, ``failures``, ``small_mechanisms`` (failures that are mechanisms of
      small pieces: :attr:`jaxdem.batch.BatchResult.small_mechanism`, counted in
      ``failures``), ``decided``, ``undecided``, ``probability`` (failures /
      decided), ``ci95`` (95% Wilson score interval), ``cov`` (coefficient of variation
      of the estimate, sqrt((1 - p) / (p N))), ``seed``, ``solves``, ``timing``.
    """
    from jaxdem.batch import solve_batch

    rng = np.random.default_rng(seed)
    z = rng.standard_normal((samples, len(variables)))
    X, _ = transform(variables, z @ np.linalg.cholesky(R).T)
    check_values(scene, variables, X)  # the scene's ranges, before any solve
    t0 = time.perf_counter()
    b = solve_batch(scene, [v.path for v in variables], X, chunk=chunk, progress=progress)
    mechanism = ~b.stable
    failed = mechanism.copy()
    if not limit.ultimate:
        reading = b.monitors[limit.monitor]
        reading = reading[:, None] if reading.ndim == 1 else reading
        if limit.component in ("ux", "uy"):
            reading = reading[:, COMPONENTS.index(limit.component)][:, None]
        with np.errstate(invalid="ignore"):
            failed |= b.converged & (limit.g(reading) <= 0)
    # probability_of_instability counts ~stable among converged | ~stable: failures
    # among the samples that ended in an equilibrium or a mechanism.
    share = probability_of_instability(dataclasses.replace(
        b, stable=~failed, converged=b.converged | mechanism))
    p, decided = share["p_unstable"], share["decided"]
    cov = math.sqrt((1 - p) / (p * decided)) if decided and p > 0 else float("inf")
    return dict(method="mc", samples=samples, seed=seed, failures=share["unstable"],
                small_mechanisms=int(np.sum(mechanism & b.small_mechanism)),
                decided=decided, undecided=share["undecided"], probability=p,
                ci95=share["ci95"], cov=cov, solves=samples,
                timing=dict(b.timing, total_s=time.perf_counter() - t0))


def samples_for_cov(probability: float, cov: float = 0.1) -> float:
    """Monte Carlo samples for a coefficient of variation ``cov`` of the estimate of
    ``probability``: N = (1 - p) / (p cov^2)."""
    return (1.0 - probability) / (probability * cov ** 2)


# ---------------------------------------------------------------------------
# The analysis


@dataclasses.dataclass
class Reliability:
    """Outcome of a FORM analysis (see the module).

    Attributes:
      scene: the scene's name.
      variables: the random :class:`jaxdem.sweep.Variable` s.
      limit: the :class:`Limit`.
      correlation: (p, p) correlation of the standard normals, or None.
      beta: the reliability index (negative when the medians fail).
      probability: Phi(-beta), FORM's probability of failure.
      design_point: path -> the design point's value (file units).
      design_point_u: path -> the design point in standard normal y (standard
        deviations of the equivalent normal from the median).
      alpha: path -> gamma_i, the signed direction cosine (positive: a load).
      importance: path -> gamma_i^2 (they sum to 1).
      status: ``"converged"``, ``"iteration_limit"``, ``"line_search_failed"``,
        ``"limit_not_reached"``, ``"no_gradient"`` or ``"no_answer_at_start"``.
      iterations: HL-RF steps taken.
      solves: ``plain`` (solves without sensitivities, trial solves of F
        included), ``with_sensitivities`` and ``batches`` (batched calls of the
        F brackets).
      history: per accepted point: ``iteration``, ``u`` (z), ``x`` (path ->
        value), ``g``, ``gradient_norm``, ``beta`` (alpha . z), ``step``.
      check: the Monte Carlo check (:func:`monte_carlo`) or None.
      warnings: every warning, in words.
      options, timing: what was asked; ``form_s``, ``check_s``, ``total_s`` (s).
    """

    scene: str
    variables: list
    limit: Limit
    correlation: np.ndarray | None
    beta: float
    probability: float
    design_point: dict[str, float]
    design_point_u: dict[str, float]
    alpha: dict[str, float]
    importance: dict[str, float]
    status: str
    iterations: int
    solves: dict
    history: list[dict]
    check: dict | None
    warnings: list[str]
    options: dict[str, Any]
    timing: dict[str, float]

    @property
    def converged(self) -> bool:
        return self.status == CONVERGED

    def to_dict(self) -> dict[str, Any]:
        """The content of ``reliability.json``: plain JSON types, NaN as null."""
        return jsonable(finite=True, x=dict(
            scene=self.scene, limit=self.limit.text, limit_state=self.limit.describe(),
            variables=[dict(path=v.path, distribution=v.kind, args=list(v.args))
                       for v in self.variables],
            correlation=None if self.correlation is None else self.correlation.tolist(),
            beta=self.beta, probability=self.probability, design_point=self.design_point,
            design_point_u=self.design_point_u, alpha=self.alpha, importance=self.importance,
            converged=self.converged, status=self.status, iterations=self.iterations,
            solves=self.solves, history=self.history, check=self.check,
            warnings=self.warnings, message=self.message(), options=self.options,
            timing=self.timing))

    def message(self) -> str:
        """One paragraph for a rock engineer."""
        n = self.solves
        cost = (f"{n['with_sensitivities']} solves with sensitivities and {n['plain']} plain"
                if not self.limit.ultimate else
                f"{n['plain']} trial solves in {n['batches']} batches")
        text = (f"FORM ({self.limit.describe()}): beta = {self.beta:.4g}, probability of "
                f"failure {self.probability:.4g}, {self.iterations} iterations ({cost}).")
        if self.importance:
            top = max(self.importance, key=self.importance.get)
            text += f" Most important: {top} ({100 * self.importance[top]:.0f}%)."
        if self.check is not None:
            c = self.check
            text += (f" Monte Carlo, {c['samples']:,} solves: {c['probability']:.4g} "
                     f"(95% interval {c['ci95'][0]:.4g} to {c['ci95'][1]:.4g}).")
            if c.get("small_mechanisms"):
                text += (f" {c['small_mechanisms']} of its {c['failures']} failures are small "
                         f"mechanisms (pieces working loose, no larger together than "
                         f"solver.max_loose_volume).")
        for w in self.warnings:
            text += f" WARNING: {w}"
        return text


@float64
def reliability(scene, vary: Sequence[Variable | str] | Mapping, limit: str | Limit, *,
                correlation=None, check=None, seed: int = 0, max_iterations: int = 30,
                tolerance: float = 1e-3, intact: bool = False, tensile: bool = False,
                step: float = 0.2, rtol: float = 2e-5, trials: int | None = None,
                chunk: int | None = None, progress: Callable[[dict], None] | None = None
                ) -> Reliability:
    """FORM reliability index of ``scene`` for a limit state (see the module).

    Args:
      scene: a validated scene (:func:`jaxdem.load_scene`).
      vary: the random variables: :class:`jaxdem.sweep.Variable` s or ``"PATH=DIST:ARGS"``
        strings (normal:MEAN:SD, lognormal:MEAN:SD, uniform:LOW:HIGH,
        truncnormal:MEAN:SD:LOW:HIGH), or {path: "DIST:ARGS"}.
      limit: ``"stable"`` or ``"MONITOR[.ux|.uy|.|u|] <= | >= VALUE"`` (m).
      correlation: None, a (p, p) matrix or {(path_a, path_b): rho}: the correlation of
        the variables' standard normals (see the module).
      check: None or ``"mc:N"`` (or N): also N Monte Carlo solves.
      seed: the Monte Carlo seed.
      max_iterations, tolerance: of the HL-RF iteration (:func:`hlrf`).
      intact, tensile: ``stable``: also reduce the intact rock's strength, the tensile
        strengths (as ``jaxdem fos``).
      step, rtol, trials: ``stable``: the central-difference step in standard normal
        space, the relative width of F's bracket, trial factors per point and round
        (default: as many as fill whole batched calls of :data:`ROWS` samples).
      chunk: samples per batch (:func:`jaxdem.batch.solve_batch`).
      progress: optional callable, called with each iteration's record.
    Returns:
      a :class:`Reliability`.
    Raises:
      SceneError: bad input, naming the field (a variable the model cannot vary, a
        monitor the scene lacks, a standard deviation <= 0).

    Example::

        r = jaxdem.reliability(scene, ["joints.set1.kn=lognormal:2e6:6e5"],
                               "crown.uy >= -0.015", check="mc:2000")
        r.beta, r.probability, r.importance, r.check["ci95"]
    """
    t0 = time.perf_counter()
    if isinstance(vary, (str, Variable)):
        vary = [vary]
    if isinstance(vary, Mapping):
        vary = [f"{k}={v}" for k, v in vary.items()]
    variables = [v if isinstance(v, Variable) else Variable.parse(v) for v in vary]
    check_variables(variables)
    limit = limit if isinstance(limit, Limit) else Limit.parse(limit, scene)
    R = correlation_matrix(variables, correlation)
    samples = parse_check(check)
    _check_options(max_iterations, tolerance, step, rtol, trials)
    median, _ = transform(variables, np.zeros(len(variables)))
    for v, x in zip(variables, median, strict=True):
        try:
            scene.with_overrides({v.path: float(x)})
        except SceneError as err:
            raise SceneError(f"--vary {v.path}", f"{err.problem} in the scene (a parameter "
                             "path such as joints.NAME.kn or bolts.0.stiffness, with a "
                             "median the scene accepts)") from None
    try:
        state = (FactorLimitState(scene, variables, intact=intact, tensile=tensile, step=step,
                                  rtol=rtol, trials=trials, chunk=chunk) if limit.ultimate else
                 MonitorLimitState(scene, variables, limit))
        L = np.linalg.cholesky(R)
        form = hlrf(lambda z: _in_z(state, L, z), len(variables),
                    max_iterations=max_iterations, tolerance=tolerance, progress=progress)
    except SceneError as err:
        if err.path in [v.path for v in variables]:
            raise SceneError(f"--vary {err.path}", err.problem) from None
        raise
    form_s = time.perf_counter() - t0
    paths = [v.path for v in variables]
    z = form["z"]
    y = L @ z
    x, dxdy = transform(variables, y)
    grad_y = np.linalg.solve(L.T, form["gradient"])   # dg/dz = L^T dg/dy
    norm = float(np.linalg.norm(grad_y))
    gamma = -grad_y / norm if norm > 0 else np.full(len(paths), np.nan)
    beta = form["beta"]
    warnings = _warnings(form, state, limit, tolerance, max_iterations)
    history = []
    for rec in form["history"]:
        xs, _ = transform(variables, L @ np.asarray(rec["z"]))
        history.append(dict(iteration=rec["iteration"], u=rec["z"],
                            x=dict(zip(paths, xs.tolist(), strict=True)), g=rec["g"],
                            gradient_norm=rec["gradient_norm"], beta=rec["beta"],
                            step=rec["step"]))
    result = Reliability(
        scene=scene.name, variables=variables, limit=limit,
        correlation=None if correlation is None else R, beta=beta,
        probability=_phi(-beta), design_point=dict(zip(paths, x.tolist(), strict=True)),
        design_point_u=dict(zip(paths, y.tolist(), strict=True)),
        alpha=dict(zip(paths, gamma.tolist(), strict=True)),
        importance=dict(zip(paths, (gamma ** 2).tolist(), strict=True)),
        status=form["status"], iterations=max(len(form["history"]) - 1, 0),
        solves=state.solves, history=history, check=None,
        warnings=warnings + list(dict.fromkeys(state.notes)),
        options=dict(max_iterations=max_iterations, tolerance=tolerance, intact=intact,
                     tensile=tensile, step=step, rtol=rtol, trials=trials,
                     check=check if check is None else f"mc:{samples}", seed=seed),
        timing=dict(form_s=form_s))
    if samples is not None:
        t1 = time.perf_counter()
        result.check = monte_carlo(scene, variables, limit, R, samples, seed=seed, chunk=chunk)
        c = result.check
        c["form_probability"] = result.probability
        c["form_solves"] = sum(result.solves[k] for k in ("plain", "with_sensitivities"))
        c["form_within_ci95"] = bool(c["ci95"][0] <= result.probability <= c["ci95"][1])
        c["samples_for_cov_10pct"] = (samples_for_cov(result.probability)
                                      if 0 < result.probability < 1 else None)
        if c["undecided"]:
            result.warnings.append(f"{c['undecided']} Monte Carlo samples found neither an "
                                   "equilibrium nor a mechanism; they are left out")
        result.timing["check_s"] = time.perf_counter() - t1
    result.timing["total_s"] = time.perf_counter() - t0
    return result


def _in_z(state, L, z):
    """g and dg/dz at z: y = L z, dg/dz = L^T dg/dy."""
    G, grad_y = state(L @ z)
    return G, L.T @ grad_y


def _phi(x: float) -> float:
    """Phi(x), the standard normal distribution function."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0)) if math.isfinite(x) else float("nan")


def _check_options(max_iterations, tolerance, step, rtol, trials) -> None:
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) \
            or max_iterations < 1:
        raise SceneError("max_iterations", f"must be a whole number >= 1 "
                         f"(got {max_iterations!r})")
    for name, value, hi in (("tolerance", tolerance, 0.5), ("step", step, 2.0),
                            ("rtol", rtol, 0.1)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 < value <= hi):
            raise SceneError(name, f"must be a number in (0, {hi:g}] (got {value!r})")
    if trials is not None and (isinstance(trials, bool) or
                               not isinstance(trials, (int, np.integer)) or trials < 2):
        raise SceneError("trials", f"must be a whole number >= 2 (got {trials!r})")


def _warnings(form, state, limit, tolerance, max_iterations) -> list[str]:
    status = form["status"]
    out = []
    if status == ITERATION_LIMIT:
        out.append(f"the HL-RF iteration did not converge in {max_iterations} iterations "
                   f"(tolerance {tolerance:g}): beta is that of the last point")
    elif status == LINE_SEARCH_FAILED:
        out.append("the HL-RF iteration stopped: no step along its direction decreased the "
                   "merit function (points without an answer, or a limit state that is not "
                   "smooth there): beta is that of the last point")
    elif status == LIMIT_NOT_REACHED:
        out.append("the limit state is not reached within beta <= 8 (probability below "
                   "6e-16), or not within the variables' bounds: the scene practically "
                   "never fails this way")
    elif status == NO_GRADIENT:
        out.append("g does not change with the variables at the last point (a bounded "
                   "distribution's end, or a limit the variables do not reach): the limit "
                   "state may not be reached within the variables' bounds")
    elif status == NO_ANSWER_AT_START:
        out.append("no value of g at the medians (" + ("no factor of safety within its "
                   "limits" if limit.ultimate else "no equilibrium: the scene as given "
                   "fails") + "): FORM cannot start")
    undecided = getattr(state, "undecided", 0)
    if undecided:
        out.append(f"{undecided} trial solves of the factor of safety found neither an "
                   "equilibrium nor a mechanism; they count as unstable (as in jaxdem fos)")
    return out


# ---------------------------------------------------------------------------
# Outputs


def write_outputs(result: Reliability, out_dir: str | Path) -> list[Path]:
    """Write ``reliability.json`` and ``reliability.png``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [write_json(result.to_dict(), out / "reliability.json"),
            plot_reliability(result, out / "reliability.png")]


def plot_reliability(result: Reliability, path: str | Path) -> Path:
    """The design point and the importance factors, and how the iteration went.

    Left: each variable's importance gamma_i^2 (red: a load, failure as it grows;
    blue: a resistance). Middle: the design point of each variable in standard
    deviations of its equivalent normal from the median, labelled with its value.
    Right: beta over the iterations (and the Monte Carlo estimate as -Phi^-1(P), if any).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from jaxdem.plots import save_figure

    paths = [v.path for v in result.variables]
    p = len(paths)
    fig = Figure(figsize=(13, 1.6 + 0.45 * max(p, 3)))
    FigureCanvasAgg(fig)
    ax_i, ax_d, ax_h = fig.subplots(1, 3, gridspec_kw=dict(width_ratios=[1, 1, 1]))
    rows = np.arange(p)[::-1]
    share = np.array([result.importance[q] for q in paths])
    sign = np.array([result.alpha[q] for q in paths])
    colours = ["tab:red" if s > 0 else "tab:blue" for s in sign]
    ax_i.barh(rows, 100 * np.nan_to_num(share), color=colours, height=0.6)
    for r, s in zip(rows, share, strict=True):
        if np.isfinite(s):
            ax_i.text(100 * s, r, f" {100 * s:.1f}%", va="center", fontsize=8)
    ax_i.set_yticks(rows)
    ax_i.set_yticklabels(paths, fontsize=8)
    ax_i.set_xlim(0, 115)
    ax_i.set_xlabel("importance factor (%): red a load, blue a resistance")
    u = np.array([result.design_point_u[q] for q in paths])
    ax_d.axvline(0.0, color="k", lw=1)
    ax_d.barh(rows, np.nan_to_num(u), color="0.6", height=0.6)
    for ax in (ax_i, ax_d):
        ax.set_ylim(-0.8, max(p, 2) - 0.2)
    for r, v, ui in zip(rows, result.variables, u, strict=True):
        # The label on the other side of the zero line, where the bar leaves room.
        median = float(transform([v], np.zeros(1))[0][0])
        ax_d.text(0.0, r, f" {result.design_point[v.path]:.4g} (median {median:.4g}) ",
                  va="center", ha="right" if ui >= 0 else "left", fontsize=8)
    lim = max(3.0, 1.2 * float(np.nanmax(np.abs(u))) if np.any(np.isfinite(u)) else 3.0)
    ax_d.set_xlim(-lim, lim)
    ax_d.set_yticks(rows)
    ax_d.set_yticklabels([])
    ax_d.set_xlabel("design point: standard deviations from the median (u)")
    it = [h["iteration"] for h in result.history]
    ax_h.plot(it, [h["beta"] for h in result.history], "o-", color="tab:purple",
              label="beta at each iteration (alpha . u)")
    ax_h.set_xlabel("iteration")
    ax_h.set_ylabel("beta")
    c = result.check
    if c is not None and c["decided"] and 0 < c["probability"] < 1:
        from scipy.special import ndtri

        b = -float(ndtri(c["probability"]))
        lo, hi = (-float(ndtri(q)) if 0 < q < 1 else b for q in c["ci95"][::-1])
        ax_h.axhspan(lo, hi, color="tab:green", alpha=0.2,
                     label=f"Monte Carlo, {c['samples']:,} solves: -Phi^-1(P), 95%")
        ax_h.axhline(b, color="tab:green", lw=1)
    ax_h.set_xticks(it)
    ax_h.legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{result.scene}: {result.limit.describe()}\nbeta = {result.beta:.4g}, "
                 f"P_f = {result.probability:.3g} ({result.status}, {result.iterations} "
                 f"iterations)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


__all__ = ["COMPONENTS", "DISTRIBUTIONS", "FactorLimitState", "Limit", "MonitorLimitState",
           "Reliability", "check_variables", "correlation_matrix", "hlrf", "monte_carlo",
           "parse_check", "plot_reliability", "reliability", "samples_for_cov", "transform",
           "write_outputs"]
