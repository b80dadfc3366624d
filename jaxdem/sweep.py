"""Parameter sweeps: grid, Latin hypercube or Monte Carlo over scene parameters.

Every sample is a full solve of the scene with some parameters changed. The
samples are solved together in batches (:func:`jaxdem.batch.solve_batch`):
one compilation, one vmapped increment for a whole chunk. Parameters that
change the block geometry (joint spacing, an excavation's radius) cannot
share one batch; a sweep over them solves its samples one after another,
with the same table as the result.

A variable is a range or a distribution (file units, friction in degrees):

    PATH=LOW:HIGH            range (uniform in a Latin hypercube or Monte Carlo)
    PATH=LOW:HIGH:log        range, uniform in log(value)
    PATH=uniform:LOW:HIGH
    PATH=normal:MEAN:SD
    PATH=lognormal:MEAN:SD   mean and standard deviation of the value itself
    PATH=truncnormal:MEAN:SD:LOW:HIGH   normal cut to [LOW, HIGH]

``grid`` takes ``samples`` levels of each variable (samples^p solves; the
levels of a distribution are its quantiles at (i + 1/2) / samples); ``lhs``
and ``mc`` draw ``samples`` points. The same seed gives the same samples.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from jaxdem.batch import BatchResult, solve_batch
from jaxdem.config import float64
from jaxdem.differentiable import NotSmooth
from jaxdem.geometry import signed_areas
from jaxdem.results import SMALL_MECHANISM, jsonable, mechanism_volume
from jaxdem.scene import SceneError, apply_overrides

METHODS = ("grid", "lhs", "mc")
KINDS = ("range", "uniform", "normal", "lognormal", "truncnormal")
_ARITY = dict(uniform=2, normal=2, lognormal=2, truncnormal=4)
#: Tornado bars run from the 10th to the 90th percentile of a distribution.
TORNADO_QUANTILES = (0.1, 0.9)
MAX_SAMPLES = 1_000_000


@dataclasses.dataclass(frozen=True)
class Variable:
    """A swept parameter: its path and its range or distribution (see the module)."""

    path: str
    kind: str
    args: tuple
    log: bool = False

    @classmethod
    def parse(cls, text: str) -> Variable:
        """``PATH=SPEC`` as the command line writes it."""
        path, sep, spec = text.partition("=")
        path = path.strip()
        where = f"--vary {path or text}"
        if not sep or not path or not spec:
            raise SceneError(where, "expected PATH=LOW:HIGH[:log] or PATH=DIST:ARGS "
                             f"(DIST one of {', '.join(KINDS[1:])})")
        parts = [p.strip() for p in spec.split(":")]
        kind, log = "range", False
        if parts[0].lower() in _ARITY or parts[0].lower() == "truncated":
            kind = "truncnormal" if parts[0].lower() == "truncated" else parts[0].lower()
            parts = parts[1:]
            if len(parts) != _ARITY[kind]:
                raise SceneError(where, f"{kind} takes {_ARITY[kind]} numbers, got {len(parts)}")
        else:
            if len(parts) == 3 and parts[2].lower() == "log":
                log, parts = True, parts[:2]
            if len(parts) != 2:
                raise SceneError(where, "expected LOW:HIGH or LOW:HIGH:log")
        try:
            args = tuple(float(p) for p in parts)
        except ValueError:
            raise SceneError(where, f"{spec!r} holds something that is not a number") from None
        return cls(path, kind, args, log).checked()

    def checked(self) -> Variable:
        where = f"--vary {self.path}"
        a = self.args
        if not all(math.isfinite(x) for x in a):
            raise SceneError(where, "holds a NaN or infinite value")
        if self.kind not in KINDS:
            raise SceneError(where, f"unknown kind {self.kind!r}")
        if self.kind in ("range", "uniform") and not a[0] < a[1]:
            raise SceneError(where, f"LOW must be below HIGH (got {a[0]:g}:{a[1]:g})")
        if self.log and a[0] <= 0:
            raise SceneError(where, "a log range needs LOW > 0")
        if self.kind in ("normal", "lognormal", "truncnormal") and not a[1] > 0:
            raise SceneError(where, "the standard deviation must be > 0")
        if self.kind == "lognormal" and not a[0] > 0:
            raise SceneError(where, "a lognormal needs a mean > 0")
        if self.kind == "truncnormal" and not a[2] < a[3]:
            raise SceneError(where, f"LOW must be below HIGH (got {a[2]:g}:{a[3]:g})")
        return self

    def quantile(self, u) -> np.ndarray:
        """The values at probabilities u in (0, 1) (for a range: its uniform distribution)."""
        # SciPy is loaded here, not with the module: ``import jaxdem`` stays quick.
        from scipy.special import ndtr, ndtri

        u = np.asarray(u, float)
        a = self.args
        if self.kind in ("range", "uniform"):
            if self.log:
                return np.exp(np.log(a[0]) + u * (np.log(a[1]) - np.log(a[0])))
            return a[0] + u * (a[1] - a[0])
        if self.kind == "normal":
            return a[0] + a[1] * ndtri(u)
        if self.kind == "lognormal":
            s2 = math.log1p((a[1] / a[0]) ** 2)
            return np.exp(math.log(a[0]) - 0.5 * s2 + math.sqrt(s2) * ndtri(u))
        lo, hi = ndtr((a[2] - a[0]) / a[1]), ndtr((a[3] - a[0]) / a[1])
        return np.clip(a[0] + a[1] * ndtri(lo + u * (hi - lo)), a[2], a[3])

    def levels(self, n: int) -> np.ndarray:
        """n grid levels: a range's ends and evenly spaced points between; a distribution's
        quantiles at (i + 1/2) / n."""
        if self.kind == "range":
            if n == 1:
                return self.quantile(np.array([0.5]))
            space = np.geomspace if self.log else np.linspace
            return space(self.args[0], self.args[1], n)  # the ends exactly
        return self.quantile((np.arange(n) + 0.5) / n)

    def tornado_points(self) -> tuple[float, float, float]:
        """(low, base, high) of a tornado bar: a range's ends and middle, a distribution's
        10th, 50th and 90th percentiles."""
        if self.kind == "range":
            lo, mid, hi = self.args[0], float(self.quantile(0.5)), self.args[1]
        else:
            lo, mid, hi = self.quantile([TORNADO_QUANTILES[0], 0.5, TORNADO_QUANTILES[1]])
        return float(lo), float(mid), float(hi)

    def describe(self) -> str:
        if self.kind == "range":
            return f"{self.args[0]:g} to {self.args[1]:g}" + (" (log)" if self.log else "")
        return f"{self.kind}({', '.join(f'{x:g}' for x in self.args)})"


def draw(variables: Sequence[Variable], samples: int, method: str, seed: int = 0) -> np.ndarray:
    """The (S, p) sample matrix (see the module for the methods)."""
    if method not in METHODS:
        raise SceneError("--method", f"must be one of {', '.join(METHODS)}, not {method!r}")
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise SceneError("--samples", f"must be a whole number >= 1, not {samples!r}")
    p = len(variables)
    if not p:
        raise SceneError("--vary", "give at least one parameter to vary")
    total = samples ** p if method == "grid" else samples
    if total > MAX_SAMPLES:
        raise SceneError("--samples", f"{total:,} solves is more than {MAX_SAMPLES:,}")
    rng = np.random.default_rng(seed)
    if method == "grid":
        axes = [v.levels(samples) for v in variables]
        return np.array(list(itertools.product(*axes)), float).reshape(-1, p)
    if method == "lhs":
        strata = np.stack([rng.permutation(samples) for _ in range(p)], axis=1)
        u = (strata + rng.random((samples, p))) / samples
    else:
        u = rng.random((samples, p))
    u = np.clip(u, 1e-12, 1 - 1e-12)
    return np.column_stack([v.quantile(u[:, j]) for j, v in enumerate(variables)])


@dataclasses.dataclass
class SweepResult:
    """Samples, their outcomes, the tornado and the probability of instability.

    Attributes:
      variables: the swept :class:`Variable` s.
      method, seed: how the samples were drawn.
      batch: the :class:`jaxdem.batch.BatchResult` of the samples (``theta``,
        ``monitors``, ``stable``, ``converged``, ``status``, ``timing``).
      tornado: monitor -> list of bars, largest swing first: ``path``, ``low``,
        ``base``, ``high`` (parameter values), ``at_low``, ``at_high`` (the
        monitor with that parameter at its low or high point and the others
        at their base), ``swing`` (at_high - at_low) and ``quantity`` (what the
        values are: "|u|", a point monitor's displacement magnitude, or
        "convergence", a section's; m).
      probability: ``unstable`` (mechanisms), ``small`` (those of them that are
        small: pieces working loose, ``batch.small_mechanism``; counted in
        ``unstable``), ``decided`` (samples that ended stable or in a mechanism),
        ``undecided`` (iteration limit or non-finite), ``p_unstable`` = unstable /
        decided, and its 95% Wilson score interval ``ci95``.
      mode: ``"batched"`` or ``"loop"`` (a parameter changes the geometry).
    """

    variables: list
    method: str
    seed: int
    batch: BatchResult
    tornado: dict
    probability: dict
    mode: str

    def columns(self) -> list[str]:
        cols = ["sample"] + [v.path for v in self.variables]
        for name, v in self.batch.monitors.items():
            cols += [f"{name}.ux", f"{name}.uy"] if v.ndim == 2 else [name]
        return cols + ["stable", "converged", "status", "stopped_stage", "stopped_load_factor",
                       "moving_volume", "small_mechanism", "loose_blocks"]

    def rows(self) -> list[dict]:
        """One dict per sample, keyed by :meth:`columns` (the table of sweep.csv)."""
        b = self.batch
        out = []
        for i in range(b.theta.shape[0]):
            row = {"sample": i}
            row.update({v.path: float(b.theta[i, j]) for j, v in enumerate(self.variables)})
            for name, v in b.monitors.items():
                if v.ndim == 2:
                    row[f"{name}.ux"], row[f"{name}.uy"] = float(v[i, 0]), float(v[i, 1])
                else:
                    row[name] = float(v[i])
            stop = (b.stopped[i] if b.stopped else None) or {}
            row.update(stable=bool(b.stable[i]), converged=bool(b.converged[i]),
                       status=b.status[i], stopped_stage=stop.get("stage", ""),
                       stopped_load_factor=stop.get("load_factor", float("nan")),
                       moving_volume=float(b.moving_volume[i]),
                       small_mechanism=bool(b.small_mechanism[i]),
                       loose_blocks=len(b.loose_blocks[i]))
            out.append(row)
        return out

    def to_csv(self, path=None) -> Path | str:
        """The table of :meth:`rows` as CSV: written to ``path`` (returns the path), or,
        without a path, returned as text.

        Example::

            text = result.to_csv()                 # "sample,joints.base.kn,...\r\n0,..."
            result.to_csv("out/sweep.csv")          # Path("out/sweep.csv")
        """
        buffer = io.StringIO(newline="")
        w = csv.DictWriter(buffer, fieldnames=self.columns())
        w.writeheader()
        for row in self.rows():
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in row.items()})
        if path is None:
            return buffer.getvalue()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", newline="") as f:
            f.write(buffer.getvalue())
        return path

    def to_dict(self) -> dict:
        """The content of sweep.json: plain JSON types, NaN as null."""
        return jsonable(finite=True, x=dict(
            method=self.method, seed=self.seed, samples=int(self.batch.theta.shape[0]),
            mode=self.mode,
            variables=[dict(path=v.path, kind=v.kind, args=list(v.args), log=v.log)
                       for v in self.variables],
            probability=self.probability, tornado=self.tornado, timing=self.batch.timing))


@float64
def sweep(scene, vary: Sequence[Variable | str] | Mapping, samples: int, *,
          method: str | None = None, seed: int = 0, tornado: bool = True,
          chunk: int | None = None, devices=None, workers: int | None = None,
          progress=None) -> SweepResult:
    """Solve ``scene`` over sampled parameters; see the module for ``vary``.

    Args:
      scene: a validated scene.
      vary: :class:`Variable` s or ``"PATH=SPEC"`` strings (or {path: spec}).
      samples: grid levels per variable, or the number of LHS / Monte Carlo draws.
      method: "grid", "lhs" or "mc"; default "grid" when every variable is a
        range, else "lhs".
      seed: the random seed (same seed, same samples).
      tornado: also solve the 1 + 2p one-at-a-time points of the tornado (those that
        are not samples already: each point is solved once).
      chunk, devices, workers: see :func:`jaxdem.batch.solve_batch`.
      progress: optional callable (samples done, samples in all).
    Returns:
      a :class:`SweepResult`.

    Example::

        result = jaxdem.sweep(scene, ["joints.set1.kn=1e6:4e6:log",
                                      "joints.set1.friction_deg=normal:30:3"], 64)
        result.to_csv("sweep.csv"); print(result.probability)
    """
    if isinstance(vary, Mapping):
        vary = [f"{k}={v}" for k, v in vary.items()]
    variables = [v if isinstance(v, Variable) else Variable.parse(v) for v in vary]
    paths = [v.path for v in variables]
    if len(set(paths)) != len(paths):
        raise SceneError("--vary", "a parameter is named twice")
    if method is None:
        method = "grid" if all(v.kind == "range" for v in variables) else "lhs"
    theta = draw(variables, samples, method, seed)
    check_values(scene, variables, theta)
    everything = np.vstack([theta, tornado_rows(variables)]) if tornado else theta
    # A point solved once however often it comes: a grid's ends (and, with an odd
    # number of levels, its middle) are the tornado's points too.
    distinct, where = distinct_rows(everything)
    try:
        batch = solve_batch(scene, paths, distinct, chunk=chunk, devices=devices,
                            workers=workers, progress=progress)
        mode = "batched"
    except NotSmooth:
        batch = solve_each(scene, paths, distinct, progress=progress)
        mode = "loop"
    S = theta.shape[0]
    main = _take(batch, where[:S])
    bars = _tornado(variables, _take(batch, where[S:])) if tornado else {}
    return SweepResult(variables=variables, method=method, seed=seed, batch=main,
                       tornado=bars, probability=probability_of_instability(main), mode=mode)


def tornado_rows(variables: Sequence[Variable]) -> np.ndarray:
    """The (1 + 2p, p) one-at-a-time points of the tornado: every variable at its base,
    then each variable at its low and at its high point with the others at their base
    (:meth:`Variable.tornado_points`)."""
    base = np.array([v.tornado_points()[1] for v in variables])
    rows = [base]
    for j, v in enumerate(variables):
        lo, _, hi = v.tornado_points()
        for x in (lo, hi):
            row = base.copy()
            row[j] = x
            rows.append(row)
    return np.array(rows)


def distinct_rows(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``theta`` (S, p) that differ, in the order they first come, and for
    each row of ``theta`` the index of its row among them (equal values exactly: the
    same parameters give the same solve)."""
    _, first, inverse = np.unique(theta, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return theta[first[order]], rank[inverse.reshape(-1)]


def tornado_solves(variables: Sequence[Variable], theta: np.ndarray) -> int:
    """How many solves the tornado adds to a sweep of the samples ``theta``: its points
    that are not samples already (:func:`sweep` solves each point once)."""
    with_tornado = np.vstack([theta, tornado_rows(variables)])
    return len(distinct_rows(with_tornado)[0]) - len(distinct_rows(theta)[0])


def solve_each(scene, params, theta, progress=None) -> BatchResult:
    """:func:`jaxdem.batch.solve_batch` by single solves, one after another (any parameter)."""
    from jaxdem.solver import solve

    S = theta.shape[0]
    monitors: dict = {}
    status, stopped, moving, loose, iterations = [], [], [], [], np.zeros(S, int)
    volume, small = np.zeros(S), np.zeros(S, bool)
    timing = dict(build_s=0.0, compile_s=0.0, solve_s=0.0, chunk=1, devices=1, workers=1)
    for i, row in enumerate(theta):
        res = solve(scene, set=dict(zip(params, (float(x) for x in row), strict=True)))
        for k in ("build_s", "compile_s", "solve_s"):
            timing[k] += res.timing[k]
        status.append(res.status)
        last = res.stages[-1]
        stopped.append(None if res.converged else
                       dict(stage=last["name"], load_factor=last["load_factor"][-1]))
        iterations[i] = sum(sum(st["iterations"]) for st in res.stages)
        moving.append(list(res.moving_blocks))
        loose.append([b["id"] for b in res.loose_blocks])
        if res.moving_blocks:  # each sample's own blocks: a loop's parameter may cut them
            area = np.abs(signed_areas(res.geometry["initial_vertices"]))
            volume[i] = mechanism_volume(res.moving_blocks, area)
            small[i] = any(w.startswith(SMALL_MECHANISM) for w in res.warnings)
        for name, m in res.monitors.items():
            value = m["displacement"] if "displacement" in m else m["convergence"]
            arr = monitors.setdefault(name, np.full((S,) + np.shape(value), np.nan))
            if res.converged:
                arr[i] = value
        if progress is not None:
            progress(i + 1, S)
    status_arr = np.array(status)
    return BatchResult(params=list(params), theta=np.asarray(theta, float), monitors=monitors,
                       status=list(status), stable=status_arr != "mechanism",
                       converged=status_arr == "converged", iterations=iterations,
                       timing=timing, moving_blocks=moving, stopped=stopped,
                       moving_volume=volume, small_mechanism=small, loose_blocks=loose)


def probability_of_instability(batch: BatchResult, z: float = 1.959964) -> dict:
    """Share of mechanisms among the samples that found an answer, with its 95% Wilson
    interval, and how many of the mechanisms are small (``small``: see
    :attr:`SweepResult.probability`)."""
    unstable = int(np.sum(~batch.stable))
    flags = getattr(batch, "small_mechanism", None)  # any object with stable and converged
    small = 0 if flags is None else int(np.sum(~batch.stable & flags))
    decided = int(np.sum(batch.converged | ~batch.stable))
    undecided = int(len(batch.stable) - decided)
    if decided == 0:
        return dict(unstable=unstable, small=small, decided=0, undecided=undecided,
                    p_unstable=float("nan"), ci95=[float("nan"), float("nan")])
    p = unstable / decided
    denom = 1 + z * z / decided
    centre = (p + z * z / (2 * decided)) / denom
    half = z * math.sqrt(p * (1 - p) / decided + z * z / (4 * decided * decided)) / denom
    return dict(unstable=unstable, small=small, decided=decided, undecided=undecided,
                p_unstable=p, ci95=[max(0.0, centre - half), min(1.0, centre + half)])


def _scalar(v: np.ndarray) -> np.ndarray:
    """A monitor's scalar: a section's convergence, a point's displacement magnitude."""
    return np.linalg.norm(v, axis=1) if v.ndim == 2 else v


def _tornado(variables, batch: BatchResult) -> dict:
    out = {}
    for name, v in batch.monitors.items():
        y = _scalar(v)
        bars = []
        for j, var in enumerate(variables):
            lo, base, hi = var.tornado_points()
            y_lo, y_hi = float(y[1 + 2 * j]), float(y[2 + 2 * j])
            bars.append(dict(path=var.path, low=lo, base=base, high=hi, at_base=float(y[0]),
                             at_low=y_lo, at_high=y_hi, swing=y_hi - y_lo,
                             quantity="|u|" if v.ndim == 2 else "convergence"))
        bars.sort(key=lambda b: -abs(b["swing"]) if math.isfinite(b["swing"]) else 0.0)
        out[name] = bars
    return out


def _take(batch: BatchResult, rows: np.ndarray) -> BatchResult:
    """The samples ``rows`` (indices, in their order, repeats allowed) of ``batch``."""
    pick = lambda items: [items[i] for i in rows]  # noqa: E731
    return dataclasses.replace(
        batch, theta=batch.theta[rows], monitors={k: v[rows] for k, v in batch.monitors.items()},
        status=pick(batch.status), stable=batch.stable[rows], converged=batch.converged[rows],
        iterations=batch.iterations[rows], moving_blocks=pick(batch.moving_blocks),
        stopped=pick(batch.stopped), moving_volume=batch.moving_volume[rows],
        small_mechanism=batch.small_mechanism[rows], loose_blocks=pick(batch.loose_blocks))


def check_values(scene, variables, theta) -> None:
    """Refuse draws the scene would refuse (a negative stiffness from a wide normal): the
    path with the first draw, then each variable's smallest and largest draw; a
    SceneError naming ``--vary PATH``."""
    for j, v in enumerate(variables):
        try:  # the path itself first: a typo is the parameter's fault, not a sample's
            apply_overrides(scene.data, {v.path: float(theta[0, j])})
        except SceneError as err:
            raise SceneError(f"--vary {v.path}", f"{err.problem} in the scene (a parameter "
                             "path such as joints.NAME.kn or bolts.0.stiffness)") from None
        for i in (int(np.argmin(theta[:, j])), int(np.argmax(theta[:, j]))):
            try:
                scene.with_overrides({v.path: float(theta[i, j])})
            except SceneError as err:
                raise SceneError(f"--vary {v.path}", f"sample {i} drew {theta[i, j]:g} from "
                                 f"{v.describe()}, which the scene refuses: {err.problem}"
                                 ) from None


__all__ = ["METHODS", "SweepResult", "Variable", "check_values", "draw",
           "probability_of_instability", "sweep"]
