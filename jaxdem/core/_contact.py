"""Contact detection: broad phase (candidate pairs) and narrow phase (spring slots).

Broad phase. Axis-aligned boxes grown by the detection margin. Blocks in
``model.big`` (walls, blocks much larger than the median) are tested against
every block; the others go into a uniform grid of cells no smaller than the
largest of them, sorted by cell key, and each block looks at the blocks of its own
and the eight neighbouring cells, laid end to end for all blocks (a ragged list of
``model.cell_capacity`` places per block on average). Capacities (pairs, neighbour
places) are fixed; when one is exceeded a flag is set and the host grows it and
recompiles (never silent truncation). Small scenes use all pairs.

Narrow phase (vertex-to-edge, per pair (a, b), a < b). Each vertex of one
block is tested against the edges of the other. A vertex inside the other
polygon grown by the margin is a spring slot, on the face it is closest to
(preferring a face anti-parallel to one of its own adjacent faces; a vertex on or
inside the other block, only among the faces its own block lies outside of near it,
so that a corner gone in along the line of the other's face is seen). The slot
is part of an edge-to-edge contact when its own adjacent face is
anti-parallel to that face within ``cos_parallel``: its effective length is
half the overlap of the two faces, so the two end points of a face-to-face
contact share Le = |p1 - p2| (paper eq. 8). Otherwise it is a corner-to-edge
contact whose effective length is ``corner_share`` (default 0.1) times the
shorter of the two faces meeting at the corner, provided the corner lies
inside the face's span (a corner at the end of a face, where faces meet end
to end at a node, bears on nothing): a corner bears on a short
length of the face, and the choice only sets the corner spring's stiffness,
never the strength check, which is per point. Where a vertex of b sits at the
contact point of a vertex of a (within that point's overlap), the two slots are
one point seen from both sides, and each takes half of it (``halved``).

The choices (which face, which own face, which vertex is near) are made on
values; the geometry that follows from them (:func:`_slot_geometry`) is
differentiable, and :func:`slot_geometry` evaluates it for any subset of the
slots (the sensitivities differentiate the active ones alone).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdem.core.state import Model, State


class Slots(NamedTuple):
    """The spring slots of a detection, S = P x 2 x V of them (S, ...) arrays
    (:func:`narrow_phase`), or any subset of them.

    ``a`` the vertex block, ``b`` the face block, ``active`` (a spring: within the
    margin, bearing on a face), ``gap`` (m, negative = overlap), ``point`` (the vertex,
    m), ``normal`` and ``tangent`` of the contacted face, ``edge`` (its index in b),
    ``own_edge`` (the vertex block's face anti-parallel to it, or -1), ``halved`` (both
    blocks see the point, each takes half), ``share`` (effective length Le of the
    point, m, paper eq. 8), ``h_a``, ``h_b`` (distances of the centroids from the
    contact line, m, eqs. 6-7), ``joint`` (joint id), ``corner`` (a corner-to-edge
    point, not part of an edge-to-edge contact), ``far_gap`` (m, the gap at the other
    end of an edge-to-edge overlap) and ``far_point`` (that end; the point itself for
    a corner).
    """

    a: jax.Array
    b: jax.Array
    active: jax.Array
    gap: jax.Array
    point: jax.Array
    normal: jax.Array
    tangent: jax.Array
    edge: jax.Array
    own_edge: jax.Array
    halved: jax.Array
    share: jax.Array
    h_a: jax.Array
    h_b: jax.Array
    joint: jax.Array
    corner: jax.Array
    far_gap: jax.Array
    far_point: jax.Array


class Corners(NamedTuple):
    """The detection's vertices without a spring near another block's node (S, ...), for
    the step bound of :func:`jaxdem.core._substep.corner_bound`: ``watch`` (a vertex
    within the margin that bears on nothing), ``node_gap`` (S, 2) its distances (m,
    negative behind) from the lines of the two faces at the face block's node nearest
    to it, ``node_normal`` (S, 2, 2) their outward normals (values, no derivative)."""

    watch: jax.Array
    node_gap: jax.Array
    node_normal: jax.Array


class History(NamedTuple):
    """Each slot's history carried from the last sub-step (:func:`remap_history`): forces
    ``fs``, ``fn``, ``fn0`` (kN/m), ``failed``, ``edge``, ``present``, ``cstate`` and
    ``gap`` (m), the arrays of :class:`jaxdem.core.state.State` laid out along a pair
    list."""

    fs: jax.Array
    fn: jax.Array
    fn0: jax.Array
    failed: jax.Array
    edge: jax.Array
    present: jax.Array
    cstate: jax.Array
    gap: jax.Array


class _Bearing(NamedTuple):
    """How a vertex bears on a face (:func:`_slot_geometry`): gap and far_gap (m), s_e (its
    position along the face, m), share (m, before halving), h_x, h_y (m), far_point."""

    gap: jax.Array
    s_e: jax.Array
    share: jax.Array
    h_x: jax.Array
    h_y: jax.Array
    far_gap: jax.Array
    far_point: jax.Array


class _PairSlots(NamedTuple):
    """The slots of the vertices of one block of each pair against the other's faces, per
    pair (:func:`_vertex_edge`, :func:`_pair_slots`): :class:`Slots`' fields before the
    pair's blocks, joints and h floors are put in (h_x, h_y: :class:`_Bearing`), and
    :class:`Corners`'. ``halved`` is None until :func:`_pair_slots` sets it."""

    active: jax.Array
    gap: jax.Array
    point: jax.Array
    normal: jax.Array
    tangent: jax.Array
    edge: jax.Array
    own_edge: jax.Array
    share: jax.Array
    h_x: jax.Array
    h_y: jax.Array
    far_gap: jax.Array
    far_point: jax.Array
    watch: jax.Array
    node_gap: jax.Array
    node_normal: jax.Array
    halved: jax.Array | None = None


