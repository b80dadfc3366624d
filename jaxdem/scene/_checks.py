"""Geometric validation of a scene: polygons (simple, counter-clockwise, convex where
blocks need it), overlaps between explicit blocks and with the domain, which joint a
shared block face gets, coordinates the dtype resolves, the generated block count
estimated before anything is generated, and ``Rock``, where the rock is (the domain less
its openings, plus the explicit blocks) for points and segments that must lie in it.

Host NumPy with :mod:`jaxdem.geometry`; reads records of :mod:`jaxdem.scene._schema`
and raises ``SceneError`` naming the field. Used by the section parsers and by
:func:`jaxdem.scene.parse_scene`, which decides the order of the checks.
"""

from __future__ import annotations

import math

import numpy as np

from jaxdem import geometry
from jaxdem.scene._fields import SceneError, fmt_point, read_vertices
from jaxdem.scene._schema import Block, Domain, Excavation, InSitu, Joint, SolverSettings

MAX_BLOCKS = 500_000
"""Most blocks a scene may generate (estimated from joint spacings and mesh size before
anything is generated): 50 times the largest model benchmarked (10,464 blocks, 2 GB)."""

MAX_POLYGON_POINTS = 1_000
"""Most vertices in one polygon (checking a polygon for crossings costs n^2)."""

MAX_OFFSET = {"float64": 1e9, "float32": 1e3}
"""Coordinates may lie at most this many model sizes from (0, 0): beyond, the dtype resolves
less than about 1e-7 (float64) or 1e-4 (float32) of the model's size, the order of the
solver's contact tolerance (1e-6, float32 1e-4, of the block size)."""

#: Two explicit blocks may overlap by at most this depth, relative to the smaller block's
#: size sqrt(area) (depth = 2 area / perimeter of the overlap, the thickness of a sliver):
#: coordinates rounded to 6 decimals (1e-6 m) pass for blocks of 0.1 m and larger. A
#: deeper overlap is refused; an accepted one is a contact already compressed by it.
OVERLAP_TOLERANCE = 1e-5


def check_polygon(v: np.ndarray, path: str, *, convex: bool = True) -> None:
    """Refuse repeated points, self-intersecting, degenerate, clockwise polygons and, when
    ``convex``, 180-degree corners and reflex corners."""
    n = len(v)
    if n > MAX_POLYGON_POINTS:
        raise SceneError(
            path, f"too many vertices (got {n:,}; at most {MAX_POLYGON_POINTS:,}); simplify it"
        )
    diag = float(np.hypot(*(v.max(axis=0) - v.min(axis=0))))
    tol = 1e-9 * diag
    if geometry.has_repeated_points(v, tol):
        diff = v[:, None, :] - v[None, :, :]
        close = np.hypot(diff[..., 0], diff[..., 1]) <= tol
        i, j = next((i, j) for i in range(n) for j in range(i + 1, n) if close[i, j])
        raise SceneError(path, f"repeated point {fmt_point(v[i])} at vertices {i} and {j}")
    # All points on one line: say "degenerate" rather than "self-intersecting".
    centred = v - v.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    thickness = float(np.ptp(centred @ vt[-1]))
    if thickness <= 1e-12 * diag:
        raise SceneError(
            path, "degenerate polygon: all vertices lie on one line (zero or near-zero area)"
        )
    if geometry.self_intersects(v):
        raise SceneError(path, "self-intersecting polygon: two of its edges cross or touch")
    area = geometry.signed_area(v)
    if abs(area) < 1e-12 * diag * diag:
        raise SceneError(path, f"degenerate polygon: near-zero area ({area:.3g} m2)")
    if area < 0.0:
        raise SceneError(path, "vertices are clockwise; list them counter-clockwise")
    if not convex:
        return
    s = geometry.corner_sines(v)
    for k in range(n):
        if abs(s[k]) <= 1e-9:
            raise SceneError(
                path,
                f"degenerate vertex {k} {fmt_point(v[k])}: collinear with its neighbours "
                "(180-degree corner); remove it",
            )
    for k in range(n):
        if s[k] < 0.0:
            raise SceneError(
                path,
                f"is not convex at vertex {k} {fmt_point(v[k])}; split it into convex blocks",
            )


_BATCH_POINTS = 32
"""Polygons of up to this many vertices are cleared by :func:`convex_polygons_pass` all at
once; larger ones (rare among blocks) go through :func:`check_polygon` one by one."""


