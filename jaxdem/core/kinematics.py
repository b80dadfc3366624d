"""Kinematics of the blocks: rigid motion, rotation, constant strain, points and anchors.

Owns the maps from a block's generalised displacement (ux, uy, theta[, eps_x,
eps_y, gamma_xy]) to the motion of its points: :func:`point_row` and
:func:`b_rows` (the rows of B), :func:`strain_times`, :func:`rotate_vectors`,
:func:`move_blocks` (the exact motion of a whole increment), :func:`bolt_geometry`
and :func:`bolt_length_derivatives` (bolt anchors), :func:`block_travel` and
:func:`group_limits` (how far a block moved, and how far it may: :func:`connected_groups`
of the blocks that move together), and the gather and
scatter between slots and blocks. Pure jax.numpy on fixed shapes; no laws.

Data flow: takes the device pytrees of :mod:`jaxdem.core.state`; used by the spring
forces (:mod:`jaxdem.core._springs`), the linear solves, the sub-step, the loads,
the driver, and by :mod:`jaxdem.results` (monitors, bolt anchors).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdem.core.state import Model, Snapshot, State

#: A block of a mechanism moves: its path in the increment that found it passed this share
#: of ``solver.max_displacement`` (the median block size where the scene leaves it out).
#: One rule for the blocks a result names (:func:`jaxdem.results.moving_blocks`), those
#: that share a travel limit (:func:`group_limits`) and those removed as loose
#: (:func:`jaxdem.solver.falling_free`).
MOVING = 0.1


def cross(r, v):
    return r[..., 0] * v[..., 1] - r[..., 1] * v[..., 0]


def point_row(r, v, ndof=3):
    """Row mapping a block's (u, theta[, eps_x, eps_y, gamma_xy]) to v . displacement of point r.

    The displacement of a point at r from the centroid is u + theta x r + E r,
    E = [[eps_x, gamma/2], [gamma/2, eps_y]] for a deformable (constant-strain)
    block. The same row maps a point force v to the block's generalised force.
    """
    cols = [v, cross(r, v)[..., None]]
    if ndof == 6:
        cols.append(jnp.stack([v[..., 0] * r[..., 0], v[..., 1] * r[..., 1],
                               0.5 * (v[..., 0] * r[..., 1] + v[..., 1] * r[..., 0])], -1))
    return jnp.concatenate(cols, axis=-1)


def strain_times(e, r):
    """E r for strains e = (eps_x, eps_y, gamma_xy) (engineering shear), broadcasting."""
    return jnp.stack([e[..., 0] * r[..., 0] + 0.5 * e[..., 2] * r[..., 1],
                      0.5 * e[..., 2] * r[..., 0] + e[..., 1] * r[..., 1]], -1)


def b_rows(free, a, b, point_a, point_b, direction, centroid, ndof=3):
    """Rows of B mapping (du_a, du_b) to the relative displacement along ``direction``.

    v . disp_a(r_a) - v . disp_b(r_b), r_a = point_a - c_a, r_b = point_b - c_b
    (the same point for a contact, the two anchors for a bolt), with
    disp from :func:`point_row`. Parts of blocks without degrees of freedom are
    zeroed. Returns (M, 2 ndof).
    """
    ra, rb = point_a - centroid[a], point_b - centroid[b]
    fa = free[a][:, None].astype(ra.dtype)
    fb = free[b][:, None].astype(ra.dtype)
    pa = point_row(ra, direction, ndof) * fa
    pb = -point_row(rb, direction, ndof) * fb
    return jnp.concatenate([pa, pb], axis=1)


def gather_pairs(du, a, b):
    return jnp.concatenate([du[a], du[b]], axis=1)


def scatter_pairs(n_blocks, a, b, x):
    """Sum (M, 2 D) row vectors into (N, D) block vectors."""
    d = x.shape[1] // 2
    return (jax.ops.segment_sum(x[:, :d], a, n_blocks)
            + jax.ops.segment_sum(x[:, d:], b, n_blocks))


def rotate_vectors(r, angle):
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([cos * r[..., 0] - sin * r[..., 1], sin * r[..., 0] + cos * r[..., 1]], -1)


def _rotate_tensor(v, angle):
    """(x, y, xy) components of a symmetric tensor rotated by ``angle`` (tensor shear)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    xx, yy, xy = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([c * c * xx + s * s * yy - 2 * c * s * xy,
                      s * s * xx + c * c * yy + 2 * c * s * xy,
                      c * s * (xx - yy) + (c * c - s * s) * xy], -1)


