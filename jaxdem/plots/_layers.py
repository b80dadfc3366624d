"""Layers drawn on a block figure: final and excavated outlines, contact points by state,
displacement arrows, bolts by state with their forces, moving blocks, support pressure on
the excavations, monitor points and sections, the water table. Each takes an axes and
plain arrays (or a ``Result``), adds its artists (collections carry a whole layer in one
artist) and returns its legend handles.

Used by the model figures (:mod:`jaxdem.plots._model`) and the scene check
(:mod:`jaxdem.plots._scene`); draws with :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import to_rgb
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.path import Path as MplPath

from jaxdem.core.state import OPEN, SLIP, STICK
from jaxdem.plots._canvas import (
    format_length,
    format_magnification,
    format_number,
    largest_per_cell,
    nice_magnification,
    polygon_centroid,
)
from jaxdem.results import Result

# Contact states: colour and legend label (green stuck, orange slipping, red open).
_STATE_STYLE = {
    STICK: ("tab:green", "stuck"),
    SLIP: ("tab:orange", "slipping"),
    OPEN: ("tab:red", "open"),
}
_MONITOR_COLOUR = "tab:blue"

# Bolt states: colour and line style; forces written on at most _MAX_BOLT_LABELS bolts.
NOT_INSTALLED = "not installed"
_BOLT_STYLE = {
    "elastic": ("saddlebrown", "-"),
    "yielded": ("darkviolet", "-"),
    "pulled out": ("0.45", "--"),
    NOT_INSTALLED: ("0.7", ":"),  # its stage was not reached: no force written
}
_SUPPORT_COLOUR = "teal"
_MAX_BOLT_LABELS = 60
_ARROW_COLOUR = "tab:purple"
# Above _MAX_ARROWS blocks, draw only the largest displacement in each cell of an
# _ARROW_GRID x _ARROW_GRID grid over the model: thousands of arrows read as noise.
_MAX_ARROWS = 1000
_ARROW_GRID = 25


def draw_final_blocks(
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


def draw_contacts(ax: Any, contacts: dict[str, Any], n_blocks: int) -> list[Any]:
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


def draw_displacements(
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
            c = polygon_centroid(initial[k])
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
        sel = largest_per_cell(centroids_a, np.where(sel, norm, -1.0), _ARROW_GRID) & sel
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
        label=f"displacements x {format_magnification(mag)}\n(max {format_length(u_max)})"
        + ("\nlargest per grid cell" if thinned else ""),
        gid="displacements",
    )


def bolt_segments(geometry: dict[str, Any]) -> list[np.ndarray]:
    return [np.asarray(b, dtype=float).reshape(2, 2) for b in geometry.get("bolts") or []]


def draw_bolts(ax: Any, result: Result, segments: list[np.ndarray], size: float,
               labels: bool = True) -> list[Any]:
    """Bolts as lines between their anchors, by state, labelled with force (kN).

    A bolt "not installed" (its stage was not reached) is drawn light grey and dotted,
    without a force. With ``labels``, the forces are written as annotations with gid
    "bolt label K" (K: the bolt's index in ``segments``) at the bolt's middle;
    :func:`~jaxdem.plots._canvas.place_bolt_labels` then moves them off their bolt and
    apart (at most ``_MAX_BOLT_LABELS``, largest first).
    """
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
        quiet = state == NOT_INSTALLED
        ax.add_collection(
            LineCollection(
                [segments[k] for k in sel],
                colors=colour,
                linestyles=ls,
                linewidths=(1.5 if quiet else 2.5) if len(segments) <= 200 else 1.2,
                zorder=6.5,
                gid=f"bolts {state}",
            )
        )
        handles.append(
            Line2D([], [], color=colour, ls=ls, lw=2.5, label=f"bolt {state} ({len(sel)})")
        )
    if not labels:
        return handles
    forces = np.array(
        [
            float((info[k] if k < len(info) else {}).get("force", np.nan))
            if states[k] != NOT_INSTALLED else np.nan
            for k in range(len(segments))
        ]
    )
    finite = np.nonzero(np.isfinite(forces))[0]
    finite = finite[np.argsort(-np.abs(forces[finite]), kind="stable")]
    if len(finite) > _MAX_BOLT_LABELS:
        finite = finite[:_MAX_BOLT_LABELS]
        handles.append(Line2D([], [], ls="", label=f"forces of the {_MAX_BOLT_LABELS} largest"))
    for k in finite:
        ax.annotate(
            f"{forces[k]:.3g} kN",
            xy=segments[k].mean(axis=0),
            xytext=(0, 0),
            textcoords="offset points",
            ha="center",
            va="center",
            fontsize=7,
            color=_BOLT_STYLE.get(states[k], ("0.3", "-"))[0],
            zorder=9,
            gid=f"bolt label {k}",
            bbox=dict(boxstyle="square,pad=0.15", fc="white", ec="none", alpha=0.85),
        )
    return handles


def draw_moving(ax: Any, final: list[np.ndarray], moving: Sequence[int], lw: float,
                size: float) -> list[Any]:
    """Blocks still moving at a mechanism: filled light red, outlined red; a block
    smaller than 3% of ``size`` (the panel's extent, m) is also ringed, so that a single
    small block is seen at the scale of the whole model."""
    return _draw_marked(ax, final, moving, lw, size, "red", "moving")


def draw_unbalanced(ax: Any, final: list[np.ndarray], unbalanced: Sequence[int], lw: float,
                    size: float) -> list[Any]:
    """Blocks out of balance where the analysis stopped at the iteration limit
    (``Result.unbalanced_blocks``): filled and outlined goldenrod (red, purple and teal
    are the moving blocks', the displacements' and the supports'), small ones ringed, as
    :func:`draw_moving` draws the moving ones."""
    return _draw_marked(ax, final, unbalanced, lw, size, "goldenrod", "out of balance")


def _draw_marked(ax: Any, final: list[np.ndarray], ids: Sequence[int], lw: float, size: float,
                 color: str, name: str) -> list[Any]:
    """The blocks ``ids`` filled in a light ``color`` and outlined in it, those smaller than
    3% of ``size`` also ringed; the legend's entry is ``name`` with their count. The
    collections' gids are "``name`` blocks" and "``name`` ring"."""
    if not ids:
        return []
    polys = [final[int(i)] for i in ids]
    fill = (*to_rgb(color), 0.3)
    ax.add_collection(
        PolyCollection(polys, closed=True, facecolors=fill, edgecolors=color,
                       linewidths=max(2.0 * lw, 1.5), zorder=4, gid=f"{name} blocks")
    )
    extent = np.array([float(np.ptp(p, axis=0).max()) for p in polys])
    small = extent < 0.03 * size
    if small.any():
        centres = np.array([polygon_centroid(p) for p, s in zip(polys, small, strict=True) if s])
        ax.scatter(centres[:, 0], centres[:, 1], s=400, facecolors="none", edgecolors=color,
                   linewidths=1.5, zorder=8.5, gid=f"{name} ring")
    return [Patch(facecolor=fill, edgecolor=color, lw=2.0, label=f"{name} ({len(ids)})")]


def draw_supports(ax: Any, excavations: dict[str, Any], supports: Sequence[dict[str, Any]],
                  rock: list[np.ndarray]) -> list[Any]:
    """Support pressure on the excavation boundary: a band along the faces of the rock
    it pushes on (where rock is left behind the outline) and arrows from the opening
    into the rock, with the pressure (kPa) written in the opening.

    ``excavations``: name -> outline (n, 2) m, counter-clockwise; ``supports``: dicts with
    ``excavation`` and ``pressure`` (kPa); ``rock``: the outlines of the blocks left.
    """
    pressure: dict[str, float] = {}
    for sp in supports or []:
        name = sp.get("excavation")
        if name in (excavations or {}):
            pressure[name] = pressure.get(name, 0.0) + float(sp.get("pressure", 0.0))
    handles = []
    for name, p in pressure.items():
        outline = np.asarray(excavations[name], dtype=float).reshape(-1, 2)
        points, normals = _outline_samples(outline, 48)
        span = float(np.ptp(outline, axis=0).max())
        behind = _inside_any(points + 0.02 * span * normals, rock)
        if not behind.any() or p <= 0.0:
            continue
        # The band: the outline between consecutive samples with rock behind both.
        nxt = np.roll(np.arange(len(points)), -1)
        pieces = [np.array([points[i], points[j]]) for i, j in enumerate(nxt)
                  if behind[i] and behind[j]]
        ax.add_collection(LineCollection(pieces, colors=_SUPPORT_COLOUR, linewidths=4.0,
                                         alpha=0.45, capstyle="butt", zorder=5.5,
                                         gid=f"support {name}"))
        arrows = np.nonzero(behind)[0][::3]
        length = 0.1 * span
        tails = points[arrows] - length * normals[arrows]
        ax.quiver(tails[:, 0], tails[:, 1], length * normals[arrows, 0],
                  length * normals[arrows, 1], angles="xy", scale_units="xy", scale=1.0,
                  color=_SUPPORT_COLOUR, width=0.004, zorder=5.6, gid=f"support arrows {name}")
        top = arrows[np.argmax(points[arrows, 1])]
        ax.annotate(f"{format_number(p)} kPa", xy=tails[list(arrows).index(top)],
                    xytext=(0, -6), textcoords="offset points", ha="center", va="top",
                    fontsize=7, color=_SUPPORT_COLOUR, zorder=9, gid="support label",
                    bbox=dict(boxstyle="square,pad=0.1", fc="white", ec="none", alpha=0.8))
        handles.append(Line2D([], [], color=_SUPPORT_COLOUR, lw=4.0, alpha=0.6,
                              label=f"support {format_number(p)} kPa ({name})"))
    return handles


def _outline_samples(outline: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """About ``n`` points evenly along a closed counter-clockwise outline (every vertex
    kept) and the outward unit normal of the edge each lies on."""
    ends = np.roll(outline, -1, axis=0)
    edges = ends - outline
    lengths = np.hypot(edges[:, 0], edges[:, 1])
    step = lengths.sum() / n
    points, normals = [], []
    for a, d, length in zip(outline, edges, lengths, strict=True):
        if length <= 0.0:
            continue
        k = max(int(np.ceil(length / step)), 1)
        t = (np.arange(k) + 0.5) / k
        points.append(a + t[:, None] * d)
        normals.append(np.tile([d[1] / length, -d[0] / length], (k, 1)))  # right of a CCW edge
    return np.concatenate(points), np.concatenate(normals)


def _inside_any(points: np.ndarray, polygons: list[np.ndarray]) -> np.ndarray:
    """Which points lie inside at least one of the polygons."""
    inside = np.zeros(len(points), dtype=bool)
    lo, hi = points.min(axis=0), points.max(axis=0)
    for poly in polygons:
        if (poly.max(axis=0) < lo).any() or (poly.min(axis=0) > hi).any():
            continue
        inside |= MplPath(poly).contains_points(points)
    return inside


def draw_monitors(ax: Any, monitors: dict[str, Any], size: float,
                  moved: dict[str, Any] | None = None) -> list[Any]:
    """Monitor points (diamonds) and sections (dashed lines), labelled.

    ``moved``: name -> a point monitor's displacement [ux, uy] (m); the diamond is then
    drawn where the rock point is now, with a thin line from its initial place (light
    diamond) when it moved visibly. Labels carry gid "monitor label" so that
    :func:`~jaxdem.plots._canvas.place_labels` can move them apart.
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


def draw_water_table(ax: Any, table: Any, shapes: Sequence[np.ndarray]) -> list[Any]:
    """The water table (polyline, m) as a blue line with a triangle marker; [] without."""
    if table is None or not np.size(table):
        return []
    t = np.asarray(table, dtype=float).reshape(-1, 2)
    ax.plot(t[:, 0], t[:, 1], color="tab:blue", lw=1.8, zorder=6.8, gid="water table")
    mid = t[len(t) // 2] if len(t) > 2 else t.mean(axis=0)
    ax.plot(mid[0], mid[1], ls="", marker="v", ms=8, color="tab:blue", zorder=6.9)
    return [Line2D([], [], color="tab:blue", lw=1.8, marker="v", ms=6, label="water table")]
