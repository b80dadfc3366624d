"""The figure of a scene before solving: ``check.png`` (:func:`plot_scene_check`, for
``jaxdem check``): blocks by material, the generated rock mass of a ``[domain]``
(:func:`jaxdem.rockmass.generate`), discontinuities, boundaries, bolts, supports, water
tables and monitors.

A validated :class:`~jaxdem.scene.Scene` (or any object with its attributes) comes in,
one PNG goes out; drawn with :mod:`jaxdem.plots._layers` and :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from jaxdem.plots._canvas import (
    finish_axes,
    line_width,
    model_size,
    new_figure,
    place_labels,
    polygon_centroid,
    save_figure,
)
from jaxdem.plots._layers import draw_monitors


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

    fig, ax = new_figure((9, 7.5))
    lw = line_width(n_all)
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
            c = polygon_centroid(p)
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
    size = model_size(everything)
    handles += draw_monitors(ax, monitors, size)

    finish_axes(ax, everything)
    place_labels(fig, ax, [t for t in ax.texts if t.get_gid() == "monitor label"])
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
    return save_figure(fig, path)


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