def move_blocks(model: Model, state: State, du, stress=None):
    """Move every block by du: exact rigid motion (ux, uy, theta) about its centroid.

    Positions are the start geometry (``model.verts0``, ``model.centroid0``)
    moved by the accumulated displacement and rotation, so that round-off
    does not pile up over many load steps: in float32 the move of one step of
    a thousand is below the resolution of a coordinate, and summing the moves
    into the coordinates lost a few percent of the displacement.

    A deformable block is first strained by (eps_x, eps_y, gamma_xy) about its
    centroid (which stays its centroid); its strain and ``stress`` (the new
    stress, tension positive) then turn with the block.
    """
    th = du[:, 2]
    u = state.u + du[:, :2]
    rot = state.rot + th
    centroid = model.centroid0 + u
    strain, new_stress = state.strain, state.stress
    if du.shape[1] == 6:
        e = du[:, 3:]
        r = state.verts - state.centroid[:, None, :]
        r = r + strain_times(e[:, None, :], r)
        tensor = lambda v: v * jnp.array([1.0, 1.0, 0.5], v.dtype)  # noqa: E731
        engineering = lambda v: v * jnp.array([1.0, 1.0, 2.0], v.dtype)  # noqa: E731
        strain = engineering(_rotate_tensor(tensor(state.strain + e), th))
        new_stress = _rotate_tensor(stress, th)
        verts = centroid[:, None, :] + rotate_vectors(r, th[:, None])
    else:
        r0 = model.verts0 - model.centroid0[:, None, :]
        verts = centroid[:, None, :] + rotate_vectors(r0, rot[:, None])
    return dataclasses.replace(state, verts=verts, centroid=centroid, u=u, rot=rot,
                               strain=strain, stress=new_stress)


class BoltAnchors(NamedTuple):
    """Each bolt's anchors where they are now (:func:`bolt_geometry`): blocks ``a``
    (anchor 2's) and ``b`` (anchor 1's), anchors ``point_a``, ``point_b`` (nb, 2) m, and
    ``e`` (nb, 2) the unit direction from anchor 1 to anchor 2."""

    a: jax.Array
    b: jax.Array
    point_a: jax.Array
    point_b: jax.Array
    e: jax.Array


