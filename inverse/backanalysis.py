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

Host code: NumPy and Python around the jitted forward model and its Jacobian.
"""

from __future__ import annotations

import csv
import io
import math
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxdem.scene import Scene, SceneError, apply_overrides

__all__ = ["BackAnalysis", "Observation", "back_analyse", "read_observations"]

DEFAULT_RELATIVE_STD = 0.05
"""Standard deviation of an observation given without one: 5 % of |value| ..."""
DEFAULT_STD_FLOOR = 1.0e-4
"""... but at least 0.1 mm (m): the resolution of a convergence tape, and what keeps a
zero reading (the horizontal displacement of a symmetric crown) from weighing infinitely."""

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

RELATIVE_SENSITIVITY_MIN = 1.0e-6
"""A parameter is insensitive (not identifiable) when the norm of its dimensionless
sensitivity column theta_j / std_i dy_i/dtheta_j is below this fraction of the largest."""
SINGULAR_RATIO = 1.0e-4
"""A direction of the normalised sensitivity matrix whose singular value is below this
fraction of the largest is undetermined (information-matrix eigenvalue ratio 1e-8): the
observations change by less than 1e-4 of what single parameters change them by."""
PARTICIPATION_MIN = 1.0e-4
"""A parameter takes part in an undetermined direction when its component in that unit
vector exceeds this (far above the ~1e-9 noise of eigenvectors of accurate Jacobians)."""
CORRELATION_MAX = 0.99
"""Two parameters whose estimates correlate with |r| above this are reported as not
identifiable: the data fix a combination of them, not each one."""
AT_BOUND = 1.0e-3
"""An estimate within this fraction of its (log-)range from a bound is reported as at it."""
START_INSIDE = 1.0e-2
"""A starting value on a bound starts this fraction of the (log-)range inside it, where
sigmoid(z) still has a usable slope (0.0099)."""

CACHE_SIZE = 8
"""Forward evaluations (values and Jacobians) remembered by theta: the line search asks
again for points it has seen, and the final analysis asks for the accepted one."""

COMPONENTS = ("ux", "uy")
"""Components of a point monitor's displacement [ux, uy] (m) that can be observed."""
OPTIMIZERS = ("gauss-newton", "lbfgs", "adam")

# Statuses of a fit; ``BackAnalysis.converged`` is True for the first only.
CONVERGED = "converged"
MAX_ITERATIONS = "max_iterations"
LINE_SEARCH_FAILED = "line_search_failed"
NO_EQUILIBRIUM_AT_START = "no_equilibrium_at_start"


# --------------------------------------------------------------------------- observations


@dataclass(frozen=True)
class Observation:
    """One measured monitor value.

    Attributes:
      monitor: name of a ``[[monitors]]`` entry of the scene.
      value: the measurement, m: the convergence of a section (positive when it
        shortens) or one displacement component of a point.
      std: its standard deviation, m (> 0). None: ``DEFAULT_RELATIVE_STD`` (5 %) of
        |value|, at least ``DEFAULT_STD_FLOOR`` (0.1 mm).
      stage: the stage at whose end it was measured; None: the last stage.
      component: "ux" or "uy" for a point monitor (required there); None for a section.
      source: where it was read (``"obs.csv, row 3"``), named in error messages.

    Example::

        Observation("crown", -0.0081, std=0.0005, component="uy", stage="excavate")
    """

    monitor: str
    value: float
    std: float | None = None
    stage: str | None = None
    component: str | None = None
    source: str | None = field(default=None, compare=False)

    def label(self) -> str:
        """Short name for tables and figures: ``crown uy @ excavate``."""
        text = self.monitor
        if self.component:
            text += f" {self.component}"
        if self.stage:
            text += f" @ {self.stage}"
        return text


def default_std(value: float) -> float:
    """The standard deviation given to an observation without one (m): 5 % of |value|,
    at least 0.1 mm."""
    return max(DEFAULT_RELATIVE_STD * abs(float(value)), DEFAULT_STD_FLOOR)


CSV_COLUMNS = ("monitor", "value", "std", "stage", "component")
CSV_REQUIRED = ("monitor", "value")


