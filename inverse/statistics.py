"""Statistics of an estimate: Gauss-Newton standard deviations, correlations, which
parameters the observations determine, and the warnings that say so in words.

Also the chi-square test that decides whether a fit is rejected (``misfit_limit``).
Takes the dimensionless sensitivity matrix at the estimate (from :mod:`inverse.fit`'s
objective, built by :mod:`inverse.backanalysis`) and gives back stds, identifiability,
the correlation matrix and sentences; imports nothing from the package. Host NumPy.
"""

from __future__ import annotations

import math

import numpy as np

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

def gauss_newton_statistics(scaled: np.ndarray, scale: np.ndarray, paths: list[str],
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


def bound_warnings(u: np.ndarray, theta: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   paths: list[str]) -> list[str]:
    """Estimates within ``AT_BOUND`` of a bound; ``u`` is each one's fraction of its
    (log-)range, ``lo`` and ``hi`` the bounds."""
    out = []
    for j, path in enumerate(paths):
        if u[j] < AT_BOUND or u[j] > 1.0 - AT_BOUND:
            side, bound = ("lower", lo[j]) if u[j] < 0.5 else ("upper", hi[j])
            out.append(f"{path} ended at its {side} bound ({theta[j]:.4g}, bound {bound:.4g}): "
                       "the observations pull it further; widen the bounds or check the model")
    return out


def precision_warnings(theta: np.ndarray, stds: np.ndarray, identifiable: np.ndarray,
                        paths: list[str]) -> list[str]:
    out = []
    for j, path in enumerate(paths):
        if identifiable[j] and theta[j] != 0.0 and stds[j] > abs(theta[j]):
            out.append(f"{path} is poorly determined: its standard deviation ({stds[j]:.3g}) "
                       f"exceeds the estimate ({theta[j]:.3g})")
    return out


REJECT_QUANTILE = 0.999
"""A fit is rejected, and the fit restarts elsewhere (``back_analyse(restarts=...)``),
when 2 x its misfit exceeds this quantile of chi^2 with n - p degrees of freedom: if the
model and the stated stds are right, the best fit's misfit lies above it once in a
thousand noise draws, so a misfit above it says the optimiser stopped in a local minimum
(or that the model or the stds are wrong, which no restart mends)."""


def misfit_limit(n: int, p: int) -> float:
    """The largest misfit (in units of chi^2 / 2) that noise explains: half the
    ``REJECT_QUANTILE`` quantile of chi^2 with n - p degrees of freedom (at least 1: with
    no more observations than parameters an exact fit exists and any misfit is
    unexplained; one degree of freedom keeps the test from rejecting round-off).

    Example::

        misfit_limit(6, 2)  # 9.23: chi^2(4) lies below 18.47 99.9 % of the time
    """
    from scipy.stats import chi2

    return 0.5 * float(chi2.ppf(REJECT_QUANTILE, max(n - p, 1)))


def fit_warnings(misfit: float, n: int, p: int) -> list[str]:
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
