"""Polygons on the host: areas, convexity, clipping and overlap search (NumPy, float64).

A polygon is an ``(n, 2)`` array of vertices in m, listed once (the first vertex is
not repeated at the end). The convex routines expect counter-clockwise order, as the
scene files do. Nothing here is traced by JAX: it runs once, before any computation,
to validate and prepare scenes. The functions of plural name (``signed_areas``,
``centroids``, ``polar_moments``, ``bboxes``, ``points_in_polygons``,
``drop_collinear_all``) answer for a whole list of polygons at once, as the singular
ones would one by one (a scene of 10,000 blocks has no Python loop over its blocks).

Example::

    >>> sq = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    >>> overlap_area(sq, sq + 0.5)
    0.25
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = [
    "bbox",
    "bboxes",
    "centroid",
    "centroids",
    "characteristic_length",
    "convex_clip",
    "convex_decompose",
    "convex_hull",
    "corner_sines",
    "distance_to_boundary",
    "drop_collinear",
    "drop_collinear_all",
    "find_overlapping_pairs",
    "has_repeated_points",
    "is_convex",
    "near_box_pairs",
    "overlap_area",
    "overlap_depths",
    "point_in_polygon",
    "point_on_segment",
    "points_in_polygons",
    "polar_moment",
    "polar_moments",
    "polygon_overlap_area",
    "segments_intersect",
    "self_intersects",
    "signed_area",
    "signed_areas",
    "slice_convex",
    "split_by_line",
]


def _as_poly(v: np.ndarray) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"polygon must have shape (n, 2), got {a.shape}")
    return a


def _next(a: np.ndarray) -> np.ndarray:
    # Same as np.roll(a, -1, axis=0), without its overhead (called per block in validation).
    return np.concatenate([a[1:], a[:1]])


def _prev(a: np.ndarray) -> np.ndarray:
    return np.concatenate([a[-1:], a[:-1]])


def _shoelace(v: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    # Relative to the first vertex: keeps digits for coordinates far from the origin.
    d = v - v[0]
    dn = _next(d)
    cross = d[:, 0] * dn[:, 1] - dn[:, 0] * d[:, 1]
    return 0.5 * float(np.sum(cross)), d, cross


def signed_area(v: np.ndarray) -> float:
    """Signed area of polygon ``v`` (m2), positive when the vertices run counter-clockwise."""
    v = _as_poly(v)
    if len(v) < 3:
        return 0.0
    return _shoelace(v)[0]


def centroid(v: np.ndarray) -> np.ndarray:
    """Area centroid of polygon ``v`` (m), shape (2,); vertex mean if the area is zero."""
    v = _as_poly(v)
    if len(v) == 0:
        raise ValueError("centroid of an empty polygon")
    if len(v) < 3:
        return v.mean(axis=0)
    area, d, cross = _shoelace(v)
    diag2 = float(np.sum((v.max(axis=0) - v.min(axis=0)) ** 2))
    if abs(area) <= 1e-14 * diag2 or area == 0.0:
        return v.mean(axis=0)
    dn = _next(d)
    c = np.sum((d + dn) * cross[:, None], axis=0) / (6.0 * area)
    return v[0] + c


def corner_sines(v: np.ndarray) -> np.ndarray:
    """Sine of the turning angle at each vertex of ``v`` (-), shape (n,); > 0 left, < 0 reflex.

    Entry k is for vertex k, between edge (k-1, k) and edge (k, k+1); 0 marks a collinear
    (180 degree) vertex or a zero-length edge.
    """
    v = _as_poly(v)
    e = _next(v) - v
    ep = _prev(e)
    cross = ep[:, 0] * e[:, 1] - ep[:, 1] * e[:, 0]
    lens = np.hypot(e[:, 0], e[:, 1])
    denom = lens * _prev(lens)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 0.0, cross / np.where(denom > 0.0, denom, 1.0), 0.0)
    return s


def is_convex(v: np.ndarray, tol: float = 1e-9) -> bool:
    """True if ``v`` is strictly convex and counter-clockwise (no reflex or 180-degree vertex).

    ``tol`` bounds the sine of the turning angle (-) below which a vertex counts as collinear.
    """
    v = _as_poly(v)
    if len(v) < 3:
        return False
    s = corner_sines(v)
    if np.any(s <= tol):
        return False
    # All left turns is not enough: a star polygon winds twice. Total turning must be 2 pi.
    e = _next(v) - v
    ep = _prev(e)
    cross = ep[:, 0] * e[:, 1] - ep[:, 1] * e[:, 0]
    dot = ep[:, 0] * e[:, 0] + ep[:, 1] * e[:, 1]
    turning = float(np.sum(np.arctan2(cross, dot)))
    return abs(turning - 2.0 * math.pi) < 1e-6


def point_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """True if point ``p`` lies within distance ``tol`` (m) of segment ``a``-``b``."""
    px, py = float(p[0]), float(p[1])
    ax, ay = float(a[0]), float(a[1])
    dx, dy = float(b[0]) - ax, float(b[1]) - ay
    len2 = dx * dx + dy * dy
    if len2 == 0.0:
        return math.hypot(px - ax, py - ay) <= tol
    t = min(1.0, max(0.0, ((px - ax) * dx + (py - ay) * dy) / len2))
    return math.hypot(px - (ax + t * dx), py - (ay + t * dy)) <= tol


def _orient(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def segments_intersect(
    p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray, tol: float = 0.0
) -> bool:
    """True if segments ``p1``-``p2`` and ``q1``-``q2`` cross or touch (within ``tol``, m)."""
    a = (float(p1[0]), float(p1[1]))
    b = (float(p2[0]), float(p2[1]))
    c = (float(q1[0]), float(q1[1]))
    d = (float(q2[0]), float(q2[1]))
    d1, d2 = _orient(c, d, a), _orient(c, d, b)
    d3, d4 = _orient(a, b, c), _orient(a, b, d)
    if ((d1 > 0.0 > d2) or (d1 < 0.0 < d2)) and ((d3 > 0.0 > d4) or (d3 < 0.0 < d4)):
        return True
    return (
        point_on_segment(a, c, d, tol)
        or point_on_segment(b, c, d, tol)
        or point_on_segment(c, a, b, tol)
        or point_on_segment(d, a, b, tol)
    )


def _diag(v: np.ndarray) -> float:
    return float(np.hypot(*(v.max(axis=0) - v.min(axis=0))))


def self_intersects(v: np.ndarray) -> bool:
    """True if two non-adjacent edges of ``v`` cross or touch, or two adjacent edges fold back.

    Touching is judged to 1e-12 of the polygon's bounding-box diagonal (round-off only).
    """
    v = _as_poly(v)
    n = len(v)
    if n < 3:
        return False
    tol = 1e-12 * _diag(v)
    pts = [(float(x), float(y)) for x, y in v]
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        # Adjacent edge (i+1, i+2) folding back over edge i shares more than vertex b.
        c = pts[(i + 2) % n]
        if a != b and b != c and (point_on_segment(c, a, b, tol) or point_on_segment(a, b, c, tol)):
            return True
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # edges 0 and n-1 share vertex 0
            if segments_intersect(a, b, pts[j], pts[(j + 1) % n], tol):
                return True
    return False


def has_repeated_points(v: np.ndarray, tol: float) -> bool:
    """True if two vertices of ``v`` lie within distance ``tol`` (m) of each other."""
    v = _as_poly(v)
    if len(v) < 2:
        return False
    diff = v[:, None, :] - v[None, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    iu = np.triu_indices(len(v), k=1)
    return bool(np.any(dist[iu] <= tol))


def point_in_polygon(p: np.ndarray, v: np.ndarray, tol: float = 0.0) -> bool:
    """True if point ``p`` is inside polygon ``v`` or within ``tol`` (m) of its boundary.

    Works for convex and non-convex simple polygons, in either orientation (even-odd rule).
    """
    v = _as_poly(v)
    px, py = float(p[0]), float(p[1])
    a = v
    b = _next(v)
    d = b - a
    len2 = np.sum(d * d, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(len2 > 0.0, ((px - a[:, 0]) * d[:, 0] + (py - a[:, 1]) * d[:, 1]) / len2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    dist = np.hypot(px - (a[:, 0] + t * d[:, 0]), py - (a[:, 1] + t * d[:, 1]))
    if np.any(dist <= tol):
        return True
    # Crossing number of a ray towards +x; half-open rule in y avoids double counts at vertices.
    ay, by = a[:, 1], b[:, 1]
    straddle = (ay > py) != (by > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[:, 0] + (py - ay) * d[:, 0] / np.where(straddle, by - ay, 1.0)
    return bool(np.count_nonzero(straddle & (px < x_cross)) % 2 == 1)


def convex_clip(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Intersection of two convex CCW polygons (Sutherland-Hodgman), (m, 2) in m; (0, 2) if none."""
    out = [(float(x), float(y)) for x, y in _as_poly(subject)]
    cl = [(float(x), float(y)) for x, y in _as_poly(clip)]
    nc = len(cl)
    for k in range(nc):
        if not out:
            break
        ax, ay = cl[k]
        bx, by = cl[(k + 1) % nc]
        ex, ey = bx - ax, by - ay
        inp, out = out, []
        prev = inp[-1]
        s_prev = ex * (prev[1] - ay) - ey * (prev[0] - ax)
        for cur in inp:
            s_cur = ex * (cur[1] - ay) - ey * (cur[0] - ax)
            if s_cur >= 0.0:
                if s_prev < 0.0:
                    t = s_prev / (s_prev - s_cur)
                    out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
                out.append(cur)
            elif s_prev >= 0.0:
                t = s_prev / (s_prev - s_cur)
                out.append((prev[0] + t * (cur[0] - prev[0]), prev[1] + t * (cur[1] - prev[1])))
            prev, s_prev = cur, s_cur
    # Drop consecutive duplicates that appear where the boundaries touch.
    pts = [q for i, q in enumerate(out) if q != out[i - 1]] if len(out) > 1 else out
    if len(pts) < 3:
        return np.zeros((0, 2))
    return np.array(pts, dtype=np.float64)