def _take(x, idx, axis):
    """``jnp.take_along_axis`` with indices known to be in range (no fill, no mask).

    Every index here (a chosen face, the next or previous vertex) is in range by
    construction; the default mode's bounds test and fill would be evaluated
    for each element, and again for each parameter's tangent.
    """
    return jnp.take_along_axis(x, idx, axis=axis, mode="promise_in_bounds")


def _dot(x, y):
    """x . y over the last axis of 2-vectors, as two products and a sum.

    Not ``jnp.sum(x * y, axis=-1)``: XLA's CPU reduction over an axis of 2
    costs several times the elementwise form, and its forward-mode tangents,
    batched over p parameters, add one such reduction per parameter.
    """
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1]


def edges(verts: jax.Array, nv: jax.Array):
    """Edge start points, end points, lengths, unit tangents and outward normals.

    Args:
      verts: (..., V, 2) counter-clockwise vertices (padding repeats vertex 0).
      nv: (...,) vertex counts.
    Returns:
      q0, q1: (..., V, 2); length: (..., V); t, n: (..., V, 2); emask: (..., V).
      Edge k runs from vertex k to vertex k + 1 (mod nv); padded edges are masked.
    """
    V = verts.shape[-2]
    k = jnp.arange(V)
    nxt = jnp.where(k + 1 < nv[..., None], k + 1, 0)
    q1 = _take(verts, nxt[..., None], axis=-2)
    d = q1 - verts
    # Padded edges have zero length: take the root of a safe value there, so
    # that derivatives stay finite (d sqrt(x) is infinite at x = 0).
    d2 = _dot(d, d)
    length = jnp.where(d2 > 0, jnp.sqrt(jnp.where(d2 > 0, d2, 1.0)), 0.0)
    emask = k < nv[..., None]
    safe = jnp.where(emask & (length > 0), length, 1.0)
    t = d / safe[..., None]
    n = jnp.stack([t[..., 1], -t[..., 0]], axis=-1)
    return verts, q1, length, t, n, emask


def bounding_boxes(verts: jax.Array, margin) -> jax.Array:
    """(N, 4) boxes (xmin, ymin, xmax, ymax), grown by half the margin on each side."""
    lo = jnp.min(verts, axis=1) - 0.5 * margin
    hi = jnp.max(verts, axis=1) + 0.5 * margin
    return jnp.concatenate([lo, hi], axis=-1)


def _boxes_overlap(bi, bj):
    return (
        (bi[..., 0] <= bj[..., 2])
        & (bj[..., 0] <= bi[..., 2])
        & (bi[..., 1] <= bj[..., 3])
        & (bj[..., 1] <= bi[..., 3])
    )