def bolt_geometry(model: Model, state: State) -> BoltAnchors:
    """Bolt rows: anchors at their current positions, direction from anchor 1 to anchor 2."""
    i, j = model.bolt_blocks[:, 0], model.bolt_blocks[:, 1]
    p1 = state.centroid[i] + rotate_vectors(model.bolt_offsets[:, 0], state.rot[i])
    p2 = state.centroid[j] + rotate_vectors(model.bolt_offsets[:, 1], state.rot[j])
    d = p2 - p1
    e = d / jnp.maximum(jnp.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    # Elongation = e . (disp of anchor 2 - disp of anchor 1): anchor 2 is "a".
    return BoltAnchors(a=j, b=i, point_a=p2, point_b=p1, e=e)


def _perp(v):
    """v turned by +90 degrees: the derivative of R(theta) v in theta is R(theta) perp(v)."""
    return jnp.stack([-v[..., 1], v[..., 0]], -1)


def _anchor_motion(ndof, u, r):
    """An anchor's move and its first and second derivatives in its block's u.

    The anchor at r from the centroid moves by m(u) = (ux, uy) + R(theta) r' - r,
    r' = r + E(eps) r for a deformable block (strained, then turned: as
    :func:`move_blocks` moves it). Returns m (..., 2), J = dm/du (..., 2, D) and
    the one non-zero row and column of d2m/du2: d2m/dtheta2 = -R r' (..., 2) and
    d2m/(dtheta deps_k) = R perp(S_k r) (..., 2, D - 3); m is linear in the rest.
    """
    angle = u[..., 2]
    arm = r + strain_times(u[..., 3:], r) if ndof == 6 else r
    q = rotate_vectors(arm, angle)  # R r'
    eye = jnp.broadcast_to(jnp.eye(2, dtype=r.dtype), q.shape[:-1] + (2, 2))
    cols = [eye, _perp(q)[..., None]]
    cross_terms = None
    if ndof == 6:
        # R S_k r (..., 3, 2): E r is linear in the strains, S_k r is it at a unit strain k.
        turned = rotate_vectors(strain_times(jnp.eye(3, dtype=r.dtype), r[..., None, :]),
                                angle[..., None])
        cols.append(jnp.swapaxes(turned, -1, -2))
        cross_terms = jnp.swapaxes(_perp(turned), -1, -2)
    return u[..., :2] + q - r, jnp.concatenate(cols, -1), -q, cross_terms


def bolt_length_derivatives(ndof, d0, ra, rb, x):
    """Anchor-to-anchor length of each bolt after the move x = (du_a, du_b), with its
    gradient and Hessian in x, in closed form: L (B,), g (B, 2 D) and the Hessian as T
    weighted rank-one terms, H = sum_t c_t v_t v_t^T: v (B, T, 2 D), c (B, T)
    (:func:`bolt_hessian`).

    ``d0`` (B, 2) = anchor a - anchor b at the sub-step's geometry, ``ra``, ``rb``
    the anchors from their blocks' centroids. Exact rigid motion (and strain), as
    :func:`move_blocks` applies it: the bolt's force comes from its actual
    elongation at any displacement, not from a sum of linearised increments. With
    d = d0 + m_a - m_b, n = d / L, t = n turned a right angle and J = dd/dx: g = J^T n
    and H = (J^T J - g g^T) / L + sum_c n_c d2d_c/dx2. In the plane J^T J - g g^T =
    J^T t t^T J: the string stiffness across the bolt's line is one term, h h^T / L with
    h = J^T t. The lever-arm terms of the anchors' rotations are one term a block, s e e^T
    on its rotation (e the unit vector of theta, s = +-n . d2m/dtheta2); a deformable
    block's coupling w of its rotation and strains, e w^T + w e^T, two more:
    ((e + w)(e + w)^T - (e - w)(e - w)^T) / 2. So T = 3 for rigid blocks, 7 for
    deformable ones: the tangent's terms without an eigen-decomposition of H (whose
    LAPACK call made every run of a bolted scene import SciPy's LAPACK, 0.13-0.9 s).
    """
    D = ndof
    m_a, J_a, tt_a, te_a = _anchor_motion(ndof, x[:, :D], ra)
    m_b, J_b, tt_b, te_b = _anchor_motion(ndof, x[:, D:], rb)
    d = d0 + m_a - m_b
    # The anchors are distinct (the scene refuses a bolt of zero length); the floor
    # only keeps the division finite.
    L = jnp.sqrt(jnp.maximum(jnp.sum(d * d, -1), jnp.finfo(d.dtype).tiny))
    n = d / L[:, None]
    J = jnp.concatenate([J_a, -J_b], -1)  # (B, 2, 2 D)
    g = jnp.einsum("bc,bcj->bj", n, J)
    t = jnp.stack([-n[:, 1], n[:, 0]], -1)
    vectors = [jnp.einsum("bc,bcj->bj", t, J)]
    weights = [1.0 / L]
    # n . d2d/dx2: theta-theta of each block, and theta-strain of a deformable one.
    for side, tt, te in ((0, tt_a, te_a), (1, tt_b, te_b)):
        sign = 1.0 - 2.0 * side
        th = side * D + 2
        e = jnp.zeros_like(g).at[:, th].set(1.0)
        vectors.append(e)
        weights.append(sign * jnp.sum(n * tt, -1))
        if te is not None:
            w = jnp.zeros_like(g).at[:, th + 1:th + 4].set(
                sign * jnp.einsum("bc,bck->bk", n, te))
            half = jnp.full_like(L, 0.5)
            vectors += [e + w, e - w]
            weights += [half, -half]
    return L, g, jnp.stack(vectors, 1), jnp.stack(weights, 1)


def bolt_hessian(v, c):
    """The Hessian (B, 2 D, 2 D) of its rank-one terms (:func:`bolt_length_derivatives`)."""
    return jnp.einsum("bt,bti,btj->bij", c, v, v)


def block_travel(model: Model, du):
    """Largest vertex displacement of each block for an increment du (m), bounded above."""
    spin = jnp.abs(du[:, 2])
    if model.ndof == 6:
        spin = spin + jnp.sum(jnp.abs(du[:, 3:]), axis=1)
    return jnp.sqrt(du[:, 0] ** 2 + du[:, 1] ** 2) + spin * model.radius


def connected_groups(moving, a, b, link):
    """Each block's group among the ``moving`` (N,) blocks joined by the slots ``link``
    (S,) between blocks ``a`` and ``b`` (S,): the least index in its group, N for a block
    that does not move.

    Label propagation: each moving block takes the least label among its linked
    neighbours, then its label's label (pointer jumping), until none changes: a few rounds,
    about the logarithm of a group's extent. Fixed shapes, a ``while_loop``: jittable and
    vmappable."""
    N = moving.shape[0]
    link = link & moving[a] & moving[b]

    def spread(c):
        lab, _ = c
        m = jnp.where(link, jnp.minimum(lab[a], lab[b]), N)
        new = lab.at[a].min(m).at[b].min(m)
        new = jnp.where(moving, jnp.minimum(new, new[jnp.minimum(new, N - 1)]), N)
        return new, jnp.any(new != lab)

    init = jnp.where(moving, jnp.arange(N), N)
    return jax.lax.while_loop(lambda c: c[1], spread, (init, jnp.array(True)))[0]


def group_limits(model: Model, snap: Snapshot, travel):
    """Each block's travel limit (N,) m, where blocks that move together share their
    group's; and each block's group (N,) (:func:`connected_groups`).

    A block's own limit (``model.travel_limit``) is its size where the scene leaves
    ``max_displacement`` out; a wedge cut into several cells that slides as one must not
    be a mechanism once its smallest cell has moved that cell's size, but once the wedge
    has moved the wedge's. Moving: a free block whose path in the increment (``travel``)
    passed :data:`MOVING` of ``max_displacement`` (as :func:`jaxdem.results.moving_blocks`
    names them); together: joined through slots of the contact list (``snap.active``: within
    the detection margin) between moving blocks. Each group's limit is the size of its
    area together, sqrt(sum area), between ``model.travel_range`` (so the group of one
    block has its own limit, and every limit is ``max_displacement`` where the scene
    gives it)."""
    N = model.n_blocks
    moving = model.free & (travel > MOVING * model.max_displacement)
    lab = connected_groups(moving, snap.a, snap.b, snap.active)
    group_area = jax.ops.segment_sum(jnp.where(moving, model.area, 0.0), lab, N + 1)
    shared = jnp.clip(jnp.sqrt(group_area[lab]), *model.travel_range)
    return jnp.where(moving, jnp.maximum(shared, model.travel_limit), model.travel_limit), lab