def read_observations(path: str | Path) -> list[Observation]:
    """Read observations from a CSV file with a header row.

    Columns: ``monitor`` and ``value`` (m) are required; ``std`` (m; blank: the
    default, see :func:`default_std`), ``stage`` (blank: the last stage) and
    ``component`` (``ux`` or ``uy``, for point monitors) are optional. Column
    names are case-insensitive; blank rows are skipped. Rows are numbered as
    the file's lines (the header is row 1).

    Args:
      path: the CSV file.

    Returns:
      the observations, in file order, each with ``source`` = ``"FILE, row N"``.

    Raises:
      SceneError: unreadable or empty file, unknown or missing column, a value
        that is not a finite number, a std that is not > 0, an unknown component;
        the message names the file, row and column.

    Example::

        # obs.csv:
        #   monitor,value,std,component,stage
        #   section 1-1,0.0123,0.0005,,
        #   crown,-0.0081,0.0005,uy,excavate
        observations = read_observations("obs.csv")
    """
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")  # -sig: a BOM written by Excel
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(name, f"cannot read the observations file ({_reason(exc)})") from None
    reader = csv.reader(io.StringIO(text))
    header: list[str] | None = None
    out: list[Observation] = []
    try:
        for row in reader:
            if not any(cell.strip() for cell in row):
                continue
            if header is None:
                header = _csv_header(row, name)
                continue
            out.append(_csv_row(row, header, f"{name}, row {reader.line_num}"))
    except csv.Error as exc:
        raise SceneError(f"{name}, row {reader.line_num}", f"not valid CSV ({exc})") from None
    if header is None:
        raise SceneError(name, "empty file: expected a header (monitor,value,std) and one row "
                               "per observation")
    if not out:
        raise SceneError(name, "no observations: the file has a header but no rows")
    return out


def _reason(exc: Exception) -> str:
    return getattr(exc, "strerror", None) or str(exc)


def _csv_header(row: list[str], name: str) -> list[str]:
    header = [cell.strip().lower() for cell in row]
    where = f"{name}, row 1 (header)"
    for column in header:
        if column not in CSV_COLUMNS:
            raise SceneError(where, f"unknown column {column!r}; allowed: {', '.join(CSV_COLUMNS)}")
        if header.count(column) > 1:
            raise SceneError(where, f"column {column!r} appears twice")
    for column in CSV_REQUIRED:
        if column not in header:
            raise SceneError(where, f"missing column {column!r} (columns: monitor,value,std, "
                                    "optionally stage and component)")
    return header


def _csv_row(row: list[str], header: list[str], where: str) -> Observation:
    if len(row) > len(header):
        raise SceneError(where, f"{len(row)} cells but the header has {len(header)} columns")
    cells = {column: (row[k].strip() if k < len(row) else "") for k, column in enumerate(header)}
    monitor = cells["monitor"]
    if not monitor:
        raise SceneError(f"{where}, monitor", "empty: name a [[monitors]] entry")
    value = _csv_number(cells["value"], f"{where}, value")
    std = None
    if cells.get("std"):
        std = _csv_number(cells["std"], f"{where}, std")
        if std <= 0.0:
            raise SceneError(f"{where}, std", f"must be > 0 (got {cells['std']}); leave it blank "
                                              "for the default")
    component = cells.get("component", "").lower() or None
    if component is not None and component not in COMPONENTS:
        raise SceneError(f"{where}, component",
                         f"must be ux or uy, or blank for a section (got {cells['component']!r})")
    stage = cells.get("stage") or None
    return Observation(monitor, value, std, stage=stage, component=component, source=where)


def _csv_number(text: str, where: str) -> float:
    if not text:
        raise SceneError(where, "empty: a number is required")
    try:
        value = float(text)
    except ValueError:
        raise SceneError(where, f"must be a number (got {text!r})") from None
    if not math.isfinite(value):
        raise SceneError(where, f"must be finite (got {text!r})")
    return value


def _as_observations(observed: Any) -> list[Observation]:
    """``observed`` (dict or sequence of Observation) -> list of Observation."""
    if isinstance(observed, Mapping):
        out = []
        for monitor, entry in observed.items():
            where = f"observed[{monitor!r}]"
            if isinstance(entry, (tuple, list)):
                if len(entry) != 2:
                    raise SceneError(where, f"expected a value or (value, std) (got {entry!r})")
                value, std = entry
            else:
                value, std = entry, None
            out.append(Observation(monitor, value, std, source=where))
        return out
    if isinstance(observed, (str, bytes)) or not isinstance(observed, Sequence):
        raise SceneError("observed", "expected {monitor: value}, {monitor: (value, std)} or a "
                                     f"list of Observation (got {type(observed).__name__})")
    for i, item in enumerate(observed):
        if not isinstance(item, Observation):
            raise SceneError(f"observed.{i}", f"expected an Observation (got {item!r})")
    return list(observed)


