"""Figures of a solved model (``blocks.png``, ``monitors.png``) and of a scene (``check.png``).

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
    write_figures(result, "out/tunnel")   # [out/tunnel/blocks.png, out/tunnel/monitors.png]
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

from jaxdem.results import OPEN, SLIP, STICK, Result

DPI = 150

# Contact states: colour and legend label (green stuck, orange slipping, red open).
_STATE_STYLE = {
    STICK: ("tab:green", "stuck"),
    SLIP: ("tab:orange", "slipping"),
    OPEN: ("tab:red", "open"),
}
_MONITOR_COLOUR = "tab:blue"
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
    dark grey, fixed blocks shaded and hatched, walls as thick black lines,
    contact points coloured by state (stuck green, slipping orange, open red,
    with counts in the legend), centroid displacement vectors as arrows,
    blocks still moving at a mechanism outlined red, monitor points and
    sections labelled.

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
    fixed = np.zeros(n_blocks, dtype=bool)
    fixed_in = np.asarray(geometry.get("fixed", [b.get("fixed", False) for b in result.blocks]))
    fixed[: min(n_blocks, fixed_in.size)] = fixed_in.astype(bool)[:n_blocks]

    fig, ax = _figure((9, 7.5))
    lw = _line_width(n_blocks)
    handles: list[Any] = []

    if initial:
        ax.add_collection(
            PolyCollection(
                initial, closed=True, facecolors="none", edgecolors="0.78", linewidths=lw, zorder=1
            )
        )
        handles.append(Line2D([], [], color="0.78", lw=1.0, label="initial"))
    if final:
        ax.add_collection(
            PolyCollection(
                final, closed=True, facecolors="none", edgecolors="0.15", linewidths=lw, zorder=2
            )
        )
        handles.append(Line2D([], [], color="0.15", lw=1.0, label="final"))
        fixed_polys = [p for p, f in zip(final, fixed, strict=False) if f]
        if fixed_polys:
            ax.add_collection(
                PolyCollection(
                    fixed_polys,
                    closed=True,
                    facecolors="0.85",
                    edgecolors="0.15",
                    hatch="///",
                    linewidths=lw,
                    zorder=0,
                )
            )
            handles.append(Patch(facecolor="0.85", edgecolor="0.15", hatch="///", label="fixed"))

    walls = [np.asarray(w, dtype=float).reshape(2, 2) for w in geometry.get("walls", [])]
    if walls:
        ax.add_collection(LineCollection(walls, colors="k", linewidths=3.0, zorder=3))
        handles.append(Line2D([], [], color="k", lw=3.0, label="wall"))

    moving = [i for i in result.moving_blocks if 0 <= int(i) < len(final)]
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

    size = _model_size(initial + final + walls)
    arrow_handle = _draw_displacements(ax, result, initial, size, magnification)
    if arrow_handle is not None:
        handles.append(arrow_handle)

    monitor_handles = _draw_monitors(ax, geometry.get("monitors") or {}, size)
    handles += monitor_handles

    _finish_axes(ax, initial + final + walls)
    ax.set_title(f"{result.scene}: {_status_text(result)}")
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
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

    x = np.arange(1, len(history) + 1)
    fig, ax = _figure((8, 4.8))
    for k, name in enumerate(names):
        values = np.array(
            [float((r.get("monitors") or {}).get(name, np.nan)) for r in history], dtype=float
        )
        kind = _monitor_kind(result, name)
        label = f"{name} ({'convergence' if kind == 'section' else '|u|'})"
        ax.plot(x, 1e3 * values, marker="o", ms=3, lw=1.5, color=f"C{k % 10}", label=label)

    # Stage boundaries: a dashed line before the first increment of each new stage.
    stages = [str(r.get("stage", "")) for r in history]
    for i, stage in enumerate(stages):
        if i == 0 or stage != stages[i - 1]:
            if i > 0:
                ax.axvline(i + 0.5, color="0.5", ls="--", lw=0.8)
            ax.annotate(
                stage,
                xy=(i + 0.6, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(2, -12),
                textcoords="offset points",
                fontsize=8,
                color="0.3",
            )

    load = np.array([float(r.get("load_factor", np.nan)) for r in history], dtype=float)
    if history and np.isfinite(load).any():
        ax2 = ax.twinx()
        ax2.plot(x, load, color="0.6", ls=":", lw=1.2)
        ax2.set_ylabel("load factor", color="0.45")
        ax2.tick_params(axis="y", colors="0.45")
        ax2.set_ylim(bottom=min(0.0, float(np.nanmin(load))))
        ax.plot([], [], color="0.6", ls=":", label="load factor")

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("load increment")
    ax.set_ylabel("monitor value (mm)")
    ax.grid(True, lw=0.4, alpha=0.5)
    if len(x):
        ax.set_xlim(0.5, len(x) + 0.5)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(f"{result.scene}: monitors")
    return _save(fig, path)


def write_figures(result: Result, out_dir: str | Path) -> list[Path]:
    """Write ``blocks.png`` and, when there are monitors, ``monitors.png`` to ``out_dir``.

    Returns:
      The paths written, ``blocks.png`` first.
    """
    out_dir = Path(out_dir)
    paths = [plot_blocks(result, out_dir / "blocks.png")]
    history_path = plot_monitor_history(result, out_dir / "monitors.png")
    if history_path is not None:
        paths.append(history_path)
    return paths


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
    marker_size = float(np.clip(400.0 / np.sqrt(len(points)), 1.0, 25.0))
    handles = []
    for code in (STICK, SLIP, OPEN):
        colour, label = _STATE_STYLE[code]
        sel = state == code
        count = int(sel.sum())
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
            Line2D([], [], ls="", marker="o", color=colour, ms=5, label=f"{label} ({count})")
        )
    return handles


def _draw_displacements(
    ax: Any, result: Result, initial: list[np.ndarray], size: float, magnification: float | None
) -> Any:
    """Centroid displacement arrows from the initial centroids; returns a legend handle."""
    if not result.blocks:
        return None
    centroids, u = [], []
    for k, b in enumerate(result.blocks):
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
        label=f"displacements x {_format_magnification(mag)}\n(max {1e3 * u_max:.3g} mm)"
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


def _draw_monitors(ax: Any, monitors: dict[str, Any], size: float) -> list[Any]:
    """Monitor points (diamonds) and sections (dashed lines), labelled."""
    if not monitors:
        return []
    offset = 0.01 * size
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
            end = seg[1]
            ax.annotate(
                str(name),
                xy=end,
                xytext=(end[0] + offset, end[1] + offset),
                color=_MONITOR_COLOUR,
                fontsize=8,
                zorder=9,
            )
            any_section = True
        elif xy.size == 2:
            p = xy.reshape(2)
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
            )
            ax.annotate(
                str(name),
                xy=p,
                xytext=(p[0] + offset, p[1] + offset),
                color=_MONITOR_COLOUR,
                fontsize=8,
                zorder=9,
            )
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


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=DPI, bbox_inches="tight")
    finally:
        fig.clear()  # release the artists now rather than at garbage collection
    return path
