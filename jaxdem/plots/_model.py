"""Figures of the solved block model: ``blocks.png`` (:func:`plot_blocks`: outlines,
walls, contacts, displacements, bolts, supports, monitors, moving blocks, on the whole
model and, with excavations, on a second panel around them) and ``stresses.png``
(:func:`plot_principal_stresses`: principal-stress crosses that fit their blocks, with
:func:`principal_stresses`, :func:`stress_crosses` and :func:`block_room`).

A :class:`~jaxdem.results.Result` (its ``geometry``, ``blocks``, ``bolts``, ``monitors``)
comes in, one PNG goes out; the layers are drawn by :mod:`jaxdem.plots._layers` on the
canvas of :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from jaxdem.plots._canvas import (
    finish_axes,
    format_number,
    line_width,
    model_size,
    nearest_centre_per_cell,
    new_figure,
    nice_ceil,
    place_bolt_labels,
    place_labels,
    polygon_centroid,
    polygons,
    save_figure,
    zoom_window,
)
from jaxdem.plots._layers import (
    bolt_segments,
    draw_bolts,
    draw_contacts,
    draw_displacements,
    draw_final_blocks,
    draw_monitors,
    draw_moving,
    draw_supports,
    draw_unbalanced,
    draw_water_table,
)
from jaxdem.plots._loose import draw_loose_blocks
from jaxdem.results import Result

_COMPRESSION = "tab:blue"
_TENSION = "tab:red"
# Above _MAX_CROSSES blocks, one principal-stress cross per cell of a grid.
_MAX_CROSSES = 2500
_CROSS_GRID = 50


def plot_blocks(result: Result, path: str | Path, *, magnification: float | None = None,
                view: Sequence[float] | None = None) -> Path:
    """Draw the block model after the solve.

    Initial outlines in light grey, final (deformed, true scale) outlines in
    dark grey, fixed blocks shaded and hatched, excavated blocks left out
    (only the opening drawn, as a light dashed outline of their initial
    vertices), walls as thick black lines, contact points coloured by state
    (stuck green, slipping orange, open red, with counts in the legend),
    centroid displacement vectors as arrows, bolts as lines between their
    current anchors coloured by state (elastic, yielded, pulled out; not installed
    light grey dotted) and labelled with their force in kN beside the bolt, support
    pressure as a band and arrows on the excavation boundary with its value, blocks
    still moving at a mechanism filled and outlined red (a small one also ringed), and
    those out of balance where the analysis stopped at the iteration limit goldenrod,
    monitor points and sections labelled.

    When the scene has excavations, a second panel shows the model around them (their
    bounding box grown by 0.6 times its size on every side, and the bolts that start
    there), its frame drawn on the whole model; the bolt forces are written there.
    ``view`` gives that panel's window instead.

    Args:
      result: a :class:`~jaxdem.results.Result` with ``geometry`` filled in.
      path: PNG file to write (parent folders are created).
      magnification: scale of the displacement arrows. By default chosen so
        that the largest arrow is about 5% of the model size, rounded to 1, 2,
        2.5 or 5 times a power of ten, and never below 1 (true scale: a block
        that travelled far has its arrow end at its final centroid). Shown in
        the legend as "displacements x 250".
      view: (x0, x1, y0, y1) m, the window of the second panel; None: around the
        excavations (no second panel without excavations or where they fill most of
        the model).

    Returns:
      ``path`` as a :class:`~pathlib.Path`.
    """
    model = _ModelLayers.of(result)
    window = _check_view(view) if view is not None else model.zoom()
    if window is None:
        fig, ax = new_figure((9, 7.5))
        axes = [ax]
    else:
        fig, axes = _two_panels(model.extent(), window)
    handles = model.draw(axes[0], magnification, labels=window is None)
    if window is not None:
        zoom = axes[1]
        x0, x1, y0, y1 = window
        # The panel's own arrow scale (about 5% of its size), unless one is given.
        zoom_handles = model.draw(zoom, magnification, labels=True,
                                  size=max(x1 - x0, y1 - y0))
        zoom.set_xlim(x0, x1)
        zoom.set_ylim(y0, y1)
        title = "around the excavations" if view is None else "view"
        arrows = [h.get_label() for h in zoom_handles if h.get_gid() == "displacements"]
        if arrows:
            title += f" ({arrows[0].splitlines()[0]})"
        zoom.set_title(title, fontsize=10)
        axes[0].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="tab:blue",
                                    lw=1.2, ls="-", zorder=10, gid="zoom frame"))
    title = f"{result.scene}: {_status_text(result)}"
    if window is None:
        axes[0].set_title(title)
    else:
        fig.suptitle(title)
    legend = dict(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    axes[-1].legend(handles=handles, **legend)
    if window is not None:
        # Lay the panels out now and keep them there: the labels are placed in pixels.
        fig.draw_without_rendering()
        fig.set_layout_engine("none")
    crowded = sum(model.place_labels(fig, ax) for ax in axes)
    if crowded:
        handles.append(Line2D([], [], ls="", label=f"{crowded} bolt forces not written\n"
                              "(no room beside the bolt)"))
        axes[-1].legend(handles=handles, **legend)
    return save_figure(fig, path)


def _check_view(view: Sequence[float]) -> tuple[float, float, float, float]:
    x0, x1, y0, y1 = (float(v) for v in view)
    if not (np.isfinite([x0, x1, y0, y1]).all() and x1 > x0 and y1 > y0):
        raise ValueError(f"view must be x0 x1 y0 y1 with x0 < x1 and y0 < y1 (got {view})")
    return x0, x1, y0, y1


def _two_panels(extent: np.ndarray, window: tuple[float, float, float, float]
                ) -> tuple[Any, list[Any]]:
    """A figure of two panels side by side, the whole model and the zoomed window, each as
    wide as its aspect ratio asks for at a common height."""
    (mx0, mx1), (my0, my1) = extent
    x0, x1, y0, y1 = window
    aspect_model = (mx1 - mx0) / max(my1 - my0, 1e-9)
    aspect_zoom = (x1 - x0) / max(y1 - y0, 1e-9)
    height = 6.0
    widths = [float(np.clip(height * a, 3.0, 11.0)) for a in (aspect_model, aspect_zoom)]
    fig = Figure(figsize=(sum(widths) + 3.5, height + 1.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, width_ratios=widths)
    return fig, list(axes)


@dataclasses.dataclass
class _ModelLayers:
    """The layers of ``blocks.png`` taken from a result once, drawn on one or two axes."""

    result: Result
    initial: list[np.ndarray]
    final: list[np.ndarray]
    fixed: np.ndarray
    excavated: np.ndarray
    walls: list[np.ndarray]
    bolts: list[np.ndarray]
    moving: list[int]
    unbalanced: list[int]

    @classmethod
    def of(cls, result: Result) -> _ModelLayers:
        geometry = result.geometry or {}
        initial = polygons(geometry.get("initial_vertices", []))
        final = polygons(geometry.get("final_vertices", [])) or initial
        n_blocks = max(len(initial), len(final))
        fixed = _block_mask(
            geometry.get("fixed", [b.get("fixed", False) for b in result.blocks]), n_blocks
        )
        excavated = _excavated(result, n_blocks)
        walls = [np.asarray(w, dtype=float).reshape(2, 2) for w in geometry.get("walls", [])]
        moving = [int(i) for i in result.moving_blocks
                  if 0 <= int(i) < len(final) and not excavated[int(i)]]
        unbalanced = [int(b["id"]) for b in getattr(result, "unbalanced_blocks", [])
                      if 0 <= int(b["id"]) < len(final) and not excavated[int(b["id"])]]
        return cls(result, initial, final, fixed, excavated, walls, bolt_segments(geometry),
                   moving, unbalanced)

    @property
    def shown(self) -> list[np.ndarray]:
        kept = [p for p, e in zip(self.final, self.excavated, strict=False) if not e]
        return self.initial + kept + self.walls

    def extent(self) -> np.ndarray:
        """[[x0, x1], [y0, y1]] of everything drawn (m)."""
        pts = np.concatenate([p.reshape(-1, 2) for p in self.shown + self.bolts])
        pts = pts[np.isfinite(pts).all(axis=1)]
        return np.stack([pts.min(axis=0), pts.max(axis=0)], axis=1)

    def openings(self) -> list[np.ndarray]:
        """The excavations' outlines: the scene's, else the excavated blocks'."""
        given = (self.result.geometry or {}).get("excavations") or {}
        outlines = [np.asarray(v, dtype=float).reshape(-1, 2) for v in given.values()]
        return outlines or [p for p, e in zip(self.initial, self.excavated, strict=False) if e]

    def zoom(self) -> tuple[float, float, float, float] | None:
        """The window around the excavations, the bolts that reach into it and the moving
        (or out-of-balance) blocks in it (None: no excavation, or it fills most of the
        model)."""
        marked = self.moving + self.unbalanced
        return zoom_window(self.openings(), self.shown + self.bolts,
                           also=self.bolts + [self.final[i] for i in marked])

    def draw(self, ax: Any, magnification: float | None, labels: bool,
             size: float | None = None) -> list[Any]:
        """All the layers on ``ax``; returns the legend handles. ``labels``: write bolt
        forces (left to the zoomed panel when there is one); ``size``: the panel's extent
        (m) that the arrows are scaled to (None: the model's)."""
        result, geometry = self.result, self.result.geometry or {}
        lw = line_width(max(len(self.initial), len(self.final)))
        handles: list[Any] = []
        kept_initial = [p for p, e in zip(self.initial, self.excavated, strict=False) if not e]
        if kept_initial:
            ax.add_collection(PolyCollection(kept_initial, closed=True, facecolors="none",
                                             edgecolors="0.78", linewidths=lw, zorder=1))
            handles.append(Line2D([], [], color="0.78", lw=1.0, label="initial"))
        handles += draw_final_blocks(ax, self.initial, self.final, self.fixed, self.excavated,
                                     lw, "0.15")
        handles += draw_loose_blocks(ax, self.initial, getattr(result, "loose_blocks", []), lw)
        if self.walls:
            ax.add_collection(LineCollection(self.walls, colors="k", linewidths=3.0, zorder=3))
            handles.append(Line2D([], [], color="k", lw=3.0, label="wall"))
        size = size or model_size(self.shown + self.bolts)
        handles += draw_moving(ax, self.final, self.moving, lw, size)
        handles += draw_unbalanced(ax, self.final, self.unbalanced, lw, size)
        handles += draw_contacts(ax, geometry.get("contacts") or {}, len(self.final))
        handles += draw_supports(ax, geometry.get("excavations") or {},
                                 geometry.get("supports") or [], kept_initial)
        arrow_handle = draw_displacements(ax, result, self.initial, size, magnification,
                                          self.excavated)
        if arrow_handle is not None:
            handles.append(arrow_handle)
        handles += draw_bolts(ax, result, self.bolts, size, labels=labels)
        handles += draw_water_table(ax, geometry.get("water_table"), self.shown)
        moved = {name: (result.monitors or {}).get(name, {}).get("displacement")
                 for name in geometry.get("monitors") or {}}
        handles += draw_monitors(ax, geometry.get("monitors") or {}, size, moved)
        finish_axes(ax, self.shown + self.bolts)
        return handles

    def place_labels(self, fig: Any, ax: Any) -> int:
        """Move the monitor and support labels apart, then the bolt forces beside their
        bolts; returns how many bolt forces found no room."""
        others = [t for t in ax.texts if t.get_gid() in ("monitor label", "support label")]
        place_labels(fig, ax, others)
        bolt_texts = [t for t in ax.texts if str(t.get_gid()).startswith("bolt label")]
        segments = [self.bolts[int(t.get_gid().split()[-1])] for t in bolt_texts]
        return place_bolt_labels(fig, ax, bolt_texts, segments, avoid=others)


