"""Figures of the monitors: ``monitors.png`` (:func:`plot_monitor_history`, monitor values
over the load increments on a cumulative stage axis, :func:`stage_axis`) and
``sections.png`` (:func:`plot_sections`, each monitor at the end of each stage, as bars).

A :class:`~jaxdem.results.Result` (``history``, ``stages``, ``monitors``) comes in, one PNG
goes out, drawn on the canvas of :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from jaxdem.plots._canvas import new_figure, save_figure
from jaxdem.results import Result


def plot_monitor_history(result: Result, path: str | Path) -> Path | None:
    """Monitor values over the load increments; ``None`` where there are no monitors.

    A point monitor is drawn as its displacement magnitude |u| (mm), a section
    as its convergence (mm, positive when the ends approach). Increments are
    numbered across stages, stage boundaries are dashed and named, and the
    load factor of each increment is drawn in grey on the right-hand axis.

    Args:
      result: a :class:`~jaxdem.results.Result` whose ``history`` lists, per
        increment, ``stage``, ``step``, ``load_factor`` and ``monitors``.
      path: PNG file to write.

    Returns:
      ``path``, or ``None`` when no monitor was recorded (nothing is written).
    """
    history = list(result.history or [])
    names: list[str] = []
    for record in history:
        for name in record.get("monitors", {}) or {}:
            if name not in names:
                names.append(name)
    if not names:
        names_from_result = list(result.monitors or {})
        if not names_from_result:
            return None
        names = names_from_result

    x, stages = stage_axis(history)
    fig, ax = new_figure((8, 4.8))
    # Before the first stage (loading, or the in-situ state) displacements count from
    # the unloaded start; from the first stage on, from the state before it (as in
    # result.json). Shade that part, narrow (_REFERENCE_WIDTH of a stage: nothing moves
    # there on this axis), so that the change of reference is not read as motion.
    squeeze = _squeeze if len(stages) > 1 else (lambda v: np.asarray(v, dtype=float))
    if len(stages) > 1:
        ax.axvspan(0.0, _REFERENCE_WIDTH, color="0.92", zorder=0, gid="reference state")
        note = "in-situ\nstate" if stages[0] == "initial" else "from the\nunloaded\nstart"
        ax.annotate(note, xy=(0.5 * _REFERENCE_WIDTH, 1.0), xycoords=("data", "axes fraction"),
                    xytext=(0, -4), textcoords="offset points", ha="center", va="top",
                    fontsize=6, color="0.4")
    for k, name in enumerate(names):
        values = np.array(
            [float((r.get("monitors") or {}).get(name, np.nan)) for r in history], dtype=float
        )
        kind = _monitor_kind(result, name)
        label = f"{name} ({'convergence' if kind == 'section' else '|u|'})"
        colour = f"C{k % 10}"
        # One line per stage, starting from where the previous stage ended; the first
        # stage after the reference state starts from 0 at its start.
        index = np.minimum(np.floor(x - 1e-9), len(stages) - 1).astype(int)
        labelled = False
        for j in range(len(stages)):
            sel = np.nonzero(index == j)[0]
            if not len(sel):
                continue
            xs, ys = x[sel], 1e3 * values[sel]
            prev = np.nonzero(index == j - 1)[0]
            if j == 0:
                xs, ys = np.concatenate([[0.0], xs]), np.concatenate([[0.0], ys])
            elif j == 1 and len(stages) > 1:
                xs, ys = np.concatenate([[1.0], xs]), np.concatenate([[0.0], ys])
            elif j > 1 and len(prev):
                xs = np.concatenate([[x[prev[-1]]], xs])
                ys = np.concatenate([[1e3 * values[prev[-1]]], ys])
            ax.plot(squeeze(xs), ys, marker="o", ms=3, lw=1.5, color=colour, markevery=slice(
                    1 if len(xs) > len(sel) else 0, None),
                    label=None if labelled else label)
            labelled = True

    # Stage boundaries at whole numbers; each stage's name at its middle.
    for j in range(1, len(stages)):
        ax.axvline(squeeze(j), color="0.5", ls="--", lw=0.8)
    ax.set_xticks(squeeze(np.arange(len(stages) + 1)))
    ax.set_xticks(squeeze(np.arange(len(stages)) + 0.5), minor=True)
    ax.set_xticklabels([""] * (len(stages) + 1))
    ax.set_xticklabels(stages, minor=True, fontsize=8)
    ax.tick_params(axis="x", which="minor", length=0)
    ax.set_xlabel("stage (each spans its load steps, load factor 0 to 1)")
    ax.set_ylabel("monitor value (mm)")
    ax.grid(True, axis="y", lw=0.4, alpha=0.5)
    if len(stages):
        ax.set_xlim(0.0, float(squeeze(len(stages))))
    ax.legend(fontsize=8, loc="best")
    ax.set_title(f"{result.scene}: monitors")
    return save_figure(fig, path)


_REFERENCE_WIDTH = 0.15
"""Width on the stage axis of the reference record before the first stage (the others
take 1 each)."""


def _squeeze(x: Any) -> np.ndarray:
    """The stage axis with the reference stage [0, 1] squeezed to [0, _REFERENCE_WIDTH]."""
    x = np.asarray(x, dtype=float)
    return np.where(x <= 1.0, _REFERENCE_WIDTH * x, x - 1.0 + _REFERENCE_WIDTH)


def stage_axis(history: Sequence[dict[str, Any]]) -> tuple[np.ndarray, list[str]]:
    """A cumulative stage axis for per-increment records: stage k (0-based, in order of
    appearance) spans [k, k + 1] and its step at load factor f sits at k + f, so the axis
    only grows (a new stage does not start again at 0). Returns (x, stage names)."""
    stages: list[str] = []
    x = []
    for r in history:
        stage = str(r.get("stage", ""))
        if not stages or stages[-1] != stage:
            stages.append(stage)
        f = r.get("load_factor")
        if f is None or not np.isfinite(float(f)):
            f = 1.0
        x.append(len(stages) - 1 + min(max(float(f), 0.0), 1.0))
    return np.array(x, dtype=float), stages


def plot_sections(result: Result, path: str | Path) -> Path | None:
    """Monitors at the end of each stage, as bars; ``None`` where there are none.

    One group of bars per monitor, one bar per stage (coloured by stage and
    labelled with its value), as in the staged-excavation figures of tunnel
    papers: section convergence (mm, positive when the ends approach) on the
    left, point monitors' displacement magnitude |u| (mm) on the right. Every
    bar counts from one reference state, the state before the first stage (as
    result.json's monitors): the loading or in-situ record before it is left out.

    Args:
      result: a :class:`~jaxdem.results.Result` whose ``stages`` each hold
        ``name`` and ``monitors`` (monitor name -> value after each increment, m).
      path: PNG file to write.

    Returns:
      ``path``, or ``None`` when no stage recorded a monitor (nothing is written).
    """
    stages = list(result.stages or [])
    # One reference state for every bar: with stages after it, the first record (the
    # loading, or the in-situ state) counts from the unloaded start and the others from
    # the state before the first stage, so it is left out.
    before = stages[0].get("name") if len(stages) > 1 else None
    if before is not None:
        stages = stages[1:]
    names: list[str] = []
    for stage in stages:
        for name, values in (stage.get("monitors") or {}).items():
            if name not in names and len(np.atleast_1d(values)):
                names.append(name)
    if not names:
        return None
    stage_names = [str(s.get("name", f"stage {k + 1}")) for k, s in enumerate(stages)]
    # values[i, j]: monitor i at the end of stage j (mm), NaN where not recorded.
    values = np.full((len(names), len(stages)), np.nan)
    for j, stage in enumerate(stages):
        monitors = stage.get("monitors") or {}
        for i, name in enumerate(names):
            series = np.atleast_1d(np.asarray(monitors.get(name, []), dtype=float))
            if len(series):
                values[i, j] = 1e3 * series[-1]
    groups = [
        (kind, title, [i for i, name in enumerate(names) if _monitor_kind(result, name) == kind])
        for kind, title in (
            ("section", "section convergence (mm)"),
            ("point", "point displacement |u| (mm)"),
        )
    ]
    groups = [g for g in groups if g[2]]
    widths = [max(len(g[2]), 1) * max(len(stages), 1) * 0.45 + 1.5 for g in groups]
    fig = Figure(figsize=(min(max(sum(widths) + 1.5, 6.0), 18.0), 4.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(groups), squeeze=False, width_ratios=widths)[0]
    n_stages = len(stages)
    bar_width = 0.8 / n_stages
    for ax, (_, title, rows) in zip(axes, groups, strict=True):
        x = np.arange(len(rows))
        for j in range(n_stages):
            heights = values[rows, j]
            pos = x - 0.4 + (j + 0.5) * bar_width
            ok = np.isfinite(heights)
            bars = ax.bar(
                pos[ok],
                heights[ok],
                width=bar_width * 0.92,
                color=f"C{j % 10}",
                edgecolor="0.2",
                linewidth=0.5,
                label=stage_names[j],
                zorder=3,
            )
            if len(rows) * n_stages <= 40:
                tiny = 1e-3 * np.nanmax(np.abs(values[rows]), initial=0.0)
                labels = [f"{v:.3g}" if abs(v) > tiny else "0" for v in heights[ok]]
                ax.bar_label(bars, labels=labels, fontsize=7, padding=2)
        ax.axhline(0.0, color="0.3", lw=0.8, zorder=2)
        ax.set_xticks(x, [names[i] for i in rows], rotation=30 if len(rows) > 6 else 0)
        ax.set_ylabel(title)
        ax.grid(True, axis="y", lw=0.4, alpha=0.5, zorder=0)
        ax.margins(y=0.15)
        ax.set_title(title.split(" (")[0], fontsize=10)
    axes[-1].legend(
        title="end of stage",
        fontsize=8,
        title_fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        frameon=False,
    )
    reference = ("from the state before the first stage" if before is not None
                 else "from the start")
    fig.suptitle(f"{result.scene}: monitors at the end of each stage ({reference})")
    return save_figure(fig, path)


def _monitor_kind(result: Result, name: str) -> str:
    entry = (result.monitors or {}).get(name) or {}
    if "convergence" in entry:
        return "section"
    where = (result.geometry or {}).get("monitors", {}).get(name)
    if where is not None and np.size(where) == 4:
        return "section"
    return "point"
