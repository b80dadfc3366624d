"""Generated rock mass: a scene's domain cut by joints, zones and excavations (host NumPy).

``generate(scene)`` turns ``[domain]``, the joint sets of ``[joints.NAME]``,
``[[discontinuities]]``, ``[[zones]]``, ``[[excavations]]`` and ``domain.mesh_size`` into
convex pieces (rigid blocks) that tile the domain exactly, each edge labelled with what
it is: ``("joint", NAME)`` on a joint trace, ``("intact", None)`` on a cut through intact
rock, ``("outer", None)`` on the domain outline. Explicit ``[[blocks]]`` are not touched
(they stay in ``scene.blocks``; the scene refuses them where they overlap the domain).

Algorithm (the UDEC way: cut whole lines, then say which parts of a cut are joints)

1. Convex split of the outline. At each reflex corner the incoming edge is extended
   into the domain until it meets the outline, and the domain is cut there (an L shape
   gets one cut along its inner wall). These cuts are intact rock.
2. Joint sets. A set with trace angle ``dip_deg`` (counter-clockwise from +x) and
   ``spacing`` s is the family of lines ``n . x = n . origin + k s`` (n the unit normal
   of the traces, origin default the domain centroid). Every piece is sliced by all the
   lines of the family that cross it at once (a convex polygon cut by parallel lines).
   Each ``[[discontinuities]]`` segment cuts the pieces its whole line crosses (bounding
   box prefilter). A non-persistent set (persistence p < 1) carries trace segments of
   length L = p / (1 - p) * gap separated by rock bridges ``gap`` (default: spacing), the
   segments of line k centred at ``d . origin + (k mod 2) P / 2 + m P`` along the trace
   (period P = L + gap, d the trace direction): successive lines stagger by half a period.
3. Trace ends. Where a trace segment (of a non-persistent set or a discontinuity) ends
   inside a piece's edge, the pieces on both sides are cut through that point at right
   angles to the trace, so that each edge is wholly joint or wholly intact. An end
   closer than 1% of the smallest length scale (spacing, mesh size, domain size) to a
   corner of the piece is moved to that corner instead (no sliver).
4. Zones, then excavations, in file order. Each outline is split into convex parts C.
   A piece that straddles C is replaced by its part inside C (given the zone's material,
   or the excavation's name) and by convex parts outside: the wedges between the rays
   from C's centroid through consecutive corners of C, beyond C's edge between them.
   The ray cuts are intact rock and stay inside the straddling piece.
5. Slivers and tiny pieces (area < 1e-3 * min(spacing, mesh_size, domain size)^2, or
   area / (longest edge)^2 < 1e-3) left by near-coincident cuts are merged into the
   neighbour (same material and excavation) with which they share the longest edge,
   when the union is convex; the trace on the shared edge then disappears and the other
   one represents both. A thin sliver (area / (longest edge)^2 < 1e-3) along a joint
   trace that cannot be merged is refused with a ``SceneError`` naming the traces
   ("joints.set1: traces nearly coincide with discontinuities.0, leaving a sliver block
   ..."). Others are kept: a small but well-shaped piece that cannot be merged (a corner
   cut off where several traces, trace-end cuts and an opening's ray cuts meet) is a
   small block, not a degenerate one, and the scene is valid.
6. Mesh (``domain.mesh_size`` h). Every piece is clipped by the square grid of lines
   x = x0 + i h, y = y0 + j h ((x0, y0) the lower-left corner of the domain's bounding box),
   so cells are convex and conform to joints and openings. Tiny or thin cells are merged
   into a cell of the same piece as in step 5 (two clipped cells that share a grid edge
   always have a convex union); cells that cannot be merged are kept. Then every cell
   outside the excavations is split into triangles (squares along alternating diagonals,
   other quadrilaterals along the shorter one, larger polygons from their centroid): the
   solver makes these cells deformable with constant strain, and constant-strain cells
   joined at their corners converge to the elastic continuum only when they are
   triangles (the linear triangle of finite elements).
7. 180-degree corners are dropped and every edge is labelled by testing it against the
   outline, the set lines and the discontinuity lines with tolerance 1e-9 * domain size:
   an edge on a trace line is a joint when at least half of it lies on trace segments
   (after step 3 that is all or nothing, up to the 1% snap), else intact.

Cost: about linear in the number of pieces; 100 m x 100 m with two persistent sets at 1 m
(10,000 blocks) generates in about a second.

Example::

    >>> from jaxdem import load_scene
    >>> from jaxdem.rockmass import generate
    >>> rm = generate(load_scene("tunnel.toml"))
    >>> len(rm.pieces), rm.pieces[0].edge_labels[0]
    (412, ('joint', 'set1'))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jaxdem import geometry
from jaxdem.scene import Scene, SceneError

__all__ = ["Piece", "RockMass", "generate"]

SLIVER_RATIO = 1e-3
"""A piece is thin when area / (longest edge)^2 is below this (-)."""
TINY_AREA = 1e-3
"""A piece is tiny when its area is below this times (smallest length scale)^2 (-)."""
SNAP = 1e-2
"""Trace ends closer than this times the smallest length scale to a corner snap to it (-)."""


@dataclass
class Piece:
    """One generated block.

    vertices: (n, 2) m, counter-clockwise, strictly convex (no 180-degree corners).
    material: name of its material (the domain's, or a zone's).
    excavation: name of the excavation it lies in, else None.
    edge_labels: per edge k (vertex k -> k+1): ("joint", joint name), ("intact", None) or
      ("outer", None).
    """

    vertices: np.ndarray
    material: str
    excavation: str | None
    edge_labels: list[tuple[str, str | None]] = field(default_factory=list)


@dataclass
class RockMass:
    """The generated pieces of a scene (explicit blocks are not included)."""

    pieces: list[Piece]

    def polygons(self) -> list[np.ndarray]:
        """The pieces' vertices, (n, 2) m each, in piece order."""
        return [p.vertices for p in self.pieces]


