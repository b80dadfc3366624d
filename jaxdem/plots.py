"""Figures of a solved model (``blocks.png``, ``monitors.png``, ``stresses.png``,
``sections.png``) and of a scene (``check.png``).

Host code only: NumPy and matplotlib's object interface with the Agg renderer
(no display, and pyplot's global state is left alone, so importing this module
does not change a notebook's backend). Every function writes one PNG, releases
its figure and returns the path. Collections
(``PolyCollection``, ``LineCollection``, ``scatter``, ``quiver``) carry all the
blocks and contacts of a layer in one artist, so a model of 10,000 blocks
draws in seconds.

Example::

    from jaxdem import load_scene, solve
    from jaxdem.plots import write_figures
    result = solve(load_scene("tunnel.toml"))
    write_figures(result, "out/tunnel")   # [out/tunnel/blocks.png, out/tunnel/monitors.png, ...]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from jaxdem.results import Result
from jaxdem.state import OPEN, SLIP, STICK

DPI = 150

# Contact states: colour and legend label (green stuck, orange slipping, red open).
_STATE_STYLE = {
    STICK: ("tab:green", "stuck"),
    SLIP: ("tab:orange", "slipping"),
    OPEN: ("tab:red", "open"),
}
_MONITOR_COLOUR = "tab:blue"
_COMPRESSION = "tab:blue"
_TENSION = "tab:red"
# Above _MAX_CROSSES blocks, one principal-stress cross per cell of a grid.
_MAX_CROSSES = 2500
_CROSS_GRID = 50
# Bolt states: colour and line style; forces written on at most _MAX_BOLT_LABELS bolts.
_BOLT_STYLE = {
    "elastic": ("saddlebrown", "-"),
    "yielded": ("darkviolet", "-"),
    "pulled out": ("0.45", "--"),
}
_MAX_BOLT_LABELS = 60
_ARROW_COLOUR = "tab:purple"
# Above _MAX_ARROWS blocks, draw only the largest displacement in each cell of an
# _ARROW_GRID x _ARROW_GRID grid over the model: thousands of arrows read as noise.
_MAX_ARROWS = 1000
_ARROW_GRID = 25


# ---------------------------------------------------------------------------
# Public functions


def plot_blocks(result: Result, path: str | Path, *, magnification: float | None = None) -> Path:
    """Draw the block model after the solve.

    Initial outlines in light grey, final (deformed, true scale) outlines in
    dark grey, fixed blocks shaded and hatched, excavated blocks left out
    (only the opening drawn, as a light dashed outline of their initial
    vertices), walls as thick black lines, contact points coloured by state
    (stuck green, slipping orange, open red, with counts in the legend),
    centroid displacement vectors as arrows, bolts as lines between their
    current anchors coloured by state (elastic, yielded, pulled out) and
    labelled with their force in kN, blocks still moving at a mechanism
    outlined red, monitor points and sections labelled.

    Args:
      result: a :class:`~jaxdem.results.Result` with ``geometry`` filled in.
      path: PNG file to write (parent folders are created).
      magnification: scale of the displacement arrows. By default chosen so
        that the largest arrow is about 5% of the model size, rounded to 1, 2,
        2.5 or 5 times a power of ten, and never below 1 (true scale: a block
        that travelled far has its arrow end at its final centroid). Shown in
        the legend as "displacements x 250".

    Returns:
      ``path`` as a :class:`~pathlib.Path`.
    """
    geometry = result.geometry or {}
    initial = _polygons(geometry.get("initial_vertices", []))
    final = _polygons(geometry.get("final_vertices", [])) or initial
    n_blocks = max(len(initial), len(final))
    fixed = _block_mask(
        geometry.get("fixed", [b.get("fixed", False) for b in result.blocks]), n_blocks
    )
    excavated = _excavated(result, n_blocks)

    fig, ax = _figure((9, 7.5))
    lw = _line_width(n_blocks)
    handles: list[Any] = []

    kept_initial = [p for p, e in zip(initial, excavated, strict=False) if not e]
    if kept_initial:
        ax.add_collection(
            PolyCollection(
                kept_initial,
                closed=True,
                facecolors="none",
                edgecolors="0.78",
                linewidths=lw,
                zorder=1,
            )
        )
        handles.append(Line2D([], [], color="0.78", lw=1.0, label="initial"))
    handles += _draw_final_blocks(ax, initial, final, fixed, excavated, lw, "0.15")

    walls = [np.asarray(w, dtype=float).reshape(2, 2) for w in geometry.get("walls", [])]
    if walls:
        ax.add_collection(LineCollection(walls, colors="k", linewidths=3.0, zorder=3))
        handles.append(Line2D([], [], color="k", lw=3.0, label="wall"))

    moving = [i for i in result.moving_blocks if 0 <= int(i) < len(final) and not excavated[int(i)]]
    if moving:
        ax.add_collection(
            PolyCollection(
                [final[int(i)] for i in moving],
                closed=True,
                facecolors="none",
                edgecolors="red",
                linewidths=max(2.0 * lw, 1.5),
                zorder=4,
            )
        )
        handles.append(Line2D([], [], color="red", lw=2.0, label=f"moving ({len(moving)})"))

    handles += _draw_contacts(ax, geometry.get("contacts") or {}, n_blocks)

    shown = initial + [p for p, e in zip(final, excavated, strict=False) if not e] + walls
    bolts = _bolt_segments(geometry)
    size = _model_size(shown + bolts)
    arrow_handle = _draw_displacements(ax, result, initial, size, magnification, excavated)
    if arrow_handle is not None:
        handles.append(arrow_handle)

    handles += _draw_bolts(ax, result, bolts, size)
    handles += _draw_water_table(ax, geometry.get("water_table"), shown)

    moved = {name: (result.monitors or {}).get(name, {}).get("displacement")
             for name in geometry.get("monitors") or {}}
    monitor_handles = _draw_monitors(ax, geometry.get("monitors") or {}, size, moved)
    handles += monitor_handles

    _finish_axes(ax, shown + bolts)
    ax.set_title(f"{result.scene}: {_status_text(result)}")
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
    _place_labels(fig, ax, [t for t in ax.texts if t.get_gid() == "monitor label"])
    return _save(fig, path)


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
    fig, ax = _figure((8, 4.8))
    # Before the first stage (loading, or the in-situ state) displacements count from
    # the unloaded start; from the first stage on, from the state before it (as in
    # result.json). Shade that part so that the change of reference is not read as motion.
    if len(stages) > 1:
        ax.axvspan(0.0, 1.0, color="0.92", zorder=0)
        note = "in-situ state" if stages[0] == "initial" else "from the unloaded start"
        ax.annotate(note, xy=(0.5, 0.0), xycoords=("data", "axes fraction"),
                    xytext=(0, 4), textcoords="offset points", ha="center", fontsize=7,
                    color="0.4")
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
            ax.plot(xs, ys, marker="o", ms=3, lw=1.5, color=colour, markevery=slice(
                    1 if len(xs) > len(sel) else 0, None),
                    label=None if labelled else label)
            labelled = True

    # Stage boundaries at whole numbers; each stage's name at its middle.
    for j in range(1, len(stages)):
        ax.axvline(j, color="0.5", ls="--", lw=0.8)
    ax.set_xticks(np.arange(len(stages) + 1))
    ax.set_xticks(np.arange(len(stages)) + 0.5, minor=True)
    ax.set_xticklabels([""] * (len(stages) + 1))
    ax.set_xticklabels(stages, minor=True, fontsize=8)
    ax.tick_params(axis="x", which="minor", length=0)
    ax.set_xlabel("stage (each spans its load steps, load factor 0 to 1)")
    ax.set_ylabel("monitor value (mm)")
    ax.grid(True, axis="y", lw=0.4, alpha=0.5)
    if len(stages):
        ax.set_xlim(0.0, float(len(stages)))
    ax.legend(fontsize=8, loc="best")
    ax.set_title(f"{result.scene}: monitors")
    return _save(fig, path)


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


def plot_principal_stresses(result: Result, path: str | Path) -> Path | None:
    """Principal-stress crosses on the final blocks; ``None`` where there are no stresses.

    The final outlines are drawn light (excavated blocks left out, the
    opening as a dashed outline, fixed blocks hatched); at each block
    centroid two perpendicular bars lie along the principal directions, each
    as long as its principal stress is large (one scale for the whole figure,
    stated in the legend as "1 m = 2000 kPa"), blue in compression, red in
    tension. Above ``_MAX_CROSSES`` blocks, one cross per cell of a
    ``_CROSS_GRID`` x ``_CROSS_GRID`` grid is drawn (the block nearest the
    cell centre). The scale draws the largest |sigma| (the peak, often a
    stress concentration at the opening) at its full length of at most 1.5
    block spacings; no bar is clipped.

    Args:
      result: a :class:`~jaxdem.results.Result` whose ``geometry`` holds
        ``stress`` (n, 3) sxx, syy, sxy (kPa, compression positive) and
        ``centroids`` (n, 2) (else the blocks' ``stress`` and centroids).
      path: PNG file to write.

    Returns:
      ``path``, or ``None`` when no block carries a stress (nothing is written).
    """
    geometry = result.geometry or {}
    initial = _polygons(geometry.get("initial_vertices", []))
    final = _polygons(geometry.get("final_vertices", [])) or initial
    n_blocks = max(len(initial), len(final), len(result.blocks))
    stress = _block_array(geometry.get("stress"), [b.get("stress") for b in result.blocks], 3)
    centroids = _block_array(
        geometry.get("centroids"),
        [_centroid(p) for p in final] or [b.get("centroid") for b in result.blocks],
        2,
    )
    n = min(len(stress), len(centroids))
    if n == 0:
        return None
    stress, centroids = stress[:n], centroids[:n]
    excavated = _excavated(result, max(n_blocks, n))
    fixed = _block_mask(
        geometry.get("fixed", [b.get("fixed", False) for b in result.blocks]), max(n_blocks, n)
    )
    sigma, directions = principal_stresses(stress)
    visible = ~excavated[:n] & np.isfinite(sigma).all(axis=1) & np.isfinite(centroids).all(axis=1)
    magnitude = np.abs(sigma).max(axis=1)
    if not (visible & (magnitude > 0)).any():
        return None

    fig, ax = _figure((9, 7.5))
    lw = _line_width(len(final))
    outline = "0.55" if len(final) <= 2000 else "0.7"
    handles = _draw_final_blocks(ax, initial, final, fixed, excavated, lw, outline)

    # Thin to one cross per grid cell, then size the bars by the block spacing.
    shown_polys = [p for p, e in zip(final, excavated, strict=False) if not e]
    sel = visible.copy()
    thinned = sel.sum() > _MAX_CROSSES
    if thinned:
        sel &= _nearest_centre_per_cell(centroids, sel, _CROSS_GRID)
        pts = centroids[visible]
        spacing = float((pts.max(axis=0) - pts.min(axis=0)).max()) / _CROSS_GRID
    else:
        areas = np.array([abs(_area(p)) for p in shown_polys])
        areas = areas[areas > 0]
        spacing = float(np.sqrt(np.median(areas))) if len(areas) else 0.0
    if not spacing > 0:
        spacing = 0.05 * _model_size(shown_polys or [centroids[visible]])
    # One scale for every bar, chosen so that the largest stress (the peak an engineer
    # looks for) is drawn at its full length, at most 1.5 block spacings; nothing is
    # clipped. The scale is a round number of kPa per metre.
    peak = float(magnitude[sel].max())
    kpa_per_m = nice_ceil(peak / (1.5 * spacing))
    segments, colours = stress_crosses(centroids[sel], sigma[sel], directions[sel], kpa_per_m)
    ax.add_collection(
        LineCollection(
            segments, colors=colours, linewidths=0.7 if thinned else 1.2, capstyle="butt", zorder=5
        )
    )
    s_sel = sigma[sel]
    label = f"compression (max {s_sel.max():.4g} kPa)"
    handles.append(Line2D([], [], color=_COMPRESSION, lw=1.5, label=label))
    if (s_sel < 0).any():
        label = f"tension (max {-s_sel.min():.4g} kPa)"
        handles.append(Line2D([], [], color=_TENSION, lw=1.5, label=label))
    note = f"scale: 1 m = {_format_number(kpa_per_m)} kPa\n(largest bar {peak:.4g} kPa)"
    if thinned:
        note += f"\n{int(sel.sum())} of {int(visible.sum())} blocks (grid)"
    handles.append(Line2D([], [], ls="", label=note))

    _finish_axes(ax, initial + shown_polys + [centroids[visible]])
    ax.set_title(f"{result.scene}: principal stresses (compression positive)")
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
    return _save(fig, path)


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
    return _save(fig, path)


def write_figures(result: Result, out_dir: str | Path) -> list[Path]:
    """Write the figures of a solve to ``out_dir``.

    ``blocks.png`` always; ``monitors.png`` (monitor histories) and
    ``sections.png`` (monitors at the end of each stage) when there are
    monitors; ``stresses.png`` (principal-stress crosses) when a block
    carries a stress.

    Returns:
      The paths written, in the order blocks, monitors, stresses, sections.
    """
    out_dir = Path(out_dir)
    paths = [plot_blocks(result, out_dir / "blocks.png")]
    for plot, name in (
        (plot_monitor_history, "monitors.png"),
        (plot_principal_stresses, "stresses.png"),
        (plot_sections, "sections.png"),
    ):
        written = plot(result, out_dir / name)
        if written is not None:
            paths.append(written)
    return paths


def plot_tornado(tornado: dict[str, list[dict[str, Any]]], path: str | Path) -> Path:
    """Tornado plot of a sweep: for each monitor, how far it moves when one parameter
    goes from its low to its high point with the others at their base.

    One panel per monitor (mm: a section's convergence, a point's |u|); one bar
    per parameter, largest swing on top, from the value at the parameter's low
    point (blue) to that at its high point (orange), about the base value (line).
    A bar whose end is a mechanism (no equilibrium) is marked "unstable".

    Args:
      tornado: :attr:`jaxdem.sweep.SweepResult.tornado`.
      path: PNG file to write.
    """
    names = list(tornado)
    rows = max((len(b) for b in tornado.values()), default=1)
    fig = Figure(figsize=(6.5 * len(names), 0.6 * rows + 1.6))
    FigureCanvasAgg(fig)
    for k, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), k + 1)
        bars = tornado[name][::-1]
        base = 1e3 * bars[0]["at_base"] if bars else 0.0
        for i, bar in enumerate(bars):
            for end, color in (("at_low", "C0"), ("at_high", "C1")):
                value = 1e3 * bar[end]
                if math.isfinite(value) and math.isfinite(base):
                    ax.barh(i, value - base, left=base, color=color, height=0.6)
                else:
                    ax.text(base, i, f" unstable ({end[3:]})", va="center", fontsize=8)
        ax.axvline(base, color="k", lw=1)
        ax.set_yticks(range(len(bars)))
        ax.set_yticklabels([f"{b['path']}\n{b['low']:.4g} to {b['high']:.4g}" for b in bars],
                           fontsize=8)
        ax.set_xlabel(f"{name}: convergence or |u| (mm)")
        ax.set_title(name)
    fig.legend(handles=[Patch(color="C0", label="parameter at its low point"),
                        Patch(color="C1", label="parameter at its high point")],
               loc="lower center", ncol=2, fontsize=8, bbox_to_anchor=(0.5, -0.02))
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return _save(fig, path)


def plot_scene_check(scene: Any, path: str | Path) -> Path:
    """Draw a validated scene before solving (``jaxdem check``).

    Blocks are filled by material (legend), fixed blocks hatched, block ids
    written at the centroids when there are fewer than 200 blocks,
    discontinuities drawn by joint, boundaries by condition (fixed: black,
    roller: blue dashed, traction: purple), monitor points and sections
    labelled. A scene with ``[domain]`` also shows its generated rock mass
    (:func:`jaxdem.rockmass.generate`): pieces filled by material, excavated
    pieces light and hatched, joint edges dark, intact cuts light; bolts as
    thick lines, supported excavations outlined thick green, the water table
    as a blue line.

    Args:
      scene: a :class:`jaxdem.scene.Scene` (or any object with ``blocks``
        (each with ``vertices`` (n, 2) m, ``material``, ``fixed``),
        ``discontinuities`` (``start``, ``end``, ``joint``), ``boundaries``
        (``start``, ``end``, ``condition``) and ``monitors`` (``name``,
        ``kind`` "point" with ``point``, or "section" with ``start``/``end``)).
      path: PNG file to write.

    Returns:
      ``path`` as a :class:`~pathlib.Path`.
    """
    blocks = list(getattr(scene, "blocks", None) or [])
    polys = [np.asarray(_get(b, "vertices", 0), dtype=float).reshape(-1, 2) for b in blocks]
    materials = [str(_get(b, "material", 1, "")) for b in blocks]
    fixed = np.array([bool(_get(b, "fixed", 2, False)) for b in blocks], dtype=bool)

    pieces: list[Any] = []
    if getattr(scene, "domain", None) is not None and hasattr(scene, "joints"):
        from jaxdem.rockmass import generate

        pieces = generate(scene).pieces
    piece_polys = [np.asarray(p.vertices, dtype=float) for p in pieces]
    n_all = len(polys) + len(piece_polys)

    fig, ax = _figure((9, 7.5))
    lw = _line_width(n_all)
    handles: list[Any] = []

    material_names = list(dict.fromkeys(materials + [str(p.material) for p in pieces]))
    colour_of = {
        m: matplotlib.colormaps["Pastel1" if len(material_names) <= 9 else "Set3"](k % 12)
        for k, m in enumerate(material_names)
    }
    handles += [
        Patch(facecolor=colour_of[m], edgecolor="0.2", label=f"material {m}")
        for m in material_names
    ]
    if piece_polys:
        dug = [p.excavation is not None for p in pieces]
        ax.add_collection(
            PolyCollection(
                piece_polys,
                closed=True,
                facecolors=[
                    "white" if d else colour_of[str(p.material)]
                    for p, d in zip(pieces, dug, strict=True)
                ],
                edgecolors="none",
                alpha=0.85,
                zorder=1,
            )
        )
        dug_polys = [v for v, d in zip(piece_polys, dug, strict=True) if d]
        if dug_polys:
            ax.add_collection(
                PolyCollection(
                    dug_polys,
                    closed=True,
                    facecolors="none",
                    edgecolors="0.6",
                    hatch="..",
                    linewidths=0.0,
                    zorder=1.5,
                )
            )
            handles.append(Patch(facecolor="white", edgecolor="0.6", hatch="..", label="excavated"))
        segs: dict[str, list[np.ndarray]] = {"joint": [], "intact": [], "outer": []}
        for p, v in zip(pieces, piece_polys, strict=True):
            w = np.roll(v, -1, axis=0)
            for k, (kind, _) in enumerate(p.edge_labels):
                segs[kind].append(np.array([v[k], w[k]]))
        edge_style = {
            "intact": ("0.7", 0.5 * lw, "intact rock cut"),
            "joint": ("0.1", 1.4 * lw, "joint"),
            "outer": ("0.1", 1.4 * lw, None),
        }
        for kind, (colour, width, label) in edge_style.items():
            if segs[kind]:
                ax.add_collection(
                    LineCollection(segs[kind], colors=colour, linewidths=width, zorder=2)
                )
                if label:
                    handles.append(Line2D([], [], color=colour, lw=max(width, 0.8), label=label))

    if polys:
        ax.add_collection(
            PolyCollection(
                polys,
                closed=True,
                facecolors=[colour_of[m] for m in materials],
                edgecolors="0.2",
                linewidths=lw,
                alpha=0.85,
                zorder=1,
            )
        )
        fixed_polys = [p for p, f in zip(polys, fixed, strict=True) if f]
        if fixed_polys:
            ax.add_collection(
                PolyCollection(
                    fixed_polys,
                    closed=True,
                    facecolors="none",
                    edgecolors="0.2",
                    hatch="///",
                    linewidths=lw,
                    zorder=2,
                )
            )
            handles.append(Patch(facecolor="none", edgecolor="0.2", hatch="///", label="fixed"))
    if n_all < 200:
        fontsize = 8 if n_all < 50 else 6
        for i, p in enumerate(polys + piece_polys):
            c = _centroid(p)
            ax.text(
                c[0],
                c[1],
                str(i),
                ha="center",
                va="center",
                fontsize=fontsize,
                fontweight="bold",
                color="0.15",
                zorder=10,
            )

    domain = getattr(scene, "domain", None)
    outline = _get(domain, "outline", None, None) if domain is not None else None
    if outline is not None and len(outline):
        ring = np.asarray(outline, dtype=float).reshape(-1, 2)
        ring = np.vstack([ring, ring[:1]])
        ax.plot(ring[:, 0], ring[:, 1], color="0.3", lw=1.0, ls="--", zorder=1)
        handles.append(Line2D([], [], color="0.3", lw=1.0, ls="--", label="domain"))

    excavations = {str(e.name): e for e in getattr(scene, "excavations", None) or []}
    supported = [str(s.excavation) for s in getattr(scene, "supports", None) or []]
    for name in dict.fromkeys(supported):
        if name in excavations:
            ring = np.asarray(excavations[name].vertices, dtype=float)
            ring = np.vstack([ring, ring[:1]])
            ax.plot(ring[:, 0], ring[:, 1], color="tab:green", lw=3.0, zorder=5)
    if any(name in excavations for name in supported):
        handles.append(Line2D([], [], color="tab:green", lw=3.0, label="support pressure"))

    discontinuities = list(getattr(scene, "discontinuities", None) or [])
    joints = [str(_get(d, "joint", 2, "")) for d in discontinuities]
    for k, joint in enumerate(dict.fromkeys(joints)):
        segs_j = [_segment(d) for d, j in zip(discontinuities, joints, strict=True) if j == joint]
        colour = f"C{(k + 3) % 10}"
        ax.add_collection(LineCollection(segs_j, colors=colour, linewidths=1.5, zorder=3))
        handles.append(Line2D([], [], color=colour, lw=1.5, label=f"joint {joint}"))

    bolts = list(getattr(scene, "bolts", None) or [])
    if bolts:
        ax.add_collection(
            LineCollection(
                [_segment(b) for b in bolts], colors="tab:brown", linewidths=3.0, zorder=6
            )
        )
        handles.append(Line2D([], [], color="tab:brown", lw=3.0, label="bolt"))

    water = getattr(scene, "water", None)
    if water is not None:
        table = np.asarray(water.table, dtype=float)
        ax.plot(table[:, 0], table[:, 1], color="tab:blue", lw=2.0, zorder=6)
        handles.append(Line2D([], [], color="tab:blue", lw=2.0, label="water table"))
    for k, st in enumerate(getattr(scene, "stages", None) or []):
        table = getattr(st, "water_table", None)
        if table is not None:
            table = np.asarray(table, dtype=float)
            ax.plot(table[:, 0], table[:, 1], color="tab:blue", lw=1.5, ls=(0, (4, 2)),
                    alpha=0.8, zorder=6, gid="water table")
            handles.append(Line2D([], [], color="tab:blue", lw=1.5, ls=(0, (4, 2)),
                                  label=f"water table from stage {k + 1} ({st.name})"))

    boundary_style = {
        "fixed": dict(color="k", lw=3.5, ls="-"),
        "roller": dict(color="tab:blue", lw=3.0, ls="--"),
        "traction": dict(color="tab:purple", lw=3.0, ls="-"),
    }
    boundaries = list(getattr(scene, "boundaries", None) or [])
    conditions = [str(_get(b, "condition", 2, "fixed")) for b in boundaries]
    for condition in dict.fromkeys(conditions):
        style = boundary_style.get(condition, dict(color="0.4", lw=3.0, ls="-"))
        segs_b = [
            _segment(b) for b, c in zip(boundaries, conditions, strict=True) if c == condition
        ]
        ax.add_collection(
            LineCollection(
                segs_b,
                colors=style["color"],
                linewidths=style["lw"],
                linestyles=style["ls"],
                zorder=4,
            )
        )
        handles.append(Line2D([], [], label=f"{condition} boundary", **style))

    monitors: dict[str, Any] = {}
    for m in getattr(scene, "monitors", None) or []:
        kind = _get(m, "kind", None, "point")
        name = str(_get(m, "name", None, "monitor"))
        if kind == "section":
            monitors[name] = np.array([_get(m, "start", None), _get(m, "end", None)], dtype=float)
        else:
            monitors[name] = np.asarray(_get(m, "point", None), dtype=float)

    everything = polys + piece_polys + [_segment(d) for d in discontinuities]
    everything += [_segment(b) for b in boundaries]
    size = _model_size(everything)
    handles += _draw_monitors(ax, monitors, size)

    _finish_axes(ax, everything)
    _place_labels(fig, ax, [t for t in ax.texts if t.get_gid() == "monitor label"])
    name = getattr(scene, "name", None) or "scene"
    n_lines = len(discontinuities)
    lines = "discontinuity" if n_lines == 1 else "discontinuities"
    title = f"{name}: {n_all} blocks"
    if piece_polys:
        title += f" ({len(piece_polys)} generated)"
    ax.set_title(f"{title}, {n_lines} {lines}")
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
    return _save(fig, path)


# ---------------------------------------------------------------------------
# Helpers


def nice_magnification(size: float, u_max: float, fraction: float = 0.05) -> float:
    """Arrow scale so that ``u_max`` draws as about ``fraction * size``, rounded.

    Rounded to the nearest 1, 2, 2.5 or 5 times a power of ten, never below 1;
    1 when nothing moved.
    """
    if not (u_max > 0 and np.isfinite(u_max) and size > 0):
        return 1.0
    raw = fraction * size / u_max
    if raw <= 1.0:
        return 1.0
    exponent = math.floor(math.log10(raw))
    # The nearest of 1, 2, 2.5, 5, 10 times 10**exponent, on a log scale.
    steps = np.array([1.0, 2.0, 2.5, 5.0, 10.0])
    step = steps[np.argmin(np.abs(np.log(steps * 10.0**exponent / raw)))]
    return float(step * 10.0**exponent)


def _format_magnification(mag: float) -> str:
    return f"{mag:.0f}" if mag >= 1 and float(mag).is_integer() else f"{mag:g}"


def _status_text(result: Result) -> str:
    """'stable', 'UNSTABLE: blocks 3, 7 moving' or 'NOT CONVERGED (iteration_limit)'."""
    if result.status not in ("converged", "mechanism"):
        return f"NOT CONVERGED ({result.status})"
    if result.stable and not result.moving_blocks:
        return "stable"
    ids = [str(int(i)) for i in result.moving_blocks]
    if not ids:
        return "UNSTABLE"
    shown = ", ".join(ids[:10])
    if len(ids) > 10:
        shown += f", ... (+{len(ids) - 10} more)"
    word = "block" if len(ids) == 1 else "blocks"
    return f"UNSTABLE: {word} {shown} moving"


def _polygons(vertices: Sequence[Any]) -> list[np.ndarray]:
    return [np.asarray(v, dtype=float).reshape(-1, 2) for v in vertices]


def _line_width(n_blocks: int) -> float:
    if n_blocks <= 200:
        return 0.9
    if n_blocks <= 2000:
        return 0.5
    return 0.25


def _centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid of a simple polygon (vertex mean when degenerate)."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    if abs(area) < 1e-300:
        return poly.mean(axis=0)
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)


def _model_size(shapes: Sequence[np.ndarray]) -> float:
    """Largest side of the bounding box of all shapes (m); 1 when empty."""
    pts = [np.asarray(s, dtype=float).reshape(-1, 2) for s in shapes if np.size(s)]
    if not pts:
        return 1.0
    allpts = np.concatenate(pts)
    allpts = allpts[np.isfinite(allpts).all(axis=1)]
    if not len(allpts):
        return 1.0
    extent = allpts.max(axis=0) - allpts.min(axis=0)
    return float(max(extent.max(), 1e-9))


def _finish_axes(ax: Any, shapes: Sequence[np.ndarray]) -> None:
    pts = [np.asarray(s, dtype=float).reshape(-1, 2) for s in shapes if np.size(s)]
    if pts:
        allpts = np.concatenate(pts)
        allpts = allpts[np.isfinite(allpts).all(axis=1)]
        if len(allpts):
            lo, hi = allpts.min(axis=0), allpts.max(axis=0)
            pad = 0.05 * max(float((hi - lo).max()), 1e-9)
            ax.set_xlim(lo[0] - pad, hi[0] + pad)
            ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def _draw_contacts(ax: Any, contacts: dict[str, Any], n_blocks: int) -> list[Any]:
    """Contact points by state; returns legend handles with counts."""
    points = np.asarray(contacts.get("points", np.zeros((0, 2))), dtype=float).reshape(-1, 2)
    state = np.asarray(contacts.get("state", np.zeros(len(points))), dtype=int).reshape(-1)
    if not len(points):
        return []
    # With a reference state (in-situ stress, stages), an open contact is news only where
    # it carried a force then: corners in the far field that never touched are left out.
    fn0 = np.asarray(contacts.get("initial_fn", np.full(len(points), np.nan)),
                     dtype=float).reshape(-1)
    quiet = np.zeros(len(points), dtype=bool)
    if len(fn0) == len(points) and np.isfinite(fn0).any():
        scale = float(np.nanmax(np.abs(fn0))) if np.isfinite(fn0).any() else 0.0
        quiet = (state == OPEN) & ~(fn0 > 1e-6 * scale)
    marker_size = float(np.clip(400.0 / np.sqrt(len(points)), 1.0, 25.0))
    handles = []
    for code in (STICK, SLIP, OPEN):
        colour, label = _STATE_STYLE[code]
        sel = (state == code) & ~quiet
        count = int(sel.sum())
        if code == OPEN and quiet.any():
            label = "opened"
            count_text = (f"{count}; {int(quiet.sum())} open that carried\nno force at the "
                          "start not drawn")
        else:
            count_text = f"{count}"
        # Stuck springs are most of a large model and the least news: draw them smaller.
        size = marker_size if code != STICK or len(points) < 2000 else 0.4 * marker_size
        if count:
            ax.scatter(
                points[sel, 0],
                points[sel, 1],
                s=size,
                c=colour,
                marker="o",
                linewidths=0,
                zorder=6,
            )
        handles.append(
            Line2D([], [], ls="", marker="o", color=colour, ms=5, label=f"{label} ({count_text})")
        )
    return handles


def _draw_displacements(
    ax: Any,
    result: Result,
    initial: list[np.ndarray],
    size: float,
    magnification: float | None,
    excavated: np.ndarray | None = None,
) -> Any:
    """Centroid displacement arrows from the initial centroids; returns a legend handle.

    Excavated blocks (``excavated[k]`` or ``"excavated"`` in the block's dict) get none.
    """
    if not result.blocks:
        return None
    centroids, u = [], []
    for k, b in enumerate(result.blocks):
        if b.get("excavated") or (excavated is not None and k < len(excavated) and excavated[k]):
            continue
        c = b.get("centroid")
        if c is None and k < len(initial):
            c = _centroid(initial[k])
        if c is None:
            continue
        centroids.append(np.asarray(c, dtype=float)[:2])
        u.append(np.asarray(b.get("u", [0.0, 0.0, 0.0]), dtype=float)[:2])
    if not centroids:
        return None
    centroids_a, u_a = np.array(centroids), np.array(u)
    norm = np.linalg.norm(u_a, axis=1)
    finite = np.isfinite(norm)
    u_max = float(norm[finite].max()) if finite.any() else 0.0
    if u_max <= 0.0:
        return None
    mag = nice_magnification(size, u_max) if magnification is None else float(magnification)
    # Arrows shorter than 1% of the largest are noise at this scale: leave them out.
    sel = finite & (norm > 0.01 * u_max)
    thinned = sel.sum() > _MAX_ARROWS
    if thinned:
        sel = _largest_per_cell(centroids_a, np.where(sel, norm, -1.0), _ARROW_GRID) & sel
    ax.quiver(
        centroids_a[sel, 0],
        centroids_a[sel, 1],
        mag * u_a[sel, 0],
        mag * u_a[sel, 1],
        angles="xy",
        scale_units="xy",
        scale=1.0,
        color=_ARROW_COLOUR,
        width=0.0025 if thinned else 0.003,
        zorder=7,
    )
    return Line2D(
        [],
        [],
        color=_ARROW_COLOUR,
        lw=1.5,
        marker=">",
        ms=5,
        label=f"displacements x {_format_magnification(mag)}\n(max {format_length(u_max)})"
        + ("\nlargest per grid cell" if thinned else ""),
    )


def _largest_per_cell(points: np.ndarray, value: np.ndarray, n_cells: int) -> np.ndarray:
    """Mask of the point with the largest ``value`` in each cell of an n x n grid."""
    lo = points.min(axis=0)
    span = np.maximum(points.max(axis=0) - lo, 1e-12)
    ij = np.minimum((n_cells * (points - lo) / span).astype(int), n_cells - 1)
    cell = ij[:, 0] * n_cells + ij[:, 1]
    order = np.lexsort((-value, cell))  # by cell, largest value first within a cell
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    keep = np.zeros(len(points), dtype=bool)
    keep[order[first]] = True
    return keep


def _draw_monitors(ax: Any, monitors: dict[str, Any], size: float,
                   moved: dict[str, Any] | None = None) -> list[Any]:
    """Monitor points (diamonds) and sections (dashed lines), labelled.

    ``moved``: name -> a point monitor's displacement [ux, uy] (m); the diamond is then
    drawn where the rock point is now, with a thin line from its initial place (light
    diamond) when it moved visibly. Labels carry gid "monitor label" so that
    :func:`_place_labels` can move them apart.
    """
    if not monitors:
        return []
    moved = moved or {}
    any_point = any_section = False
    for name, where in monitors.items():
        xy = np.asarray(where, dtype=float)
        if xy.size == 4:
            seg = xy.reshape(2, 2)
            ax.plot(
                seg[:, 0],
                seg[:, 1],
                color=_MONITOR_COLOUR,
                ls="--",
                lw=1.5,
                marker="|",
                ms=10,
                zorder=8,
            )
            # Label at the "to" end: the middle is often where a point monitor sits.
            _monitor_label(ax, name, seg[1])
            any_section = True
        elif xy.size == 2:
            start = xy.reshape(2)
            u = moved.get(name)
            p = start
            if u is not None and np.all(np.isfinite(np.asarray(u, dtype=float)[:2])):
                p = start + np.asarray(u, dtype=float)[:2]
                if np.hypot(*(p - start)) > 0.005 * size:
                    ax.plot([start[0], p[0]], [start[1], p[1]], color=_MONITOR_COLOUR, lw=0.8,
                            ls=":", zorder=8)
                    ax.plot(start[0], start[1], ls="", marker="D", ms=5, mfc="none",
                            mec=_MONITOR_COLOUR, mew=0.6, alpha=0.6, zorder=8)
            ax.plot(
                p[0],
                p[1],
                ls="",
                marker="D",
                ms=6,
                mfc="white",
                mec=_MONITOR_COLOUR,
                mew=1.5,
                zorder=8,
                gid=f"monitor point {name}",
            )
            _monitor_label(ax, name, p)
            any_point = True
    handles = []
    if any_point:
        handles.append(
            Line2D(
                [], [], ls="", marker="D", mfc="white", mec=_MONITOR_COLOUR, label="monitor point"
            )
        )
    if any_section:
        handles.append(Line2D([], [], color=_MONITOR_COLOUR, ls="--", label="monitor section"))
    return handles


def _monitor_label(ax: Any, name: str, at: np.ndarray) -> None:
    ax.annotate(str(name), xy=at, xytext=(5, 4), textcoords="offset points",
                color=_MONITOR_COLOUR, fontsize=8, zorder=9, gid="monitor label",
                bbox=dict(boxstyle="square,pad=0.1", fc="white", ec="none", alpha=0.7))


# Offsets (points) tried for a label, nearest first: right-above, right-below,
# left-above, left-below, then further out.
_LABEL_OFFSETS = [(5, 4, "left"), (5, -12, "left"), (-5, 4, "right"), (-5, -12, "right"),
                  (5, 16, "left"), (5, -24, "left"), (-5, 16, "right"), (-5, -24, "right"),
                  (5, 28, "left"), (5, -36, "left"), (-5, 28, "right"), (-5, -36, "right")]


def _place_labels(fig: Figure, ax: Any, texts: list[Any]) -> None:
    """Move annotation labels apart: each takes the first offset of ``_LABEL_OFFSETS``
    whose box overlaps no label placed before it (greedy, in drawing order)."""
    if len(texts) < 2:
        return
    renderer = fig.canvas.get_renderer()
    ax.apply_aspect()
    placed: list[Any] = []
    for text in texts:
        for dx, dy, ha in _LABEL_OFFSETS:
            text.set_position((dx, dy))
            text.set_horizontalalignment(ha)
            box = text.get_window_extent(renderer).expanded(1.05, 1.1)
            if not any(box.overlaps(other) for other in placed):
                break
        placed.append(text.get_window_extent(renderer))


def _draw_water_table(ax: Any, table: Any, shapes: Sequence[np.ndarray]) -> list[Any]:
    """The water table (polyline, m) as a blue line with a triangle marker; [] without."""
    if table is None or not np.size(table):
        return []
    t = np.asarray(table, dtype=float).reshape(-1, 2)
    ax.plot(t[:, 0], t[:, 1], color="tab:blue", lw=1.8, zorder=6.8, gid="water table")
    mid = t[len(t) // 2] if len(t) > 2 else t.mean(axis=0)
    ax.plot(mid[0], mid[1], ls="", marker="v", ms=8, color="tab:blue", zorder=6.9)
    return [Line2D([], [], color="tab:blue", lw=1.8, marker="v", ms=6, label="water table")]


def format_length(metres: float) -> str:
    """A displacement for a legend, without exponents: "4.05 mm", "1.000 m", "12 um"."""
    x = abs(float(metres))
    if not math.isfinite(x):
        return f"{metres} m"
    if x >= 1.0:
        return f"{metres:.3f} m"
    mm = 1e3 * metres
    if x >= 0.1:
        return f"{mm:.0f} mm"
    if x >= 1e-4:
        return f"{mm:.3g} mm"
    return f"{1e6 * metres:.3g} um"


def principal_stresses(stress: Any) -> tuple[np.ndarray, np.ndarray]:
    """Principal values and directions of 2D stresses [sxx, syy, sxy].

    Args:
      stress: (n, 3) or (3,) array: sxx, syy, sxy (any consistent units).

    Returns:
      ``(sigma, directions)``: ``sigma`` (n, 2) principal values, major
      (largest, i.e. most compressive with compression positive) first, and
      ``directions`` (n, 2, 2) with ``directions[i, k]`` the unit vector of
      ``sigma[i, k]`` (its sign is arbitrary). Eigen-decomposition of the
      symmetric tensor ``[[sxx, sxy], [sxy, syy]]`` by :func:`numpy.linalg.eigh`.
    """
    s = np.asarray(stress, dtype=float).reshape(-1, 3)
    tensor = np.empty((len(s), 2, 2))
    tensor[:, 0, 0], tensor[:, 1, 1] = s[:, 0], s[:, 1]
    tensor[:, 0, 1] = tensor[:, 1, 0] = s[:, 2]
    finite = np.isfinite(tensor).all(axis=(1, 2))
    values = np.full((len(s), 2), np.nan)
    vectors = np.full((len(s), 2, 2), np.nan)
    if finite.any():
        w, v = np.linalg.eigh(tensor[finite])  # ascending; eigenvectors are columns
        values[finite] = w[:, ::-1]
        vectors[finite] = np.transpose(v[:, :, ::-1], (0, 2, 1))
    return values, vectors


def stress_crosses(
    centres: np.ndarray,
    sigma: np.ndarray,
    directions: np.ndarray,
    kpa_per_m: float,
    clip: float | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Bars of principal-stress crosses: (2n, 2, 2) segments and their colours.

    Each bar is centred on its block's centroid, lies along its principal
    direction and is ``|sigma| / kpa_per_m`` long (|sigma| clipped at
    ``clip`` when given); blue for compression (sigma > 0), red for tension.
    """
    mag = np.abs(sigma)
    if clip is not None:
        mag = np.minimum(mag, clip)
    half = 0.5 * mag / kpa_per_m  # (n, 2)
    arm = directions * half[:, :, None]  # (n, 2, 2)
    c = centres[:, None, :]
    segments = np.stack([c - arm, c + arm], axis=2).reshape(-1, 2, 2)
    colours = [_COMPRESSION if v > 0 else _TENSION for v in sigma.reshape(-1)]
    return segments, colours


def nice_ceil(x: float) -> float:
    """The smallest round number (1, 1.5, 2, 2.5, 3, 4, 5, 6 or 8 times a power of ten)
    that is at least ``x``; 1 when ``x`` is not positive."""
    if not (x > 0 and np.isfinite(x)):
        return 1.0
    exponent = math.floor(math.log10(x))
    for step in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        value = step * 10.0**exponent
        if value >= x * (1 - 1e-12):
            return float(value)
    return float(10.0 ** (exponent + 1))


def _format_number(x: float) -> str:
    return f"{x:.0f}" if float(x).is_integer() else f"{x:g}"


def _block_mask(values: Any, n: int) -> np.ndarray:
    """A bool per block, padded with False (or cut) to ``n``."""
    out = np.zeros(n, dtype=bool)
    given = np.asarray(values if values is not None else [], dtype=bool).reshape(-1)
    m = min(n, given.size)
    out[:m] = given[:m]
    return out


def _excavated(result: Result, n: int) -> np.ndarray:
    """Excavated blocks: ``geometry["excavated"]``, else the blocks' ``"excavated"`` flags."""
    given = (result.geometry or {}).get("excavated")
    if given is None:
        given = [bool(b.get("excavated", False)) for b in result.blocks]
    return _block_mask(given, n)


def _block_array(values: Any, fallback: Sequence[Any], width: int) -> np.ndarray:
    """(n, width) float array from ``values``, else from the per-block ``fallback``."""
    if values is not None and np.size(values):
        return np.asarray(values, dtype=float).reshape(-1, width)
    if fallback and all(v is not None for v in fallback):
        return np.asarray(fallback, dtype=float).reshape(-1, width)
    return np.zeros((0, width))


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())


def _nearest_centre_per_cell(points: np.ndarray, valid: np.ndarray, n_cells: int) -> np.ndarray:
    """Mask of the valid point nearest its cell's centre, per cell of an n x n grid."""
    keep = np.zeros(len(points), dtype=bool)
    idx = np.nonzero(valid)[0]
    if not len(idx):
        return keep
    pts = points[idx]
    lo = pts.min(axis=0)
    span = np.maximum(pts.max(axis=0) - lo, 1e-12)
    frac = n_cells * (pts - lo) / span
    ij = np.minimum(frac.astype(int), n_cells - 1)
    dist = np.linalg.norm(frac - (ij + 0.5), axis=1)
    keep[idx] = _largest_per_cell(pts, -dist, n_cells)
    return keep


def _draw_final_blocks(
    ax: Any,
    initial: list[np.ndarray],
    final: list[np.ndarray],
    fixed: np.ndarray,
    excavated: np.ndarray,
    lw: float,
    colour: str,
) -> list[Any]:
    """Final outlines of the blocks left, fixed ones hatched, the opening dashed."""
    handles: list[Any] = []
    kept = [(p, bool(f)) for p, f, e in zip(final, fixed, excavated, strict=False) if not e]
    if kept:
        ax.add_collection(
            PolyCollection(
                [p for p, _ in kept],
                closed=True,
                facecolors="none",
                edgecolors=colour,
                linewidths=lw,
                zorder=2,
            )
        )
        handles.append(Line2D([], [], color=colour, lw=1.0, label="final"))
        fixed_polys = [p for p, f in kept if f]
        if fixed_polys:
            ax.add_collection(
                PolyCollection(
                    fixed_polys,
                    closed=True,
                    facecolors="0.85",
                    edgecolors=colour,
                    hatch="///",
                    linewidths=lw,
                    zorder=0,
                )
            )
            handles.append(Patch(facecolor="0.85", edgecolor=colour, hatch="///", label="fixed"))
    opening = [p for p, e in zip(initial, excavated, strict=False) if e]
    if opening:
        ax.add_collection(
            PolyCollection(
                opening,
                closed=True,
                facecolors="none",
                edgecolors="0.65",
                linestyles="--",
                linewidths=max(0.5 * lw, 0.3),
                zorder=1,
            )
        )
        handles.append(
            Line2D([], [], color="0.65", lw=1.0, ls="--", label=f"excavated ({len(opening)})")
        )
    return handles


def _bolt_segments(geometry: dict[str, Any]) -> list[np.ndarray]:
    return [np.asarray(b, dtype=float).reshape(2, 2) for b in geometry.get("bolts") or []]


def _draw_bolts(ax: Any, result: Result, segments: list[np.ndarray], size: float) -> list[Any]:
    """Bolts as lines between their anchors, by state, labelled with force (kN)."""
    if not segments:
        return []
    info = list(result.bolts or [])
    states = [
        str((info[k] if k < len(info) else {}).get("state", "elastic"))
        for k in range(len(segments))
    ]
    handles = []
    for state in dict.fromkeys(list(_BOLT_STYLE) + states):
        sel = [k for k, s in enumerate(states) if s == state]
        if not sel:
            continue
        colour, ls = _BOLT_STYLE.get(state, ("0.3", "-"))
        ax.add_collection(
            LineCollection(
                [segments[k] for k in sel],
                colors=colour,
                linestyles=ls,
                linewidths=2.5 if len(segments) <= 200 else 1.2,
                zorder=6.5,
            )
        )
        handles.append(
            Line2D([], [], color=colour, ls=ls, lw=2.5, label=f"bolt {state} ({len(sel)})")
        )
    forces = np.array(
        [
            float((info[k] if k < len(info) else {}).get("force", np.nan))
            for k in range(len(segments))
        ]
    )
    finite = np.nonzero(np.isfinite(forces))[0]
    if len(finite) > _MAX_BOLT_LABELS:
        finite = finite[np.argsort(-np.abs(forces[finite]))[:_MAX_BOLT_LABELS]]
        handles.append(Line2D([], [], ls="", label=f"forces of the {_MAX_BOLT_LABELS} largest"))
    for k in finite:
        mid = segments[k].mean(axis=0)
        ax.annotate(
            f"{forces[k]:.3g} kN",
            xy=mid,
            xytext=(3, 3),
            textcoords="offset points",
            fontsize=7,
            color=_BOLT_STYLE.get(states[k], ("0.3", "-"))[0],
            zorder=9,
        )
    return handles


def _monitor_kind(result: Result, name: str) -> str:
    entry = (result.monitors or {}).get(name) or {}
    if "convergence" in entry:
        return "section"
    where = (result.geometry or {}).get("monitors", {}).get(name)
    if where is not None and np.size(where) == 4:
        return "section"
    return "point"


def _get(obj: Any, name: str, index: int | None, default: Any = None) -> Any:
    """``obj.name``, else ``obj[name]`` (mapping), else ``obj[index]`` (tuple), else default."""
    if hasattr(obj, name):
        return getattr(obj, name)
    if isinstance(obj, dict):
        return obj.get(name, default)
    if index is not None and isinstance(obj, (tuple, list)) and len(obj) > index:
        return obj[index]
    return default


def _segment(item: Any) -> np.ndarray:
    """(2, 2) segment of a discontinuity or boundary: ``start``/``end`` or a tuple."""
    start = _get(item, "start", 0)
    end = _get(item, "end", 1)
    return np.array([start, end], dtype=float).reshape(2, 2)


def _figure(figsize: tuple[float, float]) -> tuple[Figure, Any]:
    """A figure outside pyplot (nothing global to close), drawn by Agg."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


#: Called as ``inspect(fig, path)`` after each figure is saved, before it is released
#: (tests look at the drawn artists through it); None: nothing.
inspect = None


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=DPI, bbox_inches="tight")
        if inspect is not None:
            inspect(fig, path)
    finally:
        fig.clear()  # release the artists now rather than at garbage collection
    return path