def broad_phase(model: Model, verts: jax.Array, capacity: int, alive: jax.Array):
    """Candidate pairs (a < b) whose grown boxes overlap and that can move.

    ``alive`` (N,) masks out excavated blocks and the dead blocks that fill a
    model up to its size class (``State.alive``: there is no default, since
    every model past 7 blocks has some).

    Returns:
      pairs: (capacity, 2) int32, empty entries (N, N), sorted by a * N + b.
      count: number of candidate pairs found (more than ``capacity``: overflow).
      cell_full: the blocks had more neighbours in their cells than ``model.cell_capacity``
        times N places, or there are more wide pairs than ``model.wide_capacity``
        (:func:`narrow_phase`).
    """
    N = model.n_blocks
    box = bounding_boxes(verts, model.margin)
    ids = jnp.arange(N)
    movable = model.free & alive
    if not model.use_cells:
        ok = _boxes_overlap(box[:, None, :], box[None, :, :])
        ok = ok & (ids[:, None] < ids[None, :]) & alive[:, None] & alive[None, :]
        ok = ok & (movable[:, None] | movable[None, :])
        count = jnp.sum(ok)
        a, b = jnp.nonzero(ok, size=capacity, fill_value=N)
        pairs = jnp.stack([a, b], axis=-1).astype(jnp.int32)
        return pairs, count, _wide_full(model, pairs)

    is_big = jnp.zeros(N, bool).at[model.big].set(True) if model.n_big else jnp.zeros(N, bool)
    # The small live blocks go in cells; dead blocks (excavated, or the padding of a
    # size class, which copies a block that may be big) neither take room in a cell
    # nor set its size.
    hashed = ~is_big & alive
    # Cells no smaller than the largest small block in any orientation.
    small_r = jnp.where(hashed, model.radius, 0.0)
    cell = 2.0 * jnp.max(small_r) + 2.0 * model.margin
    centre = 0.5 * (box[:, :2] + box[:, 2:])
    origin = jnp.min(jnp.where(hashed[:, None], centre, jnp.inf), axis=0)
    cxy = jnp.clip(jnp.floor((centre - origin) / cell).astype(jnp.int32), 0, 2**15 - 2) + 1
    key = jnp.where(hashed, cxy[:, 0] * 2**16 + cxy[:, 1], -1)
    order = jnp.argsort(key)
    skey = key[order]
    offsets = jnp.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)], jnp.int32)
    nkey = (cxy[:, None, 0] + offsets[None, :, 0]) * 2**16 + (cxy[:, None, 1] + offsets[None, :, 1])
    start = jnp.searchsorted(skey, nkey, side="left")
    stop = jnp.searchsorted(skey, nkey, side="right")
    # Each block's neighbours, cell by cell, laid end to end in ``room`` places (the
    # blocks of its own and the eight cells around, a ragged list): not ``room`` per
    # cell for every cell. Cells hold very different numbers of blocks where block sizes
    # vary (a fine mesh round a tunnel in a coarse one), and padding every cell to the
    # fullest one cost seed example 2 1.5 million places (30 ms a detection) for the
    # 150,000 or so it has.
    per_cell = jnp.where(hashed[:, None], stop - start, 0).reshape(-1)  # (9 N,)
    room = N * model.cell_capacity
    cell_full = jnp.sum(per_cell) > room
    q = jnp.repeat(jnp.arange(9 * N), per_cell, total_repeat_length=room)
    place = jnp.arange(room)
    first = jnp.cumsum(per_cell) - per_cell
    inside = place < jnp.sum(per_cell)
    i = q // 9
    j = order[jnp.clip(start.reshape(-1)[q] + place - first[q], 0, N - 1)]
    ok_cell = inside & (i < j) & _boxes_overlap(box[i], box[j])
    ok_cell = ok_cell & alive[i] & alive[j] & (movable[i] | movable[j])
    cand_a = [i]
    cand_b = [j]
    cand_ok = [ok_cell]
    if model.n_big:
        g = model.big
        ok_big = _boxes_overlap(box[g][:, None, :], box[None, :, :])
        # Big-big pairs once (from the lower id), big-small pairs from the big side.
        once = ~is_big[None, :] | (ids[None, :] > g[:, None])
        ok_big = ok_big & (g[:, None] != ids[None, :]) & once
        ok_big = ok_big & alive[g][:, None] & alive[None, :]
        ok_big = ok_big & (movable[g][:, None] | movable[None, :])
        ga = jnp.broadcast_to(g[:, None], ok_big.shape)
        gb = jnp.broadcast_to(ids[None, :], ok_big.shape)
        cand_a.append(jnp.minimum(ga, gb).reshape(-1))
        cand_b.append(jnp.maximum(ga, gb).reshape(-1))
        cand_ok.append(ok_big.reshape(-1))
    a = jnp.concatenate(cand_a)
    b = jnp.concatenate(cand_b)
    ok = jnp.concatenate(cand_ok)
    count = jnp.sum(ok)
    sel = jnp.nonzero(ok, size=capacity, fill_value=a.shape[0])[0]
    a = jnp.concatenate([a, jnp.array([N])])[sel]
    b = jnp.concatenate([b, jnp.array([N])])[sel]
    # Sort by key so that history matching and output are order-independent.
    k = a.astype(jnp.int64) * (N + 1) + b
    o = jnp.argsort(k)
    pairs = jnp.stack([a[o], b[o]], axis=-1).astype(jnp.int32)
    return pairs, count, cell_full | _wide_full(model, pairs)


def _wide_full(model: Model, pairs):
    """More wide pairs (:func:`wide_pairs`) than the narrow phase has places for."""
    if model.narrow_vertices >= model.n_vertices or not model.wide_capacity:
        return jnp.array(False)
    return jnp.sum(wide_pairs(model, pairs)) > model.wide_capacity