def _status_text(result: Result) -> str:
    """'stable', 'UNSTABLE: blocks 3, 7 moving' or 'NOT CONVERGED (iteration_limit)' (with
    the blocks out of balance where it names them: ': blocks 712, 855 out of balance')."""
    if result.status not in ("converged", "mechanism"):
        ids = [b["id"] for b in getattr(result, "unbalanced_blocks", [])]
        if not ids:
            return f"NOT CONVERGED ({result.status})"
        return f"NOT CONVERGED ({result.status}): {_blocks_named(ids)} out of balance"
    if result.stable and not result.moving_blocks:
        return "stable"
    if not result.moving_blocks:
        return "UNSTABLE"
    return f"UNSTABLE: {_blocks_named(result.moving_blocks)} moving"


def _blocks_named(ids) -> str:
    """'block 3', 'blocks 3, 7', 'blocks 1, ..., 10, ... (+5 more)' (the first ten)."""
    names = [str(int(i)) for i in ids]
    shown = ", ".join(names[:10])
    if len(names) > 10:
        shown += f", ... (+{len(names) - 10} more)"
    return f"{'block' if len(names) == 1 else 'blocks'} {shown}"


def plot_principal_stresses(result: Result, path: str | Path) -> Path | None:
    """Principal-stress crosses on the final blocks; ``None`` where there are no stresses.

    The final outlines are drawn light (excavated blocks left out, the
    opening as a dashed outline, fixed blocks hatched); at each block
    centroid two perpendicular bars lie along the principal directions, each
    as long as its principal stress is large (one scale for the whole figure,
    stated in the legend as "1 m = 2000 kPa"), blue in compression, red in
    tension. Above ``_MAX_CROSSES`` blocks, one cross per cell of a
    ``_CROSS_GRID`` x ``_CROSS_GRID`` grid is drawn (the block nearest the
    cell centre). The scale is the round number of kPa per metre at which every
    bar fits inside its block along its direction (:func:`bar_room`), or, in a block
    smaller than the typical (median) one (a sliver where joints cross), within the
    typical block's size; such a bar is then cut at its block's edge (counted in the
    legend), so that no bar leaves its block. A key bar of a round stress is drawn below
    the legend. With excavations, a second panel shows the crosses around them at the
    same scale.

    Args:
      result: a :class:`~jaxdem.results.Result` whose ``geometry`` holds
        ``stress`` (n, 3) sxx, syy, sxy (kPa, compression positive) and
        ``centroids`` (n, 2) (else the blocks' ``stress`` and centroids).
      path: PNG file to write.

    Returns:
      ``path``, or ``None`` when no block carries a stress (nothing is written).
    """
    geometry = result.geometry or {}
    initial = polygons(geometry.get("initial_vertices", []))
    final = polygons(geometry.get("final_vertices", [])) or initial
    n_blocks = max(len(initial), len(final), len(result.blocks))
    stress = _block_array(geometry.get("stress"), [b.get("stress") for b in result.blocks], 3)
    centroids = _block_array(
        geometry.get("centroids"),
        [polygon_centroid(p) for p in final] or [b.get("centroid") for b in result.blocks],
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

    lw = line_width(len(final))
    outline = "0.55" if len(final) <= 2000 else "0.7"

    # Thin to one cross per grid cell, then size the bars by the block each sits in.
    shown_polys = [p for p, e in zip(final, excavated, strict=False) if not e]
    sel = visible.copy()
    thinned = sel.sum() > _MAX_CROSSES
    if thinned:
        sel &= nearest_centre_per_cell(centroids, sel, _CROSS_GRID)
    # One scale for every bar, a round number of kPa per metre, at which each bar fits
    # in its block along its own direction (the chord through the centroid), or, in a
    # block smaller than the typical one (a sliver where joints cross, often where the
    # peak is), within the typical block's size; there the bar is then cut at the
    # block's edge, so that no bar leaves its block.
    outlines = [final[i] if i < len(final) else None for i in np.nonzero(sel)[0]]
    chord = bar_room(outlines, centroids[sel], directions[sel])
    typical = float(np.median(block_room(outlines, centroids[sel])))
    peak = float(magnitude[sel].max())
    kpa_per_m = nice_ceil(float(np.max(np.abs(sigma[sel]) / np.maximum(chord, typical))))
    cut = np.abs(sigma[sel]) > chord * kpa_per_m * (1 + 1e-12)
    segments, colours = stress_crosses(centroids[sel], sigma[sel], directions[sel], kpa_per_m,
                                       clip=chord * kpa_per_m)
    model = _ModelLayers.of(result)
    window = model.zoom()
    if window is None:
        fig, ax = new_figure((9, 7.5))
        axes = [ax]
    else:
        fig, axes = _two_panels(model.extent(), window)
    for ax in axes:
        handles = draw_final_blocks(ax, initial, final, fixed, excavated, lw, outline)
        ax.add_collection(LineCollection(segments, colors=colours,
                                         linewidths=0.7 if thinned else 1.2, capstyle="butt",
                                         zorder=5, gid="stress bars"))
        finish_axes(ax, initial + shown_polys + [centroids[visible]])
    s_sel = sigma[sel]
    label = f"compression (max {s_sel.max():.4g} kPa)"
    handles.append(Line2D([], [], color=_COMPRESSION, lw=1.5, label=label))
    if (s_sel < 0).any():
        label = f"tension (max {-s_sel.min():.4g} kPa)"
        handles.append(Line2D([], [], color=_TENSION, lw=1.5, label=label))
    note = f"scale: 1 m = {format_number(kpa_per_m)} kPa\n(largest stress {peak:.4g} kPa)"
    if cut.any():
        note += (f"\n{int(cut.sum())} bars in blocks smaller than\nthe typical one cut at "
                 "the block's edge")
    if thinned:
        note += f"\n{int(sel.sum())} of {int(visible.sum())} blocks (grid)"
    handles.append(Line2D([], [], ls="", label=note))
    ax = axes[-1]
    key = nice_ceil(0.5 * peak)
    ax.add_artist(AnchoredSizeBar(ax.transData, key / kpa_per_m, f"{format_number(key)} kPa",
                                  loc="lower left", bbox_to_anchor=(1.02, 0.0),
                                  bbox_transform=ax.transAxes, color=_COMPRESSION, size_vertical=0,
                                  frameon=False, fontproperties={"size": 8}, sep=3))
    title = f"{result.scene}: principal stresses (compression positive)"
    if window is None:
        ax.set_title(title)
    else:
        x0, x1, y0, y1 = window
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_title("around the excavations (same scale)", fontsize=10)
        axes[0].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="tab:blue",
                                    lw=1.2, zorder=10, gid="zoom frame"))
        fig.suptitle(title)
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
    return save_figure(fig, path)


