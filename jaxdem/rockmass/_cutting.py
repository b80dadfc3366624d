"""Cutting the domain into convex pieces (steps 2 to 5 of :mod:`jaxdem.rockmass`): the
pieces in work (``Work``: polygons with their material, excavation and parent), slicing by
a joint set's lines or a discontinuity's line, cuts across a trace at its ends, splitting
along a zone's or an opening's outline (wedges outside each convex part), and merging
slivers and tiny pieces into a convex neighbour.

Host NumPy with :mod:`jaxdem.geometry`; takes the lines of :mod:`jaxdem.rockmass._traces`
and modifies a ``Work`` in place for :func:`jaxdem.rockmass.generate`; the mesh
(:mod:`jaxdem.rockmass._mesh`) cuts the same ``Work`` further.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxdem import geometry
from jaxdem.rockmass._traces import Family

SLIVER_RATIO = 1e-3
"""A piece is thin when area / (longest edge)^2 is below this (-)."""
TINY_AREA = 1e-3
"""A piece is tiny when its area is below this times (smallest length scale)^2 (-)."""


class Work:
    """Pieces while they are being cut: polygons and per-piece tags."""

    def __init__(self) -> None:
        self.polys: list[np.ndarray] = []
        self.material: list[str] = []
        self.excavation: list[str | None] = []
        self.parent: list[int] = []

    def add(self, v: np.ndarray, material: str, excavation: str | None, parent: int) -> None:
        self.polys.append(v)
        self.material.append(material)
        self.excavation.append(excavation)
        self.parent.append(parent)

    def __len__(self) -> int:
        return len(self.polys)

    def boxes(self) -> np.ndarray:
        return geometry.bboxes(self.polys).reshape(-1, 4)

    def replace(self, i: int, parts: list[np.ndarray]) -> None:
        """Piece i becomes parts[0]; the other parts are appended with i's tags."""
        self.polys[i] = parts[0]
        for p in parts[1:]:
            self.add(p, self.material[i], self.excavation[i], self.parent[i])


def piece_area(v: np.ndarray) -> float:
    return geometry.signed_area(v)


def slice_family(work: Work, fam: Family, tol: float) -> None:
    new = Work()
    for i, v in enumerate(work.polys):
        proj = v @ fam.normal
        kmin = math.ceil((float(proj.min()) - fam.c0 + tol) / fam.spacing)
        kmax = math.floor((float(proj.max()) - fam.c0 - tol) / fam.spacing)
        offsets = fam.c0 + np.arange(kmin, kmax + 1) * fam.spacing
        for part in geometry.slice_convex(v, fam.normal, offsets, tol):
            new.add(part, work.material[i], work.excavation[i], work.parent[i])
    work.__dict__.update(new.__dict__)


