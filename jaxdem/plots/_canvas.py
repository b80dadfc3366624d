"""The canvas every figure is drawn on: a matplotlib ``Figure`` outside pyplot with the
Agg renderer (:func:`new_figure`), saved at ``DPI`` and released (:func:`save_figure`, which calls
the ``inspect`` hook), axes fitted to the shapes (:func:`finish_axes`), labels moved
apart (:func:`place_labels`) and bolt forces beside their bolts (:func:`place_bolt_labels`),
a window around the excavations (:func:`zoom_window`), round scales and lengths for legends
(:func:`nice_magnification`, :func:`nice_ceil`, :func:`format_length`) and thinning to
one item per grid cell (:func:`largest_per_cell`).

Host NumPy and matplotlib only, no knowledge of results or scenes: the figure modules
(:mod:`jaxdem.plots._model`, :mod:`jaxdem.plots._monitors`, :mod:`jaxdem.plots._scene`,
:mod:`jaxdem.plots._sweep`) and the layers (:mod:`jaxdem.plots._layers`) call it.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.path import Path as MplPath

DPI = 150
PNG_OPTIONS = {"compress_level": 1}
"""zlib level of the PNGs: at the default 6 the encoding took 0.44 s of the 2.3 s that
the incline's four figures took in a profile (a loaded machine); at 1 it is no longer
among the profile's top entries, for files 1.2-1.4 times larger."""