def _where(obs: Observation, i: int, name: str) -> str:
    """Field path of ``name`` of observation ``i`` for messages."""
    return f"{obs.source}, {name}" if obs.source else f"observed.{i}.{name}"


def _checked_observations(observations: list[Observation],
                          scene: Scene | None) -> list[Observation]:
    """Validate against the scene (monitors, kinds, stages) and fill in default stds."""
    if not observations:
        raise SceneError("observed", "no observations given")
    monitors = {m.name: m.kind for m in scene.monitors} if scene is not None else None
    stage_names = [s.name for s in scene.stages] if scene is not None else None
    out = []
    for i, obs in enumerate(observations):
        if not isinstance(obs.monitor, str) or not obs.monitor:
            raise SceneError(_where(obs, i, "monitor"), "must be a monitor name")
        value = _finite(obs.value, _where(obs, i, "value"))
        std = obs.std
        if std is None:
            std = default_std(value)
        else:
            std = _finite(std, _where(obs, i, "std"))
            if std <= 0.0:
                raise SceneError(_where(obs, i, "std"), f"must be > 0 (got {std:g})")
        if obs.component is not None and obs.component not in COMPONENTS:
            raise SceneError(_where(obs, i, "component"),
                             f"must be ux or uy, or None for a section (got {obs.component!r})")
        if monitors is not None:
            _check_monitor(obs, i, monitors)
        if obs.stage is not None and stage_names is not None and obs.stage not in stage_names:
            known = ", ".join(stage_names) if stage_names else "none ([[stages]] name = ...)"
            raise SceneError(_where(obs, i, "stage"),
                             f"no stage named {obs.stage!r} in the scene (stages: {known})")
        out.append(replace(obs, value=value, std=std))
    return out


def _check_monitor(obs: Observation, i: int, monitors: dict[str, str]) -> None:
    kind = monitors.get(obs.monitor)
    if kind is None:
        known = ", ".join(monitors) if monitors else "none ([[monitors]] name = ...)"
        raise SceneError(_where(obs, i, "monitor"),
                         f"no monitor named {obs.monitor!r} in the scene (monitors: {known})")
    if kind == "point" and obs.component is None:
        raise SceneError(_where(obs, i, "component"),
                         f"{obs.monitor!r} is a point monitor: say which displacement was "
                         "measured, ux or uy")
    if kind == "section" and obs.component is not None:
        raise SceneError(_where(obs, i, "component"),
                         f"{obs.monitor!r} is a section (one convergence): leave component blank")