# --------------------------------------------------------------------------- cut lines


@dataclass
class _Family:
    """The parallel trace lines of a joint set: n . x = c0 + k spacing."""

    source: str
    joint: str
    normal: np.ndarray
    direction: np.ndarray
    c0: float
    spacing: float
    s0: float
    length: float  # trace segment length (m); inf when persistent
    period: float  # length + bridge (m)

    def covered(self, k: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Length (m) of [lo, hi] (along the trace) that lies on trace segments of line k."""
        if not math.isfinite(self.length):
            return hi - lo
        start = self.s0 + (np.mod(k, 2) * 0.5 * self.period) - 0.5 * self.length

        def cum(s: np.ndarray) -> np.ndarray:
            u = s - start
            return np.floor(u / self.period) * self.length + np.minimum(
                np.mod(u, self.period), self.length
            )

        return cum(hi) - cum(lo)

    def ends(self, k: int, smin: float, smax: float) -> np.ndarray:
        """Along-trace coordinates (m) of the segment ends of line k within [smin, smax]."""
        if not math.isfinite(self.length):
            return np.zeros(0)
        centre0 = self.s0 + (k % 2) * 0.5 * self.period
        m = np.arange(
            math.floor((smin - centre0) / self.period) - 1,
            math.ceil((smax - centre0) / self.period) + 2,
        )
        c = centre0 + m * self.period
        e = np.concatenate([c - 0.5 * self.length, c + 0.5 * self.length])
        return np.sort(e[(e >= smin) & (e <= smax)])


@dataclass
class _Line:
    """One discontinuity: the line n . x = offset, a joint on [s0, s1] along d."""

    source: str
    joint: str
    normal: np.ndarray
    direction: np.ndarray
    offset: float
    s0: float
    s1: float


def _unit(angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    d = np.array([math.cos(angle_rad), math.sin(angle_rad)])
    return d, np.array([-d[1], d[0]])


def _families(scene: Scene, origin_default: np.ndarray) -> list[_Family]:
    out = []
    for name, j in scene.joints.items():
        if not j.is_set:
            continue
        d, n = _unit(math.radians(float(j.dip_deg)))  # type: ignore[arg-type]
        o = np.array(j.origin, dtype=float) if j.origin is not None else origin_default
        length = j.trace_length
        out.append(
            _Family(
                source=f"joints.{name}",
                joint=name,
                normal=n,
                direction=d,
                c0=float(n @ o),
                spacing=float(j.spacing),  # type: ignore[arg-type]
                s0=float(d @ o),
                length=length,
                period=length + j.bridge_length if math.isfinite(length) else math.inf,
            )
        )
    return out


def _lines(scene: Scene) -> list[_Line]:
    out = []
    for i, disc in enumerate(scene.discontinuities):
        a = np.asarray(disc.start, float)
        b = np.asarray(disc.end, float)
        d = (b - a) / float(np.hypot(*(b - a)))
        n = np.array([-d[1], d[0]])
        out.append(
            _Line(
                source=f"discontinuities.{i}",
                joint=disc.joint,
                normal=n,
                direction=d,
                offset=float(n @ a),
                s0=float(d @ a),
                s1=float(d @ b),
            )
        )
    return out


# --------------------------------------------------------------------------- pieces in work


class _Work:
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
        lo = np.array([p.min(axis=0) for p in self.polys]).reshape(-1, 2)
        hi = np.array([p.max(axis=0) for p in self.polys]).reshape(-1, 2)
        return np.concatenate([lo, hi], axis=1)

    def replace(self, i: int, parts: list[np.ndarray]) -> None:
        """Piece i becomes parts[0]; the other parts are appended with i's tags."""
        self.polys[i] = parts[0]
        for p in parts[1:]:
            self.add(p, self.material[i], self.excavation[i], self.parent[i])


def _area(v: np.ndarray) -> float:
    return geometry.signed_area(v)


def _slice_family(work: _Work, fam: _Family, tol: float) -> None:
    new = _Work()
    for i, v in enumerate(work.polys):
        proj = v @ fam.normal
        kmin = math.ceil((float(proj.min()) - fam.c0 + tol) / fam.spacing)
        kmax = math.floor((float(proj.max()) - fam.c0 - tol) / fam.spacing)
        offsets = fam.c0 + np.arange(kmin, kmax + 1) * fam.spacing
        for part in geometry.slice_convex(v, fam.normal, offsets, tol):
            new.add(part, work.material[i], work.excavation[i], work.parent[i])
    work.__dict__.update(new.__dict__)


def _cut_by_line(work: _Work, normal: np.ndarray, offset: float, tol: float) -> None:
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


def _trace_ends(
    families: list[_Family], lines: list[_Line], outline: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, trace direction) of every trace segment end that may lie in the domain."""
    out = []
    box = geometry.bbox(outline)
    corners = np.array([[box[0], box[1]], [box[2], box[1]], [box[2], box[3]], [box[0], box[3]]])
    for fam in families:
        if not math.isfinite(fam.length):
            continue
        pn = corners @ fam.normal
        ps = corners @ fam.direction
        kmin = math.ceil((pn.min() - fam.c0) / fam.spacing)
        kmax = math.floor((pn.max() - fam.c0) / fam.spacing)
        for k in range(kmin, kmax + 1):
            c = fam.c0 + k * fam.spacing
            for s in fam.ends(k, float(ps.min()), float(ps.max())):
                out.append((c * fam.normal + s * fam.direction, fam.direction))
    for line in lines:
        for s in (line.s0, line.s1):
            out.append((line.offset * line.normal + s * line.direction, line.direction))
    return out


def _cut_at_ends(
    work: _Work, ends: list[tuple[np.ndarray, np.ndarray]], tol: float, snap: float
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


def _clip(v: np.ndarray, planes: list[tuple[np.ndarray, float, bool]], tol: float):
    for n, off, below in planes:
        lo, hi = geometry.split_by_line(v, n, off, tol)
        v = lo if below else hi
        if v is None:
            return None
    return v


def _cut_by_region(
    work: _Work,
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
            inner = _clip(v, inside_planes, tol)
            if inner is None or _area(inner) <= area_tol:
                continue
            if abs(_area(inner) - _area(v)) <= area_tol:
                parts = [v]
            else:
                parts = [inner]
                for planes in wedges:
                    w = _clip(v, planes, tol)
                    if w is not None and _area(w) > area_tol:
                        parts.append(w)
            work.replace(i, parts)
            if material is not None:
                work.material[i] = material
            if excavation is not None:
                work.excavation[i] = excavation


def _mesh(work: _Work, h: float, origin: np.ndarray, tol: float) -> None:
    new = _Work()
    ex = np.array([1.0, 0.0])
    ey = np.array([0.0, 1.0])
    for i, v in enumerate(work.polys):
        lo, hi = v.min(axis=0), v.max(axis=0)
        xs = origin[0] + h * np.arange(
            math.ceil((lo[0] - origin[0] + tol) / h), math.floor((hi[0] - origin[0] - tol) / h) + 1
        )
        for strip in geometry.slice_convex(v, ex, xs, tol):
            slo, shi = strip[:, 1].min(), strip[:, 1].max()
            ys = origin[1] + h * np.arange(
                math.ceil((slo - origin[1] + tol) / h), math.floor((shi - origin[1] - tol) / h) + 1
            )
            for cell in geometry.slice_convex(strip, ey, ys, tol):
                new.add(cell, work.material[i], work.excavation[i], i)
    work.__dict__.update(new.__dict__)


GROWTH = 0.25
"""Graded mesh: a cell at distance d from an excavation is at most mesh_size + GROWTH d."""


def _graded_squares(box, h: float, h_max: float, outlines: list) -> np.ndarray:
    """Quadtree squares (x0, y0, size) covering ``box``: size h at the excavation outlines.

    Roots of size h 2^k (the largest not above ``h_max``) on the grid from the box's
    lower-left corner; a square splits in four while it is larger than
    h + GROWTH d, d the distance from the square to the nearest outline.
    """
    segs = np.concatenate([np.stack([v, np.roll(v, -1, axis=0)], axis=1) for v in outlines])
    p0, d = segs[:, 0], segs[:, 1] - segs[:, 0]
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)

    def distance(c):  # (M, 2) points -> (M,) distance to the nearest outline segment
        t = np.clip(np.einsum("mij,ij->mi", c[:, None, :] - p0, d) / dd, 0.0, 1.0)
        q = p0 + t[..., None] * d
        return np.min(np.linalg.norm(c[:, None, :] - q, axis=-1), axis=1)

    size = h * 2 ** math.floor(math.log2(h_max / h))
    nx = math.ceil((box[2] - box[0]) / size - 1e-9)
    ny = math.ceil((box[3] - box[1]) / size - 1e-9)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    todo = np.stack([box[0] + ix.ravel() * size, box[1] + iy.ravel() * size,
                     np.full(ix.size, size)], axis=1)
    leaves = []
    while len(todo):
        s = todo[:, 2]
        gap = np.maximum(distance(todo[:, :2] + 0.5 * s[:, None]) - s / math.sqrt(2.0), 0.0)
        split = s > h + GROWTH * gap + 1e-9 * h
        leaves.append(todo[~split])
        q = todo[split]
        half = 0.5 * q[:, 2:3]
        todo = np.concatenate([np.concatenate([q[:, :2] + half * off, half], axis=1)
                               for off in np.array([[0, 0], [1, 0], [0, 1], [1, 1]])]) \
            if len(q) else np.zeros((0, 3))
    return np.concatenate(leaves)


def _mesh_by_squares(work: _Work, squares: np.ndarray, tol: float) -> None:
    """Clip every piece by the squares (x0, y0, size) that overlap it."""
    new = _Work()
    ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    lo_sq, hi_sq = squares[:, :2], squares[:, :2] + squares[:, 2:3]
    for i, v in enumerate(work.polys):
        lo, hi = v.min(axis=0), v.max(axis=0)
        hit = np.nonzero(np.all(lo_sq < hi - tol, axis=1) & np.all(hi_sq > lo + tol, axis=1))[0]
        for k in hit:
            (x0, y0), (x1, y1) = lo_sq[k], hi_sq[k]
            cell = _clip(v, [(ex, x0, False), (ex, x1, True), (ey, y0, False), (ey, y1, True)],
                         tol)
            if cell is not None and _area(cell) > tol * tol:
                new.add(cell, work.material[i], work.excavation[i], i)
    work.__dict__.update(new.__dict__)


def _triangulate(work: _Work, h: float, origin: np.ndarray, tol: float) -> None:
    """Split every cell outside the excavations into triangles (constant-strain cells).

    A triangle keeps its shape; a quadrilateral splits along its shorter
    diagonal, equal diagonals (grid squares) alternating with the parity of the
    grid cell, so that the mesh has no preferred direction; larger polygons fan
    from their centroid. Cells of an excavation are removed before anything
    deforms and stay whole.
    """
    new = _Work()
    for i, v in enumerate(work.polys):
        tags = (work.material[i], work.excavation[i], work.parent[i])
        v = geometry.drop_collinear(v, tol)
        if work.excavation[i] is not None or len(v) == 3:
            new.add(v, *tags)
            continue
        if len(v) == 4:
            d02 = np.linalg.norm(v[2] - v[0])
            d13 = np.linalg.norm(v[3] - v[1])
            if abs(d02 - d13) <= 1e-6 * max(d02, d13):
                c = geometry.centroid(v)
                k = np.floor((c - origin) / h).astype(int)
                split02 = (k[0] + k[1]) % 2 == 0
            else:
                split02 = d02 < d13
            tris = [v[[0, 1, 2]], v[[0, 2, 3]]] if split02 else [v[[0, 1, 3]], v[[1, 2, 3]]]
        else:
            c = geometry.centroid(v)
            tris = [np.array([c, v[k], v[(k + 1) % len(v)]]) for k in range(len(v))]
        for t in tris:
            new.add(t, *tags)
    work.__dict__.update(new.__dict__)


# --------------------------------------------------------------------------- slivers


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


def _merge_slivers(
    work: _Work, keys: list[Any], lmin: float, tol: float, eps_area: float
) -> list[int]:
    """Merge slivers into a convex union with a same-key neighbour; returns the unmerged."""
    n = len(work)
    if n < 2:
        return []
    areas = np.array([_area(v) for v in work.polys])
    slivers = [i for i in np.argsort(areas) if _is_sliver(work.polys[i], areas[i], lmin)]
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
            au = _area(u)
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


# --------------------------------------------------------------------------- labels


def _label_edges(
    polys: list[np.ndarray],
    outline: np.ndarray,
    families: list[_Family],
    lines: list[_Line],
    tol: float,
) -> tuple[np.ndarray, list[str | None], list[str | None], np.ndarray]:
    """Per edge of all pieces (concatenated): kind (0 intact, 1 joint, 2 outer), joint name,
    source of the cut line it lies on (``joints.NAME``/``discontinuities.i``), piece offsets."""
    counts = np.array([len(v) for v in polys])
    starts = np.concatenate([[0], np.cumsum(counts)])
    A = np.concatenate(polys)
    B = np.concatenate([np.roll(v, -1, axis=0) for v in polys])
    ne = len(A)
    kind = np.zeros(ne, dtype=np.int8)
    name_idx = np.full(ne, -1)
    src_idx = np.full(ne, -1)
    names: list[str] = []
    sources: list[str] = []

    m = len(outline)
    for k in range(m):
        p, q = outline[k], outline[(k + 1) % m]
        e = q - p
        le = float(np.hypot(*e))
        u = e / le
        nn = np.array([-u[1], u[0]])
        da, db = np.abs((A - p) @ nn), np.abs((B - p) @ nn)
        ta, tb = (A - p) @ u, (B - p) @ u
        on = (da <= tol) & (db <= tol)
        on &= (np.minimum(ta, tb) >= -tol) & (np.maximum(ta, tb) <= le + tol)
        kind[on] = 2

    for fam in families:
        pa = A @ fam.normal - fam.c0
        pb = B @ fam.normal - fam.c0
        ka = np.rint(pa / fam.spacing)
        kb = np.rint(pb / fam.spacing)
        on = (
            (np.abs(pa - ka * fam.spacing) <= tol)
            & (np.abs(pb - kb * fam.spacing) <= tol)
            & (ka == kb)
            & (src_idx < 0)
        )
        idx = np.nonzero(on)[0]
        if not len(idx):
            continue
        sources.append(fam.source)
        src_idx[idx] = len(sources) - 1
        sa, sb = A[idx] @ fam.direction, B[idx] @ fam.direction
        lo, hi = np.minimum(sa, sb), np.maximum(sa, sb)
        cov = fam.covered(ka[idx], lo, hi)
        joint = idx[(cov >= 0.5 * (hi - lo)) & (kind[idx] == 0)]
        names.append(fam.joint)
        kind[joint] = 1
        name_idx[joint] = len(names) - 1

    for line in lines:
        pa = A @ line.normal - line.offset
        pb = B @ line.normal - line.offset
        on = (np.abs(pa) <= tol) & (np.abs(pb) <= tol)
        idx = np.nonzero(on)[0]
        if not len(idx):
            continue
        sources.append(line.source)
        src_idx[idx[src_idx[idx] < 0]] = len(sources) - 1
        sa, sb = A[idx] @ line.direction, B[idx] @ line.direction
        lo, hi = np.minimum(sa, sb), np.maximum(sa, sb)
        s0, s1 = min(line.s0, line.s1), max(line.s0, line.s1)
        cov = np.clip(np.minimum(hi, s1) - np.maximum(lo, s0), 0.0, None)
        joint = idx[(cov >= 0.5 * (hi - lo)) & (kind[idx] == 0)]
        names.append(line.joint)
        kind[joint] = 1
        name_idx[joint] = len(names) - 1

    name_of = [names[k] if k >= 0 else None for k in name_idx]
    src_of = [sources[k] if k >= 0 else None for k in src_idx]
    return kind, name_of, src_of, starts


# --------------------------------------------------------------------------- generate


def _refuse_sliver(
    work: _Work,
    i: int,
    outline: np.ndarray,
    families: list[_Family],
    lines: list[_Line],
    tol: float,
) -> None:
    v = work.polys[i]
    e = np.roll(v, -1, axis=0) - v
    emax = float(np.max(np.hypot(e[:, 0], e[:, 1])))
    a = _area(v)
    if a >= SLIVER_RATIO * emax * emax:
        return  # small but not thin: keep it
    _, _, src, _ = _label_edges([v], outline, families, lines, tol)
    found = list(dict.fromkeys(s for s in src if s is not None))
    if not found:
        return  # not made by joints: keep it
    c = geometry.centroid(v)
    where = f"({c[0]:g}, {c[1]:g})"
    what = (
        f"traces nearly coincide with {found[1]}"
        if len(found) > 1
        else "a trace nearly coincides with the domain outline or a zone or excavation outline"
    )
    raise SceneError(
        found[0],
        f"{what}, leaving a sliver block at {where} (area {a:.3g} m2, width "
        f"about {a / emax:.3g} m) that cannot be merged into a convex neighbour; move one "
        "of them (origin, spacing or the discontinuity's ends)",
    )


def generate(scene: Scene) -> RockMass:
    """Cut the scene's domain into convex pieces (see the module docstring).

    Args:
      scene: a validated :class:`jaxdem.scene.Scene`. Without ``[domain]`` there is
        nothing to generate and the rock mass is empty.

    Returns:
      :class:`RockMass` whose pieces tile the domain exactly (areas sum to its area).

    Raises:
      SceneError: where near-coincident joint traces leave a sliver that cannot be merged.
    """
    dom = scene.domain
    if dom is None:
        return RockMass(pieces=[])
    outline = np.asarray(dom.outline, dtype=float)
    box = geometry.bbox(outline)
    size = float(math.hypot(box[2] - box[0], box[3] - box[1]))
    tol = 1e-9 * size
    eps_area = 1e-13 * size * size
    families = _families(scene, geometry.centroid(outline))
    lines = _lines(scene)
    scales = [f.spacing for f in families] + [max(box[2] - box[0], box[3] - box[1])]
    if dom.mesh_size is not None:
        scales.append(dom.mesh_size)
    lmin = min(scales)

    work = _Work()
    for k, part in enumerate(geometry.convex_decompose(outline, tol)):
        work.add(part, dom.material, None, k)
    for fam in families:
        _slice_family(work, fam, tol)
    for line in lines:
        _cut_by_line(work, line.normal, line.offset, tol)
    _cut_at_ends(work, _trace_ends(families, lines, outline), tol, SNAP * lmin)
    area_tol = max(eps_area, 1e-12 * lmin * lmin)
    for zone in scene.zones:
        _cut_by_region(
            work, np.asarray(zone.vertices, float), tol, area_tol, material=zone.material
        )
    for exc in scene.excavations:
        _cut_by_region(work, np.asarray(exc.vertices, float), tol, area_tol, excavation=exc.name)

    keys = list(zip(work.material, work.excavation, strict=True))
    for i in _merge_slivers(work, keys, lmin, tol, eps_area):
        _refuse_sliver(work, i, outline, families, lines, tol)

    if dom.mesh_size is not None:
        outlines = [np.asarray(e.vertices, float) for e in scene.excavations]
        if dom.mesh_max_size is not None and dom.mesh_max_size > dom.mesh_size and outlines:
            squares = _graded_squares(box, float(dom.mesh_size), float(dom.mesh_max_size),
                                      outlines)
            _mesh_by_squares(work, squares, tol)
        else:
            _mesh(work, float(dom.mesh_size), np.array(box[:2]), tol)
        _merge_slivers(work, list(work.parent), lmin, tol, eps_area)
        _triangulate(work, float(dom.mesh_size), np.array(box[:2]), tol)

    polys = []
    keep = []
    for i, v in enumerate(work.polys):
        u = geometry.drop_collinear(v, tol)
        if len(u) >= 3 and _area(u) > 0.0:
            polys.append(u)
            keep.append(i)
    kind, names, _, starts = _label_edges(polys, outline, families, lines, tol)
    words = ("intact", "joint", "outer")
    pieces = []
    for n, i in enumerate(keep):
        labels = [
            (words[kind[k]], names[k] if kind[k] == 1 else None)
            for k in range(starts[n], starts[n + 1])
        ]
        pieces.append(Piece(polys[n], work.material[i], work.excavation[i], labels))
    return RockMass(pieces=pieces)
