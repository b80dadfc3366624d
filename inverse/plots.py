"""Figures of a back-analysis: ``misfit.png``, ``fit.png``, ``sensitivity.png``.

Host code only: NumPy and matplotlib's object interface with the Agg renderer
(pyplot's global state is left alone). Every function writes one PNG, releases
its figure and returns the path. Displacements and convergences are drawn in mm.

Example::

    from inverse import back_analyse
    from inverse.plots import write_figures
    result = back_analyse(scene, observations, fit=["joints.set1.kn"])
    write_figures(result, "out/fit")   # [out/fit/misfit.png, out/fit/fit.png, ...]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from inverse.backanalysis import BackAnalysis

__all__ = ["plot_fit", "plot_misfit", "plot_sensitivity", "write_figures"]

DPI = 150
MM = 1e3  # m -> mm
_MEASURED = "0.15"
_FITTED = "tab:red"
_START = "0.55"
# Above this many cells the sensitivity map is drawn without numbers in the cells.
_MAX_ANNOTATED_CELLS = 120


def write_figures(result: BackAnalysis, out_dir: str | Path) -> list[Path]:
    """Write ``misfit.png``, ``fit.png`` and ``sensitivity.png`` in ``out_dir``.

    Args:
      result: a :class:`~inverse.BackAnalysis`.
      out_dir: folder (created if needed).

    Returns:
      the paths written.
    """
    out = Path(out_dir)
    return [
        plot_misfit(result, out / "misfit.png"),
        plot_fit(result, out / "fit.png"),
        plot_sensitivity(result, out / "sensitivity.png"),
    ]


def plot_misfit(result: BackAnalysis, path: str | Path) -> Path:
    """Misfit against iteration, log scale, with the misfit that noise alone would leave.

    A perfect model with the stated standard deviations ends near (n - p) / 2 for n
    observations and p parameters (chi^2 / 2 with n - p degrees of freedom); that
    level is drawn dashed when n > p.

    Args:
      result: a :class:`~inverse.BackAnalysis`.
      path: PNG file to write.

    Returns:
      ``path``.
    """
    history = np.asarray(result.history, dtype=float)
    iterations = np.arange(history.size)
    shown = np.isfinite(history) & (history > 0.0)  # a log axis cannot show 0 or inf
    fig = _figure((7.0, 4.2))
    ax = fig.add_subplot()
    ax.semilogy(iterations[shown], history[shown], marker="o", ms=4, lw=1.5, color="tab:blue",
                label="misfit")
    n, p = len(result.observations), len(result.paths)
    if n > p:
        ax.axhline((n - p) / 2, color="0.5", ls="--", lw=1.0,
                   label=f"expected from noise alone, (n - p)/2 = {(n - p) / 2:g}")
    if shown.any():
        last = int(iterations[shown][-1])
        ax.annotate(f"{history[last]:.3g}", xy=(last, history[last]), xytext=(4, 6),
                    textcoords="offset points", fontsize=8)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("iteration")
    ax.set_ylabel(r"misfit  $\frac{1}{2}\sum_i ((y_i - y_i^{obs}) / \sigma_i)^2$")
    ax.set_title(f"Back-analysis ({result.optimizer}): {result.status.replace('_', ' ')}, "
                 f"{result.evaluations.get('gradient', 0)} solves with derivatives")
    ax.grid(True, which="both", lw=0.4, alpha=0.5)
    ax.legend(fontsize=8, loc="upper right")
    return _save(fig, path)


def plot_fit(result: BackAnalysis, path: str | Path) -> Path:
    """Measured (with +-1 std error bars) and fitted value of each observation, in mm,
    and below them the residuals in standard deviations (bands at +-1 and +-2).

    Args:
      result: a :class:`~inverse.BackAnalysis`.
      path: PNG file to write.

    Returns:
      ``path``.
    """
    obs = result.observations
    n = len(obs)
    x = np.arange(n)
    measured = MM * np.array([o.value for o in obs], dtype=float)
    std = MM * np.array([o.std for o in obs], dtype=float)
    fitted = MM * np.asarray(result.fitted, dtype=float)
    fig = _figure((max(6.0, 0.75 * n + 2.5), 6.0))
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.4]})

    top.errorbar(x, measured, yerr=std, fmt="o", color=_MEASURED, ms=5, capsize=4, lw=1.2,
                 label=r"measured $\pm 1\sigma$")
    top.plot(x, fitted, "D", color=_FITTED, ms=5, label="fitted")
    top.axhline(0.0, color="0.7", lw=0.8)
    top.set_ylabel("displacement or convergence (mm)")
    top.set_title(f"Measured and fitted values (misfit {result.misfit:.3g})")
    top.grid(True, axis="y", lw=0.4, alpha=0.5)
    top.legend(fontsize=8, loc="best")

    with np.errstate(invalid="ignore", divide="ignore"):
        residual = (fitted - measured) / std
    bottom.axhspan(-2, 2, color="0.93")
    bottom.axhspan(-1, 1, color="0.85")
    bottom.bar(x, np.nan_to_num(residual), color=_FITTED, width=0.5)
    bottom.axhline(0.0, color="0.4", lw=0.8)
    limit = max(2.5, float(np.nanmax(np.abs(residual))) * 1.15) if np.isfinite(residual).any() \
        else 2.5
    bottom.set_ylim(-limit, limit)
    bottom.set_ylabel(r"(fitted - measured) / $\sigma$")
    bottom.set_xticks(x)
    bottom.set_xticklabels([o.label() for o in obs], rotation=30, ha="right", fontsize=8)
    bottom.set_xlim(-0.6, n - 0.4)
    return _save(fig, path)


def plot_sensitivity(result: BackAnalysis, path: str | Path) -> Path:
    """Heat map of the dimensionless sensitivity theta_j / std_i dy_i/dtheta_j at the
    estimate: how many standard deviations observation i moves for a 100 % change of
    parameter j (to first order). A column of near-zeros is a parameter nothing
    measures; two proportional columns are parameters only a combination of which
    is determined.

    Args:
      result: a :class:`~inverse.BackAnalysis`.
      path: PNG file to write.

    Returns:
      ``path``.
    """
    s = np.asarray(result.sensitivity["dimensionless"], dtype=float)
    n, p = s.shape
    fig = _figure((max(5.0, 1.6 * p + 3.5), max(3.0, 0.45 * n + 1.8)))
    ax = fig.add_subplot()
    finite = np.isfinite(s)
    vmax = float(np.abs(s[finite]).max()) if finite.any() else 1.0
    vmax = vmax if vmax > 0.0 else 1.0
    image = ax.imshow(s, cmap="RdBu_r", norm=TwoSlopeNorm(0.0, -vmax, vmax), aspect="auto")
    if n * p <= _MAX_ANNOTATED_CELLS:
        for i in range(n):
            for j in range(p):
                if finite[i, j]:
                    dark = abs(s[i, j]) > 0.6 * vmax
                    # Below 0.5 % of the largest reads as 0 (not "-0" or "3e-17").
                    text = f"{s[i, j]:.2g}" if abs(s[i, j]) >= 5e-3 * vmax else "0"
                    ax.text(j, i, text, ha="center", va="center", fontsize=8,
                            color="white" if dark else "black")
    ax.set_xticks(np.arange(p))
    ax.set_xticklabels([_parameter_label(result, path) for path in result.paths], fontsize=8)
    ax.set_yticks(np.arange(n))
    ax.set_yticklabels([o.label() for o in result.observations], fontsize=8)
    bar = fig.colorbar(image, ax=ax)
    bar.set_label(r"$\theta_j / \sigma_i\ \partial y_i / \partial \theta_j$  "
                  "(std per 100 % change)", fontsize=8)
    ax.set_title("Sensitivity of each observation to each parameter", fontsize=10)
    return _save(fig, path)


def _parameter_label(result: BackAnalysis, path: str) -> str:
    label = path
    if not result.identifiable.get(path, True):
        label += "\n(not identifiable)"
    return label


def _figure(figsize: tuple[float, float]) -> Figure:
    """A figure outside pyplot (nothing global to close), drawn by Agg."""
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=DPI)
    finally:
        fig.clear()  # release the artists now rather than at garbage collection
    return path
