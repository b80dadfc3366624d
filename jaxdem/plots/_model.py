"""Figures of the solved block model: ``blocks.png`` (:func:`plot_blocks`: outlines,
walls, contacts, displacements, bolts, monitors, moving blocks) and ``stresses.png``
(:func:`plot_principal_stresses`: principal-stress crosses, with
:func:`principal_stresses` and :func:`stress_crosses`).

A :class:`~jaxdem.results.Result` (its ``geometry``, ``blocks``, ``bolts``, ``monitors``)
comes in, one PNG goes out; the layers are drawn by :mod:`jaxdem.plots._layers` on the
canvas of :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.lines import Line2D

from jaxdem.plots._canvas import (
    finish_axes,
    format_number,
    line_width,
    model_size,
    nearest_centre_per_cell,
    new_figure,
    nice_ceil,
    place_labels,
    polygon_area,
    polygon_centroid,
    polygons,
    save_figure,
)
from jaxdem.plots._layers import (
    bolt_segments,
    draw_bolts,
    draw_contacts,
    draw_displacements,
    draw_final_blocks,
    draw_monitors,
    draw_water_table,
)
from jaxdem.plots._loose import draw_loose_blocks
from jaxdem.results import Result

_COMPRESSION = "tab:blue"
_TENSION = "tab:red"
# Above _MAX_CROSSES blocks, one principal-stress cross per cell of a grid.
_MAX_CROSSES = 2500
_CROSS_GRID = 50


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
    initial = polygons(geometry.get("initial_vertices", []))
    final = polygons(geometry.get("final_vertices", [])) or initial
    n_blocks = max(len(initial), len(final))
    fixed = _block_mask(
        geometry.get("fixed", [b.get("fixed", False) for b in result.blocks]), n_blocks
    )
    excavated = _excavated(result, n_blocks)

    fig, ax = new_figure((9, 7.5))
    lw = line_width(n_blocks)
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
    handles += draw_final_blocks(ax, initial, final, fixed, excavated, lw, "0.15")
    handles += draw_loose_blocks(ax, initial, getattr(result, "loose_blocks", []), lw)

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

    handles += draw_contacts(ax, geometry.get("contacts") or {}, n_blocks)

    shown = initial + [p for p, e in zip(final, excavated, strict=False) if not e] + walls
    bolts = bolt_segments(geometry)
    size = model_size(shown + bolts)
    arrow_handle = draw_displacements(ax, result, initial, size, magnification, excavated)
    if arrow_handle is not None:
        handles.append(arrow_handle)

    handles += draw_bolts(ax, result, bolts, size)
    handles += draw_water_table(ax, geometry.get("water_table"), shown)

    moved = {name: (result.monitors or {}).get(name, {}).get("displacement")
             for name in geometry.get("monitors") or {}}
    monitor_handles = draw_monitors(ax, geometry.get("monitors") or {}, size, moved)
    handles += monitor_handles

    finish_axes(ax, shown + bolts)
    ax.set_title(f"{result.scene}: {_status_text(result)}")
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
    place_labels(fig, ax, [t for t in ax.texts if t.get_gid() == "monitor label"])
    return save_figure(fig, path)


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

    fig, ax = new_figure((9, 7.5))
    lw = line_width(len(final))
    outline = "0.55" if len(final) <= 2000 else "0.7"
    handles = draw_final_blocks(ax, initial, final, fixed, excavated, lw, outline)

    # Thin to one cross per grid cell, then size the bars by the block spacing.
    shown_polys = [p for p, e in zip(final, excavated, strict=False) if not e]
    sel = visible.copy()
    thinned = sel.sum() > _MAX_CROSSES
    if thinned:
        sel &= nearest_centre_per_cell(centroids, sel, _CROSS_GRID)
        pts = centroids[visible]
        spacing = float((pts.max(axis=0) - pts.min(axis=0)).max()) / _CROSS_GRID
    else:
        areas = np.array([abs(polygon_area(p)) for p in shown_polys])
        areas = areas[areas > 0]
        spacing = float(np.sqrt(np.median(areas))) if len(areas) else 0.0
    if not spacing > 0:
        spacing = 0.05 * model_size(shown_polys or [centroids[visible]])
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
    note = f"scale: 1 m = {format_number(kpa_per_m)} kPa\n(largest bar {peak:.4g} kPa)"
    if thinned:
        note += f"\n{int(sel.sum())} of {int(visible.sum())} blocks (grid)"
    handles.append(Line2D([], [], ls="", label=note))

    finish_axes(ax, initial + shown_polys + [centroids[visible]])
    ax.set_title(f"{result.scene}: principal stresses (compression positive)")
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False
    )
    return save_figure(fig, path)


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