def bar_room(outlines: Sequence[np.ndarray | None], centres: np.ndarray,
             directions: np.ndarray) -> np.ndarray:
    """Per block and principal direction, the longest bar centred on ``centres[i]`` along
    ``directions[i, k]`` that stays inside ``outlines[i]``: twice the nearer of the
    outline's crossings ahead and behind (m), shape (n, 2). A block without an outline
    gets the median of the others."""
    room = np.full((len(centres), 2), np.nan)
    for i, (poly, c) in enumerate(zip(outlines, centres, strict=True)):
        if poly is None or len(poly) < 3:
            continue
        a = poly - c
        e = np.roll(poly, -1, axis=0) - poly
        for k in range(2):
            d = directions[i, k]
            # c + t d = a + s e: t along the bar, s along the edge (Cramer's rule).
            det = e[:, 0] * d[1] - e[:, 1] * d[0]
            ok = np.abs(det) > 1e-300
            safe = np.where(ok, det, 1.0)
            t = (e[:, 0] * a[:, 1] - e[:, 1] * a[:, 0]) / safe
            sp = (d[0] * a[:, 1] - d[1] * a[:, 0]) / safe
            hit = ok & (sp >= -1e-12) & (sp <= 1 + 1e-12)
            ahead = t[hit & (t > 0)].min(initial=np.inf)
            behind = -t[hit & (t < 0)].max(initial=-np.inf)
            room[i, k] = 2.0 * min(ahead, behind)
    ok = np.isfinite(room) & (room > 0)
    room[~ok] = float(np.median(room[ok])) if ok.any() else 1.0
    return room


