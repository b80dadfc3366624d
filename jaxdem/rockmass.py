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

Where it lives (this module is the public face and runs the steps in order; each module
imports only those above it): :mod:`jaxdem.rockmass_traces` (joint-set and discontinuity
lines, trace ends, edge labels), :mod:`jaxdem.rockmass_cutting` (pieces in work, cuts,
zones and openings, slivers), :mod:`jaxdem.rockmass_mesh` (grid or graded cells,
triangles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from jaxdem import geometry
from jaxdem.rockmass_cutting import (
    SLIVER_RATIO,
    _area,
    _cut_at_ends,
    _cut_by_line,
    _cut_by_region,
    _merge_slivers,
    _slice_family,
    _Work,
)
from jaxdem.rockmass_mesh import _graded_squares, _mesh, _mesh_by_squares, _triangulate
from jaxdem.rockmass_traces import _families, _Family, _label_edges, _Line, _lines, _trace_ends
from jaxdem.scene import Scene
from jaxdem.scene_fields import SceneError

__all__ = ["Piece", "RockMass", "generate"]

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