def overlap_area(a: np.ndarray, b: np.ndarray) -> float:
    """Area of the intersection of two convex CCW polygons (m2); 0 if they only touch."""
    inter = convex_clip(a, b)
    if len(inter) < 3:
        return 0.0
    return max(0.0, signed_area(inter))


def overlap_depths(polys: Sequence[np.ndarray], i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Interpenetration depth (m) of the pairs ``(i[k], j[k])`` of convex CCW polygons.

    The separating-axis depth: over the face normals of both polygons, the least
    overlap of their projections, which is the shortest translation that parts them
    (0 where they are apart or only touch). A corner sunk into a face gives its
    depth below the face, two faces pressed together their closure, and a polygon
    that has passed into another along a shared line (where every vertex lies on
    the other's boundary) the depth it has gone in. Vectorised over the pairs, in
    slices of about ``_PAIR_SLICE`` vertex-axis products.
    """
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    out = np.zeros(len(i))
    if len(i) == 0:
        return out
    groups = polygon_groups(polys)
    n = max(g[0] for g in groups)
    # Every polygon padded to n vertices by repeating its first (padded edges have no
    # length and give no axis).
    verts = np.zeros((len(polys), n, 2))
    for m, idx, v in groups:
        verts[idx, :m] = v
        verts[idx, m:] = v[:, :1]
    edge = _next_many(verts) - verts
    length = np.hypot(edge[..., 0], edge[..., 1])
    normal = np.stack([edge[..., 1], -edge[..., 0]], axis=-1) / np.where(length > 0, length,
                                                                          1.0)[..., None]
    step = max(1, _PAIR_SLICE // (4 * n * n))
    for s in range(0, len(i), step):
        a, b = i[s:s + step], j[s:s + step]
        axes = np.concatenate([normal[a], normal[b]], axis=1)  # (p, 2n, 2)
        valid = np.concatenate([length[a], length[b]], axis=1) > 0
        pa = np.einsum("pvk,pak->pav", verts[a], axes)  # (p, 2n, n)
        pb = np.einsum("pvk,pak->pav", verts[b], axes)
        pen = np.minimum(pa.max(-1) - pb.min(-1), pb.max(-1) - pa.min(-1))
        out[s:s + step] = np.maximum(np.min(np.where(valid, pen, np.inf), axis=1), 0.0)
    return out


def bbox(v: np.ndarray) -> tuple[float, float, float, float]:
    """Bounding box ``(xmin, ymin, xmax, ymax)`` of ``v`` (m)."""
    v = _as_poly(v)
    lo = v.min(axis=0)
    hi = v.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def characteristic_length(v: np.ndarray) -> float:
    """Characteristic size of polygon ``v``: sqrt(|area|) (m)."""
    return math.sqrt(abs(signed_area(v)))


_PAIR_SLICE = 2**22


def near_box_pairs(boxes: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)``, i < j, of boxes ``(xmin, ymin, xmax, ymax)`` (N, 4) that overlap or
    lie within ``tol`` (m) of each other in x and in y, as two arrays in increasing (i, j).

    Sweep and prune, as :func:`find_overlapping_pairs`: N log N plus the number of boxes
    that overlap in x (listed in slices of about ``_PAIR_SLICE`` pairs).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    n = len(boxes)
    order = np.argsort(boxes[:, 0], kind="stable")
    xmin = boxes[order, 0]
    first = np.arange(1, n + 1)
    count = np.maximum(np.searchsorted(xmin, boxes[order, 2] + tol, side="right") - first, 0)
    total = np.cumsum(count)
    found_i, found_j = [], []
    start = 0
    while start < n:
        done = total[start] - count[start]
        stop = min(max(int(np.searchsorted(total, done + _PAIR_SLICE)), start + 1), n)
        c = count[start:stop]
        s = np.repeat(np.arange(start, stop), c)
        t = np.arange(len(s)) - np.repeat(np.cumsum(c) - c, c) + np.repeat(first[start:stop], c)
        i, j = np.minimum(order[s], order[t]), np.maximum(order[s], order[t])
        bi, bj = boxes[i], boxes[j]
        near = ((bj[:, 0] <= bi[:, 2] + tol) & (bi[:, 0] <= bj[:, 2] + tol)
                & (bj[:, 1] <= bi[:, 3] + tol) & (bi[:, 1] <= bj[:, 3] + tol))
        found_i.append(i[near])
        found_j.append(j[near])
        start = stop
    i = np.concatenate(found_i) if found_i else np.zeros(0, np.int64)
    j = np.concatenate(found_j) if found_j else np.zeros(0, np.int64)
    key = np.lexsort((j, i))
    return i[key], j[key]


def find_overlapping_pairs(polys: Sequence[np.ndarray], tol_area: float) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, i < j, of convex CCW polygons whose intersection exceeds ``tol_area`` (m2).

    Sweep and prune: boxes sorted by xmin, each box compared only with those that start
    before it ends in x, and the y test vectorised; only boxes that overlap with positive
    area are clipped. About N log N plus the number of x-overlapping boxes, not N^2.
    """
    n = len(polys)
    if n < 2:
        return []
    polys = [_as_poly(p) for p in polys]
    boxes = bboxes(polys)
    order = np.argsort(boxes[:, 0], kind="stable")
    xmin, ymin, xmax, ymax = boxes[order].T
    # ends[i]: first sorted index whose box starts at or after box i ends in x; the
    # candidates of box i are i + 1 .. ends[i] - 1, all listed at once (in slices of
    # about _PAIR_SLICE pairs, so that memory stays bounded when many boxes share an x-range).
    first = np.arange(1, n + 1)
    count = np.maximum(np.searchsorted(xmin, xmax, side="left") - first, 0)
    total = np.cumsum(count)
    pairs: list[tuple[int, int]] = []
    start = 0
    while start < n:
        done = total[start] - count[start]  # pairs of the boxes before start
        stop = min(max(int(np.searchsorted(total, done + _PAIR_SLICE)), start + 1), n)
        c = count[start:stop]
        ii = np.repeat(np.arange(start, stop), c)
        jj = np.arange(len(ii)) - np.repeat(np.cumsum(c) - c, c) + np.repeat(first[start:stop], c)
        hit = (ymin[jj] < ymax[ii]) & (ymax[jj] > ymin[ii]) & (xmax[jj] > xmin[ii])
        for i, j in zip(ii[hit].tolist(), jj[hit].tolist(), strict=True):
            a, b = int(order[i]), int(order[j])
            if overlap_area(polys[a], polys[b]) > tol_area:
                pairs.append((min(a, b), max(a, b)))
        start = stop
    pairs.sort()
    return pairs


# --------------------------------------------------------------------------- cutting and splitting


def drop_collinear(v: np.ndarray, tol: float) -> np.ndarray:
    """``v`` without repeated vertices and without vertices within ``tol`` (m) of the line
    through their neighbours (180-degree corners); (m, 2), possibly fewer than 3 rows."""
    pts = [np.asarray(q, dtype=np.float64) for q in _as_poly(v)]
    changed = True
    while changed and len(pts) >= 3:
        changed = False
        n = len(pts)
        for k in range(n):
            a, b, c = pts[k - 1], pts[k], pts[(k + 1) % n]
            ac = c - a
            lac = math.hypot(ac[0], ac[1])
            if math.hypot(*(b - a)) <= tol or math.hypot(*(c - b)) <= tol:
                del pts[k]
                changed = True
                break
            dist = abs(ac[0] * (b[1] - a[1]) - ac[1] * (b[0] - a[0])) / lac if lac > 0 else 0.0
            # Only a vertex between its neighbours is a 180-degree corner (not a spike).
            if dist <= tol and float(np.dot(b - a, c - b)) > 0.0:
                del pts[k]
                changed = True
                break
    if not pts:
        return np.zeros((0, 2))
    return np.array(pts, dtype=np.float64)


def split_by_line(
    v: np.ndarray, normal: np.ndarray, offset: float, tol: float
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Split convex polygon ``v`` by the line ``normal . x = offset`` (m).

    Returns ``(below, above)``: the parts with ``normal . x <= offset`` and ``>= offset``,
    each convex and counter-clockwise, or None where that side is empty. Vertices within
    ``tol`` (m, ``normal`` a unit vector) of the line count as on it, so a line that only
    grazes a corner or runs along an edge does not cut.
    """
    v = _as_poly(v)
    d = v @ np.asarray(normal, dtype=np.float64) - offset
    d = np.where(np.abs(d) <= tol, 0.0, d)
    if (d >= 0.0).all():
        return None, v
    if (d <= 0.0).all():
        return v, None
    below: list[np.ndarray] = []
    above: list[np.ndarray] = []
    n = len(v)
    for i in range(n):
        j = (i + 1) % n
        di, dj = d[i], d[j]
        if di <= 0.0:
            below.append(v[i])
        if di >= 0.0:
            above.append(v[i])
        if (di < 0.0 < dj) or (dj < 0.0 < di):
            q = v[i] + (di / (di - dj)) * (v[j] - v[i])
            below.append(q)
            above.append(q)
    lo = np.array(below) if len(below) >= 3 else None
    hi = np.array(above) if len(above) >= 3 else None
    return lo, hi


def slice_convex(
    v: np.ndarray, normal: np.ndarray, offsets: Sequence[float], tol: float
) -> list[np.ndarray]:
    """Convex polygon ``v`` cut by the parallel lines ``normal . x = offsets[k]`` (sorted, m).

    Returns the pieces in order of increasing ``normal . x``; lines that miss ``v`` (or
    graze it within ``tol``) leave it whole.
    """
    out: list[np.ndarray] = []
    rest: np.ndarray | None = _as_poly(v)
    for off in offsets:
        if rest is None:
            break
        lo, hi = split_by_line(rest, normal, float(off), tol)
        if lo is not None and hi is not None:
            out.append(lo)
            rest = hi
        elif lo is not None:  # rest lies wholly below: later lines miss it too
            break
    if rest is not None:
        out.append(rest)
    return out


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Convex hull of ``points`` (m): counter-clockwise, no collinear points (monotone chain)."""
    pts = sorted({(float(x), float(y)) for x, y in _as_poly(points)})
    if len(pts) < 3:
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def half(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        h: list[tuple[float, float]] = []
        for p in seq:
            while len(h) >= 2 and _orient(h[-2], h[-1], p) <= 0.0:
                h.pop()
            h.append(p)
        return h

    lower = half(pts)
    upper = half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)


def _ray_hit(v: np.ndarray, i: int, tol: float) -> tuple[int, np.ndarray] | None:
    """Nearest crossing of the ray that extends edge (i-1, i) beyond vertex i with the
    boundary of ``v``: (edge index j, point)."""
    n = len(v)
    b = v[i]
    d = v[i] - v[i - 1]
    d = d / math.hypot(d[0], d[1])
    best: tuple[float, int, np.ndarray] | None = None
    for j in range(n):
        if j in ((i - 1) % n, i):
            continue
        e0, e1 = v[j], v[(j + 1) % n]
        e = e1 - e0
        den = d[0] * (-e[1]) - d[1] * (-e[0])
        if abs(den) <= 1e-300:
            continue
        r = e0 - b
        t = (r[0] * (-e[1]) - r[1] * (-e[0])) / den
        u = (d[0] * r[1] - d[1] * r[0]) / den
        le = math.hypot(e[0], e[1])
        if t > tol and -tol <= u * le <= le + tol and (best is None or t < best[0]):
            best = (t, j, b + t * d)
    return None if best is None else (best[1], best[2])


def convex_decompose(v: np.ndarray, tol: float) -> list[np.ndarray]:
    """Split a simple counter-clockwise polygon into convex CCW pieces (m).

    At each reflex corner the incoming edge is extended into the polygon until it meets
    the boundary, and the polygon is cut along that chord (for an L shape: one cut along
    the inner wall). Each cut removes a reflex corner and adds none. ``tol`` (m) merges
    near-coincident points and 180-degree corners.
    """
    out: list[np.ndarray] = []
    stack = [drop_collinear(v, tol)]
    while stack:
        p = stack.pop()
        if len(p) < 3:
            continue
        s = corner_sines(p)
        reflex = np.nonzero(s < -1e-12)[0]
        if len(reflex) == 0:
            out.append(p)
            continue
        i = int(reflex[0])
        hit = _ray_hit(p, i, tol)
        if hit is None:  # cannot happen for a simple polygon; keep it rather than loop
            out.append(p)
            continue
        j, q = hit
        n = len(p)
        a_idx = [(i + k) % n for k in range((j - i) % n + 1)]  # i .. j
        b_idx = [(j + 1 + k) % n for k in range((i - j - 1) % n + 1)]  # j+1 .. i
        a = np.vstack([p[a_idx], q[None, :]])
        b = np.vstack([q[None, :], p[b_idx]])
        stack.append(drop_collinear(a, tol))
        stack.append(drop_collinear(b, tol))
    return out


def polygon_overlap_area(a: np.ndarray, b: np.ndarray, tol: float = 0.0) -> float:
    """Area (m2) common to two simple CCW polygons, convex or not (via convex pieces)."""
    pa = convex_decompose(a, tol) if not is_convex(a) else [_as_poly(a)]
    pb = convex_decompose(b, tol) if not is_convex(b) else [_as_poly(b)]
    total = 0.0
    for x in pa:
        bx = bbox(x)
        for y in pb:
            by = bbox(y)
            if bx[0] > by[2] or by[0] > bx[2] or bx[1] > by[3] or by[1] > bx[3]:
                continue
            total += overlap_area(x, y)
    return total


def distance_to_boundary(p: np.ndarray, v: np.ndarray) -> float:
    """Distance (m) from point ``p`` to the boundary of polygon ``v``."""
    v = _as_poly(v)
    a = v
    d = _next(v) - a
    len2 = np.sum(d * d, axis=1)
    q = np.asarray(p, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(len2 > 0.0, np.sum((q - a) * d, axis=1) / len2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    foot = a + t[:, None] * d
    return float(np.min(np.hypot(q[0] - foot[:, 0], q[1] - foot[:, 1])))


def polar_moment(v: np.ndarray, c: np.ndarray) -> float:
    """Polar moment of area of polygon ``v`` about point ``c`` divided by its area (m2):
    r_g^2 = J / A, J = Ixx + Iyy (shoelace formulas); about the centroid, the radius of
    gyration squared."""
    p = _as_poly(v) - c
    x0, y0 = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    cross = x0 * y1 - x1 * y0
    ixx = np.sum(cross * (y0**2 + y0 * y1 + y1**2)) / 12.0
    iyy = np.sum(cross * (x0**2 + x0 * x1 + x1**2)) / 12.0
    area = np.sum(cross) / 2.0
    return float((ixx + iyy) / area)


# --------------------------------------------------------------------------- many polygons at once
#
# One answer per polygon of a list, as the scalar functions above give one by one, without a
# Python loop over the polygons: the polygons are grouped by vertex count (polygon_groups),
# each group an (m, n, 2) array, and the scalar formulas run on whole groups. Each polygon's
# n terms are summed in the scalar function's order, so that the answers are the scalar
# functions' to the last bit (tests/test_geometry.py compares them).


def polygon_groups(polys: Sequence[np.ndarray]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The polygons grouped by vertex count: ``(n, indices, vertices)`` per count n, with
    ``vertices`` (m, n, 2) in m the polygons ``polys[indices]``, in increasing n."""
    counts = np.fromiter((len(p) for p in polys), dtype=np.int64, count=len(polys))
    out = []
    for n in np.unique(counts):
        idx = np.nonzero(counts == n)[0]
        v = np.asarray(np.stack([polys[i] for i in idx]), dtype=np.float64).reshape(len(idx),
                                                                                   int(n), 2)
        out.append((int(n), idx, v))
    return out


def _next_many(v: np.ndarray) -> np.ndarray:
    return np.concatenate([v[:, 1:], v[:, :1]], axis=1)


def _prev_many(v: np.ndarray) -> np.ndarray:
    return np.concatenate([v[:, -1:], v[:, :-1]], axis=1)


def _shoelace_many(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = v - v[:, :1]
    dn = _next_many(d)
    cross = d[..., 0] * dn[..., 1] - dn[..., 0] * d[..., 1]
    return 0.5 * np.sum(cross, axis=1), d, cross


def signed_areas(polys: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`signed_area` of each polygon (m2), shape (N,)."""
    out = np.zeros(len(polys))
    for n, idx, v in polygon_groups(polys):
        if n >= 3:
            out[idx] = _shoelace_many(v)[0]
    return out


def centroids(polys: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`centroid` of each polygon (m), shape (N, 2)."""
    out = np.zeros((len(polys), 2))
    for n, idx, v in polygon_groups(polys):
        if n == 0:
            raise ValueError("centroid of an empty polygon")
        mean = v.mean(axis=1)
        if n < 3:
            out[idx] = mean
            continue
        area, d, cross = _shoelace_many(v)
        diag2 = np.sum((v.max(axis=1) - v.min(axis=1)) ** 2, axis=1)
        flat = (np.abs(area) <= 1e-14 * diag2) | (area == 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            c = np.sum((d + _next_many(d)) * cross[..., None], axis=1) / (6.0 * area)[:, None]
        out[idx] = np.where(flat[:, None], mean, v[:, 0] + c)
    return out


def polar_moments(polys: Sequence[np.ndarray], centres: np.ndarray) -> np.ndarray:
    """:func:`polar_moment` of each polygon about its point of ``centres`` (N, 2) (m2),
    shape (N,)."""
    centres = np.asarray(centres, dtype=np.float64)
    out = np.zeros(len(polys))
    for _, idx, v in polygon_groups(polys):
        p = v - centres[idx][:, None, :]
        x0, y0 = p[..., 0], p[..., 1]
        x1, y1 = np.roll(x0, -1, axis=1), np.roll(y0, -1, axis=1)
        cross = x0 * y1 - x1 * y0
        ixx = np.sum(cross * (y0**2 + y0 * y1 + y1**2), axis=1) / 12.0
        iyy = np.sum(cross * (x0**2 + x0 * x1 + x1**2), axis=1) / 12.0
        area = np.sum(cross, axis=1) / 2.0
        out[idx] = (ixx + iyy) / area
    return out


def bboxes(polys: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`bbox` of each polygon, (N, 4) rows ``(xmin, ymin, xmax, ymax)`` (m)."""
    out = np.zeros((len(polys), 4))
    for _, idx, v in polygon_groups(polys):
        out[idx, :2] = v.min(axis=1)
        out[idx, 2:] = v.max(axis=1)
    return out


def _in_polygon_many(p: np.ndarray, v: np.ndarray, tol: float) -> np.ndarray:
    """:func:`point_in_polygon` of points ``p`` (c, 2) in polygons ``v`` (c, n, 2), (c,)."""
    px, py = p[:, 0:1], p[:, 1:2]
    a = v
    b = _next_many(v)
    d = b - a
    len2 = np.sum(d * d, axis=2)
    ax, ay, dx, dy = a[..., 0], a[..., 1], d[..., 0], d[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(len2 > 0.0, ((px - ax) * dx + (py - ay) * dy) / len2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    dist = np.hypot(px - (ax + t * dx), py - (ay + t * dy))
    by = b[..., 1]
    straddle = (ay > py) != (by > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = ax + (py - ay) * dx / np.where(straddle, by - ay, 1.0)
    odd = np.count_nonzero(straddle & (px < x_cross), axis=1) % 2 == 1
    return np.any(dist <= tol, axis=1) | odd


def points_in_polygons(points: np.ndarray, polys: Sequence[np.ndarray],
                       tol: float = 0.0) -> np.ndarray:
    """:func:`point_in_polygon` of every point (P, 2) in every polygon: (P, N) bool.

    Only the pairs whose point lies in the polygon's bounding box grown by ``tol`` (m)
    are tested (a point farther from the box is farther than ``tol`` from the polygon
    and outside it); those are tested all at once.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out = np.zeros((len(pts), len(polys)), dtype=bool)
    if not len(pts) or not len(polys):
        return out
    groups = polygon_groups(polys)
    count = np.zeros(len(polys), dtype=np.int64)
    row = np.zeros(len(polys), dtype=np.int64)
    for n, idx, _ in groups:
        count[idx] = n
        row[idx] = np.arange(len(idx))
    box = bboxes(polys)
    lo, hi = box[:, :2] - 2.0 * tol, box[:, 2:] + 2.0 * tol
    chunk = max(1, 2**22 // len(polys))
    for s in range(0, len(pts), chunk):
        q = pts[s:s + chunk]
        near = np.all((lo[None] <= q[:, None]) & (q[:, None] <= hi[None]), axis=2)
        pi, ni = np.nonzero(near)
        for n, _, v in groups:
            sel = count[ni] == n
            if np.any(sel):
                out[s + pi[sel], ni[sel]] = _in_polygon_many(q[pi[sel]], v[row[ni[sel]]], tol)
    return out


def drop_collinear_all(polys: Sequence[np.ndarray], tol: float) -> list[np.ndarray]:
    """:func:`drop_collinear` of each polygon, as a list.

    A polygon whose edges are all longer than 2 ``tol`` and whose vertices all lie
    farther than 2 ``tol`` (m) from the line through their neighbours loses nothing: it
    is kept as it is, found for all polygons at once; only the others go through the
    scalar function.
    """
    whole = np.zeros(len(polys), dtype=bool)
    for n, idx, v in polygon_groups(polys):
        if n < 3:
            continue
        a, b, c = _prev_many(v), v, _next_many(v)
        ac = c - a
        lac = np.hypot(ac[..., 0], ac[..., 1])
        cross = np.abs(ac[..., 0] * (b[..., 1] - a[..., 1]) - ac[..., 1] * (b[..., 0] - a[..., 0]))
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = np.where(lac > 0.0, cross / np.where(lac > 0.0, lac, 1.0), 0.0)
        edge = np.hypot(*(c - b).transpose(2, 0, 1))
        whole[idx] = np.all((edge > 2.0 * tol) & (dist > 2.0 * tol), axis=1)
    return [np.array(p, dtype=np.float64) if whole[i] else drop_collinear(p, tol)
            for i, p in enumerate(polys)]