def block_widths(e_all):
    """Each block's least width (N,): the depth of its deepest vertex below one of its faces.

    The face and the vertex are found on values (a choice has no derivative);
    the width is then evaluated at them. ``e_all``: :func:`edges` of every block.
    """
    q0, _, _, _, ny, em = e_all
    sg = jax.lax.stop_gradient
    depth = -_dot(sg(q0)[:, None, :, :] - sg(q0)[:, :, None, :], sg(ny)[:, :, None, :])
    depth = jnp.where(em[:, None, :] & em[:, :, None], depth, -jnp.inf)  # (N, face, vertex)
    deepest = jnp.argmax(depth, axis=-1)  # (N, face)
    thin = jnp.argmin(jnp.where(em, jnp.max(depth, axis=-1), jnp.inf), axis=-1)  # (N,)
    pick = lambda x, i: _take(x, i[:, None, None], axis=1)[:, 0]  # noqa: E731
    v_deep = _take(deepest, thin[:, None], axis=1)[:, 0]
    return -_dot(pick(q0, v_deep) - pick(q0, thin), pick(ny, thin))


def _slot_geometry(model: Model, xv, x_next, x_prev, cx, cy, q, n, t, L_e, l_out, l_in, po,
                   pi, inside=None):
    """The differentiable part of slots whose face (and own face) are chosen.

    A vertex xv of block X (its neighbours x_next, x_prev; its outgoing and
    incoming faces' lengths l_out, l_in) bearing on the face of Y that starts at
    q (normal n, tangent t, length L_e); po, pi: X's outgoing or incoming face
    is anti-parallel to it (edge-to-edge). ``inside``: the vertex is inside
    the face's span (None: from the values here). Any shapes that broadcast;
    :func:`_vertex_edge` calls it per pair, :func:`slot_geometry` per slot.
    Returns a :class:`_Bearing`.
    """
    gap = _dot(xv - q, n)
    s_e = _dot(xv - q, t)
    # Overlap of X's anti-parallel face with the contacted face, along that face.
    other = jnp.where(po[..., None], x_next, x_prev)
    s0 = s_e
    s1 = _dot(other - q, t)
    lo = jnp.clip(jnp.minimum(s0, s1), 0.0, L_e)
    hi = jnp.clip(jnp.maximum(s0, s1), 0.0, L_e)
    # Faces that meet end to end at a node overlap by round-off (1e-16 m, on either side of
    # zero): no length.
    overlap = jnp.where(hi - lo > model.touch_tol, hi - lo, 0.0)
    # Gap at the far end of the overlap (linear along the faces): faces within
    # 2 degrees of parallel can still be a sliver's width apart there.
    d1 = _dot(other - q, n)
    s_far = jnp.where(jnp.abs(lo - s0) > jnp.abs(hi - s0), lo, hi)
    run = jnp.where(jnp.abs(s1 - s0) > 0, s1 - s0, 1.0)
    far_gap = gap + (d1 - gap) * (s_far - s0) / run
    corner = model.corner_share * jnp.minimum(l_out, l_in)
    parallel = po | pi
    # A corner bears on a face only inside its span: at the end of a face
    # (faces meeting end to end at a mesh node) it touches without bearing.
    if inside is None:
        inside = (s_e > model.span_tol) & (s_e < L_e - model.span_tol)
    share = jnp.where(parallel, 0.5 * overlap, jnp.where(inside, corner, 0.0))
    # Each centroid's distance to its own side of an edge-to-edge contact: X's to its
    # own face (through its vertex), Y's to its face. Measured both to Y's face, an
    # overlap shortened X's h (and stiffened its spring) but not Y's, and a contact seen
    # from both blocks (coincident corners) got two different springs. A corner has
    # no face of its own on the contact: its h is to Y's face.
    h_x = jnp.maximum(_dot(cx - jnp.where(parallel[..., None], xv, q), n), 0.0)
    h_y = jnp.maximum(_dot(q - cy, n), 0.0)
    return _Bearing(gap=gap, s_e=s_e, share=share, h_x=h_x, h_y=h_y,
                    far_gap=jnp.where(parallel, far_gap, gap),
                    far_point=xv + jnp.where(parallel, s_far - s0, 0.0)[..., None] * t)


def _slot_finish(model: Model, g: _Bearing | _PairSlots, halved, X, Y, widths):
    """(share, h_a, h_b) from g's share, h_x and h_y: share halved where both sides see
    the point; h_a, h_b with their floors.

    A centroid on or behind the contact line (a corner reaching round the
    end of a face) would give h = 0 and, against a rigid wall, an infinite
    spring: h is at least a tenth of the block's size, its radius or, for an
    elongated block, its least width (a 10 m x 0.01 m sliver lying on its
    face has h = 5 mm, not 0.5 m: a floor on the radius would make it 100
    times too soft).
    """
    return (jnp.where(halved, 0.5, 1.0) * g.share,
            jnp.maximum(g.h_x, 0.1 * jnp.minimum(model.radius[X], widths[X])),
            jnp.maximum(g.h_y, 0.1 * jnp.minimum(model.radius[Y], widths[Y])))


#: How far (a fraction of the smaller block's step length) a corner may pass into another
#: block at a node where it has no spring before the step is cut
#: (:func:`jaxdem.core._substep.corner_bound`); one half as far in, it has a spring.
CORNER_PASS = 0.1