def _finite(value: Any, where: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise SceneError(where, f"must be a number (got {value!r})") from None
    if not math.isfinite(x):
        raise SceneError(where, f"must be finite (got {value!r})")
    return x


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class _Transform:
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


def _check_fit(fit: Any, scene: Scene | None) -> list[str]:
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


def _check_bounds(bounds: Mapping | None, paths: list[str]) -> dict[str, tuple[float, float]]:
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
        lo, hi = _finite(entry[0], where), _finite(entry[1], where)
        if not lo < hi:
            raise SceneError(where, f"lo must be < hi (got {lo:g}, {hi:g})")
        out[path] = (lo, hi)
    return out


def _transform(paths: list[str], theta0: np.ndarray,
               bounds: dict[str, tuple[float, float]]) -> _Transform:
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
    return _Transform(lo=lo, hi=hi, log=(lo > 0.0) & (hi > 0.0))


def _start(theta0: np.ndarray, transform: _Transform) -> np.ndarray:
    """z of the starting values; one on a bound (a cohesion starting at its lower bound 0)
    starts START_INSIDE of the range inside it, where sigmoid(z) still has a slope."""
    a, b = transform._ends
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(transform.log, np.log(np.abs(theta0)), theta0)
    u = np.clip((t - a) / (b - a), START_INSIDE, 1.0 - START_INSIDE)
    return np.log(u) - np.log1p(-u)


def _scales(theta: np.ndarray, transform: _Transform) -> np.ndarray:
    """Scale of each parameter for dimensionless sensitivities: |theta|, or the width of
    its bounds where theta = 0."""
    width = transform.hi - transform.lo
    return np.where(np.abs(theta) > 0.0, np.abs(theta), width)


# --------------------------------------------------------------------------- objective


class _Objective:
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

    def __init__(self, model: Callable, transform: _Transform, observed: np.ndarray,
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
        # The optimiser loop runs under jax.disable_jit (see _run_lbfgs); the model is
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
        elif not _finite_entry(entry):
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
        if not _finite_entry((y, jac)):
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


def _finite_entry(entry: tuple[np.ndarray, Any]) -> bool:
    y, jac = entry
    return bool(np.all(np.isfinite(y)) and (jac is None or np.all(np.isfinite(jac))))


def _observed_model(f: Callable, observations: list[Observation], stages: list[str] | None,
                    last_stage: str | None) -> Callable:
    """theta -> the model value of each observation, shape (n,), from ``f``'s dict."""

    def model(theta):
        out = f(theta)
        values = []
        for i, obs in enumerate(observations):
            block = out
            if stages is not None:
                stage = obs.stage or last_stage
                if stage not in out:
                    raise SceneError(_where(obs, i, "stage"),
                                     f"the model gives no values for stage {stage!r}")
                block = out[stage]
            if obs.monitor not in block:
                raise SceneError(_where(obs, i, "monitor"),
                                 f"the model gives no monitor named {obs.monitor!r}")
            values.append(_component(jnp.asarray(block[obs.monitor]), obs, i))
        return jnp.stack(values)

    return model


def _component(value: jax.Array, obs: Observation, i: int) -> jax.Array:
    if value.shape == (2,):  # a point monitor: [ux, uy]
        if obs.component is None:
            raise SceneError(_where(obs, i, "component"),
                             f"{obs.monitor!r} is a point monitor: say which displacement was "
                             "measured, ux or uy")
        return value[COMPONENTS.index(obs.component)]
    if value.shape == ():  # a section: its convergence
        if obs.component is not None:
            raise SceneError(_where(obs, i, "component"),
                             f"{obs.monitor!r} is a section (one convergence): leave component "
                             "blank")
        return value
    raise SceneError(_where(obs, i, "monitor"),
                     f"the model gives {obs.monitor!r} with shape {value.shape}; expected (2,) "
                     "for a point or () for a section")


def _resolve_stages(observations: list[Observation], scene: Scene | None,
                    stages: Sequence[str] | None) -> tuple[list[str] | None, str | None]:
    """The stages to ask the model for (None: only the end of the analysis) and the name
    of the last stage, which observations without a stage belong to."""
    scene_stages = [s.name for s in scene.stages] if scene is not None else []
    named = [obs.stage for obs in observations if obs.stage is not None]
    if stages is None and not named:
        return None, None
    if scene is not None and named and not scene_stages:
        i = next(i for i, obs in enumerate(observations) if obs.stage is not None)
        raise SceneError(_where(observations[i], i, "stage"),
                         "the scene has no [[stages]]: leave the stage out (the end of the "
                         "analysis)")
    if stages is not None:
        stages = [str(s) for s in stages]
        last = scene_stages[-1] if scene_stages else (stages[-1] if stages else None)
        for i, obs in enumerate(observations):
            if (obs.stage or last) not in stages:
                raise SceneError(_where(obs, i, "stage"),
                                 f"stage {obs.stage or last!r} is not among stages= {stages}")
        return stages, last
    if not scene_stages:
        raise SceneError("stages", "observations name stages: pass the scene, or stages=[...] "
                                   "in the order the model reports them")
    last = scene_stages[-1]
    wanted = set(named) | ({last} if any(obs.stage is None for obs in observations) else set())
    return [s for s in scene_stages if s in wanted], last


# --------------------------------------------------------------------------- optimisers


@dataclass
class _Run:
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


def _run_lbfgs(objective: _Objective, z0: np.ndarray, max_iterations: int, tolerance: float,
               report: Callable) -> _Run:
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
            return _Run(np.asarray(z), history, 0, NO_EQUILIBRIUM_AT_START, _NO_START)
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
    return _Run(np.asarray(best_z), history, k, status, message)


def _run_adam(objective: _Objective, z0: np.ndarray, max_iterations: int, tolerance: float,
              learning_rate: float, report: Callable) -> _Run:
    """optax Adam on the host gradient; returns the best point seen (Adam's misfit is
    not monotone). A point without equilibrium sends it back to the best point with
    half the learning rate."""
    z = np.asarray(z0, dtype=np.float64)
    value, grad = objective.misfit_and_grad(z)
    history = [value]
    report(0, z, value, grad)
    if not math.isfinite(value):
        return _Run(z, history, 0, NO_EQUILIBRIUM_AT_START, _NO_START)
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
    return _Run(best_z, history, k, status, message)


LM_DAMPING = 1.0e-3
"""Starting Levenberg-Marquardt damping (relative to the diagonal of J^T J); divided by
3 after a step that lowers the misfit, multiplied by 10 after one that does not."""
LM_MAX_STEP = 0.125
"""Largest Levenberg-Marquardt step of one parameter, as a fraction of its (log-)range (a
factor 3.2 within the default bounds): a trust region, so that a step from far away
cannot jump from bound to bound, nor try a point where the model is a mechanism (whose
solve may take many times as long)."""
U_EDGE = 1.0e-15
"""A Gauss-Newton estimate on a bound is handed back as z = logit(U_EDGE) (or of 1 - U_EDGE)."""


def _run_gauss_newton(objective: _Objective, z0: np.ndarray, max_iterations: int,
                      tolerance: float, report: Callable) -> _Run:
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
    raised. Not optax: the least-squares structure is what makes it converge in a
    handful of solves.
    """
    tr = objective.transform
    a, b = tr._ends

    def theta_of(u):
        t = a + (b - a) * u
        return np.clip(np.where(tr.log, np.exp(t), t), tr.lo, tr.hi)

    def weighted(u):
        theta = theta_of(u)
        y, jac = objective.evaluate(theta, derivatives=True)
        if not _finite_entry((y, jac)):
            return None, None
        r = (y - objective.observed) / objective.std
        dtheta_du = (b - a) * np.where(tr.log, theta, 1.0)
        return r, (jac / objective.std[:, None]) * dtheta_du

    def z_of(u):
        u = np.clip(u, U_EDGE, 1.0 - U_EDGE)
        return np.log(u) - np.log1p(-u)

    def held(u, g):
        """Parameters on a bound that the gradient pushes further out."""
        return ((u <= 0.0) & (g > 0.0)) | ((u >= 1.0) & (g < 0.0))

    def projected(u, g):
        return np.where(held(u, g), 0.0, g)

    u = tr.fraction(np.asarray(z0, dtype=np.float64))
    r, Ju = weighted(u)
    if r is None:
        report(0, z_of(u), math.inf, np.zeros_like(u))
        return _Run(z_of(u), [math.inf], 0, NO_EQUILIBRIUM_AT_START, _NO_START)
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
                return _Run(z_of(u), history, k - 1, LINE_SEARCH_FAILED, _STUCK)
            r_new, J_new = weighted(u_new)
            if r_new is not None and 0.5 * float(r_new @ r_new) < value:
                break
            damping *= 10.0
            if damping > 1e12:
                return _Run(z_of(u), history, k - 1, LINE_SEARCH_FAILED, _STUCK)
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
    return _Run(z_of(u), history, k, status, message)


_NO_START = ("the model has no equilibrium at the starting parameters (the forward solve "
             "returned NaN): start from values at which `jaxdem run` converges")
_STUCK = ("the line search found no step that lowers the misfit (every trial point was worse "
          "or had no equilibrium); the estimate is the best point found")


def _limit_message(max_iterations: int) -> str:
    return (f"stopped at the iteration limit ({max_iterations}) before the misfit settled; "
            "a larger max_iterations may lower it further")


# --------------------------------------------------------------------------- result


@dataclass
class BackAnalysis:
    """The outcome of :func:`back_analyse`. Parameters are in file units (kn, ks in
    kPa/m, friction in degrees, ...), observations and model values in m.

    Attributes:
      paths: the fitted parameters' dotted paths, in the order of every array here.
      params: {path: estimate}.
      std: {path: Gauss-Newton standard deviation}; inf where not identifiable.
      identifiable: {path: bool}.
      correlation: (p, p) correlation of the estimates; NaN off the diagonal for a
        parameter that no observation is sensitive to.
      start, bounds: starting values {path: theta0} and {path: (lo, hi)}.
      observations: the observations used (defaults filled in for std).
      fitted: (n,) model value of each observation at the estimate, m.
      sensitivity: at the estimate, ``"jacobian"`` (n, p) dy_i/dtheta_j (m per
        parameter unit) and ``"dimensionless"`` (n, p) s_j / std_i dy_i/dtheta_j with
        s_j = |theta_j| (the width of the bounds where theta_j = 0): how many standard
        deviations observation i moves for a 100 % change of parameter j, to first order.
      misfit: 1/2 sum ((fitted - observed) / std)^2 at the estimate.
      history: misfit at the start and after each iteration (inf where Adam stepped
        onto a point without equilibrium).
      iterations: iterations done.
      evaluations: solves made: ``forward`` (values only), ``gradient`` (values and
        Jacobian from one jacfwd solve), ``no_equilibrium`` (of those, how many gave NaN
        values, or raised) and ``no_derivative`` (finite values, NaN derivatives).
      converged: True when the stopping rule was met.
      status: "converged", "max_iterations", "line_search_failed" or
        "no_equilibrium_at_start".
      message: what happened, in words.
      warnings: sentences about identifiability, bounds and the quality of the fit.
      optimizer: "gauss-newton", "lbfgs" or "adam".
    """

    paths: list[str]
    params: dict[str, float]
    std: dict[str, float]
    identifiable: dict[str, bool]
    correlation: np.ndarray
    start: dict[str, float]
    bounds: dict[str, tuple[float, float]]
    observations: list[Observation]
    fitted: np.ndarray
    sensitivity: dict[str, np.ndarray]
    misfit: float
    history: list[float]
    iterations: int
    evaluations: dict[str, int]
    converged: bool
    status: str
    message: str
    warnings: list[str]
    optimizer: str

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict (what ``back_analysis.json`` holds): NaN and inf are
        written as null.

        Example::

            json.dumps(result.to_dict(), allow_nan=False)
        """
        rows = []
        for obs, y in zip(self.observations, self.fitted, strict=True):
            rows.append({
                "monitor": obs.monitor,
                "component": obs.component,
                "stage": obs.stage,
                "observed": _json(obs.value),
                "std": _json(obs.std),
                "fitted": _json(y),
                "residual": _json(y - obs.value),
                "normalized_residual": _json((y - obs.value) / obs.std),
            })
        return {
            "paths": list(self.paths),
            "params": {p: _json(v) for p, v in self.params.items()},
            "std": {p: _json(v) for p, v in self.std.items()},
            "identifiable": dict(self.identifiable),
            "correlation": _json(self.correlation),
            "start": {p: _json(v) for p, v in self.start.items()},
            "bounds": {p: [_json(lo), _json(hi)] for p, (lo, hi) in self.bounds.items()},
            "observations": rows,
            "sensitivity": {key: _json(value) for key, value in self.sensitivity.items()},
            "misfit": _json(self.misfit),
            "history": _json(self.history),
            "iterations": self.iterations,
            "evaluations": dict(self.evaluations),
            "converged": self.converged,
            "status": self.status,
            "message": self.message,
            "warnings": list(self.warnings),
            "optimizer": self.optimizer,
        }


def _json(x: Any) -> Any:
    """Floats, or nested lists of them, with non-finite values as None."""
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_json(v) for v in x]
    x = float(x)
    return x if math.isfinite(x) else None


# --------------------------------------------------------------------------- public entry


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
      max_iterations: most optimiser iterations (0: analyse the starting point).
      tolerance: of the stopping rule above.
      learning_rate: Adam's step in z-space (``ADAM_LEARNING_RATE``); unused by L-BFGS.
      stages: the stage names the model reports (``jaxdem.differentiable``'s
        ``stages``); None: the stages the observations name, plus the last one if
        some observation names none; no stages at all when none does.
      forward: ``(f, theta0)`` to use instead of ``jaxdem.differentiable(scene, fit,
        stages=...)``; ``f`` must follow its contract (dict of monitors, or of stages
        of monitors when ``stages`` is not None).
      progress: called at the start and after each iteration with a dict:
        ``iteration``, ``misfit``, ``params`` ({path: value}), ``gradient_norm``
        (in z-space), ``evaluations``.

    Returns:
      a :class:`BackAnalysis`; its ``status`` says whether the fit converged, and is
      ``"no_equilibrium_at_start"`` when the model has none at theta0.

    Raises:
      SceneError: an unknown monitor, stage or parameter path, a point observation
        without component, bad bounds or std; the message names the field.
      ValueError: an unknown optimizer, max_iterations < 0, tolerance <= 0, or a
        ``theta0`` whose length is not that of ``fit``.

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
    if not tolerance > 0.0:
        raise ValueError(f"tolerance must be > 0 (got {tolerance!r})")
    if scene is None and forward is None:
        raise ValueError("give the scene, or forward=(f, theta0)")

    paths = _check_fit(fit, scene)
    bounds = _check_bounds(bounds, paths)
    observations = _checked_observations(_as_observations(observed), scene)
    stage_list, last_stage = _resolve_stages(observations, scene, stages)
    if forward is None:
        import jaxdem

        forward = jaxdem.differentiable(scene, params=paths, stages=stage_list)
    f, theta0 = forward
    theta0 = np.asarray(theta0, dtype=np.float64).reshape(-1)
    if theta0.shape != (len(paths),):
        raise ValueError(f"theta0 has {theta0.size} values for {len(paths)} fitted parameters")
    transform = _transform(paths, theta0, bounds)

    observed_values = np.array([obs.value for obs in observations])
    std = np.array([obs.std for obs in observations])
    model = _observed_model(f, observations, stage_list, last_stage)
    objective = _Objective(model, transform, observed_values, std)

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
        })

    z0 = _start(theta0, transform)
    if optimizer == "lbfgs":
        run = _run_lbfgs(objective, z0, int(max_iterations), tolerance, report)
    elif optimizer == "gauss-newton":
        run = _run_gauss_newton(objective, z0, int(max_iterations), tolerance, report)
    else:
        run = _run_adam(objective, z0, int(max_iterations), tolerance, learning_rate, report)
    return _analyse(run, theta0, objective, transform, paths, observations, optimizer)