def block_room(outlines: Sequence[np.ndarray | None], centres: np.ndarray) -> np.ndarray:
    """Per block, the longest bar centred on ``centres[i]`` that stays inside the block in
    any direction: twice the distance from the centre to the nearest edge of
    ``outlines[i]`` (m). A block without an outline gets the median of the others."""
    room = np.full(len(centres), np.nan)
    for i, (poly, c) in enumerate(zip(outlines, centres, strict=True)):
        if poly is None or len(poly) < 3:
            continue
        a, b = poly, np.roll(poly, -1, axis=0)
        d = b - a
        t = np.clip(((c - a) * d).sum(axis=1) / np.maximum((d * d).sum(axis=1), 1e-300), 0, 1)
        room[i] = 2.0 * float(np.hypot(*(a + t[:, None] * d - c).T).min())
    ok = np.isfinite(room) & (room > 0)
    room[~ok] = float(np.median(room[ok])) if ok.any() else 1.0
    return room


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
    clip: float | np.ndarray | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Bars of principal-stress crosses: (2n, 2, 2) segments and their colours.

    Each bar is centred on its block's centroid, lies along its principal
    direction and is ``|sigma| / kpa_per_m`` long (|sigma| clipped at
    ``clip`` when given: a number, or (n, 2) per bar); blue for compression
    (sigma > 0), red for tension.
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