def cut_by_line(work: Work, normal: np.ndarray, offset: float, tol: float) -> None:
    if not len(work):
        return
    b = work.boxes()
    corners = np.stack(
        [b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1
    )  # (N, 4, 2)
    d = corners @ normal - offset
    hit = np.nonzero((d.min(axis=1) < -tol) & (d.max(axis=1) > tol))[0]
    for i in hit:
        lo, hi = geometry.split_by_line(work.polys[i], normal, offset, tol)
        if lo is not None and hi is not None:
            work.replace(int(i), [lo, hi])


def cut_at_ends(
    work: Work, ends: list[tuple[np.ndarray, np.ndarray]], tol: float, snap: float
) -> None:
    """Cut the pieces whose edge holds a trace end, across the trace through that end."""
    if not ends or not len(work):
        return
    boxes = work.boxes()
    children: list[list[int]] = [[i] for i in range(len(work))]
    for e, d in ends:
        near = np.nonzero(
            (boxes[:, 0] - tol <= e[0])
            & (e[0] <= boxes[:, 2] + tol)
            & (boxes[:, 1] - tol <= e[1])
            & (e[1] <= boxes[:, 3] + tol)
        )[0]
        for orig in near:
            for i in list(children[orig]):
                v = work.polys[i]
                if geometry.distance_to_boundary(e, v) > tol:
                    continue
                if float(np.min(np.hypot(*(v - e).T))) <= snap:
                    continue
                lo, hi = geometry.split_by_line(v, d, float(d @ e), tol)
                if lo is not None and hi is not None:
                    work.replace(i, [lo, hi])
                    children[orig].append(len(work) - 1)


def _wedges(part: np.ndarray) -> list[list[tuple[np.ndarray, float, bool]]]:
    """Half-planes (normal, offset, keep_below) of each wedge outside convex ``part``."""
    c = geometry.centroid(part)
    m = len(part)
    out = []
    for k in range(m):
        a = part[k] - c
        b = part[(k + 1) % m] - c
        e = part[(k + 1) % m] - part[k]
        m1 = np.array([a[1], -a[0]]) / math.hypot(*a)
        m2 = np.array([-b[1], b[0]]) / math.hypot(*b)
        n3 = np.array([e[1], -e[0]]) / math.hypot(*e)  # outward normal of edge k
        out.append(
            [(m1, float(m1 @ c), True), (m2, float(m2 @ c), True), (n3, float(n3 @ part[k]), False)]
        )
    return out


def _outside(v: np.ndarray, normals: np.ndarray, offsets: np.ndarray, below: np.ndarray,
             tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Per half-plane (normal . x <= offset where ``below``, >= otherwise): whether convex
    ``v`` lies wholly outside it, and whether wholly inside, both by more than a margin
    (2 tol, plus the round-off of coordinates far from (0, 0)): the parts that clipping by
    other half-planes leaves of ``v`` lie there too, and each such half-plane empties them,
    or leaves them whole (:func:`geometry.split_by_line` puts points within tol on the line)."""
    margin = 2.0 * tol + 1e-12 * (float(np.max(np.abs(v))) + float(np.max(np.abs(offsets))))
    d = v @ normals.T - offsets
    s = np.where(below, d, -d)  # > 0: on the side clipped away
    return s.min(axis=0) > margin, s.max(axis=0) < -margin


def clip(v: np.ndarray, planes: list[tuple[np.ndarray, float, bool]], tol: float):
    """Convex ``v`` clipped by the half-planes ``(normal, offset, keep_below)`` in turn; None
    if nothing is left. Half-planes that hold ``v`` whole are passed over (:func:`_outside`)."""
    if not planes:
        return v
    normals = np.array([n for n, _, _ in planes], dtype=np.float64)
    offsets = np.array([off for _, off, _ in planes], dtype=np.float64)
    below = np.array([b for _, _, b in planes], dtype=bool)
    outside, inside = _outside(v, normals, offsets, below, tol)
    if outside.any():
        return None
    for k in np.nonzero(~inside)[0]:
        n, off, keep_below = planes[k]
        lo, hi = geometry.split_by_line(v, n, off, tol)
        v = lo if keep_below else hi
        if v is None:
            return None
    return v


def cut_by_region(
    work: Work,
    outline: np.ndarray,
    tol: float,
    area_tol: float,
    material: str | None = None,
    excavation: str | None = None,
) -> None:
    """Split pieces along a zone or excavation outline and tag the parts inside it."""
    for part in geometry.convex_decompose(outline, tol):
        box = geometry.bbox(part)
        inside_planes = [(n, off, True) for n, off, _ in (w[2] for w in _wedges(part))]
        wedges = _wedges(part)
        # All the wedges' half-planes, to pass over the wedges a piece lies wholly outside.
        w_normals = np.array([[n for n, _, _ in w] for w in wedges]).reshape(-1, 2)
        w_offsets = np.array([[off for _, off, _ in w] for w in wedges]).ravel()
        w_below = np.array([[b for _, _, b in w] for w in wedges]).ravel()
        boxes = work.boxes()
        cand = np.nonzero(
            (boxes[:, 0] < box[2] - tol)
            & (boxes[:, 2] > box[0] + tol)
            & (boxes[:, 1] < box[3] - tol)
            & (boxes[:, 3] > box[1] + tol)
        )[0]
        for i in cand:
            i = int(i)
            v = work.polys[i]
            inner = clip(v, inside_planes, tol)
            if inner is None or piece_area(inner) <= area_tol:
                continue
            if abs(piece_area(inner) - piece_area(v)) <= area_tol:
                parts = [v]
            else:
                parts = [inner]
                outside, _ = _outside(v, w_normals, w_offsets, w_below, tol)
                for k in np.nonzero(~outside.reshape(len(wedges), 3).any(axis=1))[0]:
                    w = clip(v, wedges[k], tol)
                    if w is not None and piece_area(w) > area_tol:
                        parts.append(w)
            work.replace(i, parts)
            if material is not None:
                work.material[i] = material
            if excavation is not None:
                work.excavation[i] = excavation


def _shared_length(v: np.ndarray, w: np.ndarray, tol: float) -> float:
    """Length (m) of boundary that convex polygons ``v`` and ``w`` share."""
    a, b = v, np.roll(v, -1, axis=0)
    c, d = w, np.roll(w, -1, axis=0)
    e = b - a
    le = np.hypot(e[:, 0], e[:, 1])
    u = e / le[:, None]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    # (m, k): distances of w's edge ends from v's edge lines, and positions along them.
    dc = np.abs(np.einsum("mi,kmi->km", nrm, c[:, None, :] - a[None, :, :])).T
    dd = np.abs(np.einsum("mi,kmi->km", nrm, d[:, None, :] - a[None, :, :])).T
    tc = np.einsum("mi,kmi->km", u, c[:, None, :] - a[None, :, :]).T
    td = np.einsum("mi,kmi->km", u, d[:, None, :] - a[None, :, :]).T
    on = (dc <= tol) & (dd <= tol)
    lo = np.maximum(np.minimum(tc, td), 0.0)
    hi = np.minimum(np.maximum(tc, td), le[:, None])
    return float(np.sum(np.where(on, np.clip(hi - lo, 0.0, None), 0.0)))


def _is_sliver(v: np.ndarray, a: float, lmin: float) -> bool:
    e = np.roll(v, -1, axis=0) - v
    emax = float(np.max(np.hypot(e[:, 0], e[:, 1])))
    return a < TINY_AREA * lmin * lmin or a < SLIVER_RATIO * emax * emax


def _thin(polys: list[np.ndarray], areas: np.ndarray, lmin: float) -> np.ndarray:
    """:func:`_is_sliver` of every piece at once."""
    emax = np.zeros(len(polys))
    for _, idx, v in geometry.polygon_groups(polys):
        e = np.roll(v, -1, axis=1) - v
        emax[idx] = np.max(np.hypot(e[..., 0], e[..., 1]), axis=1)
    return (areas < TINY_AREA * lmin * lmin) | (areas < SLIVER_RATIO * emax * emax)


def merge_slivers(
    work: Work, keys: list[Any], lmin: float, tol: float, eps_area: float
) -> list[int]:
    """Merge slivers into a convex union with a same-key neighbour; returns the unmerged."""
    n = len(work)
    if n < 2:
        return []
    areas = geometry.signed_areas(work.polys)
    thin = _thin(work.polys, areas, lmin)
    slivers = [i for i in np.argsort(areas) if thin[i]]
    if not slivers:
        return []
    codes = {k: c for c, k in enumerate(dict.fromkeys(keys))}
    code = np.array([codes[k] for k in keys])
    boxes = work.boxes()
    alive = np.ones(n, dtype=bool)
    failed = []
    for i in slivers:
        i = int(i)
        if not alive[i]:
            continue
        v = work.polys[i]
        a = areas[i]
        if not _is_sliver(v, a, lmin):
            continue
        bx = boxes[i]
        cand = np.nonzero(
            alive
            & (code == code[i])
            & (boxes[:, 0] <= bx[2] + tol)
            & (boxes[:, 2] >= bx[0] - tol)
            & (boxes[:, 1] <= bx[3] + tol)
            & (boxes[:, 3] >= bx[1] - tol)
        )[0]
        shared = [(_shared_length(v, work.polys[j], tol), int(j)) for j in cand if j != i]
        shared = sorted((s for s in shared if s[0] > tol), reverse=True)
        merged = False
        for _, j in shared:
            u = geometry.convex_hull(np.vstack([v, work.polys[j]]))
            au = piece_area(u)
            if au - (a + areas[j]) <= 1e-9 * (a + areas[j]) + eps_area:
                u = geometry.drop_collinear(u, tol)
                work.polys[j] = u
                areas[j] = au
                boxes[j] = [*u.min(axis=0), *u.max(axis=0)]
                alive[i] = False
                merged = True
                break
        if not merged:
            failed.append(i)
    keep = np.nonzero(alive)[0]
    gone = set(np.nonzero(~alive)[0].tolist())
    failed = [int(np.searchsorted(keep, i)) for i in failed if i not in gone]
    for name in ("polys", "material", "excavation", "parent"):
        seq = getattr(work, name)
        setattr(work, name, [seq[k] for k in keep])
    return failed