# --------------------------------------------------------------------------- analysis


def _analyse(run: _Run, theta0: np.ndarray, objective: _Objective, transform: _Transform,
             paths: list[str], observations: list[Observation], optimizer: str) -> BackAnalysis:
    theta = transform.theta(run.z)
    y, jac = objective.evaluate(theta, derivatives=True)
    r = (y - objective.observed) / objective.std
    misfit = 0.5 * float(r @ r)
    warnings: list[str] = []
    if run.status == NO_EQUILIBRIUM_AT_START or not _finite_entry((y, jac)):
        if run.status != NO_EQUILIBRIUM_AT_START:
            warnings.append("the model's values or derivatives at the estimate are not finite: "
                            "no standard deviations")
        p = len(paths)
        stds, identifiable = np.full(p, np.inf), np.zeros(p, dtype=bool)
        correlation = np.where(np.eye(p, dtype=bool), 1.0, np.nan)
        scaled = np.full_like(jac, np.nan)
    else:
        scale = _scales(theta, transform)
        scaled = jac / objective.std[:, None] * scale[None, :]
        stds, identifiable, correlation = _gauss_newton(scaled, scale, paths, warnings)
        warnings += _bound_warnings(run.z, theta, transform, paths)
        warnings += _precision_warnings(theta, stds, identifiable, paths)
        warnings += _fit_warnings(misfit, len(observations), len(paths))
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
    )


