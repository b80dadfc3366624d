"""The report of a back-analysis: :class:`BackAnalysis` and its JSON form.

What :func:`inverse.back_analyse` returns and ``back_analysis.json`` holds; the
figures (:mod:`inverse.plots`) and the command line read it. Holds values only: it is
filled by :mod:`inverse.backanalysis` and imports only :class:`Observation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from inverse.observations import Observation


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
      starts: every local fit, the one from the given start first, then the restarts
        after a rejected fit (``back_analyse``'s ``restarts``), each a dict: ``start``
        and ``params`` ({path: value} where it started, after any restoration, and
        where it ended), ``misfit`` (its lowest), ``status``, ``iterations`` and
        ``solves`` (with and without derivatives). ``history``, ``iterations``,
        ``status`` and ``message`` above are those of the fit that gave the estimate
        (the lowest misfit); ``evaluations`` counts the solves of all.
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
    starts: list[dict[str, Any]] = field(default_factory=list)

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
            "starts": [dict(s, misfit=_json(s["misfit"])) for s in self.starts],
        }


def _json(x: Any) -> Any:
    """Floats, or nested lists of them, with non-finite values as None."""
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_json(v) for v in x]
    x = float(x)
    return x if math.isfinite(x) else None