def new_figure(figsize: tuple[float, float]) -> tuple[Figure, Any]:
    """A figure outside pyplot (nothing global to close), drawn by Agg."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


def warm_up() -> None:
    """Draw a small labelled figure to nowhere: matplotlib's modules and fonts are loaded.

    The command line runs this while the solver compiles (see
    :func:`jaxdem.core.compile_cache.while_compiling`), so that the figures after the
    answer do not pay for the loading.
    """
    fig, ax = new_figure((1.0, 1.0))
    ax.set_title("jaxdem")
    ax.plot([0.0, 1.0], [0.0, 1.0])
    fig.savefig(io.BytesIO(), format="png", dpi=DPI, bbox_inches="tight", pil_kwargs=PNG_OPTIONS)
    fig.clear()


#: Called as ``inspect(fig, path)`` after each figure is saved, before it is released
#: (tests look at the drawn artists through it); None: nothing.
inspect = None


def save_figure(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, dpi=DPI, bbox_inches="tight", pil_kwargs=PNG_OPTIONS)
        if inspect is not None:
            inspect(fig, path)
    finally:
        fig.clear()  # release the artists now rather than at garbage collection
    return path


def finish_axes(ax: Any, shapes: Sequence[np.ndarray]) -> None:
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


def model_size(shapes: Sequence[np.ndarray]) -> float:
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


def line_width(n_blocks: int) -> float:
    if n_blocks <= 200:
        return 0.9
    if n_blocks <= 2000:
        return 0.5
    return 0.25


def polygons(vertices: Sequence[Any]) -> list[np.ndarray]:
    return [np.asarray(v, dtype=float).reshape(-1, 2) for v in vertices]


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid of a simple polygon (vertex mean when degenerate)."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    if abs(area) < 1e-300:
        return poly.mean(axis=0)
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)


def polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())


# Offsets (points) tried for a label, nearest first: right-above, right-below,
# left-above, left-below, then further out.
_LABEL_OFFSETS = [(5, 4, "left"), (5, -12, "left"), (-5, 4, "right"), (-5, -12, "right"),
                  (5, 16, "left"), (5, -24, "left"), (-5, 16, "right"), (-5, -24, "right"),
                  (5, 28, "left"), (5, -36, "left"), (-5, 28, "right"), (-5, -36, "right")]


def place_labels(fig: Figure, ax: Any, texts: list[Any]) -> None:
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


def place_bolt_labels(fig: Figure, ax: Any, texts: list[Any], segments: list[np.ndarray],
                      avoid: Sequence[Any] = ()) -> int:
    """Put each bolt's force label beside its bolt, off every bolt line and apart.

    ``texts[k]`` labels ``segments[k]`` (its (2, 2) anchors, m); labels are placed in
    order (largest force first). Each tries, in turn, the middle, a third and two thirds
    along its bolt, on either side, at a distance perpendicular to the bolt that just
    clears the line; it takes the first place whose box (in pixels) crosses no bolt and
    overlaps no label placed before it nor a box of ``avoid`` (other labels). A label that
    finds no place, or whose bolt is outside the axes' view, is removed.

    Returns:
      How many labels were removed for want of room (not counting those out of view).
    """
    if not texts:
        return 0
    renderer = fig.canvas.get_renderer()
    ax.apply_aspect()
    to_pixels = ax.transData
    points_per_pixel = 72.0 / fig.dpi
    bolt_paths = [MplPath(to_pixels.transform(seg)) for seg in segments]
    view = ax.get_window_extent(renderer)
    placed = [box for box in (t.get_window_extent(renderer) for t in avoid)]
    crowded = 0
    for text, seg in zip(texts, segments, strict=True):
        ends = to_pixels.transform(seg)
        if not any(view.contains(*end) for end in (ends[0], ends[1], ends.mean(axis=0))):
            text.remove()
            continue
        d = ends[1] - ends[0]
        normal = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-9)
        text.set_position((0.0, 0.0))
        box = text.get_window_extent(renderer)
        # The distance from the box centre to the line at which the box just clears it.
        clear = 0.5 * (box.width * abs(normal[0]) + box.height * abs(normal[1])) + 3.0
        spot = None
        for t in (0.5, 0.33, 0.67, 0.2, 0.8):
            anchor = seg[0] + t * (seg[1] - seg[0])
            for side in (1.0, -1.0):
                offset = side * clear * normal * points_per_pixel
                text.xy = anchor
                text.set_position(tuple(offset))
                box = text.get_window_extent(renderer)
                grown = box.expanded(1.05, 1.1)
                if any(grown.overlaps(other) for other in placed):
                    continue
                if any(path.intersects_bbox(box, filled=False) for path in bolt_paths):
                    continue
                spot = box
                break
            if spot is not None:
                break
        if spot is None:
            text.remove()
            crowded += 1
        else:
            placed.append(spot)
    return crowded


def zoom_window(focus: Sequence[np.ndarray], model: Sequence[np.ndarray],
                also: Sequence[np.ndarray] = (), margin: float = 0.6,
                largest: float = 0.6) -> tuple[float, float, float, float] | None:
    """A view (x0, x1, y0, y1) around ``focus`` (the excavations' outlines, m): their
    bounding box grown by ``margin`` times its larger side on every side, made
    square-ish (neither side under half the other), grown to take in the shapes of
    ``also`` that reach into it (bolts, moving blocks) with 5% to spare, and kept inside
    the model's bounding box. None when there is nothing to focus on or the view would
    cover more than ``largest`` of the model's width and height (the whole model is then
    close enough)."""
    f, m = _points(focus), _points(model)
    if not len(f) or not len(m):
        return None
    lo, hi = f.min(axis=0), f.max(axis=0)
    side = max(float((hi - lo).max()), 1e-9)
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo) + margin * side
    half = np.maximum(half, 0.5 * half.max())
    lo, hi = centre - half, centre + half
    for shape in also:
        pts = _points([shape])
        if len(pts) and ((pts >= lo) & (pts <= hi)).all(axis=1).any():
            lo = np.minimum(lo, pts.min(axis=0) - 0.05 * side)
            hi = np.maximum(hi, pts.max(axis=0) + 0.05 * side)
    m_lo, m_hi = m.min(axis=0), m.max(axis=0)
    lo, hi = np.maximum(lo, m_lo), np.minimum(hi, m_hi)
    if ((hi - lo) > largest * (m_hi - m_lo)).all():
        return None
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _points(shapes: Sequence[np.ndarray]) -> np.ndarray:
    """All finite points of ``shapes`` as one (n, 2) array."""
    pts = [np.asarray(s, dtype=float).reshape(-1, 2) for s in shapes if np.size(s)]
    if not pts:
        return np.zeros((0, 2))
    every = np.concatenate(pts)
    return every[np.isfinite(every).all(axis=1)]


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


def format_magnification(mag: float) -> str:
    return f"{mag:.0f}" if mag >= 1 and float(mag).is_integer() else f"{mag:g}"


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


def format_number(x: float) -> str:
    return f"{x:.0f}" if float(x).is_integer() else f"{x:g}"


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


def largest_per_cell(points: np.ndarray, value: np.ndarray, n_cells: int) -> np.ndarray:
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


def nearest_centre_per_cell(points: np.ndarray, valid: np.ndarray, n_cells: int) -> np.ndarray:
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
    keep[idx] = largest_per_cell(pts, -dist, n_cells)
    return keep