def _gauss_newton(scaled: np.ndarray, scale: np.ndarray, paths: list[str],
                  warnings: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Standard deviations, identifiability and correlations from the dimensionless
    sensitivity matrix S (n, p), S_ij = s_j / std_i dy_i/dtheta_j.

    In the scaled coordinates q = theta / s the information matrix is S^T S. Columns
    are normalised (N = S / |S_j|) so that one SVD, N = U Sigma V^T, reads the same
    whatever the parameters' units; directions with a small singular value are not
    determined, and so is every parameter that takes part in one. The covariance of
    the rest sums over the determined directions only.
    """
    p = scaled.shape[1]
    column = np.linalg.norm(scaled, axis=0)
    largest = float(column.max())
    sensitive = column > RELATIVE_SENSITIVITY_MIN * largest  # none when every column is 0
    for j in np.flatnonzero(~sensitive):
        relative = column[j] / largest if largest > 0.0 else 0.0
        warnings.append(f"{paths[j]} is not identifiable from the observations: no monitor is "
                        f"sensitive to it (relative sensitivity {relative:.1e})")

    idx = np.flatnonzero(sensitive)
    identifiable = sensitive.copy()
    stds = np.full(p, np.inf)
    correlation = np.where(np.eye(p, dtype=bool), 1.0, np.nan)
    if idx.size == 0:
        return stds, identifiable, correlation

    normalised = scaled[:, idx] / column[idx]
    _, sigma, vt = np.linalg.svd(normalised, full_matrices=True)
    sigma = np.concatenate([sigma, np.zeros(idx.size - sigma.size)])  # fewer rows than columns
    determined = sigma > SINGULAR_RATIO * sigma[0]
    # Correlations from an inverse whose undetermined directions get a tiny eigenvalue:
    # they dominate, so an exact trade-off reads as r = +-1 with its true sign.
    floor = (1e-2 * SINGULAR_RATIO * sigma[0]) ** 2
    full = (vt.T / np.maximum(sigma**2, floor)) @ vt
    d = np.sqrt(np.diag(full))
    correlation[np.ix_(idx, idx)] = full / np.outer(d, d)

    in_null = np.any(np.abs(vt[~determined]) > PARTICIPATION_MIN, axis=0)  # per sensitive
    if in_null.any():
        identifiable[idx[in_null]] = False
        warnings.append(_tradeoff_sentence(idx[in_null], correlation, paths))

    # Covariance in q over the determined directions, back to theta units; among the
    # parameters outside every undetermined direction it is their full covariance.
    cov_n = (vt[determined].T / sigma[determined] ** 2) @ vt[determined]
    stds[idx] = np.sqrt(np.diag(cov_n)) * scale[idx] / column[idx]
    kept = np.flatnonzero(~in_null)
    d = np.sqrt(np.diag(cov_n)[kept])
    correlation[np.ix_(idx[kept], idx[kept])] = cov_n[np.ix_(kept, kept)] / np.outer(d, d)

    for a_pos, a in enumerate(idx[kept]):
        for b in idx[kept][a_pos + 1:]:
            r = correlation[a, b]
            if abs(r) > CORRELATION_MAX:
                identifiable[[a, b]] = False
                warnings.append(_pair_sentence(paths[a], paths[b], r))
    stds[~identifiable] = np.inf
    return stds, identifiable, correlation


def _pair_sentence(a: str, b: str, r: float) -> str:
    return (f"{a} and {b} are nearly perfectly correlated (r = {r:.4f}): only their combination "
            "is determined")


def _tradeoff_sentence(members: np.ndarray, correlation: np.ndarray, paths: list[str]) -> str:
    if members.size == 2:
        a, b = members
        return _pair_sentence(paths[a], paths[b], correlation[a, b])
    names = [paths[j] for j in members]
    return (f"{', '.join(names[:-1])} and {names[-1]} are not identifiable one by one: the "
            "observations change the same way whichever of them changes, so only a "
            "combination of them is determined")


def _bound_warnings(z: np.ndarray, theta: np.ndarray, transform: _Transform,
                    paths: list[str]) -> list[str]:
    out = []
    u = transform.fraction(z)
    for j, path in enumerate(paths):
        if u[j] < AT_BOUND or u[j] > 1.0 - AT_BOUND:
            side, bound = ("lower", transform.lo[j]) if u[j] < 0.5 else ("upper", transform.hi[j])
            out.append(f"{path} ended at its {side} bound ({theta[j]:.4g}, bound {bound:.4g}): "
                       "the observations pull it further; widen the bounds or check the model")
    return out


def _precision_warnings(theta: np.ndarray, stds: np.ndarray, identifiable: np.ndarray,
                        paths: list[str]) -> list[str]:
    out = []
    for j, path in enumerate(paths):
        if identifiable[j] and theta[j] != 0.0 and stds[j] > abs(theta[j]):
            out.append(f"{path} is poorly determined: its standard deviation ({stds[j]:.3g}) "
                       f"exceeds the estimate ({theta[j]:.3g})")
    return out


def _fit_warnings(misfit: float, n: int, p: int) -> list[str]:
    """A misfit beyond the 99th percentile of chi^2 / 2 with n - p degrees of freedom."""
    dof = n - p
    if dof <= 0 or not math.isfinite(misfit):
        return []
    from scipy.stats import chi2

    if 2.0 * misfit <= chi2.ppf(0.99, dof):
        return []
    return [f"the model does not fit the observations within their standard deviations "
            f"(misfit {misfit:.4g}; about {dof / 2:.3g} expected for {n} observations and {p} "
            "parameters): the stds may be too small, or the model misses a mechanism"]