def block_steps(model: Model):
    """The farthest each block (N,) may travel in one sub-step (m): ``step_length``, and a
    small block at most a quarter of its radius."""
    return jnp.minimum(model.step_length, 0.25 * model.radius)


def _vertex_edge(model: Model, xv, nvx, vmx, cx, ex, ey, cy, width, entered):
    """Slots of the vertices of block X against the edges of block Y, per pair.

    Args:
      xv: (P, V, 2) vertices of X; nvx: (P,) counts; vmx: (P, V) mask.
      cx, cy: (P, 2) centroids. ex, ey: edges of X and of Y (output of :func:`edges`).
      width: (P,) Y's least width (:func:`block_widths`).
      entered: (P,) depth (m) inside Y past which a vertex at a node has a spring.
    Returns a :class:`_PairSlots` of (P, V, ...) arrays, ``halved`` None: active, gap
    (m, negative = overlap), point, normal and tangent of the contacted face, edge index,
    share (m), h_x, h_y (m), own_edge (X's face anti-parallel to it, or -1), far_gap and
    far_point; watch, node_gap (P, V, 2) and node_normal (P, V, 2, 2) (see
    :func:`narrow_phase`).
    """
    q0, _, ly, ty, ny, emy = ey
    V = xv.shape[1]
    # Which face each vertex bears on, and whether it is near, is decided on
    # values alone (a choice has no derivative): the O(P V^2) vertex-face
    # tables are built from stop_gradient copies, and only the chosen face's
    # gap and position are differentiated, O(P V). Sensitivities (jvp of the
    # detection, jaxdem.differentiable) then carry no V^2 tangents.
    sg = jax.lax.stop_gradient
    rel = sg(xv)[:, :, None, :] - sg(q0)[:, None, :, :]  # (P, V, V_edges, 2)
    d = _dot(rel, sg(ny)[:, None, :, :])
    d = jnp.where(emy[:, None, :], d, -jnp.inf)
    dmax = jnp.max(d, axis=-1)
    # Adjacent faces of each vertex of X: outgoing (v -> v+1) and incoming (v-1 -> v).
    _, _, lx, tx, _, _ = ex
    k = jnp.arange(V)
    prev = jnp.where(k[None, :] > 0, k[None, :] - 1, nvx[:, None] - 1)
    nxt = jnp.where(k[None, :] + 1 < nvx[:, None], k[None, :] + 1, 0)
    t_in = _take(tx, prev[..., None], axis=1)
    l_in = _take(lx, prev, axis=1)
    c_out = _dot(sg(tx)[:, :, None, :], sg(ty)[:, None, :, :])  # (P, V, Ve)
    c_in = _dot(sg(t_in)[:, :, None, :], sg(ty)[:, None, :, :])
    par_out = c_out < -model.cos_parallel
    par_in = c_in < -model.cos_parallel
    # A vertex on or inside Y (within touch_tol of its nearest face, and within that
    # face's span, not at a node) bears only on a face that X, near the vertex, lies
    # outside of: one of its own faces is anti-parallel to it or leaves the vertex
    # across its line by more than the parallel tolerance. A face whose line X's
    # corner lies along or within (the face of a block on the same side of a joint
    # trace as X: a slab that slides along a daylighting joint past the point where
    # that trace goes on between two blocks below) is never its contact: its gap is
    # zero however deep the corner has gone in through Y's other face. Without such
    # a face, at a node and for a vertex outside Y, every face: a vertex just outside
    # a face with its block's faces pointing into the face's line is an open slot on
    # it as before. Where the slab turns a little, one of the two corners is inside
    # the other block, and that side sees the overlap.
    sin_par = jnp.sqrt(jnp.maximum(1.0 - model.cos_parallel**2, 0.0))
    leaves = jnp.maximum(_dot(sg(tx)[:, :, None, :], sg(ny)[:, None, :, :]),
                         -_dot(sg(t_in)[:, :, None, :], sg(ny)[:, None, :, :]))
    entry = emy[:, None, :] & ((leaves > sin_par) | par_out | par_in)
    nearest = jnp.argmax(d, axis=-1)[..., None]
    s_near = _dot(sg(xv) - _take(sg(q0), nearest, axis=1), _take(sg(ty), nearest, axis=1))
    l_near = _take(ly, nearest[..., 0], axis=1)
    on = (jnp.any(entry, axis=-1) & (dmax <= model.touch_tol)
          & (s_near > model.span_tol) & (s_near < l_near - model.span_tol))
    # Y's node nearest to the vertex, and its two faces: that of the nearest face's
    # nearer end, and the face meeting it there (for :func:`corner_bound`).
    f1 = nearest[..., 0]
    nvy = jnp.sum(emy, axis=-1)[:, None]
    f2 = jnp.where(s_near >= 0.5 * l_near, jnp.where(f1 + 1 < nvy, f1 + 1, 0),
                   jnp.where(f1 > 0, f1 - 1, nvy - 1))
    node_gap = jnp.stack([dmax, _take(d, f2[..., None], axis=-1)[..., 0]], axis=-1)
    node_normal = jnp.stack([_take(sg(ny), f1[..., None], axis=1),
                             _take(sg(ny), f2[..., None], axis=1)], axis=-2)
    entry = entry | ~on[..., None]
    d_entry = jnp.where(entry, d, -jnp.inf)
    # A vertex that overlaps near a corner is on the face anti-parallel to its own.
    # "Near" is within the margin, but less than half of Y's least width: the
    # far face of a thin block is never near.
    window = jnp.minimum(model.margin, 0.5 * sg(width))
    near_face = d_entry >= jnp.max(d_entry, axis=-1, keepdims=True) - window[:, None, None]
    # Among the near faces anti-parallel to one of the vertex's own, the least
    # penetrated; without one, the least penetrated face. (A bonus added to d
    # rounded d away: at a corner of Y where both of X's faces are anti-parallel
    # to one of Y's, the choice fell to the order of Y's edges, and a mirrored
    # scene chose the other face.)
    eligible = near_face & (par_out | par_in)
    score = jnp.where(jnp.any(eligible, axis=-1, keepdims=True),
                      jnp.where(eligible, d, -jnp.inf), d_entry)
    e = jnp.argmax(score, axis=-1).astype(jnp.int32)
    take = lambda x: _take(x, e[..., None], axis=-1)[..., 0]  # noqa: E731
    # The face chosen is within the window of the vertex's nearest face: a vertex
    # whose only faces of entry are deeper than that bears on nothing (Y's far
    # side would give a spurious overlap).
    beside = take(d) < dmax - window[:, None]
    n = _take(ny, e[..., None], axis=1)
    t = _take(ty, e[..., None], axis=1)
    q = _take(q0, e[..., None], axis=1)
    L_e = _take(ly, e, axis=1)
    po = take(par_out)
    pi = take(par_in)
    # A corner that has gone past the end of Y's face it was sliding along bears on
    # the face it crossed from there on, at its end too: the end of a face is
    # where two faces meet end to end at a node, but this corner came along the
    # other face's line, not to the node.
    s_v = _dot(sg(xv) - sg(q), sg(t))
    crossed = on & (take(d) < dmax - model.touch_tol)
    # A corner that came to a node of Y where it had no spring (corner to corner) and
    # went on into Y, ``entered`` deep (half of :data:`CORNER_PASS` of a step length)
    # behind all of Y's faces, bears on the face it went in through, the least
    # penetrated, however near the node: the step was cut there for the next detection
    # to give it this spring (:func:`jaxdem.core._substep.corner_bound`). Without it
    # such a corner stayed at the node, each step cut at once.
    inside = (((s_v > model.span_tol) & (s_v < L_e - model.span_tol)) | crossed
              | (dmax <= -entered[:, None]))
    g = _slot_geometry(model, xv, _take(xv, nxt[..., None], axis=1),
                       _take(xv, prev[..., None], axis=1), cx[:, None, :], cy[:, None, :], q, n,
                       t, L_e, lx, l_in, po, pi, inside)
    # A vertex a little past the end of a face still bears on it: blocks whose
    # corners coincide (a regular grid) shift by joint shear, and the contact
    # point must not hop to the other block's vertex and lose its history.
    in_span = (g.s_e >= -model.span_tol) & (g.s_e <= L_e + model.span_tol)
    near = vmx & (dmax <= model.margin) & in_span & ~beside
    # Faces that meet end to end (a diagonal neighbour on a grid) share no
    # length: no spring.
    active = near & (g.share > 0)
    own_edge = jnp.where(po, k[None, :], jnp.where(pi, prev, -1))
    # A vertex within the margin that bears on nothing (at a node of Y: corner to
    # corner, faces meeting end to end) has no spring to stop it: its step is bounded
    # by the two faces at that node instead (:func:`corner_bound`).
    watch = vmx & (dmax <= model.margin) & ~active
    return _PairSlots(active=active, gap=g.gap, point=xv, normal=n, tangent=t, edge=e,
                      own_edge=own_edge, share=g.share, h_x=g.h_x, h_y=g.h_y,
                      far_gap=g.far_gap, far_point=g.far_point, watch=watch,
                      node_gap=node_gap, node_normal=node_normal)


