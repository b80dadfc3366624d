"""The generator: :func:`generate` runs steps 1-7 of :mod:`jaxdem.rockmass` in order and
returns the :class:`RockMass` of convex, labelled pieces."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field

import numpy as np

from jaxdem import geometry
from jaxdem.rockmass._bonding import bond_small_blocks
from jaxdem.rockmass._cutting import (
    SLIVER_RATIO,
    Work,
    cut_at_ends,
    cut_by_line,
    cut_by_region,
    merge_slivers,
    piece_area,
    slice_family,
)
from jaxdem.rockmass._mesh import graded_squares, mesh_by_squares, mesh_pieces, triangulate
from jaxdem.rockmass._traces import (
    Family,
    Line,
    discontinuity_lines,
    joint_families,
    label_edges,
    trace_ends,
)
from jaxdem.scene import Scene, SceneError

__all__ = ["Piece", "RockMass", "generate", "min_block_area", "small_block_area"]

SNAP = 1e-2
"""Trace ends closer than this times the smallest length scale to a corner snap to it (-)."""
MIN_BLOCK_FRACTION = 0.1
"""Default ``domain.min_block_area``: this times the smallest joint-set spacing squared (-).
A block of the regular pattern of two sets is at least spacing^2 (s1 s2 / sin of the angle
between them), so only the pieces that an opening cuts off a block are below it
(tests/test_loose_blocks.py)."""


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
    work: Work,
    i: int,
    outline: np.ndarray,
    families: list[Family],
    lines: list[Line],
    tol: float,
) -> None:
    v = work.polys[i]
    e = np.roll(v, -1, axis=0) - v
    emax = float(np.max(np.hypot(e[:, 0], e[:, 1])))
    a = piece_area(v)
    if a >= SLIVER_RATIO * emax * emax:
        return  # small but not thin: keep it
    _, _, src, _ = label_edges([v], outline, families, lines, tol)
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


_GENERATED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""Each scene's rock mass, cut once while the scene lives: the command line counts the
blocks before the solve, the solver lays them out and the figures draw them (seed example
3's 1,292 pieces: 0.09-0.15 s a cut)."""


def generate(scene: Scene) -> RockMass:
    """Cut the scene's domain into convex pieces (see the module docstring).

    Args:
      scene: a validated :class:`jaxdem.scene.Scene`. Without ``[domain]`` there is
        nothing to generate and the rock mass is empty.

    Returns:
      :class:`RockMass` whose pieces tile the domain exactly (areas sum to its area): a
      copy of the scene's (cut at the first call; a scene is immutable), the caller's to
      change.

    Raises:
      SceneError: where near-coincident joint traces leave a sliver that cannot be merged.
    """
    if scene.domain is None:
        return RockMass(pieces=[])
    made = _GENERATED.get(scene)
    if made is None:
        made = _GENERATED[scene] = _cut(scene)
    return RockMass(pieces=[Piece(p.vertices.copy(), p.material, p.excavation,
                                  list(p.edge_labels)) for p in made.pieces])


def _cut(scene: Scene) -> RockMass:
    """:func:`generate`'s work, for a scene with a domain."""
    dom = scene.domain
    outline = np.asarray(dom.outline, dtype=float)
    box = geometry.bbox(outline)
    size = float(math.hypot(box[2] - box[0], box[3] - box[1]))
    tol = 1e-9 * size
    eps_area = 1e-13 * size * size
    families = joint_families(scene, geometry.centroid(outline))
    lines = discontinuity_lines(scene)
    scales = [f.spacing for f in families] + [max(box[2] - box[0], box[3] - box[1])]
    if dom.mesh_size is not None:
        scales.append(dom.mesh_size)
    lmin = min(scales)

    work = Work()
    for k, part in enumerate(geometry.convex_decompose(outline, tol)):
        work.add(part, dom.material, None, k)
    for fam in families:
        slice_family(work, fam, tol)
    for line in lines:
        cut_by_line(work, line.normal, line.offset, tol)
    cut_at_ends(work, trace_ends(families, lines, outline), tol, SNAP * lmin)
    area_tol = max(eps_area, 1e-12 * lmin * lmin)
    for zone in scene.zones:
        cut_by_region(
            work, np.asarray(zone.vertices, float), tol, area_tol, material=zone.material
        )
    for exc in scene.excavations:
        cut_by_region(work, np.asarray(exc.vertices, float), tol, area_tol, excavation=exc.name)

    keys = list(zip(work.material, work.excavation, strict=True))
    for i in merge_slivers(work, keys, lmin, tol, eps_area):
        _refuse_sliver(work, i, outline, families, lines, tol)

    if dom.mesh_size is not None:
        outlines = [np.asarray(e.vertices, float) for e in scene.excavations]
        if dom.mesh_max_size is not None and dom.mesh_max_size > dom.mesh_size and outlines:
            squares = graded_squares(box, float(dom.mesh_size), float(dom.mesh_max_size),
                                     outlines)
            mesh_by_squares(work, squares, tol)
        else:
            mesh_pieces(work, float(dom.mesh_size), np.array(box[:2]), tol)
        merge_slivers(work, list(work.parent), lmin, tol, eps_area)
        triangulate(work, float(dom.mesh_size), np.array(box[:2]), tol)

    dropped = geometry.drop_collinear_all(work.polys, tol)
    areas = geometry.signed_areas(dropped)
    keep = [i for i, u in enumerate(dropped) if len(u) >= 3 and areas[i] > 0.0]
    polys = [dropped[i] for i in keep]
    kind, names, _, starts = label_edges(polys, outline, families, lines, tol)
    words = ("intact", "joint", "outer")
    labels = [(words[k], name if k == 1 else None)
              for k, name in zip(kind.tolist(), names, strict=True)]
    starts = starts.tolist()
    pieces = [Piece(polys[n], work.material[i], work.excavation[i],
                    labels[starts[n]:starts[n + 1]]) for n, i in enumerate(keep)]
    bond_small_blocks(pieces, min_block_area(scene), 1e2 * tol)
    return RockMass(pieces=pieces)


def min_block_area(scene: Scene) -> float:
    """``domain.min_block_area`` (m2), else :func:`small_block_area`."""
    dom = scene.domain
    if dom is not None and dom.min_block_area is not None:
        return float(dom.min_block_area)
    return small_block_area(scene)


def small_block_area(scene: Scene) -> float:
    """A small block of the scene's rock mass (m2): :data:`MIN_BLOCK_FRACTION` times the
    smallest joint-set spacing squared; 0 in a scene without a domain or joint sets. The
    default of ``domain.min_block_area`` and of ``solver.max_loose_volume``."""
    spacings = [j.spacing for j in scene.joints.values() if j.is_set]
    if scene.domain is None or not spacings:
        return 0.0
    return MIN_BLOCK_FRACTION * min(spacings) ** 2
