"""Layers drawn on a block figure: final and excavated outlines, contact points by state,
displacement arrows, bolts by state with their forces, monitor points and sections, the
water table. Each takes an axes and plain arrays (or a ``Result``), adds its artists
(collections carry a whole layer in one artist) and returns its legend handles.

Used by the model figures (:mod:`jaxdem.plots._model`) and the scene check
(:mod:`jaxdem.plots._scene`); draws with :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from jaxdem.core.state import OPEN, SLIP, STICK
from jaxdem.plots._canvas import (
    format_length,
    format_magnification,
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
    )


def bolt_segments(geometry: dict[str, Any]) -> list[np.ndarray]:
    return [np.asarray(b, dtype=float).reshape(2, 2) for b in geometry.get("bolts") or []]


def draw_bolts(ax: Any, result: Result, segments: list[np.ndarray], size: float) -> list[Any]:
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