def _pair_slots(model: Model, verts, nv, vmask, e_all, widths, centroid, pairs):
    """:func:`narrow_phase`'s slots of each pair: a :class:`_PairSlots` of (P, 2, V', ...)
    arrays, V' = verts.shape[1]
    (``nv``, ``vmask`` and ``e_all``, the blocks' :func:`edges`, for these vertices;
    ``widths`` from all of them)."""
    N = model.n_blocks
    P = pairs.shape[0]
    valid = pairs[:, 0] < N
    a = jnp.clip(pairs[:, 0], 0, N - 1)
    b = jnp.clip(pairs[:, 1], 0, N - 1)
    va, vb = verts[a], verts[b]
    nva, nvb = nv[a], nv[b]
    vma = vmask[a] & valid[:, None]
    vmb = vmask[b] & valid[:, None]
    ea, eb = (tuple(x[a] for x in e_all), tuple(x[b] for x in e_all))
    ca, cb = centroid[a], centroid[b]
    # Both sides in one call, the second side's pairs after the first's: one copy of the
    # vertex-face tests in the program, not two (a program's size is its time to compile
    # and to load).
    both = lambda x, y: jnp.concatenate([x, y])  # noqa: E731
    step = block_steps(model)
    entered = 0.5 * CORNER_PASS * jnp.minimum(step[a], step[b])
    s = _vertex_edge(model, both(va, vb), both(nva, nvb), both(vma, vmb), both(ca, cb),
                     tuple(map(both, ea, eb)), tuple(map(both, eb, ea)), both(cb, ca),
                     both(widths[b], widths[a]), both(entered, entered))
    s0, s1 = jax.tree.map(lambda x: x[:P], s), jax.tree.map(lambda x: x[P:], s)
    # A vertex of b at a contact point of a vertex of a (within that point's
    # overlap) is the same contact point, seen from both sides: each side's slot
    # takes half of it. Keeping one side's only (the lower block index's) made
    # the answer depend on how the blocks are numbered: at a junction of several
    # blocks the two sides' points can bear on different faces, and a mirrored
    # scene, numbered otherwise, got other springs (tests/test_metamorphic.py).
    dv = vb[:, :, None, :] - va[:, None, :, :]  # (P, V of b, V of a)
    reach = (1.5 * jnp.maximum(jnp.abs(s0.gap)[:, None, :], jnp.abs(s1.gap)[:, :, None])
             + model.span_tol)
    same = (_dot(dv, dv) <= reach**2) & s0.active[:, None, :] & s1.active[:, :, None]
    s0 = s0._replace(halved=jnp.any(same, axis=1))
    s1 = s1._replace(halved=jnp.any(same, axis=2))
    return jax.tree.map(lambda x, y: jnp.stack([x, y], axis=1), s0, s1)


