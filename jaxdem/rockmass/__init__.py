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
8. Small blocks. A rock body (pieces joined by intact faces) on an excavation's outline
   and smaller than ``domain.min_block_area`` (default 0.1 x the smallest joint-set
   spacing squared, below every block of the regular pattern) is merged into the
   neighbouring body of the same material and excavation with which it shares the most
   joint length (faces shared whole), smallest first: those faces become intact rock on
   both sides. The geometry does not change (a union is not convex in general: the
   model's non-convex block is convex pieces bonded by intact rock).

Cost: about linear in the number of pieces; 100 m x 100 m with two persistent sets at 1 m
(10,000 blocks) generates in about a second.

Example::

    >>> from jaxdem import load_scene
    >>> from jaxdem.rockmass import generate
    >>> rm = generate(load_scene("tunnel.toml"))
    >>> len(rm.pieces), rm.pieces[0].edge_labels[0]
    (412, ('joint', 'set1'))

Where it lives (this package re-exports the public names; :mod:`jaxdem.rockmass._generate`
runs the steps in order; each module imports only those above it):
:mod:`jaxdem.rockmass._traces` (joint-set and discontinuity lines, trace ends, edge
labels), :mod:`jaxdem.rockmass._cutting` (pieces in work, cuts, zones and openings,
slivers), :mod:`jaxdem.rockmass._mesh` (grid or graded cells, triangles),
:mod:`jaxdem.rockmass._bonding` (small blocks bonded to a neighbour).
"""

from jaxdem.rockmass._generate import (
    Piece,
    RockMass,
    generate,
    min_block_area,
    small_block_area,
)

__all__ = ["Piece", "RockMass", "generate", "min_block_area", "small_block_area"]