def convex_polygons_pass(polys: list[np.ndarray]) -> np.ndarray:
    """True where :func:`check_polygon` (``convex=True``) certainly accepts the polygon, found
    for all polygons at once (NumPy over groups of equal vertex count).

    Each of its tests is made with twice its tolerance (vertices at least 2e-9 of the
    diagonal apart, thickness and area above 2e-12 of it, corner sines above 2e-9, edges
    that are not neighbours at least 2e-12 of it apart and not crossing): a polygon
    cleared here passes the scalar checks whatever the round-off. False means "not
    cleared": :func:`check_polygon` then decides and names the problem.
    """
    ok = np.zeros(len(polys), dtype=bool)
    for n, idx, v in geometry.polygon_groups(polys):
        if 3 <= n <= _BATCH_POINTS:
            ok[idx] = _group_passes(v)
    return ok


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (m) from points p to segments a-b, all (..., 2)."""
    d = b - a
    len2 = d[..., 0] ** 2 + d[..., 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(len2 > 0.0, np.sum((p - a) * d, axis=-1) / len2, 0.0)
    q = a + np.clip(t, 0.0, 1.0)[..., None] * d
    return np.hypot(p[..., 0] - q[..., 0], p[..., 1] - q[..., 1])


def _group_passes(v: np.ndarray) -> np.ndarray:
    """:func:`convex_polygons_pass` of polygons ``v`` (m, n, 2) of one vertex count."""
    n = v.shape[1]
    ext = v.max(axis=1) - v.min(axis=1)
    diag = np.hypot(ext[:, 0], ext[:, 1])
    # Repeated points.
    i, j = np.triu_indices(n, k=1)
    gap = np.hypot(*(v[:, i] - v[:, j]).transpose(2, 0, 1))
    ok = np.all(gap > 2e-9 * diag[:, None], axis=1)
    # All points on one line; clockwise or near-zero area.
    centred = v - v.mean(axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    ok &= np.ptp(np.einsum("mnk,mk->mn", centred, vt[:, -1]), axis=1) > 2e-12 * diag
    ok &= geometry.signed_areas(list(v)) > 2e-12 * diag * diag
    # Reflex and 180-degree corners.
    e = np.roll(v, -1, axis=1) - v
    ep = np.roll(e, 1, axis=1)
    lens = np.hypot(e[..., 0], e[..., 1])
    turn = ep[..., 0] * e[..., 1] - ep[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        sines = turn / (lens * np.roll(lens, 1, axis=1))
    ok &= np.all(sines > 2e-9, axis=1)
    # Self-intersection: an edge folding back over the next, two other edges crossing or
    # touching (geometry.self_intersects).
    tol = 2e-12 * diag[:, None]
    a, b, c = v, np.roll(v, -1, axis=1), np.roll(v, -2, axis=1)
    ok &= np.all((_segment_distance(c, a, b) > tol) & (_segment_distance(a, b, c) > tol), axis=1)
    pairs = [(p, q) for p in range(n) for q in range(p + 2, n) if not (p == 0 and q == n - 1)]
    if pairs:
        p, q = np.array(pairs).T
        a0, a1, b0, b1 = v[:, p], v[:, (p + 1) % n], v[:, q], v[:, (q + 1) % n]

        def orient(x, y, z):
            return ((y[..., 0] - x[..., 0]) * (z[..., 1] - x[..., 1])
                    - (y[..., 1] - x[..., 1]) * (z[..., 0] - x[..., 0]))

        d1, d2 = orient(b0, b1, a0), orient(b0, b1, a1)
        d3, d4 = orient(a0, a1, b0), orient(a0, a1, b1)
        cross = (np.sign(d1) * np.sign(d2) < 0.0) & (np.sign(d3) * np.sign(d4) < 0.0)
        near = np.minimum(np.minimum(_segment_distance(a0, b0, b1), _segment_distance(a1, b0, b1)),
                          np.minimum(_segment_distance(b0, a0, a1), _segment_distance(b1, a0, a1)))
        ok &= np.all(~cross & (near > tol), axis=1)
    return ok


def read_polygon(t: dict, key: str, path: str, far: tuple[float, str] | None = None) -> np.ndarray:
    """A required simple CCW polygon field (may be non-convex), read-only. ``far``: (model
    size, dtype) to refuse first a vertex too far away (that spoils the checks' tolerance)."""
    if key not in t:
        raise SceneError(f"{path}.{key}", "required field is missing")
    v = read_vertices(t[key], f"{path}.{key}")
    if far is not None:
        k = int(np.argmax(np.max(np.abs(v), axis=1)))
        check_far(v[k], f"{path}.{key}.{k}", *far)
    check_polygon(v, f"{path}.{key}", convex=False)
    v.setflags(write=False)
    return v


def overlap_depth(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(area m2, depth m) of the overlap of two convex polygons; depth = 2 area / perimeter
    of the overlap, the thickness of a sliver (0, 0 when they do not overlap)."""
    clip = geometry.convex_clip(np.asarray(a, float), np.asarray(b, float))
    if len(clip) < 3:
        return 0.0, 0.0
    area = abs(geometry.signed_area(clip))
    perimeter = float(np.sum(np.hypot(*(np.roll(clip, -1, axis=0) - clip).T)))
    return area, (2.0 * area / perimeter if perimeter > 0.0 else 0.0)


def check_overlaps(blocks: tuple[Block, ...]) -> None:
    """Refuse explicit blocks that overlap deeper than OVERLAP_TOLERANCE times the smaller
    block's size sqrt(area)."""
    if not blocks:
        return
    polys = [b.vertices for b in blocks]
    areas = geometry.signed_areas(polys)
    pairs = geometry.find_overlapping_pairs(polys, 1e-9 * float(np.min(areas)))
    bad = []
    for i, j in pairs:
        a, depth = overlap_depth(polys[i], polys[j])
        size = math.sqrt(min(areas[i], areas[j]))
        if depth > OVERLAP_TOLERANCE * size:
            bad.append((j, i, a, depth, size))
    if bad:
        j, i, a, depth, size = min(bad)
        raise SceneError(
            f"blocks.{j}",
            f"overlaps blocks.{i} (area {a:.3g} m2): {depth:.3g} m deep, where up to "
            f"{OVERLAP_TOLERANCE:g} of the smaller block's size ({OVERLAP_TOLERANCE * size:.3g} "
            "m) is accepted",
        )


def _shared_faces(blocks: tuple[Block, ...], tol: float,
                  labels: list[str]) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """(i, j, p, q): blocks i < j of different ``labels`` share the segment p-q of a face
    (anti-parallel edges on one line, overlapping by more than ``tol``)."""
    out = []
    codes = {name: k for k, name in enumerate(dict.fromkeys(labels))}
    code = np.array([codes[name] for name in labels])
    near_i, near_j = geometry.near_box_pairs(geometry.bboxes([b.vertices for b in blocks]), tol)
    differ = code[near_i] != code[near_j]
    for i, j in zip(near_i[differ].tolist(), near_j[differ].tolist(), strict=True):
        va, vb = blocks[i].vertices, blocks[j].vertices
        for a0, a1 in zip(va, np.roll(va, -1, axis=0), strict=True):
            d = a1 - a0
            L = float(np.hypot(*d))
            t = d / L
            n = np.array([-t[1], t[0]])
            for b0, b1 in zip(vb, np.roll(vb, -1, axis=0), strict=True):
                if abs((b0 - a0) @ n) > tol or abs((b1 - a0) @ n) > tol:
                    continue
                lo = max(0.0, min((b0 - a0) @ t, (b1 - a0) @ t))
                hi = min(L, max((b0 - a0) @ t, (b1 - a0) @ t))
                if hi - lo > tol and (b1 - b0) @ t < 0.0:
                    out.append((i, j, a0 + lo * t, a0 + hi * t))
    return out


def _on_discontinuity(p: np.ndarray, q: np.ndarray, discs: tuple, tol: float) -> bool:
    """Whether the segment p-q lies on a [[discontinuities]] line (as the model reads it)."""
    for d in discs:
        e = d.end - d.start
        L = float(np.hypot(*e))
        t = e / L
        n = np.array([-t[1], t[0]])
        if abs((p - d.start) @ n) <= tol and abs((q - d.start) @ n) <= tol:
            sp, sq = (p - d.start) @ t, (q - d.start) @ t
            if min(sp, sq) >= -tol and max(sp, sq) <= L + tol:
                return True
    return False


def check_block_joints(blocks: tuple[Block, ...], discs: tuple, joints: dict,
                       has_default: bool, default_joint: str, tol: float) -> None:
    """Which joint each explicit block face gets must be explicit.

    A face on a [[discontinuities]] line takes that line's joint; any other face takes its
    block's ``joint``, else ``scene.default_joint``. With several joints, a block that
    has neither and a face no line covers is ambiguous (refused). Two blocks whose joints
    differ may share a face only where a line says which joint it is.
    """
    if not blocks:
        return
    if len(joints) > 1 and not has_default:
        for i, b in enumerate(blocks):
            if b.joint is not None:
                continue
            v = b.vertices
            for k, (p, q) in enumerate(zip(v, np.roll(v, -1, axis=0), strict=True)):
                if not _on_discontinuity(p, q, discs, tol):
                    raise SceneError(
                        "scene.default_joint",
                        f"required when the scene has several joints ({', '.join(joints)}) "
                        f"and explicit blocks: face {k} of blocks.{i} ({fmt_point(p)}-"
                        f"{fmt_point(q)}) lies on no [[discontinuities]] line, so its joint "
                        "is not given; set [scene] default_joint = NAME, or joint = NAME on "
                        "the [[blocks]]",
                    )
    if len(joints) < 2 or all(b.joint is None for b in blocks):
        return
    own = [b.joint if b.joint is not None else default_joint for b in blocks]
    for i, j, p, q in _shared_faces(blocks, tol, own):
        if not _on_discontinuity(p, q, discs, tol):
            which = {i: "joint" if blocks[i].joint is not None else "default_joint",
                     j: "joint" if blocks[j].joint is not None else "default_joint"}
            path = f"blocks.{j}.joint" if blocks[j].joint is not None else f"blocks.{i}.joint"
            raise SceneError(
                path,
                f"blocks.{i} ({which[i]} {own[i]!r}) and blocks.{j} ({which[j]} {own[j]!r}) "
                f"share the face {fmt_point(p)}-{fmt_point(q)} but their joints differ; put a "
                "[[discontinuities]] line on that face to say which joint it is",
            )


def check_blocks_outside_domain(blocks: tuple[Block, ...], domain: Domain | None) -> None:
    if domain is None or not blocks:
        return
    parts = geometry.convex_decompose(domain.outline, 0.0)
    dbox = geometry.bbox(domain.outline)
    for i, b in enumerate(blocks):
        bb = geometry.bbox(b.vertices)
        if bb[0] >= dbox[2] or dbox[0] >= bb[2] or bb[1] >= dbox[3] or dbox[1] >= bb[3]:
            continue
        a = sum(geometry.overlap_area(b.vertices, q) for q in parts)
        if a > 1e-9 * geometry.signed_area(b.vertices):
            raise SceneError(
                f"blocks.{i}",
                f"overlaps the domain (area {a:.3g} m2); explicit blocks lie outside it",
            )


def segment_touches_box(a: np.ndarray, b: np.ndarray, box: tuple, tol: float) -> bool:
    xmin, ymin, xmax, ymax = box
    for q in (a, b):
        if xmin - tol <= q[0] <= xmax + tol and ymin - tol <= q[1] <= ymax + tol:
            return True
    corners = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
    return any(
        geometry.segments_intersect(a, b, corners[k], corners[(k + 1) % 4], tol) for k in range(4)
    )


class Rock:
    """Where the rock is: the domain less its excavations, plus the explicit blocks."""

    def __init__(
        self,
        blocks: tuple[Block, ...],
        domain: Domain | None,
        excavations: tuple[Excavation, ...],
        tol: float,
    ) -> None:
        self.blocks = blocks
        self.boxes = geometry.bboxes([b.vertices for b in blocks]).reshape(-1, 4)
        self.domain = domain
        self.excavations = excavations
        self.tol = tol

    def excavation_at(self, q: np.ndarray) -> str | None:
        """Name of the excavation with ``q`` strictly inside (beyond tol), else None."""
        for e in self.excavations:
            if geometry.point_in_polygon(q, e.vertices) and (
                geometry.distance_to_boundary(q, e.vertices) > self.tol
            ):
                return e.name
        return None

    def contains(self, q: np.ndarray) -> bool:
        tol = self.tol
        b = self.boxes
        near = np.nonzero(
            (b[:, 0] - tol <= q[0])
            & (q[0] <= b[:, 2] + tol)
            & (b[:, 1] - tol <= q[1])
            & (q[1] <= b[:, 3] + tol)
        )[0]
        if any(geometry.point_in_polygon(q, self.blocks[k].vertices, tol) for k in near):
            return True
        if self.domain is None or not geometry.point_in_polygon(q, self.domain.outline, tol):
            return False
        return self.excavation_at(q) is None

    def touches(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether segment a-b meets a block or the domain (within 1e3 tol, as the model
        finds faces on a boundary)."""
        tol = 1e3 * self.tol
        lo, hi = np.minimum(a, b) - tol, np.maximum(a, b) + tol
        bx = self.boxes
        near = np.nonzero(
            (bx[:, 0] <= hi[0]) & (lo[0] <= bx[:, 2]) & (bx[:, 1] <= hi[1]) & (lo[1] <= bx[:, 3])
        )[0]
        polys = [self.blocks[k].vertices for k in near]
        if self.domain is not None:
            polys.append(self.domain.outline)
        for v in polys:
            if geometry.point_in_polygon(a, v, tol):
                return True
            edges = zip(v, np.roll(v, -1, axis=0), strict=True)
            if any(geometry.segments_intersect(a, b, p, q, tol) for p, q in edges):
                return True
        return False

    def where(self, q: np.ndarray) -> str:
        """Why ``q`` is not in rock, for messages."""
        name = self.excavation_at(q)
        if name is not None and self.domain is not None:
            return f"{fmt_point(q)} is inside excavation {name!r}, not in rock"
        return f"{fmt_point(q)} is outside the rock"


def check_block_count(
    domain: Domain | None,
    joints: dict[str, Joint],
    excavations: tuple[Excavation, ...],
    n_explicit: int,
) -> None:
    """Refuse a scene that would generate more than MAX_BLOCKS blocks, judged from an
    estimate made before anything is generated (which would exhaust time or memory).

    Per joint set: its trace lines across the domain and, with persistence < 1, its trace
    ends (each cuts a block); per pair of sets: their crossings, area sin(angle) p1 p2 /
    (s1 s2); a mesh: 2 triangles per square cell of mesh_size (graded: of mesh_max_size,
    plus 4 perimeter / mesh_size along the excavations), 2 more per cell that a trace or
    an excavation outline cuts. Within a factor 1.5 of the generated count on the examples.
    """
    if domain is None:
        return
    v = domain.outline
    area = geometry.signed_area(v)
    made: dict[str, float] = {}  # field path -> blocks it makes
    sets = []  # (name, dip (rad), spacing, persistence, joint)
    for name, j in joints.items():
        if j.dip_deg is not None and j.spacing is not None:
            sets.append((name, math.radians(j.dip_deg), j.spacing, j.persistence or 1.0, j))
    traces = 0.0  # total trace length (m), about
    for name, dip, spacing, persistence, j in sets:
        d = np.array([math.cos(dip), math.sin(dip)])
        lines = float(np.ptp(v @ np.array([-d[1], d[0]]))) / spacing
        along = float(np.ptp(v @ d))
        made[f"joints.{name}.spacing"] = lines
        traces += lines * along * persistence
        if math.isfinite(j.trace_length):
            key = f"joints.{name}.{'gap' if j.gap is not None else 'spacing'}"
            ends = 2.0 * lines * along / (j.trace_length + j.bridge_length)
            made[key] = made.get(key, 0.0) + ends
    for k, (na, dip_a, sa, pa, _) in enumerate(sets):
        for nb, dip_b, sb, pb, _ in sets[k + 1:]:
            key = f"joints.{na if sa <= sb else nb}.spacing"
            made[key] += area * abs(math.sin(dip_a - dip_b)) * pa * pb / sa / sb
    h, grown = domain.mesh_size, domain.mesh_max_size
    if h is not None:
        edges = [np.roll(e.vertices, -1, axis=0) - e.vertices for e in excavations]
        perimeter = sum(float(np.sum(np.hypot(e[:, 0], e[:, 1]))) for e in edges)
        if grown is not None and grown > h and excavations:
            cells = area / grown / grown + 4.0 * perimeter / h
        else:
            cells = area / h / h
        made["domain.mesh_size"] = 2.0 * (cells + (perimeter + traces) / h)
    total = n_explicit + 1.0 + sum(made.values())
    if total > MAX_BLOCKS:
        path = max(made, key=lambda key: made[key])
        raise SceneError(
            path,
            f"too small: the scene would generate about {total:.3g} blocks, more than the "
            f"{MAX_BLOCKS:,} accepted",
        )


def check_coordinates(
    blocks: tuple[Block, ...],
    domain: Domain | None,
    joints: dict[str, Joint],
    box: tuple,
    size: float,
    solver: SolverSettings,
) -> None:
    """Coordinates the dtype can resolve, and solver lengths in proportion to the model."""
    if max(abs(x) for x in box) > MAX_OFFSET[solver.dtype] * size:
        polys = [("domain.outline", domain.outline)] if domain is not None else []
        polys += [(f"blocks.{i}.vertices", b.vertices) for i, b in enumerate(blocks)]
        path, v = max(polys, key=lambda pv: float(np.max(np.abs(pv[1]))))
        k = int(np.argmax(np.max(np.abs(v), axis=1)))
        check_far(v[k], f"{path}.{k}", size, solver.dtype)
    for name, j in joints.items():
        if j.origin is not None:
            check_far(np.array(j.origin), f"joints.{name}.origin", size, solver.dtype)
    # Substeps move at most step_length until a block has travelled max_displacement, and
    # contact detection looks 2 step_length ahead: bound both by the model's size.
    if solver.max_displacement is not None and solver.max_displacement > 10.0 * size:
        raise SceneError(
            "solver.max_displacement",
            f"larger than 10 times the model ({solver.max_displacement:g} m > "
            f"{10.0 * size:.3g} m): a block would have left the model long before",
        )
    step = solver.step_length
    if step is not None and not 1e-6 * size <= step <= size:
        raise SceneError(
            "solver.step_length",
            f"must be between 1e-6 times and once the model's size ({1e-6 * size:.3g} m to "
            f"{size:.3g} m; got {step:g})",
        )


def check_far(q: np.ndarray, path: str, size: float, dtype: str) -> None:
    """Refuse a point so far from (0, 0) that ``dtype`` cannot resolve a model ``size`` m
    across there (MAX_OFFSET model sizes)."""
    limit = MAX_OFFSET[dtype] * size
    if float(np.max(np.abs(q))) > limit:
        raise SceneError(
            path,
            f"{fmt_point(q)} is too far from (0, 0) for a model {size:.3g} m across "
            f"({dtype} resolves it only within {limit:.3g} m of (0, 0)); shift the "
            "coordinates towards (0, 0)",
        )


# --- plausibility warnings (valid values, most likely in the wrong unit) -----------------

PLAUSIBLE_E = (1e4, 1e9)
"""Young's modulus (kPa) of rock: below 10 MPa (softer than any rock; a weak mudstone is
about 100 MPa = 1e5 kPa) it was most likely written in GPa or MPa; above 1,000 GPa
(stiffer than any rock, and than steel) in Pa."""

PLAUSIBLE_JOINT_STIFFNESS = (1e3, 1e9)
"""Normal and shear stiffness (kPa/m) of rock joints: from about 1 MPa/m (shear of a
clay-filled joint) to 1,000 GPa/m (normal stiffness of a tight joint in hard rock is
10 to 100 GPa/m). Below, it was most likely written in MPa/m or GPa/m; above, in Pa/m."""

MIN_FRICTION_DEG = 5.0
"""A friction angle in (0, 5) deg was most likely written in radians (0.52 rad = 30 deg).
Exactly 0 is a deliberate frictionless joint and is not warned about."""


def plausibility_warnings(materials: dict, joints: dict) -> tuple[str, ...]:
    """Sentences about values that are valid but most likely in the wrong unit, each
    starting with the field's dotted path: E outside :data:`PLAUSIBLE_E`, a joint's kn or
    ks outside :data:`PLAUSIBLE_JOINT_STIFFNESS`, a friction angle in (0,
    :data:`MIN_FRICTION_DEG`). They do not refuse the scene (a sand-filled model or a
    frictionless check may mean them)."""
    out = []
    for name, m in materials.items():
        lo, hi = PLAUSIBLE_E
        if m.E < lo:
            out.append(f"materials.{name}.E: {m.E:g} kPa is below {lo:g} kPa (10 MPa), softer "
                       "than any rock; E is in kPa: was it written in GPa or MPa? "
                       "(20 GPa is E = 2e7)")
        elif m.E > hi:
            out.append(f"materials.{name}.E: {m.E:g} kPa is above {hi:g} kPa (1,000 GPa), "
                       "stiffer than any rock; E is in kPa: was it written in Pa? "
                       "(20 GPa is E = 2e7)")
        out += _friction_warning(f"materials.{name}.friction_deg", m.friction_deg)
    for name, j in joints.items():
        for key in ("kn", "ks"):
            out += _stiffness_warning(f"joints.{name}.{key}", getattr(j, key))
        out += _friction_warning(f"joints.{name}.friction_deg", j.friction_deg)
    return tuple(out)


def _friction_warning(path: str, phi: float) -> list[str]:
    if not 0.0 < phi < MIN_FRICTION_DEG:
        return []
    return [f"{path}: {phi:g} deg is below {MIN_FRICTION_DEG:g} deg; angles are in degrees: "
            f"was it written in radians? ({phi:g} rad = {math.degrees(phi):.0f} deg; "
            "0 means a frictionless joint)"]


def _stiffness_warning(path: str, k: float) -> list[str]:
    lo, hi = PLAUSIBLE_JOINT_STIFFNESS
    if k < lo:
        return [f"{path}: {k:g} kPa/m is below {lo:g} kPa/m (1 MPa/m), softer than any rock "
                "joint; stiffness is in kPa/m: was it written in MPa/m or GPa/m? "
                "(10 GPa/m is 1e7)"]
    if k > hi:
        return [f"{path}: {k:g} kPa/m is above {hi:g} kPa/m (1,000 GPa/m), stiffer than any "
                "rock joint; stiffness is in kPa/m: was it written in Pa/m? (10 GPa/m is 1e7)"]
    return []


def in_situ_strength_warnings(in_situ: InSitu | None, domain: Domain | None, zones,
                              materials: dict) -> tuple[str, ...]:
    """A gravity in-situ state that the intact rock cannot carry, one sentence a material.

    With intact-rock cells (``domain.mesh_size``) the cells' contacts have the rock's
    Mohr-Coulomb strength. Gravity gives sigma_v = gamma z and sigma_h = k0 sigma_v at
    depth z below ``surface_y``; the rock fails where sigma_1 - N sigma_3 >= 2 c sqrt(N),
    N = tan^2(45 + phi / 2): with k0 < 1 below z* = 2 c sqrt(N) / (gamma (1 - N k0))
    (never where N k0 >= 1), with k0 > 1 below 2 c sqrt(N) / (gamma (k0 - N)). A domain
    (or zone) that reaches below z* starts from stresses its rock cannot hold: the
    initial state must find a plastic equilibrium before any excavation (slow, or no
    answer within the iteration limit). Valid input, so a warning, not a refusal."""
    if (in_situ is None or in_situ.mode != "gravity" or in_situ.surface_y is None
            or domain is None or not domain.mesh_size):
        return ()
    regions = [(f"materials.{domain.material}", domain.material,
                float(np.min(domain.outline[:, 1])))]
    regions += [(f"materials.{z.material}", z.material, float(np.min(z.vertices[:, 1])))
                for z in zones]
    out, seen = [], set()
    for path, name, y_low in regions:
        m = materials[name]
        if name in seen or m.unit_weight <= 0.0:
            continue
        seen.add(name)
        n = math.tan(math.radians(45.0 + m.friction_deg / 2.0)) ** 2
        k0 = in_situ.k0
        excess = (1.0 - n * k0) if k0 <= 1.0 else (k0 - n)
        if excess <= 0.0:
            continue
        depth = 2.0 * m.cohesion * math.sqrt(n) / (m.unit_weight * excess)
        deepest = in_situ.surface_y - y_low
        if deepest <= depth:
            continue
        ucs = 2.0 * m.cohesion * math.sqrt(n)
        out.append(
            f"in_situ: at k0 = {k0:g} the initial stress exceeds the strength of {path} "
            f"(cohesion {m.cohesion:g} kPa, friction {m.friction_deg:g} deg: uniaxial strength "
            f"{ucs:.0f} kPa) below y = {in_situ.surface_y - depth:.1f} m, {depth:.1f} m deep "
            f"(the rock reaches y = {y_low:g} m, sigma_v {m.unit_weight * deepest:.0f} kPa): "
            "the intact rock there fails under its own weight before any excavation, and "
            "the initial state has to find a plastic equilibrium (slow, or no answer within "
            f"the iteration limit); a k0 between {1.0 / n:.2f} and {n:.2f} keeps it elastic at "
            "any depth")
    return tuple(out)