def wide_pairs(model: Model, pairs):
    """(P,) the pairs that :func:`narrow_phase` tests with all V vertices: one of their
    blocks has more than ``model.narrow_vertices``."""
    N = model.n_blocks
    wide = model.nv > model.narrow_vertices
    return (pairs[:, 0] < N) & (wide[jnp.clip(pairs[:, 0], 0, N - 1)]
                                | wide[jnp.clip(pairs[:, 1], 0, N - 1)])


def _pad_vertices(slots: _PairSlots, V) -> _PairSlots:
    """(P, 2, v, ...) slots padded to V vertices with copies of vertex 0's, inactive (the
    values a padded vertex, a copy of the first, has; active, watch and halved False)."""
    def pad(key, x):
        fill = jnp.broadcast_to(x[:, :, :1], x.shape[:2] + (V - x.shape[2],) + x.shape[3:])
        if key in ("active", "watch", "halved"):
            fill = jnp.zeros_like(fill)
        return jnp.concatenate([x, fill], axis=2)

    return _PairSlots(*(pad(k, x) for k, x in zip(slots._fields, slots, strict=True)))


def narrow_phase(model: Model, verts, centroid, pairs) -> tuple[Slots, Corners]:
    """Spring slots of every candidate pair, flattened to S = P * 2 * V.

    Returns the :class:`Slots` (``own_edge`` and ``halved`` are the choices that
    :func:`slot_geometry` takes again) and, for the step bound of vertices without a
    spring (:func:`jaxdem.core._substep.corner_bound`), the :class:`Corners`.
    """
    N = model.n_blocks
    P = pairs.shape[0]
    V = model.n_vertices
    # Each block's edges and width once, then per pair: not twice per pair (primal
    # and tangents).
    e_all = edges(verts, model.nv)
    widths = block_widths(e_all)
    v = model.narrow_vertices
    if v >= V:
        out = _pair_slots(model, verts, model.nv, model.vmask, e_all, widths, centroid, pairs)
    else:
        # Most pairs with the first v vertices of their blocks (all they have), then the
        # wide ones (a block with more: :func:`jaxdem.core.model._narrow_split`) again with
        # all V, over the first's values (none where no block has more than v: V is a size
        # class, and may be more than any block has). A block with more than v vertices is
        # cut to its first v in the first pass (a convex polygon still, its values unused).
        nv = jnp.minimum(model.nv, v)
        out = _pair_slots(model, verts[:, :v], nv, model.vmask[:, :v], edges(verts[:, :v], nv),
                          widths, centroid, pairs)
        out = _pad_vertices(out, V)
        if model.wide_capacity:
            at = jnp.nonzero(wide_pairs(model, pairs), size=model.wide_capacity,
                             fill_value=P)[0]
            wide = jnp.concatenate([pairs, jnp.full((1, 2), N, pairs.dtype)])[at]
            w = _pair_slots(model, verts, model.nv, model.vmask, e_all, widths, centroid, wide)
            out = jax.tree.map(lambda x, y: x.at[at].set(y, mode="drop"), out, w)
    a = jnp.clip(pairs[:, 0], 0, N - 1)
    b = jnp.clip(pairs[:, 1], 0, N - 1)
    A = jnp.stack([jnp.broadcast_to(a[:, None], (P, V)), jnp.broadcast_to(b[:, None], (P, V))], 1)
    B = jnp.stack([jnp.broadcast_to(b[:, None], (P, V)), jnp.broadcast_to(a[:, None], (P, V))], 1)
    # Joint of the slot: that of the contacted face, else of the own face, else the default.
    j_face = model.edge_joint[B, out.edge]
    j_own = jnp.where(out.own_edge >= 0, model.edge_joint[A, jnp.maximum(out.own_edge, 0)], -1)
    default = model.joint_kn.shape[0] - 1
    joint = jnp.where(j_face >= 0, j_face, jnp.where(j_own >= 0, j_own, default))
    S = P * 2 * V
    flat = lambda x: x.reshape((S,) + x.shape[3:])  # noqa: E731
    f = jax.tree.map(flat, out)
    share, h_a, h_b = _slot_finish(model, f, f.halved, flat(A), flat(B), widths)
    slots = Slots(a=flat(A), b=flat(B), active=f.active, gap=f.gap, point=f.point,
                  normal=f.normal, tangent=f.tangent, edge=f.edge, own_edge=f.own_edge,
                  halved=f.halved, share=share, h_a=h_a, h_b=h_b, joint=flat(joint),
                  corner=f.own_edge < 0, far_gap=f.far_gap, far_point=f.far_point)
    return slots, Corners(watch=f.watch, node_gap=f.node_gap, node_normal=f.node_normal)


def slot_geometry(model: Model, verts, centroid, slots: Slots, vertex) -> Slots:
    """The differentiable fields of given slots (any subset, in any order) of :func:`narrow_phase`.

    ``slots`` holds each slot's choices as :func:`narrow_phase` made them (``a``,
    ``b``, ``edge``, ``own_edge``, ``halved``; ``joint``, ``active`` and ``corner`` are
    kept as they are), ``vertex`` the vertex's index in block a. Returns ``slots``
    with ``gap``, ``point``, ``normal``, ``tangent``, ``share``, ``h_a``, ``h_b``,
    ``far_gap`` and ``far_point`` evaluated at ``verts`` and ``centroid``: the same
    values as :func:`narrow_phase` where the slot is active (``inside`` is then
    implied), and their derivatives through the same expressions. The sensitivities
    differentiate the active slots alone.
    """
    X, Y, k, e, own = slots.a, slots.b, vertex, slots.edge, slots.own_edge
    e_all = edges(verts, model.nv)
    q0, _, length, t_all, n_all, _ = e_all
    nv = model.nv[X]
    prev = jnp.where(k > 0, k - 1, nv - 1)
    nxt = jnp.where(k + 1 < nv, k + 1, 0)
    xv = verts[X, k]
    n, t = n_all[Y, e], t_all[Y, e]
    g = _slot_geometry(model, xv, verts[X, nxt], verts[X, prev], centroid[X], centroid[Y],
                       q0[Y, e], n, t, length[Y, e], length[X, k], length[X, prev], own == k,
                       own == prev, inside=jnp.ones(k.shape, bool))
    share, h_a, h_b = _slot_finish(model, g, slots.halved, X, Y, block_widths(e_all))
    return slots._replace(gap=g.gap, point=xv, normal=n, tangent=t, share=share, h_a=h_a,
                          h_b=h_b, far_gap=g.far_gap, far_point=g.far_point)


def remap_history(state: State, new_pairs: jax.Array, n_blocks: int) -> History:
    """Carry each slot's history (forces, failure, face) to the new pair list.

    Slots are matched by their stable key (pair, side, vertex). Returns the old
    arrays laid out along ``new_pairs`` (P, 2, V) (empty where the pair is new).
    """
    N1 = n_blocks + 1
    okey = state.pairs[:, 0].astype(jnp.int64) * N1 + state.pairs[:, 1]
    nkey = new_pairs[:, 0].astype(jnp.int64) * N1 + new_pairs[:, 1]
    order = jnp.argsort(okey)
    sk = okey[order]
    pos = jnp.clip(jnp.searchsorted(sk, nkey), 0, sk.shape[0] - 1)
    hit = (sk[pos] == nkey) & (new_pairs[:, 0] < n_blocks)
    src = order[pos]
    pick = lambda x, empty: jnp.where(  # noqa: E731
        hit[:, None, None], x[src], jnp.asarray(empty, x.dtype))
    return History(
        fs=pick(state.fs, 0), fn=pick(state.fn, 0), fn0=pick(state.fn0, 0),
        failed=pick(state.failed, False),
        edge=pick(state.edge, -1),
        present=pick(state.present, False), cstate=pick(state.cstate, 0),
        gap=pick(state.gap, 0),
    )
