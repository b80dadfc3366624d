"""Incremental static solver: increment (jitted), load steps, and the host driver.

One increment applies the loads of one load step (block forces, water table,
installed bolts) and looks for static equilibrium with large displacements:

  repeat (geometry sub-steps, ``lax.while_loop``):
    detect contacts at the current geometry, carry each slot's history;
    Newton iteration on the increment du of the free blocks
    (``lax.while_loop``): trial spring forces from the gaps and the
    committed shear forces, tension cut-off and Mohr-Coulomb, residual
    R = F_ext + sum B^T f; solve (K_t + eps M) ddu = R, where K_t is the
    tangent of the current states (open: none; slipping: normal spring only,
    which keeps K_t symmetric) and eps M a small pseudo-mass;
    the step is shortened so that no block travels more than
    ``step_length`` (nor more than a quarter of its own radius) in one
    sub-step;
    move and rotate the blocks by du (exact rigid motion), commit the
    spring forces and states.
  until a sub-step converges (every free block's |R| <= tol times its own
  force scale, no state change) with a negligible du, or a block has
  travelled ``max_displacement`` (mechanism).

eps M only shapes the path: the converged answer solves R = 0 whatever eps
is, and where K_t is singular (a free block, a sliding mechanism) it turns
the step into a finite move along the mechanism, which the step length
bounds. Where slots slip, the elastic (secant) matrix converges only
linearly; once it has reduced R twice with the states held, or has stalled
(three iterations without progress), the slip tangent is tried (on the
direct paths the exact one, with the coupling of shear to normal force),
and kept while it reduces R. When the secant iteration stalls and even the
slip tangent makes no progress (R stays put: a block
just past limit equilibrium, whose small residual would move it only by
R / (eps k) an iteration), the step goes the whole step length along the
mechanism, so that it is followed and reported, not left to creep into the
iteration limit. A slot whose state flips four times in one sub-step is
frozen in its last state for the rest of that sub-step, which ends
open/close chatter. Frozen slots only shape the path: a sub-step converges
only if every block also balances with the forces the contact law gives
(a frozen slot at its limit: within the tolerance), and returns those. A
frozen slot that breaks its law there (stuck beyond its strength, closed
in tension) takes the law's state and the iteration goes on.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem import model as model_mod
from jaxdem.contact import broad_phase, narrow_phase, remap_history
from jaxdem.laws import forces_in_state, mohr_coulomb, slot_properties
from jaxdem.state import OPEN, SLIP, STICK, Loads, Model, State, grow_capacity


# Admissibility of a converged increment (result.json "admissibility"): what
# "converged" requires besides each block's residual below the tolerance.
OVERLAP_TOL = 0.1
"""Largest overlap of two blocks at a contact, relative to the smaller one's size
(its largest centroid-to-vertex distance). A joint spring's compression is its
force over kn, a joint's closure: a few mm under some MPa, which on the small
blocks of a generated rock mass (0.1-0.2 m) is a few percent of their size (the
bundled demo reaches 2.2%). Ten percent is far beyond any closure and well below
a block sunk into its neighbour (the jammed key block of issue 16 was 16%)."""
STRENGTH_TOL = 1e-3
"""Largest excess of a contact's forces over its strength (shear beyond
c share + fn tan(phi), tension beyond the cut-off), relative to the force scale
of its blocks (the scale of the equilibrium test)."""
IMBALANCE_FACTOR = 100.0
"""Largest global imbalance |applied + reactions| of the free blocks, relative to
the forces in play (:func:`_imbalance`), in units of ``solver.tolerance`` (each
block balances to the tolerance; their sum to about ten times it, tests/test_properties.py):
1e-4 at the default tolerance."""


class Status(enum.IntEnum):
    """Outcome of an increment, with the message shown to the user."""

    CONVERGED = 0
    MECHANISM = 1
    ITERATION_LIMIT = 2
    CAPACITY_OVERFLOW = 3
    NON_FINITE = 4
    OVERLAP = 5
    LAW_VIOLATION = 6
    IMBALANCE = 7

    @property
    def message(self) -> str:
        return {
            Status.CONVERGED: "Static equilibrium found.",
            Status.MECHANISM: "No equilibrium: blocks kept moving beyond max_displacement "
            "(a mechanism). The named blocks fall, slide or topple.",
            Status.ITERATION_LIMIT: "The iteration limit was reached before equilibrium. "
            "Try increasing solver.max_iterations or solver.load_steps.",
            Status.CAPACITY_OVERFLOW: "The contact list overflowed its capacity.",
            Status.NON_FINITE: "The solution became non-finite (NaN or infinity).",
            Status.OVERLAP: "Balance was found, but with blocks overlapping by more than "
            f"{OVERLAP_TOL:.0%} of the adjacent block's size: not an admissible state.",
            Status.LAW_VIOLATION: "Balance was found, but a contact carries more than its "
            "strength allows (Mohr-Coulomb or tension cut-off): not an admissible state.",
            Status.IMBALANCE: "The blocks do not balance the loads as a whole (global "
            f"imbalance over {IMBALANCE_FACTOR:g} x solver.tolerance): not an admissible state.",
        }[self]

    @property
    def label(self) -> str:
        return self.name.lower()


# ---------------------------------------------------------------------------
# Kinematics and forces of the spring slots

def _cross(r, v):
    return r[..., 0] * v[..., 1] - r[..., 1] * v[..., 0]


def point_row(r, v, ndof=3):
    """Row mapping a block's (u, theta[, eps_x, eps_y, gamma_xy]) to v . displacement of point r.

    The displacement of a point at r from the centroid is u + theta x r + E r,
    E = [[eps_x, gamma/2], [gamma/2, eps_y]] for a deformable (constant-strain)
    block. The same row maps a point force v to the block's generalised force.
    """
    cols = [v, _cross(r, v)[..., None]]
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


def _gather(du, a, b):
    return jnp.concatenate([du[a], du[b]], axis=1)


def _scatter(n_blocks, a, b, x):
    """Sum (M, 2 D) row vectors into (N, D) block vectors."""
    d = x.shape[1] // 2
    return (jax.ops.segment_sum(x[:, :d], a, n_blocks)
            + jax.ops.segment_sum(x[:, d:], b, n_blocks))


def _cell_stiffness(model: Model, free):
    """(N, 6, 6) block-diagonal stiffness of deformable blocks: A D on the strains."""
    K = jnp.zeros((model.n_blocks, 6, 6), model.area.dtype)
    kc = (model.area * free)[:, None, None] * model.cell_D
    return K.at[:, 3:, 3:].set(kc)


def _rotate_tensor(v, angle):
    """(x, y, xy) components of a symmetric tensor rotated by ``angle`` (tensor shear)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    xx, yy, xy = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([c * c * xx + s * s * yy - 2 * c * s * xy,
                      s * s * xx + c * c * yy + 2 * c * s * xy,
                      c * s * (xx - yy) + (c * c - s * s) * xy], -1)


@functools.partial(jax.tree_util.register_dataclass, meta_fields=[], data_fields=[
    "geo", "prop", "Bn", "Bs", "fs_old", "fn0", "failed", "pw", "bolt", "load", "free", "stress",
    "Kc"])
@dataclasses.dataclass(frozen=True)
class _Sub:
    """Everything fixed during one geometry sub-step (a pytree that lives inside jit).

    Contacts: ``geo``, ``prop``, rows ``Bn``, ``Bs`` (S, 2 D), committed shear
    force ``fs_old``, initial normal force ``fn0``, ``failed``, water force
    ``pw`` (S,) (pore pressure x share, on joint slots). Bolts (when the
    scene has them): ``bolt`` dict with ``a``, ``b``, ``B`` (nb, 2 D), ``f_old``,
    ``active``. ``load``: (N, D) external load. ``free``: (N,) blocks with
    degrees of freedom (not fixed, not excavated). ``stress``: (N, 3)
    committed stress of deformable blocks (tension positive); ``Kc``: their
    (N, 6, 6) stiffness (None for rigid blocks).
    """

    geo: dict
    prop: dict
    Bn: jax.Array
    Bs: jax.Array
    fs_old: jax.Array
    fn0: jax.Array
    failed: jax.Array
    pw: jax.Array
    bolt: dict | None
    load: jax.Array
    free: jax.Array
    stress: jax.Array
    Kc: jax.Array | None


def _bolt_length(ndof, d0, ra, rb, x):
    """Current anchor-to-anchor length of one bolt after the move x = (du_a, du_b) (m).

    ``d0`` = anchor a - anchor b at the sub-step's geometry, ``ra``, ``rb`` the anchors
    from their blocks' centroids. Exact rigid motion (rotation by du[2], and for a
    deformable block its strain first), as :func:`_move` applies it: the bolt's force
    comes from its actual elongation at any displacement, not from a sum of
    linearised increments.
    """
    def moved(u, r):
        if ndof == 6:
            r_new = r + strain_times(u[3:], r)
        else:
            r_new = r
        return u[:2] + _rotate(r_new, u[2]) - r

    d = d0 + moved(x[:ndof], ra) - moved(x[ndof:], rb)
    # The anchors are distinct (the scene refuses a bolt of zero length); the floor
    # only keeps sqrt's derivative finite.
    return jnp.sqrt(jnp.maximum(jnp.sum(d * d), jnp.finfo(d.dtype).tiny))


def _bolt_kinematics(model: Model, sub: _Sub, du):
    """Length L (B,), its gradient g (B, 2 D) and Hessian H (B, 2 D, 2 D) in (du_a, du_b).

    g is the bolt's row (the elongation of a small move, which turns with the
    anchor-to-anchor line) and H its change: F H is the bolt's geometric
    stiffness, the string stiffness F / L across its line and the lever-arm
    terms of its anchors' rotations. Parts of blocks without degrees of freedom
    are zero.
    """
    bolt = sub.bolt
    D = model.ndof
    mask = jnp.concatenate([jnp.repeat(bolt["free_a"][:, None], D, 1),
                            jnp.repeat(bolt["free_b"][:, None], D, 1)], 1).astype(du.dtype)
    x = _gather(du, bolt["a"], bolt["b"]) * mask
    length = functools.partial(_bolt_length, D)
    L, g = jax.vmap(jax.value_and_grad(length, argnums=3))(bolt["d0"], bolt["ra"], bolt["rb"], x)
    H = jax.vmap(jax.hessian(length, argnums=3))(bolt["d0"], bolt["ra"], bolt["rb"], x)
    return L, g * mask, H * mask[:, :, None] * mask[:, None, :]


def _bolt_law(model: Model, sub: _Sub, L):
    """Bolt axial forces (kN/m, tension positive) and states from the current length L (m).

    Elastic, k (L - rest), between the compression it may carry (``bolt_comp``; 0: it
    goes slack, state 3) and its tension capacity min(yield, anchor capacity),
    where it is plastic (state 1 yielded, 2 pulled out; 4 yielded in compression):
    the plastic elongation is kept at commit (:func:`_commit`), so that unloading
    is elastic from the yielded length.
    """
    bolt = sub.bolt
    trial = model.bolt_k * (L - bolt["rest"])
    cap, comp = model.bolt_cap, model.bolt_comp
    force = jnp.where(bolt["active"], jnp.clip(trial, -comp, cap), 0.0)
    state = jnp.select([trial > cap, (trial < 0) & (comp <= 0), trial < -comp],
                       [jnp.where(model.bolt_pullout, 2, 1), 3, 4], 0)
    state = jnp.where(bolt["active"], state, 0)
    return force, state.astype(jnp.int32)


def _bolt_rest(model: Model, sub: _Sub, L, force, state):
    """The rest length after the step: plastic elongation or shortening kept."""
    k = model.bolt_k
    plastic = (state == 1) | (state == 2) | (state == 4)
    return jnp.where(sub.bolt["active"] & plastic, L - force / k, sub.bolt["rest"])


def _evaluate(model: Model, sub: _Sub, du, frozen, frozen_state, prev, band):
    """Spring forces, states and the residual for a trial increment du.

    The springs carry the effective normal force fn (compression positive):
    fn0 - kn * gap, through the tension cut-off and Mohr-Coulomb; the blocks
    also receive the water force pw on the faces of joint slots, open or
    closed (:func:`water_force`). ``prev`` is the
    previous iterate's state and ``band`` the open/close hysteresis (kN/m) of
    :func:`jaxdem.laws.mohr_coulomb`. A ``frozen`` slot carries the forces of
    ``frozen_state`` (:func:`jaxdem.laws.forces_in_state`); ``misfit`` (kN/m)
    is how far they are from the law's, |d fn| + |d fs| (zero where not
    frozen), and ``R_law`` the residual with the law's forces everywhere.
    """
    geo = sub.geo
    x = _gather(du, geo["a"], geo["b"])
    dn = jnp.sum(sub.Bn * x, axis=1)
    ds = jnp.sum(sub.Bs * x, axis=1)
    gap = geo["gap"] + dn
    fn_trial = sub.fn0 - sub.prop["kn"] * gap
    fs_trial = sub.fs_old + sub.prop["ks"] * ds
    active = geo["active"]
    fn_l, fs_l, st_l = mohr_coulomb(fn_trial, fs_trial, sub.prop, sub.failed, active, prev, band)
    fn_f, fs_f = forces_in_state(fn_trial, fs_trial, sub.prop, sub.failed, frozen_state)
    fn = jnp.where(frozen, fn_f, fn_l)
    fs = jnp.where(frozen, fs_f, fs_l)
    st = jnp.where(frozen, frozen_state, st_l)
    # Water presses on a joint's faces whether it is closed or open (within
    # the contact margin, where the slot is active): the springs carry only
    # the effective force. Tying pw to the closed state would make the force
    # jump by pw where a joint opens, and a slot whose water lifts its faces
    # apart would chatter open/closed with no equilibrium in either state.
    total_n = fn + sub.pw if model.has_water else fn
    d_n = jnp.where(frozen & active, fn_l - fn, 0.0)
    d_s = jnp.where(frozen & active, fs_l - fs, 0.0)
    internal = _scatter(model.n_blocks, geo["a"], geo["b"],
                        sub.Bn * total_n[:, None] - sub.Bs * fs[:, None])
    to_law = _scatter(model.n_blocks, geo["a"], geo["b"],
                      sub.Bn * d_n[:, None] - sub.Bs * d_s[:, None])
    out = dict(fn=fn, fs=fs, state=st, gap=gap, fn_trial=fn_trial, fs_trial=fs_trial,
               total_n=total_n, misfit=jnp.abs(d_n) + jnp.abs(d_s), law_state=st_l)
    if model.n_bolts:
        L, g, H = _bolt_kinematics(model, sub, du)
        bf, bst = _bolt_law(model, sub, L)
        bolt = sub.bolt
        bolt_rows = -g * bf[:, None]
        internal = internal + _scatter(model.n_blocks, bolt["a"], bolt["b"], bolt_rows)
        out.update(bolt_force=bf, bolt_state=bst, bolt_length=L, bolt_g=g, bolt_H=H,
                   bolt_rows=bolt_rows)
    if model.ndof == 6:
        # Deformable blocks: the stress (committed + D d_eps) resists the strains.
        dsig = jnp.einsum("nij,nj->ni", model.cell_D, du[:, 3:])
        internal = internal.at[:, 3:].add(-model.area[:, None] * (sub.stress + dsig))
        out["stress"] = sub.stress + dsig
    out["internal"] = internal
    out["R"] = jnp.where(sub.free[:, None], sub.load + internal, 0.0)
    out["R_law"] = jnp.where(sub.free[:, None], out["R"] + to_law, 0.0)
    return out


def _block_residual(model: Model, R):
    """(N,) max(|Rx|, |Ry|, |M| / radius, |R_strain| / radius) of each block (kN/m)."""
    r = jnp.maximum(jnp.abs(R[:, 0]), jnp.abs(R[:, 1]))
    return jnp.maximum(r, jnp.max(jnp.abs(R[:, 2:]), axis=1) / model.radius)


def _block_scale(model: Model, sub: _Sub, ev=None):
    """(N,) force scale (kN/m) of each block's equilibrium test.

    The largest of the block's load and of the forces on it: spring forces
    (committed, in-situ and water; with ``ev`` also the current ones, |fn| +
    |fs|), bolt forces, and for a deformable block its stress times area over
    radius, measured like :func:`_block_residual`. Each block is balanced to
    the tolerance of its own forces: with one scale for the whole scene (the
    largest load) a 1 m block on a 1000 m one would pass with a residual of
    the order of its own weight, and could slide unnoticed.
    """
    N = model.n_blocks

    def per_block(c, a, b):
        # segment_max gives -inf to blocks without any entry.
        return jnp.maximum(jnp.maximum(jax.ops.segment_max(c, a, N),
                                       jax.ops.segment_max(c, b, N)), 0.0)

    c = jnp.abs(sub.fn0) + jnp.abs(sub.fs_old) + jnp.abs(sub.pw)
    if ev is not None:
        c = jnp.maximum(c, jnp.abs(ev["total_n"]) + jnp.abs(ev["fs"]))
    s = jnp.maximum(jnp.linalg.norm(sub.load[:, :2], axis=1),
                    jnp.max(jnp.abs(sub.load[:, 2:]), axis=1) / model.radius)
    s = jnp.maximum(s, per_block(jnp.where(sub.geo["active"], c, 0.0), sub.geo["a"],
                                 sub.geo["b"]))
    if model.n_bolts:
        bolt = sub.bolt
        f = jnp.abs(bolt["f_old"])
        if ev is not None:
            f = jnp.maximum(f, jnp.abs(ev["bolt_force"]))
        s = jnp.maximum(s, per_block(jnp.where(bolt["active"], f, 0.0), bolt["a"], bolt["b"]))
    if model.ndof == 6:
        stress = jnp.abs(sub.stress) if ev is None else jnp.abs(ev["stress"])
        s = jnp.maximum(s, jnp.max(stress, axis=1) * model.area / model.radius)
    return s


def _stiffness_terms(model: Model, sub: _Sub, ev, consistent):
    """The iteration matrix K_t = sum_m k_m B_m B_m^T as rank-one terms (a, b, B, k).

    Closed slots carry both springs: for a slipping slot this is the elastic
    (secant) stiffness, which keeps every step of the order of the elastic
    compliance. With ``consistent``, slipping slots lose their shear spring
    (and yielded bolts theirs): the tangent of the slip law (its symmetric
    part; the direct solvers add the coupling d fs / d fn = tan(phi) while
    it is tried, :func:`_with_slip_coupling`; the cg path does without),
    tried once the states hold so that slip settles in a few iterations, and
    used once the elastic iteration stalls so that a sliding mechanism makes
    a finite move (bounded by the step length) instead of creeping at
    elastic speed.
    """
    st = ev["state"]
    closed = sub.geo["active"] & (st != OPEN)
    kn = jnp.where(closed, sub.prop["kn"], 0.0)
    ks = jnp.where(closed & ((st == STICK) | ~consistent), sub.prop["ks"], 0.0)
    a, b = sub.geo["a"], sub.geo["b"]
    terms = [(a, b, sub.Bn, kn), (a, b, sub.Bs, ks)]
    if model.n_bolts:
        terms.append(_bolt_terms(model, sub, ev, consistent))
    return [jnp.concatenate(x) for x in zip(*terms, strict=True)]


def _bolt_terms(model: Model, sub: _Sub, ev, consistent):
    """The bolts' tangent as rank-one terms (a, b, v, lambda): 2 D a bolt.

    K_b = k g g^T + F H (:func:`_bolt_kinematics`): the axial spring (none for a
    plastic or slack bolt in the consistent tangent; the elastic one in the
    secant) and the geometric stiffness of its force, which holds a block hung
    on a bolt sideways (F / L) and in rotation. Symmetric: written as its
    eigen-pairs, so that every linear solver takes it as it takes the springs.
    Its negative part (a block hung below its centroid is unstable in rotation)
    is kept for the direct solvers and left out of the conjugate-gradient
    iteration, which needs a positive definite matrix (Newton then converges
    linearly there).
    """
    bolt = sub.bolt
    D = model.ndof
    g, H, F = ev["bolt_g"], ev["bolt_H"], ev["bolt_force"]
    axial = jnp.where(bolt["active"] & ((ev["bolt_state"] == 0) | ~consistent), model.bolt_k, 0.0)
    K = axial[:, None, None] * g[:, :, None] * g[:, None, :] + F[:, None, None] * H
    K = jnp.where(bolt["active"][:, None, None], 0.5 * (K + jnp.swapaxes(K, 1, 2)), 0.0)
    lam, vec = jnp.linalg.eigh(K)
    if model.linear_solver == "cg":
        lam = jnp.maximum(lam, 0.0)
    nb = g.shape[0]
    rep = lambda x: jnp.repeat(x, 2 * D)  # noqa: E731
    return (rep(bolt["a"]), rep(bolt["b"]), jnp.swapaxes(vec, 1, 2).reshape(nb * 2 * D, 2 * D),
            lam.reshape(-1))


def _n_bolt_terms(model: Model) -> int:
    """Rank-one terms of the bolts at the end of a term list (:func:`_bolt_terms`)."""
    return model.n_bolts * 2 * model.ndof


def _with_slip_coupling(model: Model, sub: _Sub, ev, terms, on):
    """``terms`` (a, b, B, k) with the slip law's coupling added where ``on``: (a, b, L, Rt, k).

    A slipping slot's shear force follows its normal force, d fs / d fn_trial =
    sign(fs) tan(phi) (:func:`jaxdem.laws.forces_in_state`), so the exact
    tangent has the unsymmetric terms -(d fs / d fn_trial) kn Bs Bn^T. With
    them Newton converges quadratically once the states hold, where the slip
    tangent's symmetric part converges linearly (about 0.7 an iteration). The
    group goes after the slots' two and before the bolts, as
    :func:`_assemble_dense` expects.
    """
    a, b, B, k = terms
    S = sub.geo["a"].shape[0]
    law = lambda fn_t: forces_in_state(fn_t, ev["fs_trial"], sub.prop, sub.failed,  # noqa: E731
                                       ev["state"])[1]
    _, sn = jax.jvp(law, (ev["fn_trial"],), (jnp.ones_like(ev["fn_trial"]),))
    closed = sub.geo["active"] & (ev["state"] != OPEN)
    kc = jnp.where(on & closed, -sn * sub.prop["kn"], 0.0)
    ga, gb = sub.geo["a"], sub.geo["b"]
    cat = jnp.concatenate
    return (cat([a[:2 * S], ga, a[2 * S:]]), cat([b[:2 * S], gb, b[2 * S:]]),
            cat([B[:2 * S], sub.Bs, B[2 * S:]]), cat([B[:2 * S], sub.Bn, B[2 * S:]]),
            cat([k[:2 * S], kc, k[2 * S:]]))


def _assemble_dense(model: Model, sub: _Sub, a, b, L, Rt, k, diag):
    """sum_m k_m L_m R_m^T + blockdiag(Kc) + diag(diag) as a dense (D N, D N) matrix.

    L and Rt (M, 2 D) are the left and right rows of each term over the DOFs of
    its blocks (a, b); L = Rt for the symmetric iteration matrix. The terms
    start with whole groups of spring slots (P pairs x 2 sides x V vertices,
    in the order of ``sub.geo``) and end with the bolts. The 2 V slots of a
    pair share its two blocks, so they are summed into one (2 D, 2 D) block
    per pair first (a dense contraction) and only that is scattered: 2 V
    times fewer scattered entries than one per slot.
    """
    N, D = model.n_blocks, model.ndof
    S = sub.geo["a"].shape[0]
    V = model.n_vertices
    P = S // (2 * V)
    T = (k.shape[0] - _n_bolt_terms(model)) // S

    def by_pair(x):
        # (T S, 2 D) rows -> (T, P, 2 V, 2 D), ordered (first block, second block) of
        # the pair: side 1 has its vertex block second, so its halves swap.
        x = x[:T * S].reshape(T, P, 2, V, 2 * D)
        swapped = jnp.concatenate([x[..., D:], x[..., :D]], axis=-1)
        return jnp.concatenate([x[:, :, :1], swapped[:, :, 1:]], axis=2).reshape(
            T, P, 2 * V, 2 * D)

    # Sum over the slots of each pair of k L R^T: elementwise products and a
    # reduction (XLA fuses them), not P tiny matrix products.
    kL = (k[:T * S].reshape(T, P, 2 * V)[..., None] * by_pair(L))
    Kp = jnp.sum(kL[..., :, None] * by_pair(Rt)[..., None, :], axis=(0, 2))
    first = a[:S].reshape(P, 2 * V)[:, 0]
    second = b[:S].reshape(P, 2 * V)[:, 0]
    # The rest (bolts): a (2 D, 2 D) block per term.
    a, b, L, Rt, k = a[T * S:], b[T * S:], L[T * S:], Rt[T * S:], k[T * S:]
    Kp = jnp.concatenate([Kp, k[:, None, None] * L[:, :, None] * Rt[:, None, :]])
    first, second = jnp.concatenate([first, a]), jnp.concatenate([second, b])
    # Scatter whole (D, D) blocks into K laid out as (N, D, N, D): whole windows,
    # far cheaper than one scattered scalar per entry, and a batch of them
    # (vmap) stays cache-friendly. The diagonal goes in the same way.
    Kp = Kp.reshape(-1, 2, D, 2, D)
    rows = jnp.concatenate([first, first, second, second])
    cols = jnp.concatenate([first, second, first, second])
    blocks = jnp.concatenate([Kp[:, 0, :, 0], Kp[:, 0, :, 1], Kp[:, 1, :, 0], Kp[:, 1, :, 1]])
    own = jnp.arange(N)
    diag_blocks = diag.reshape(N, D)[:, :, None] * jnp.eye(D, dtype=diag.dtype)
    if sub.Kc is not None:
        diag_blocks = diag_blocks + sub.Kc
    rows, cols = jnp.concatenate([rows, own]), jnp.concatenate([cols, own])
    blocks = jnp.concatenate([blocks, diag_blocks.astype(blocks.dtype)])
    K4 = jnp.zeros((N, D, N, D), diag.dtype).at[rows, :, cols, :].add(blocks)
    return K4.reshape(N * D, N * D)

def _solve_dense(model: Model, sub: _Sub, terms, R):
    """(K_t + eps M)^-1 R by LU on the assembled (D N, D N) matrix.

    ``terms`` is (a, b, L, Rt, k) (:func:`_with_slip_coupling`): K is
    unsymmetric where the slip coupling is on. LU every iteration, not
    Cholesky where K is symmetric: under vmap a choice between the two would
    run both, and two batched LAPACK calls that may run at once can deadlock
    XLA's CPU thread pool (see :func:`jaxdem.batch._one_per_device`). LU
    costs about 7% of a batched sweep's time (measured on the 52-block
    benchmark tunnel).
    """
    a, b, L, Rt, k = terms
    diag = jnp.where(jnp.repeat(sub.free, model.ndof), model.pseudo_mass.reshape(-1), 1.0)
    K = _assemble_dense(model, sub, a, b, L, Rt, k, diag)
    return jnp.linalg.solve(K, R.reshape(-1)).reshape(R.shape)


def _host_matrix(a, b, L, Rt, k, Kc, diag):
    """K = sum_m k_m L_m Rt_m^T + blockdiag(Kc) + diag(diag) as a SciPy CSC matrix (host arrays).

    Only terms with k != 0 enter, so the padded slot list costs nothing.
    """
    import scipy.sparse

    n = diag.shape[0]
    D = L.shape[1] // 2
    on = k != 0
    a, b, L, Rt, k = a[on], b[on], L[on], Rt[on], k[on]
    dofs = np.concatenate([D * a[:, None] + np.arange(D), D * b[:, None] + np.arange(D)], axis=1)
    rows = [np.repeat(dofs, 2 * D, axis=1).ravel()]
    cols = [np.tile(dofs, (1, 2 * D)).ravel()]
    vals = [(k[:, None, None] * L[:, :, None] * Rt[:, None, :]).ravel()]
    if Kc.size:
        own = D * np.arange(n // D)[:, None] + np.arange(D)
        rows.append(np.repeat(own, D, axis=1).ravel())
        cols.append(np.tile(own, (1, D)).ravel())
        vals.append(Kc.ravel())
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals.append(diag)
    return scipy.sparse.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


def _host_sparse_solve(a, b, L, Rt, k, Kc, diag, rhs, active=True, symmetric=True):
    """Assemble K = sum_m k_m L_m Rt_m^T + blockdiag(Kc) + diag(diag) on the host and solve.

    Only terms with k != 0 enter, so the padded slot list costs nothing.
    The factorisation is SciPy's SuperLU (minimum-degree ordering of K + K^T).
    ``rhs`` is (n,) or (n, p). CPU only: on a GPU the matrix would travel to
    the host (use "cg" there). ``active`` False returns zeros at once: a batch
    member whose iteration has finished (vmap runs the loop body for every
    member until the last one is done) costs no factorisation.
    """
    import scipy.sparse.linalg

    if not bool(np.asarray(active)):
        return np.zeros_like(np.asarray(rhs))
    symmetric = bool(np.asarray(symmetric))
    a, b, L, Rt, k, Kc, diag, rhs = (np.asarray(x) for x in (a, b, L, Rt, k, Kc, diag, rhs))
    K = _host_matrix(a, b, L, Rt, k, Kc, diag)
    if symmetric:
        # K is symmetric positive definite: symmetric ordering, no pivoting
        # (ten times faster than SuperLU's default partial pivoting).
        lu = scipy.sparse.linalg.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                      options=dict(SymmetricMode=True))
    else:
        lu = scipy.sparse.linalg.splu(K, permc_spec="MMD_AT_PLUS_A")
    return lu.solve(rhs).astype(rhs.dtype)


def _solve_sparse(model: Model, sub: _Sub, terms, R, active=True, symmetric=True):
    """(K_t + eps M)^-1 R by a sparse direct solve (SciPy's SuperLU through a host callback).

    Fill-in of a 2D contact graph is mild, so cost and memory grow about
    linearly with the number of blocks, and a direct solve does not slow down
    near a mechanism as an iterative one does. The springs go to the host as
    rank-one terms (12 numbers each, not their 144 matrix entries) and are
    assembled there; vmap solves batch members one after another, and skips
    those that are not ``active`` (their Newton iteration has finished).
    ``terms`` is (a, b, L, Rt, k); ``symmetric`` (a traced bool) picks
    SuperLU's symmetric mode, False where the slip coupling is on.
    """
    a, b, L, Rt, k = terms
    D = model.ndof
    Kc = sub.Kc if sub.Kc is not None else jnp.zeros((0, D, D), R.dtype)
    diag = jnp.where(jnp.repeat(sub.free, D), model.pseudo_mass.reshape(-1), 1.0)
    rhs = R.reshape(-1)
    x = jax.pure_callback(_host_sparse_solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                          a, b, L, Rt, k, Kc, diag, rhs, jnp.asarray(active),
                          jnp.asarray(symmetric), vmap_method="sequential")
    return x.reshape(R.shape)


# Stopping rule of the iterative solve: the Newton loop's forcing term lies in
# [min, max] (relative 2-norm residual of CG); min is also the default.
_CG_RTOL_MIN = {True: 1e-10, False: 1e-5}  # float64, float32
_CG_RTOL_MAX = 1e-2


def _compact_terms(model: Model, terms):
    """The rank-one terms with k != 0, packed into a fixed capacity (the product's cost).

    A slot list holds 2 V slots per candidate pair, of which a touching pair
    uses one or two (a corner, or the two ends of a face-to-face contact):
    the matrix-free product runs over 2 slots per candidate pair instead of
    2 V, V times fewer. Should more terms be nonzero than that
    (never seen: it needs more than two springs per pair on average over the
    padded pair list), the surplus ones are left out of the iteration matrix:
    it stays symmetric positive definite, Newton's residual still has every
    spring, and the outer iteration converges, linearly instead of
    quadratically.
    """
    a, b, B, k = terms
    m = k.shape[0]
    n_bolt = _n_bolt_terms(model)
    cap = min(m, (m - n_bolt) * 2 // max(model.n_vertices * 2, 2) + n_bolt)
    if cap >= m:
        return terms
    (idx,) = jnp.nonzero(k != 0, size=cap, fill_value=0)
    keep = jnp.arange(cap) < jnp.sum(k != 0)
    return a[idx], b[idx], B[idx], jnp.where(keep, k[idx], 0.0)


def _pcg(matvec, precond, rhs, rtol, maxiter):
    """Preconditioned conjugate gradients from x = 0 until |r| <= rtol |rhs| (2-norms).

    Returns (x, iterations). ``rtol`` may be traced (an inexact-Newton forcing
    term). Fixed shapes, one ``lax.while_loop``; vmaps (members stop together).
    """
    dot = lambda u, v: jnp.sum(u * v)  # noqa: E731
    stop = (rtol * jnp.linalg.norm(rhs)) ** 2
    z = precond(rhs)
    init = (jnp.zeros_like(rhs), rhs, z, z, dot(rhs, z), jnp.array(0))

    def cond(c):
        return (dot(c[1], c[1]) > stop) & (c[5] < maxiter)

    def body(c):
        x, r, z, p, rz, it = c
        q = matvec(p)
        pq = dot(p, q)
        alpha = jnp.where(pq > 0, rz / jnp.where(pq > 0, pq, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * q
        z = precond(r)
        rz_new = dot(r, z)
        beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        return x, r, z, z + beta * p, rz_new, it + 1

    x, _, _, _, _, it = jax.lax.while_loop(cond, body, init)
    return x, it


def _solve_cg(model: Model, sub: _Sub, terms, R, rtol=None):
    """(K_t + eps M)^-1 R by conjugate gradients, matrix-free, block-Jacobi preconditioned.

    The product K x is a gather/scatter over the springs with k != 0 (packed
    by :func:`_compact_terms`): cost and memory linear in the number of
    contacts, and no host callback, so it runs on a GPU and batches under
    vmap. ``rtol`` is the relative residual at which CG stops (2-norm): the
    Newton loop passes an Eisenstat-Walker forcing term (it corrects what CG
    leaves; its residual test decides convergence), default 1e-10 (1e-5 in
    float32, which cannot resolve 1e-10).
    """
    N, nd = model.n_blocks, model.ndof
    a, b, B, k = _compact_terms(model, terms)
    pm = jnp.where(sub.free[:, None], model.pseudo_mass, 1.0)

    def matvec(x):
        y = _scatter(N, a, b, B * (k * jnp.sum(B * _gather(x, a, b), 1))[:, None])
        if sub.Kc is not None:
            y = y + jnp.einsum("nij,nj->ni", sub.Kc, x)
        return jnp.where(sub.free[:, None], y, 0.0) + pm * x

    def block(part):
        Bp = B[:, part]
        return k[:, None, None] * Bp[:, :, None] * Bp[:, None, :]

    D = (jax.ops.segment_sum(block(slice(0, nd)), a, N)
         + jax.ops.segment_sum(block(slice(nd, 2 * nd)), b, N))
    if sub.Kc is not None:
        D = D + sub.Kc
    D = jnp.where(sub.free[:, None, None], D, 0.0) + jax.vmap(jnp.diag)(pm)
    Dinv = jnp.linalg.inv(D)

    def precond(x):
        return jnp.einsum("nij,nj->ni", Dinv, x)

    if rtol is None:
        rtol = _CG_RTOL_MIN[R.dtype == jnp.float64]
    x, _ = _pcg(matvec, precond, R, rtol, 4 * N * nd + 200)
    return x


def _travel(model: Model, du):
    """Largest vertex displacement of each block for an increment du (m), bounded above."""
    spin = jnp.abs(du[:, 2])
    if model.ndof == 6:
        spin = spin + jnp.sum(jnp.abs(du[:, 3:]), axis=1)
    return jnp.sqrt(du[:, 0] ** 2 + du[:, 1] ** 2) + spin * model.radius


def _newton(model: Model, sub: _Sub, st0):
    """Newton iteration on du at fixed geometry (one sub-step).

    Returns du, the final evaluation, and the loop record (converged, clipped,
    iteration count, relative residual).
    """
    S = st0.shape[0]
    N = model.n_blocks
    dtype = sub.load.dtype
    # Force scale of the convergence test, per block (_block_scale): its load
    # or the largest force on it (an in-situ state has large contact forces
    # and no net load). No block is asked to balance below 1000 round-offs of
    # the scene's largest force scale (nor is a scene without loads below
    # 1e-3 f_ref), which is all that a block without load or contacts has.
    s0 = _block_scale(model, sub)
    biggest = jnp.maximum(jnp.max(jnp.where(sub.free, s0, 0.0)), model.f_ref * 1e-3)
    floor = 1e3 * jnp.finfo(dtype).eps * biggest
    s0 = jnp.maximum(s0, floor)
    # Open/close hysteresis of a slot: a tenth of the tolerance of the
    # smaller free block it touches.
    s_slot = jnp.minimum(jnp.where(sub.free, s0, jnp.inf)[sub.geo["a"]],
                         jnp.where(sub.free, s0, jnp.inf)[sub.geo["b"]])
    band = 0.1 * model.tol * jnp.where(jnp.isfinite(s_slot), s_slot, biggest)
    zeros_s = jnp.zeros(S, jnp.int32)
    # A small block moves at most a quarter of its radius per sub-step.
    step = jnp.minimum(model.step_length, 0.25 * model.radius)

    def cond(c):
        return ~c["done"]

    def body(c):
        ev = _evaluate(model, sub, c["du"], c["frozen"], c["frozen_state"], c["st"], band)
        changed = (ev["state"] != c["st"]) & sub.geo["active"]
        scale_b = jnp.maximum(s0, _block_scale(model, sub, ev))
        tol = model.tol * scale_b
        # Largest residual of a free block relative to its own tolerance.
        rnorm = jnp.max(jnp.where(sub.free, _block_residual(model, ev["R"]) / tol, 0.0))
        # Frozen slots only shape the path: the answer must balance every
        # block with the forces of the contact law itself (R_law), within the
        # same tolerance, so that no state against the law is returned. Where
        # it does not, the frozen slots with a misfit on an unbalanced block
        # were frozen on the way to an answer elsewhere (stuck beyond their
        # strength, closed in tension): they take the law's state, and the
        # iteration goes on with it (an active-set update).
        balanced = (rnorm <= 1.0) & ~jnp.any(changed)
        off = sub.free & (_block_residual(model, ev["R_law"]) > tol)
        converged = balanced & ~jnp.any(off)
        a, b = sub.geo["a"], sub.geo["b"]
        reassign = balanced & c["frozen"] & (ev["misfit"] > 0) & (off[a] | off[b])
        flips = c["flips"] + changed.astype(jnp.int32)
        newly = (flips >= 4) & ~c["frozen"]
        frozen = c["frozen"] | newly
        frozen_state = jnp.where(newly, ev["state"],
                                 jnp.where(reassign, ev["law_state"], c["frozen_state"]))
        # The secant matrix (slipping slots keep their shear spring) converges
        # only linearly where slots slip, the slower the more the shear springs
        # dominate (a rate of 0.96 an iteration is common). Once it has
        # reduced the residual twice in a row with the states held and slots
        # slipping, the slip tangent is tried, and kept while it reduces the
        # residual and no state changes: on the direct paths with the slip
        # coupling (the exact tangent of the held states), on the cg path its
        # symmetric part. Near a mechanism it is nearly singular: a tried
        # step that does not reduce the residual, or that would leave the step
        # length (that step is not taken), hands back to the secant for the
        # rest of the sub-step. Three secant iterations that barely reduce the
        # residual (stall) mean a mechanism or slip that the secant cannot
        # settle: the slip tangent, kept while it reduces the residual, and
        # ``creeping`` below.
        still = ~jnp.any(changed)
        progress = rnorm <= 0.98 * c["rprev"]
        settled = jnp.where(still & progress, c["settled"] + 1, 0)
        failed = c["trying"] & ~progress
        stall = jnp.where(still & ~progress & ~failed, c["stall"] + 1, 0)
        slipping = jnp.any(sub.geo["active"] & (ev["state"] == SLIP))
        if model.n_bolts:
            slipping |= jnp.any(sub.bolt["active"] & (ev["bolt_state"] != 0))
        untried = c["untried"] & ~failed
        trying = still & untried & slipping & (c["trying"] | (settled >= 2)
                                               | (c["tangent"] & progress))
        tangent = trying | (stall >= 3)

        def newton_step():
            terms = _stiffness_terms(model, sub, ev, tangent)
            if model.linear_solver == "cg":
                # Inexact Newton (Eisenstat-Walker, choice 2): solve as accurately
                # as Newton's own progress warrants, and no more accurately than
                # the tolerance needs (the residual test below still decides).
                ratio = jnp.where(jnp.isfinite(c["rprev"]), rnorm / c["rprev"], jnp.inf)
                tol_min = jnp.min(jnp.where(sub.free, tol, jnp.inf))
                need = 0.1 * tol_min / jnp.maximum(jnp.linalg.norm(ev["R"]),
                                                   jnp.finfo(tol.dtype).tiny)
                eta = jnp.clip(jnp.maximum(0.9 * ratio**2, need),
                               _CG_RTOL_MIN[tol.dtype == jnp.float64], _CG_RTOL_MAX)
                return _solve_cg(model, sub, terms, ev["R"], eta)
            terms = _with_slip_coupling(model, sub, ev, terms, trying)
            if model.linear_solver == "sparse":
                return _solve_sparse(model, sub, terms, ev["R"], ~c["done"] & ~converged, ~trying)
            return _solve_dense(model, sub, terms, ev["R"])

        # The iterate that converged takes no step: its matrix is not
        # assembled nor factorised (one factorisation a sub-step). Under vmap
        # a cond on a per-member flag would run both branches, so a batch
        # (model.lanes) skips only when none of its members needs a step; the
        # sparse path also skips the host solve of each member that does not.
        idle = converged
        if model.lanes is not None:
            idle = jax.lax.psum(jnp.where(converged | c["done"], 0, 1), model.lanes) == 0
        ddu = jax.lax.cond(idle, lambda: jnp.zeros_like(c["du"]), newton_step)
        t_now = _travel(model, c["du"])
        t_step = _travel(model, ddu)
        room = jnp.maximum(step - t_now, 0.0)
        fit = jnp.min(jnp.where(t_step > 0, room / jnp.where(t_step > 0, t_step, 1.0), jnp.inf))
        # Still no progress with the slip tangent: a mechanism whose residual
        # is small (a block just past limit equilibrium) would only creep, by
        # R / (eps k) an iteration, and run out of iterations instead of
        # showing that it moves. Along the mechanism R does not change, so go
        # the whole step along it (the elastic part of ddu, eps times
        # smaller, stays negligible) and let the next sub-step follow it.
        creeping = c["stall"] >= 5
        s_travel = jnp.where(creeping & jnp.isfinite(fit), fit, jnp.minimum(fit, 1.0))
        # No step lands a block inside another. A slot may close during the step
        # but not sink deeper than its spring's own compression under the forces
        # in play (the larger force scale of its two blocks over its normal
        # stiffness): a falling block lands on its support, it does not plunge a
        # step length into it. Newton's own step (scale <= 1) compresses a
        # closed spring as its law says, so closed slots bound only a step
        # scaled beyond it (``creeping``); every step actually taken is checked.
        s_slot = jnp.where(sub.free, scale_b, 0.0)
        s_slot = jnp.maximum(s_slot[sub.geo["a"]], s_slot[sub.geo["b"]])
        sink = s_slot / jnp.maximum(sub.prop["kn"], jnp.finfo(dtype).tiny)
        dn_step = jnp.sum(sub.Bn * _gather(ddu, sub.geo["a"], sub.geo["b"]), axis=1)
        closing = sub.geo["active"] & (dn_step < 0)
        depth = jnp.maximum(ev["gap"], 0.0) + sink
        s_slots = jnp.where(closing, depth / jnp.where(closing, -dn_step, 1.0), jnp.inf)
        is_open = ev["state"] == OPEN
        s_slots = jnp.where(is_open, s_slots, jnp.maximum(s_slots, 1.0))
        s_gap = jnp.min(s_slots, initial=jnp.inf)
        scale = jnp.minimum(s_travel, s_gap)
        clipped = (s_travel <= s_gap) & ((s_travel < 1.0) | creeping)
        overshoot = trying & clipped
        untried = untried & ~overshoot
        scale = jnp.where(overshoot, 0.0, scale)
        clipped = clipped & ~overshoot
        du = jnp.where(converged, c["du"], c["du"] + scale * ddu)
        finite = jnp.all(jnp.isfinite(du))
        it = c["it"] + 1
        done = converged | clipped | ~finite | (it >= model.max_iterations)
        return dict(du=du, st=ev["state"], flips=flips, frozen=frozen, frozen_state=frozen_state,
                    it=it, done=done, converged=converged, clipped=clipped & ~converged,
                    finite=finite, rnorm=rnorm * model.tol, rprev=rnorm, stall=stall,
                    settled=settled, trying=trying, untried=untried, tangent=tangent)

    init = dict(du=jnp.zeros((N, model.ndof), sub.load.dtype), st=st0, flips=zeros_s,
                frozen=jnp.zeros(S, bool), frozen_state=zeros_s, it=jnp.array(0),
                done=jnp.array(False), converged=jnp.array(False), clipped=jnp.array(False),
                finite=jnp.array(True), rnorm=jnp.array(jnp.inf, sub.load.dtype),
                rprev=jnp.array(jnp.inf, sub.load.dtype), stall=jnp.array(0),
                settled=jnp.array(0), trying=jnp.array(False), untried=jnp.array(True),
                tangent=jnp.array(False))
    c = jax.lax.while_loop(cond, body, init)
    # A converged sub-step returns (and commits) the law's own forces and
    # states, which balance the blocks; one cut short keeps the frozen ones.
    ev = _evaluate(model, sub, c["du"], c["frozen"] & ~c["converged"], c["frozen_state"], c["st"],
                   band)
    return c["du"], ev, c


def _rotate(r, angle):
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([cos * r[..., 0] - sin * r[..., 1], sin * r[..., 0] + cos * r[..., 1]], -1)


def _move(model: Model, state: State, du, stress=None):
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
        verts = centroid[:, None, :] + _rotate(r, th[:, None])
    else:
        r0 = model.verts0 - model.centroid0[:, None, :]
        verts = centroid[:, None, :] + _rotate(r0, rot[:, None])
    return dataclasses.replace(state, verts=verts, centroid=centroid, u=u, rot=rot,
                               strain=strain, stress=new_stress)


def water_force(model: Model, geo, prop, water_x, water_y, scale=1.0):
    """Pore-pressure force on each joint slot, gamma_w (y_table(x) - y) x share (kN/m).

    Hydrostatic below the table, zero above it; none on intact bonds and walls.
    """
    p = geo["point"]
    head = jnp.interp(p[:, 0], water_x, water_y) - p[:, 1]
    on_joint = geo["active"] & ~prop["bonded"] & ~model.joint_intact[geo["joint"]]
    return jnp.where(on_joint, scale * model.gamma_w * jnp.maximum(head, 0.0) * geo["share"], 0.0)


def bolt_geometry(model: Model, state: State):
    """Bolt rows: anchors at their current positions, direction from anchor 1 to anchor 2."""
    i, j = model.bolt_blocks[:, 0], model.bolt_blocks[:, 1]
    p1 = state.centroid[i] + _rotate(model.bolt_offsets[:, 0], state.rot[i])
    p2 = state.centroid[j] + _rotate(model.bolt_offsets[:, 1], state.rot[j])
    d = p2 - p1
    e = d / jnp.maximum(jnp.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    # Elongation = e . (disp of anchor 2 - disp of anchor 1): anchor 2 is "a".
    return dict(a=j, b=i, point_a=p2, point_b=p1, e=e)


def _snap_gaps(geo: dict, carried) -> dict:
    """Round-off gaps of springs that carry nothing set to zero (values only).

    A gap is a difference of coordinates, resolved to eps |x| at best: two faces
    that touch give gaps of +-1e-16 m, and springs that push blocks apart with
    k x 1e-16 m. A free block pushed by such forces (a key block at rest between
    its joints, with no force yet) slid on them at round-off scale, the slip
    iteration stalled, and the stall was followed as a mechanism: the block was
    moved 59 mm. A spring that has carried a force (``carried``, kN/m: its
    committed normal and shear forces) keeps its gap, however small: its force
    is its history (in float32 a compression of a few eps |x| is a real one). The
    derivatives of the gaps are kept (jaxdem.differentiable).
    """
    eps = jnp.finfo(geo["gap"].dtype).eps
    resolution = 8.0 * eps * jnp.max(jnp.abs(geo["point"]), axis=1)
    small = (jnp.abs(geo["gap"]) <= resolution) & (carried == 0)
    return dict(geo, gap=geo["gap"] - jax.lax.stop_gradient(jnp.where(small, geo["gap"], 0.0)))


def _prepare(model: Model, state: State, loads: Loads):
    """Detect contacts at the current geometry and carry their history: a sub-step's data.

    Returns (mdl, sub, st0, pairs, need): the model with ``free`` restricted to
    the blocks alive now, the :class:`_Sub`, the slots' starting states, the
    pair list and what the contact list needed (``pairs``, ``cell_full``).
    """
    N = model.n_blocks
    free = model.free & state.alive
    mdl = dataclasses.replace(model, free=free)
    pairs, count, cell_full = broad_phase(mdl, state.verts, state.capacity, state.alive)
    hist = remap_history(state, pairs, N)
    geo = narrow_phase(mdl, state.verts, state.centroid, pairs)
    prop = slot_properties(mdl, geo)
    flat = lambda x: x.reshape(-1)  # noqa: E731
    carried = jnp.where(flat(hist["present"]), jnp.abs(flat(hist["fn"])) + jnp.abs(flat(hist["fs"])),
                        0.0)
    geo = _snap_gaps(geo, carried)
    same = flat(hist["present"]) & (flat(hist["edge"]) == geo["edge"]) & geo["active"]
    failed = jnp.where(same, flat(hist["failed"]), geo["gap"] > model.touch_tol)
    fs_old = jnp.where(same, flat(hist["fs"]), 0.0)
    fn0 = jnp.where(same, flat(hist["fn0"]), 0.0)
    # A new slot starts closed where its faces touch: round-off in a gap of
    # zero must not leave a block resting on its support without springs.
    st0 = jnp.where(same, flat(hist["cstate"]),
                    jnp.where(geo["gap"] <= model.touch_tol, STICK, OPEN)).astype(jnp.int32)
    D = model.ndof
    Bn = b_rows(free, geo["a"], geo["b"], geo["point"], geo["point"], geo["normal"],
                state.centroid, D)
    Bs = b_rows(free, geo["a"], geo["b"], geo["point"], geo["point"], geo["tangent"],
                state.centroid, D)
    if model.has_water:
        pw = water_force(mdl, geo, prop, loads.water_x, loads.water_y, loads.water_scale)
    else:
        pw = jnp.zeros_like(fs_old)
    bolt = None
    if model.n_bolts:
        bg = bolt_geometry(model, state)
        alive_b = state.alive[bg["a"]] & state.alive[bg["b"]] & loads.bolt_active
        d0 = bg["point_a"] - bg["point_b"]
        # A bolt is installed unstressed: its rest length is its length when it
        # first acts (bolt_rest 0 until then), and grows with its plastic elongation.
        length0 = jnp.linalg.norm(d0, axis=1)
        rest = jnp.where(state.bolt_rest > 0, state.bolt_rest, length0)
        bolt = dict(a=bg["a"], b=bg["b"], f_old=state.bolt_force, active=alive_b, d0=d0,
                    ra=bg["point_a"] - state.centroid[bg["a"]],
                    rb=bg["point_b"] - state.centroid[bg["b"]], rest=rest,
                    free_a=free[bg["a"]], free_b=free[bg["b"]])
    sub = _Sub(geo=geo, prop=prop, Bn=Bn, Bs=Bs, fs_old=fs_old, fn0=fn0, failed=failed, pw=pw,
               bolt=bolt, load=jnp.where(free[:, None], loads.force, 0.0), free=free,
               stress=state.stress, Kc=_cell_stiffness(model, free) if D == 6 else None)
    return mdl, sub, st0, pairs, dict(pairs=count, cell_full=cell_full)


def _commit(model: Model, state: State, sub: _Sub, pairs, du, ev):
    """Move the blocks by du and commit the springs' forces and states.

    Returns (state, balance, snapshot): the new state, the global balance of
    the free blocks and the contact snapshot (forces at the sub-step's points).
    """
    N, D = model.n_blocks, model.ndof
    geo, free = sub.geo, sub.free
    st = ev["state"]
    active = geo["active"]
    opened = (st == OPEN) & ((sub.prop["tension"] > 0) | (ev["gap"] > model.touch_tol))
    failed_new = sub.failed | (active & ~sub.prop["bonded"] & ((st == SLIP) | opened))
    moved = _move(model, state, du, ev.get("stress"))
    shape = state.fs.shape
    new_state = dataclasses.replace(
        moved, pairs=pairs, fs=ev["fs"].reshape(shape), fn=ev["fn"].reshape(shape),
        fn0=sub.fn0.reshape(shape), failed=failed_new.reshape(shape),
        edge=geo["edge"].reshape(shape), cstate=st.reshape(shape),
        present=active.reshape(shape))
    if model.n_bolts:
        rest = _bolt_rest(model, sub, ev["bolt_length"], ev["bolt_force"], ev["bolt_state"])
        new_state = dataclasses.replace(
            new_state, bolt_force=ev["bolt_force"], bolt_state=ev["bolt_state"],
            bolt_rest=jnp.where(sub.bolt["active"], rest, state.bolt_rest))
    # Global balance (about the origin) of the free blocks: applied loads and
    # the forces from blocks without degrees of freedom (bolts anchored in
    # them included).
    c_xy = state.centroid
    moment = lambda F: F[:, 2] + _cross(c_xy, F[:, :2])  # noqa: E731
    a, b = geo["a"], geo["b"]
    f_row = sub.Bn * ev["total_n"][:, None] - sub.Bs * ev["fs"][:, None]
    reaction = (jax.ops.segment_sum(jnp.where((~free[b])[:, None], f_row[:, :3], 0.0), a, N)
                + jax.ops.segment_sum(jnp.where((~free[a])[:, None], f_row[:, D:D + 3], 0.0),
                                      b, N))
    if model.n_bolts:
        bolt = sub.bolt
        rows = ev["bolt_rows"]
        reaction = reaction + (
            jax.ops.segment_sum(jnp.where((~free[bolt["b"]])[:, None], rows[:, :3], 0.0),
                                bolt["a"], N)
            + jax.ops.segment_sum(jnp.where((~free[bolt["a"]])[:, None], rows[:, D:D + 3], 0.0),
                                  bolt["b"], N))
    # The imbalance is relative to the forces in play: the summed loads and
    # reactions, or, where both are nil (an in-situ stress that balances
    # itself, with no load), the largest spring force carried at the start or
    # the end of the sub-step (the forces the convergence test, _block_scale,
    # was relative to: an in-situ force released to nothing is still the
    # scale its block was balanced to), and at least the convergence test's
    # floor (1e-3 f_ref), so that round-off over round-off does not read as
    # an imbalance of 1.
    carried = jnp.maximum(jnp.abs(ev["total_n"]) + jnp.abs(ev["fs"]),
                          jnp.abs(sub.fn0) + jnp.abs(sub.fs_old) + jnp.abs(sub.pw))
    carried = jnp.max(jnp.where(active, carried, 0.0), initial=0.0)
    carried = jnp.maximum(carried, 1e-3 * model.f_ref)
    admissible = _admissibility(model, sub, ev)
    balance = dict(
        **admissible,
        applied=jnp.stack([sub.load[:, 0].sum(), sub.load[:, 1].sum(), moment(sub.load).sum()]),
        reaction=jnp.stack([reaction[:, 0].sum(), reaction[:, 1].sum(), moment(reaction).sum()]),
        scale=jnp.maximum(jnp.maximum(jnp.sum(jnp.linalg.norm(reaction[:, :2], axis=1)),
                                      jnp.sum(jnp.linalg.norm(sub.load[:, :2], axis=1))),
                          carried),
    )
    joint = active & ~sub.prop["bonded"] & ~model.joint_intact[geo["joint"]]
    snapshot = dict(point=geo["point"], normal=geo["normal"], a=a, b=b, active=active,
                    fn=ev["fn"], fs=ev["fs"], pw=ev["total_n"] - ev["fn"], state=st, joint=joint)
    return new_state, balance, snapshot


def _admissibility(model: Model, sub: _Sub, ev) -> dict:
    """How far the sub-step's answer is from admissible (see :data:`OVERLAP_TOL`).

    ``overlap`` (m): the deepest interpenetration at a contact; ``overlap_rel``: the
    same relative to the smaller block's size; ``excess``: the largest excess of a
    contact's forces over its strength (Mohr-Coulomb, tension cut-off), relative
    to the force scale of its blocks. The contact law itself never exceeds its
    strength; a slot held frozen in its state may, by up to the tolerance.
    """
    geo, prop = sub.geo, sub.prop
    a, b, active = geo["a"], geo["b"], geo["active"]
    size = jnp.where(sub.free, model.radius, jnp.inf)
    size = jnp.minimum(size[a], size[b])
    size = jnp.where(jnp.isfinite(size), size, jnp.maximum(model.radius[a], model.radius[b]))
    depth = jnp.where(active, jnp.maximum(-ev["gap"], 0.0), 0.0)
    fn, fs = ev["fn"], ev["fs"]
    bonded = prop["bonded"] & ~sub.failed
    c = jnp.where(sub.failed, 0.0, prop["cohesion"])
    t_cap = jnp.where(sub.failed, 0.0, prop["tension"])
    limit = jnp.maximum(c + fn * prop["tanphi"], 0.0)
    over = jnp.maximum(jnp.abs(fs) - limit, -fn - t_cap)
    scale = jnp.where(sub.free, _block_scale(model, sub, ev), 0.0)
    scale = jnp.maximum(jnp.maximum(scale[a], scale[b]), model.f_ref * 1e-3)
    excess = jnp.where(active & ~bonded & (ev["state"] != OPEN), jnp.maximum(over, 0.0) / scale,
                       0.0)
    return dict(overlap=jnp.max(depth, initial=0.0),
                overlap_rel=jnp.max(depth / size, initial=0.0),
                excess=jnp.max(excess, initial=0.0))


def _substep(model: Model, state: State, loads: Loads):
    """Detect contacts, iterate to equilibrium at fixed geometry, commit the motion.

    ``need["new_failures"]`` says whether a spring failed (first slipped or
    opened) in this sub-step: it then loses its cohesion and tensile strength,
    which the law applies from the next sub-step on, so the increment cannot
    end here (a slot that failed would be reported with its intact strength).
    """
    mdl, sub, st0, pairs, need = _prepare(model, state, loads)
    return _newton_and_commit(mdl, state, sub, st0, pairs, need)


def _newton_and_commit(mdl: Model, state: State, sub: _Sub, st0, pairs, need):
    """The rest of :func:`_substep` once contacts are detected: Newton, then commit."""
    du, ev, c = _newton(mdl, sub, st0)
    new_state, balance, snapshot = _commit(mdl, state, sub, pairs, du, ev)
    need = dict(need, new_failures=jnp.any(new_state.failed.reshape(-1) & ~sub.failed))
    return new_state, du, c, need, balance, snapshot


def _increment(model: Model, state: State, loads: Loads, tangents=None, skip=None):
    """Geometry sub-steps until equilibrium; with ``tangents``, their sensitivities too.

    ``skip`` (a bool scalar) returns ``state`` untouched: a batch member that has
    already failed, or one that need not be redone, costs no iterations.
    """
    N = model.n_blocks
    dtype = state.verts.dtype
    _, _, _, _, balance0, snap0 = jax.eval_shape(_substep, model, state, loads)
    zeros_like = lambda t: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), t)  # noqa: E731

    def cond(c):
        return c["status"] < 0

    def body(c):
        if tangents is None:
            st_new, du, newton, need, balance, snap = _substep(model, c["state"], loads)
        else:
            (st_new, du, newton, need, balance, snap), (dstate, dsnap) = _substep_tangent(
                model, c["state"], loads, tangents["model"], c["dstate"], tangents["loads"])
        overflow = (need["pairs"] > state.capacity) | need["cell_full"]
        travel = c["travel"] + _travel(model, du)
        small = jnp.max(_travel(model, du)) <= model.touch_tol
        stuck = jnp.where(newton["converged"] | newton["clipped"], 0, c["stuck"] + 1)
        substeps = c["substeps"] + 1
        # The first outcome that holds ends the increment; -1 goes on. An
        # equilibrium counts only if it is admissible (no overlap, no law broken,
        # the whole in balance): else the status says which check failed.
        done = newton["converged"] & small & ~need["new_failures"]
        status = jnp.select(
            [overflow, ~newton["finite"], done & (balance["overlap_rel"] > OVERLAP_TOL),
             done & (balance["excess"] > STRENGTH_TOL),
             done & (_imbalance_jax(balance) > IMBALANCE_FACTOR * model.tol), done,
             jnp.max(travel) > model.max_displacement,
             (stuck >= 3) | (substeps >= model.max_substeps)],
            [Status.CAPACITY_OVERFLOW, Status.NON_FINITE, Status.OVERLAP, Status.LAW_VIOLATION,
             Status.IMBALANCE, Status.CONVERGED, Status.MECHANISM, Status.ITERATION_LIMIT],
            -1)
        keep = overflow | ~newton["finite"]
        hold = lambda old, new: jax.tree.map(lambda o, n: jnp.where(keep, o, n), old, new)  # noqa: E731
        out = dict(state=hold(c["state"], st_new), status=status, substeps=substeps, stuck=stuck,
                   iterations=c["iterations"] + newton["it"], travel=travel,
                   residual=newton["rnorm"], balance=balance, snapshot=snap,
                   pairs_needed=jnp.maximum(c["pairs_needed"], need["pairs"]),
                   cell_full=c["cell_full"] | need["cell_full"],
                   approximate=c["approximate"] | ~newton["converged"])
        if tangents is not None:
            out.update(dstate=hold(c["dstate"], dstate), dsnapshot=dsnap)
        return out

    status0 = jnp.array(-1) if skip is None else jnp.where(skip, Status.CONVERGED, -1)
    init = dict(state=state, status=status0, substeps=jnp.array(0), stuck=jnp.array(0),
                iterations=jnp.array(0), travel=jnp.zeros(N, dtype),
                residual=jnp.array(jnp.inf, dtype), balance=zeros_like(balance0),
                snapshot=zeros_like(snap0), pairs_needed=jnp.array(0), cell_full=jnp.array(False),
                approximate=jnp.array(False))
    if tangents is not None:
        init["dstate"] = tangents["state"]
        p = jax.tree.leaves(tangents["state"])[0].shape[0]
        init["dsnapshot"] = {k: jnp.zeros((p,) + snap0[k].shape, dtype) for k in SNAPSHOT_FLOATS}
    c = jax.lax.while_loop(cond, body, init)
    info = {k: c[k] for k in ("status", "substeps", "iterations", "travel", "residual",
                              "balance", "snapshot", "pairs_needed", "cell_full", "approximate")}
    info["joints"] = _joint_motion(model, state, c["state"], c["snapshot"])
    if tangents is not None:
        info.update(dstate=c["dstate"], dsnapshot=c["dsnapshot"])
    return c["state"], info


def _joint_motion(model: Model, start: State, end: State, snap) -> dict:
    """Largest joint slip and opening (m) of an increment, and the blocks where they are.

    At each joint contact of the final geometry (open or closed, walls included,
    intact bonds not), the relative displacement over the increment of the two
    blocks' material points now at the contact point: its tangential part is the
    slip, its normal part the opening (positive apart). ``slip_rel`` is the slip
    relative to the smaller block's size, which the command line warns about
    above :data:`LARGE_SLIP`.
    """
    p, n = snap["point"], snap["normal"]
    t = jnp.stack([-n[:, 1], n[:, 0]], axis=1)

    def moved(i):
        back = _rotate(p - end.centroid[i], -(end.rot[i] - start.rot[i]))
        return p - (start.centroid[i] + back)

    a, b = snap["a"], snap["b"]
    rel = moved(a) - moved(b)
    joint = snap["joint"]
    slip = jnp.where(joint, jnp.abs(jnp.sum(rel * t, axis=1)), 0.0)
    opening = jnp.where(joint, jnp.sum(rel * n, axis=1), 0.0)
    size = jnp.where(model.free, model.radius, jnp.inf)
    size = jnp.minimum(size[a], size[b])
    size = jnp.where(jnp.isfinite(size), size, 1.0)
    i, j = jnp.argmax(slip), jnp.argmax(opening)
    return dict(slip=slip[i], slip_rel=slip[i] / size[i], slip_blocks=jnp.stack([a[i], b[i]]),
                opening=jnp.maximum(opening[j], 0.0), opening_blocks=jnp.stack([a[j], b[j]]))


LARGE_SLIP = 0.05
"""Joint slip in one increment, relative to the smaller block's size, above which the
command line warns ("stable, but joint slip of ... at blocks ...: review"): a block
that slid 5% of its size has moved far for an elastic answer, though it came to rest."""


@jax.jit
def increment(model: Model, state: State, loads: Loads):
    """One load increment: geometry sub-steps until equilibrium under ``loads``.

    Returns (state, info): info holds ``status`` (a Status value), ``iterations``
    (Newton iterations), ``substeps``, ``residual`` (relative), ``travel``
    (N,) path length of each block in this increment (m), ``balance``, the
    final contact ``snapshot`` and ``approximate`` (a sub-step ended without
    equilibrium, cut by the step length: see :func:`increment_tangent`).
    """
    return _increment(model, state, loads)


@jax.jit
def increment_tangent(model: Model, state: State, loads: Loads, tangents: dict):
    """:func:`increment` with forward-mode sensitivities of the state to p parameters.

    ``tangents`` holds ``model`` ({field: (p, ...)} for :data:`SMOOTH_MODEL`),
    ``loads`` ({field: (p, ...)} for :data:`LOAD_FLOATS`) and ``state``
    ({field: (p, ...)} for :data:`STATE_FLOATS`): the derivatives of those
    inputs with respect to each parameter. ``info`` then also holds ``dstate``,
    the derivatives of the new state, and ``dsnapshot``, those of the final
    contact snapshot.

    Each sub-step that ends in equilibrium, R(du*; geometry, history,
    theta) = 0, is differentiated implicitly with its contact states held
    (stick, slip, open and the bolts' states as found): du*' = K^-1 dR/dtheta,
    with K = -dR/d(du) the exact tangent of the held states (unsymmetric where
    slots slip). Geometry, detection and the committed history are chained
    through exactly, so the result is the derivative of the discrete solution
    wherever no state changes under a small change of theta. A sub-step cut
    short by the step length (a large motion on the way to equilibrium) is
    held fixed, and ``info["approximate"]`` says that one was.
    """
    return _increment(model, state, loads, tangents)


# Model fields that scene parameters change smoothly (see jaxdem.differentiable).
SMOOTH_MODEL = ("joint_kn", "joint_ks", "joint_c", "joint_t", "joint_tanphi", "kn_inv", "ks_inv",
                "cell_D", "bolt_k", "bolt_cap", "bolt_comp", "gamma_w")
STATE_FLOATS = ("verts", "centroid", "u", "rot", "fs", "fn", "fn0", "bolt_force", "bolt_rest",
                "strain", "stress")
LOAD_FLOATS = ("force", "water_y")
SNAPSHOT_FLOATS = ("point", "normal", "fn", "fs", "pw")


def _fields(obj, names) -> dict:
    return {k: getattr(obj, k) for k in names}


def _tangent_terms(model: Model, sub: _Sub, ev):
    """The exact tangent K = -dR/d(du) with the slots' states held, as terms (a, b, L, R, k).

    The slip tangent (:func:`_stiffness_terms` with ``consistent``: both
    springs of a sticking slot, the normal one of a slipping slot, none of an
    open one; elastic bolts) with the slip law's coupling d fs / d fn_trial =
    sign(fs) tan(phi), which makes K unsymmetric (:func:`_with_slip_coupling`):
    the matrix Newton's tried tangent uses on the direct paths.
    """
    terms = _stiffness_terms(model, sub, ev, True)
    return _with_slip_coupling(model, sub, ev, terms, jnp.ones((), bool))


TANGENT_REFINEMENTS = 2
"""Refinement steps of the sensitivity solve on its regularised factorisation (see
:func:`_tangent_solve`): each multiplies the regularisation's error by eps / lambda."""


def _host_tangent_solve(a, b, L, Rt, k, Kc, diag, pm, rhs):
    """:func:`_tangent_solve` on the host: SuperLU of K + eps M, refined on K; NaN if singular."""
    import scipy.sparse
    import scipy.sparse.linalg

    a, b, L, Rt, k, Kc, diag, pm, rhs = (np.asarray(x) for x in (a, b, L, Rt, k, Kc, diag, pm,
                                                                  rhs))
    K = _host_matrix(a, b, L, Rt, k, Kc, diag)
    try:
        lu = scipy.sparse.linalg.splu(K + scipy.sparse.diags(pm, format="csc"),
                                      permc_spec="MMD_AT_PLUS_A")
    except RuntimeError:  # "Factor is exactly singular": no derivative here
        return np.full_like(rhs, np.nan)
    x = lu.solve(rhs)
    for _ in range(TANGENT_REFINEMENTS):
        x = x + lu.solve(rhs - K @ x)
    return np.where(np.all(np.isfinite(x)), x, np.nan).astype(rhs.dtype)


def _tangent_solve(model: Model, sub: _Sub, terms, rhs):
    """K^-1 rhs for p right-hand sides (p, N, D), K the exact (possibly unsymmetric) tangent.

    K is singular where a free block has a neutral direction in the held states
    (its contacts all open or slipping, or a rotation about its one contact
    point). So K + eps M is factorised, eps M the forward solve's pseudo-mass
    (``model.pseudo_mass``), and the answer refined on K itself
    (:data:`TANGENT_REFINEMENTS` steps, x += (K + eps M)^-1 (rhs - K x)): where K
    is regular the pseudo-mass's error, a relative eps / lambda per step, is
    gone (1e-6 -> 1e-18), and along a neutral direction, which no load
    excites, the derivative stays zero (the minimum-norm answer). Where the
    rhs does push along a neutral direction the derivative there is bounded by
    (1 + refinements) rhs / eps, as the forward solve's own step is.
    A factorisation that is still singular, or any non-finite entry, gives NaN
    everywhere: "no derivative at this point", which the back-analysis reads
    as a step to take back.
    """
    p = rhs.shape[0]
    N, D = model.n_blocks, model.ndof
    a, b, L, Rt, k = terms
    free = jnp.repeat(sub.free, D)
    diag = jnp.where(free, 0.0, 1.0).astype(rhs.dtype)
    pm = jnp.where(free, model.pseudo_mass.reshape(-1), 0.0).astype(rhs.dtype)
    B = rhs.reshape(p, N * D).T
    if model.linear_solver == "dense":
        K = _assemble_dense(model, sub, a, b, L, Rt, k, diag)
        lu = jax.scipy.linalg.lu_factor(K + jnp.diag(pm))
        x = jax.scipy.linalg.lu_solve(lu, B)
        for _ in range(TANGENT_REFINEMENTS):
            x = x + jax.scipy.linalg.lu_solve(lu, B - K @ x)
        x = jnp.where(jnp.all(jnp.isfinite(x)), x, jnp.nan)
    else:
        Kc = sub.Kc if sub.Kc is not None else jnp.zeros((0, D, D), rhs.dtype)
        x = jax.pure_callback(_host_tangent_solve, jax.ShapeDtypeStruct(B.shape, B.dtype),
                              a, b, L, Rt, k, Kc, diag, pm, B, vmap_method="sequential")
    return x.T.reshape(rhs.shape)


def _substep_tangent(model: Model, state: State, loads: Loads, dmodel, dstate, dloads):
    """:func:`_substep` and the derivatives of its new state and snapshot.

    Returns (the outputs of :func:`_substep`, (dstate, dsnapshot)); see
    :func:`increment_tangent`.
    """
    mf0, sf0, lf0 = (_fields(model, SMOOTH_MODEL), _fields(state, STATE_FLOATS),
                     _fields(loads, LOAD_FLOATS))

    # Geometry, detection and history (the candidate pairs of this sub-step are
    # integers: no derivative), linearised once: the forward sub-step iterates
    # on its primal, and its tangent serves all p parameters.
    def prepare(mf, sf, lf):
        m = dataclasses.replace(model, **mf)
        s = dataclasses.replace(state, **sf)
        ld = dataclasses.replace(loads, **lf)
        _, sub, st0, pairs, need = _prepare(m, s, ld)
        return sub, (st0, pairs, need)

    sub, prepare_lin, (st0, pairs, need) = jax.linearize(prepare, mf0, sf0, lf0, has_aux=True)
    mdl = dataclasses.replace(model, free=sub.free)
    forward = _newton_and_commit(mdl, state, sub, st0, pairs, need)
    new_state, du, converged = forward[0], forward[1], forward[2]["converged"]
    held = new_state.cstate.reshape(-1)
    all_held = jnp.ones(held.shape, bool)
    leaves, tree = jax.tree.flatten(sub)
    smooth = [jnp.issubdtype(x.dtype, jnp.inexact) for x in leaves]
    floats = lambda sb: [x for x, f in zip(jax.tree.leaves(sb), smooth, strict=True) if f]  # noqa: E731

    def with_floats(fl):
        it = iter(fl)
        return tree.unflatten([next(it) if f else x for x, f in zip(leaves, smooth, strict=True)])

    dsub = jax.vmap(lambda dm, ds, dl: floats(prepare_lin(dm, ds, dl)))(dmodel, dstate, dloads)

    # Equilibrium and commit at fixed geometry, in the held states.
    def settle(mf, fl, sf, x):
        m = dataclasses.replace(model, **mf)
        sb = with_floats(fl)
        mdl = dataclasses.replace(m, free=sb.free)
        s = dataclasses.replace(state, **sf)
        ev = _evaluate(mdl, sb, x, all_held, held, held, 0.0)
        new, _, snap = _commit(mdl, s, sb, pairs, x, ev)
        return (ev["R"], _fields(new, STATE_FLOATS), {k: snap[k] for k in SNAPSHOT_FLOATS}), ev

    # Linearised apart in the parameters (at the converged du) and in du: each
    # evaluates only its own tangent paths, where one linearisation in all four
    # would carry zero tangents through the other's.
    fl0 = floats(sub)
    _, lin_p, ev = jax.linearize(lambda mf, fl, sf: settle(mf, fl, sf, du), mf0, fl0, sf0,
                                 has_aux=True)
    dR, ds1, dsnap1 = jax.vmap(lin_p)(dmodel, dsub, dstate)
    ddu = _tangent_solve(mdl, sub, _tangent_terms(mdl, sub, ev), dR)
    ddu = jnp.where(converged, ddu, 0.0)
    _, lin_x = jax.linearize(lambda x: settle(mf0, fl0, sf0, x)[0][1:], du)
    ds2, dsnap2 = jax.vmap(lin_x)(ddu)
    add = lambda x, y: jax.tree.map(jnp.add, x, y)  # noqa: E731
    return forward, (add(ds1, ds2), add(dsnap1, dsnap2))


# ---------------------------------------------------------------------------
# Host driver

_COMPILED: collections.OrderedDict = collections.OrderedDict()
MAX_COMPILED = 16
"""Compiled increments kept in memory (least recently used dropped first)."""


COMPILE_TIMES = {"lower_s": 0.0, "compile_s": 0.0}
"""Time spent in :func:`_compiled` by this process: tracing and lowering, and XLA
compilation (or loading from the persistent cache), s."""


CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
"""XLA options of jaxdem's large programs on a CPU. Without the new fusion emitters
XLA compiled the increment in 0.6 to 0.7 of the time (10.3 -> 6.1 s dense, 10.7 ->
7.7 s cg, 20 x 20 grid; 14 -> 9 s, incline) and the solve was no slower, with
bitwise the same answers (BENCHMARKS.md, "Time to answer"). A jaxlib that does
not know an option compiles without them."""


def _xla_compile(lowered):
    """``lowered.compile()``, with :data:`CPU_COMPILER_OPTIONS` on a CPU."""
    if CPU_COMPILER_OPTIONS and jax.default_backend() == "cpu":
        try:
            return lowered.compile(compiler_options=dict(CPU_COMPILER_OPTIONS))
        except jax.errors.JaxRuntimeError:  # an option this XLA does not have
            pass
    return lowered.compile()


def _compiled(fn, *args, **static):
    """``fn`` (jitted) compiled for these argument shapes and static settings; compile time (s).

    ``static`` holds ``fn``'s static keyword arguments; the compiled program is
    called without them.

    One compilation per shape: the samples of a sweep and the iterations of a
    back-analysis reuse it. At most :data:`MAX_COMPILED` are kept: a compiled
    increment holds about 35 MB and hundreds of memory mappings, and a process
    that solved some hundreds of differently-shaped scenes ran out of mappings
    and crashed in XLA's compiler. When one is dropped, JAX's own caches (the
    small host-step programs) are cleared with it; the persistent compilation
    cache on disk still serves a shape that comes back.
    """
    leaves, tree = jax.tree.flatten(args)
    key = (fn, tree, tuple((x.shape, str(x.dtype)) for x in leaves), tuple(sorted(static.items())))
    if key in _COMPILED:
        _COMPILED.move_to_end(key)
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    lowered = fn.lower(*args, **static)
    t1 = time.perf_counter()
    compiled = _xla_compile(lowered)
    COMPILE_TIMES["lower_s"] += t1 - t0
    COMPILE_TIMES["compile_s"] += time.perf_counter() - t1
    _COMPILED[key] = compiled
    if len(_COMPILED) > MAX_COMPILED:
        _COMPILED.popitem(last=False)
        jax.clear_caches()
    return compiled, time.perf_counter() - t0


def _grow_tangent(dstate: dict, capacity: int) -> dict:
    """Slot derivatives (p, P, 2, V) padded with zeros to a larger pair capacity."""
    out = dict(dstate)
    for k in ("fs", "fn", "fn0"):
        x = dstate[k]
        out[k] = jnp.zeros((x.shape[0], capacity) + x.shape[2:], x.dtype).at[:, :x.shape[1]].set(x)
    return out


def run_increment(model: Model, state: State, loads: Loads, tangents: dict | None = None):
    """One increment with capacity growth: on overflow, grow and redo from ``state``.

    Returns (model, state, info, compile_s): the model changes only when a
    grid cell capacity grew. Growing recompiles; nothing is ever truncated.
    With ``tangents`` (see :func:`increment_tangent`) the state's derivatives
    are carried along (``info["dstate"]``).
    """
    compile_s = 0.0
    while True:
        if tangents is None:
            fn, dt = _compiled(increment, model, state, loads)
            new, info = fn(model, state, loads)
        else:
            fn, dt = _compiled(increment_tangent, model, state, loads, tangents)
            new, info = fn(model, state, loads, tangents)
        compile_s += dt
        if int(info["status"]) != Status.CAPACITY_OVERFLOW:
            return model, new, info, compile_s
        if bool(info["cell_full"]):
            model = dataclasses.replace(model, cell_capacity=2 * model.cell_capacity)
        need = int(info["pairs_needed"])
        if need > state.capacity:
            capacity = model_mod.bucket(max(2 * state.capacity, int(1.3 * need) + 16))
            state = grow_capacity(state, capacity)
            if tangents is not None:
                tangents = dict(tangents, state=_grow_tangent(tangents["state"], capacity))


def _imbalance_jax(balance):
    """:func:`_imbalance` on the device (a traced scalar)."""
    f = balance["applied"][:2] + balance["reaction"][:2]
    return jnp.linalg.norm(f) / jnp.maximum(balance["scale"], jnp.finfo(f.dtype).tiny)


def _imbalance(balance) -> float:
    """Global force balance of the free blocks, relative.

    |applied + reaction| over the larger of the summed magnitudes of the
    block loads and of the reactions (forces from fixed blocks, walls and
    their bolts), so that it stays meaningful when the loads cancel out (an
    in-situ state held by walls on all sides), and of the largest spring
    force carried (no load and no net reaction: a self-balanced in-situ
    stress; see :func:`_commit`).
    """
    applied = np.asarray(balance["applied"])[:2]  # sliced on the host: no program to compile
    reaction = np.asarray(balance["reaction"])[:2]
    return float(np.linalg.norm(applied + reaction) / max(float(balance["scale"]), 1e-300))


@functools.partial(jax.jit, static_argnames=("mode",))
def _preload(model: Model, state: State, loads: Loads, sigma, surface_y, gamma, k0, mode: str):
    """Contacts at the start with the forces of the in-situ stress field (zero displacement).

    Each touching spring gets its part of the traction of the stress tensor
    (compression positive) on its face: the consistent (linear-element) nodal
    force of the traction t along the overlap, share x (2 t(here) + t(far end)) / 3,
    which gives the exact force and moment of a traction that varies linearly
    along the face (the gravity field does). fn0 is its normal part (minus the
    pore pressure: springs carry effective force) and fs minus its tangential
    part. ``mode`` "gravity": sigma_yy = gamma (surface_y - y), sigma_xx = k0
    sigma_yy; "uniform": ``sigma`` = (sxx, syy, sxy).
    """
    pairs, count, cell_full = broad_phase(model, state.verts, state.capacity, state.alive)
    geo = narrow_phase(model, state.verts, state.centroid, pairs)
    prop = slot_properties(model, geo)
    p, n, t = geo["point"], geo["normal"], geo["tangent"]

    def traction(x):
        if mode == "gravity":
            syy = gamma * jnp.maximum(surface_y - x[:, 1], 0.0)
            sxx, sxy = k0 * syy, jnp.zeros_like(syy)
        else:
            sxx, syy, sxy = (jnp.broadcast_to(sigma[k], x[:, 0].shape) for k in range(3))
        return sxx * n[:, 0] + sxy * n[:, 1], sxy * n[:, 0] + syy * n[:, 1]

    (tx0, ty0), (tx1, ty1) = traction(p), traction(geo["far_point"])
    tx, ty = (2.0 * tx0 + tx1) / 3.0, (2.0 * ty0 + ty1) / 3.0
    touching = geo["active"] & (geo["gap"] <= model.touch_tol)
    # Faces in contact carry the in-situ traction; a corner touching a face
    # (a cell corner on a boundary wall, a hanging node) is a point of a
    # tessellation and carries none, nor do nearly parallel faces that meet at
    # one end only (a sliver between them), else the state would not be in
    # equilibrium.
    loaded = touching & ~geo["corner"] & (geo["far_gap"] <= model.touch_tol)
    pw = water_force(model, geo, prop, loads.water_x, loads.water_y) if model.has_water else 0.0
    fn0 = jnp.where(loaded, (tx * n[:, 0] + ty * n[:, 1]) * geo["share"] - pw, 0.0)
    fs = jnp.where(loaded, -(tx * t[:, 0] + ty * t[:, 1]) * geo["share"], 0.0)
    shape = state.fs.shape
    stress = state.stress
    if model.ndof == 6:
        # Each deformable block starts with the stress its contact forces and
        # boundary tractions imply, (1/A) sum r (x) F: exactly in equilibrium.
        every = jnp.ones(model.n_blocks, bool)
        rows = lambda v: b_rows(every, geo["a"], geo["b"], p, p, v, state.centroid, 6)  # noqa: E731
        f_row = rows(n) * (fn0 + pw)[:, None] - rows(t) * fs[:, None]
        virial = _scatter(model.n_blocks, geo["a"], geo["b"], f_row)[:, 3:] + loads.force[:, 3:]
        stress = virial / model.area[:, None]
    new = dataclasses.replace(
        state, pairs=pairs, fn0=fn0.reshape(shape), fn=fn0.reshape(shape), fs=fs.reshape(shape),
        failed=(geo["gap"] > model.touch_tol).reshape(shape), edge=geo["edge"].reshape(shape),
        cstate=jnp.where(touching, STICK, OPEN).astype(jnp.int32).reshape(shape),
        present=geo["active"].reshape(shape), stress=stress)
    return new, (count > state.capacity) | cell_full


def make_loads(model: Model, force, water_x=None, water_y=None, bolt_active=None,
               water_scale=1.0) -> Loads:
    """Loads for one increment: block forces (N, 3), optional water table and bolt switches."""
    # From host arrays (the driver's) the Loads are built in NumPy and sent
    # to the device in one transfer; from JAX arrays (under jit or vmap),
    # with jax.numpy.
    from_jax = any(isinstance(x, jax.Array)
                 for x in (force, water_x, water_y, bolt_active, water_scale))
    xp = jnp if from_jax else np
    dtype = model.radius.dtype
    no_water = xp.array([0.0, 1.0], dtype), xp.array([-1e30, -1e30], dtype)
    loads = Loads(
        force=xp.asarray(force, dtype),
        water_x=no_water[0] if water_x is None else xp.asarray(water_x, dtype),
        water_y=no_water[1] if water_y is None else xp.asarray(water_y, dtype),
        water_scale=xp.asarray(water_scale, dtype),
        bolt_active=(xp.ones(model.n_bolts, bool) if bolt_active is None
                     else xp.asarray(bolt_active, bool)))
    return loads if from_jax else jax.device_put(loads)


@dataclasses.dataclass
class Data:
    """What the host driver applies, with derivatives: every array has a leading axis 1 + p.

    Entry 0 is the value, entries 1..p its derivatives with respect to p scene
    parameters (p = 0 for a plain solve). The driver only adds and scales these
    arrays, so derivatives follow the values through stages and load steps.
    For a batch (``jaxdem.batch``) the leading axis holds the samples instead.

    Attributes:
      weight, traction: (1 + p, N, D) self-weight and boundary tractions (kN/m).
      supports: one (1 + p, N, D) load per entry of ``Layout.supports``.
      sigma: (1 + p, 3) uniform in-situ stress (kPa, compression positive);
        k0, gamma, surface: (1 + p,) gravity in-situ K0, unit weight (kN/m3)
        and ground surface (m).
      water_x: (X,) abscissae of the water tables (m); water_y: (1 + p, X) the
        scene's table; stage_water: {stage name: (1 + p, X)}.
      dmodel: {field: (p, ...)} derivatives of the model's :data:`SMOOTH_MODEL`
        fields (None when p = 0).
    """

    weight: np.ndarray
    traction: np.ndarray
    supports: list
    sigma: np.ndarray
    k0: np.ndarray
    gamma: np.ndarray
    surface: np.ndarray
    water_x: np.ndarray
    water_y: np.ndarray
    stage_water: dict
    dmodel: dict | None = None

    @property
    def p(self) -> int:
        return self.weight.shape[0] - 1


def gravity_material(scene, layout) -> str:
    """The material whose unit weight makes the gravity in-situ stress: the domain's,
    else that of the first rock block that is not excavated."""
    if scene.domain is not None:
        return scene.domain.material
    return next(layout.materials[i] for i in range(layout.n_rock) if layout.excavation[i] is None)


def scene_data(scene, layout) -> Data:
    """The driver's inputs of a scene as built, without derivatives (p = 0)."""
    one = lambda x: np.asarray(x, float)[None]  # noqa: E731
    in_situ = scene.in_situ
    gamma = surface = k0 = 0.0
    sigma = np.zeros(3)
    if in_situ is not None:
        k0 = in_situ.k0
        sigma = np.array([in_situ.sigma_xx, in_situ.sigma_yy, in_situ.sigma_xy])
        if in_situ.mode == "gravity":
            name = gravity_material(scene, layout)
            gamma, surface = scene.materials[name].unit_weight, in_situ.surface_y
    water = scene.water
    tables = ([water.table] if water is not None else []) + [
        st.water_table for st in scene.stages if st.water_table is not None]
    xs = (np.unique(np.concatenate([np.asarray(t, float)[:, 0] for t in tables]))
          if tables else np.array([0.0, 1.0]))
    sample = lambda table: np.interp(xs, *np.asarray(table, float).T)  # noqa: E731
    return Data(
        weight=one(layout.weight), traction=one(layout.traction),
        supports=[one(sp["force"]) for sp in layout.supports], sigma=one(sigma), k0=one(k0),
        gamma=one(gamma), surface=one(surface), water_x=xs,
        water_y=one(sample(water.table) if water is not None else np.full(xs.shape, -1e30)),
        stage_water={st.name: one(sample(st.water_table)) for st in scene.stages
                     if st.water_table is not None})


def _release(centroid, snap, removed, ndof):
    """Forces (N, D) that the blocks being removed exert on the others, from a contact snapshot.

    The force of each contact on a remaining block is (fn + pw) n - fs t at the
    contact point; :func:`point_row` is linear in the force, so it gives the
    generalised force directly.
    """
    N = centroid.shape[0]
    act = snap["active"]
    a, b, p, n = snap["a"], snap["b"], snap["point"], snap["normal"]
    t = jnp.stack([-n[:, 1], n[:, 0]], axis=1)
    F = (snap["fn"] + snap["pw"])[:, None] * n - snap["fs"][:, None] * t
    out = jnp.zeros((N, ndof), F.dtype)
    for on, by, sign in ((a, b, 1.0), (b, a, -1.0)):
        sel = act & removed[by] & ~removed[on]
        f = jnp.where(sel[:, None], sign * F, 0.0)
        out = out + jax.ops.segment_sum(point_row(p - centroid[on], f, ndof), on, N)
    return out


_release_jit = jax.jit(_release, static_argnums=3)


@functools.partial(jax.jit, static_argnames=("ndof",))
def _release_with_tangent(centroid, snap, removed, dcentroid, dsnap, ndof):
    """:func:`_release` (N, D) and its derivatives (p, N, D)."""
    def rel(c, floats):
        return _release(c, dict(snap, **floats), removed, ndof)

    floats = {k: snap[k] for k in SNAPSHOT_FLOATS}
    value = rel(centroid, floats)
    tangent = jax.vmap(lambda dc, ds: jax.jvp(rel, (centroid, floats), (dc, ds))[1])(
        dcentroid, dsnap)
    return value, tangent


@functools.partial(jax.jit, static_argnames=("mode",))
def _preload_tangent(model: Model, state: State, loads: Loads, args, dmodel, dloads, dargs,
                     mode: str):
    """:func:`_preload` (its state and overflow flag) and the derivatives (p, ...) of its state.

    args = (sigma, surface_y, gamma, k0) and dargs their derivatives (p, ...).
    One compiled call: the plain :func:`_preload` runs op by op (compiling it
    would cost seconds for a millisecond saved in a single solve), and the
    linearisation gives its values with the derivatives.
    """
    def pre(mf, lf, a):
        m = dataclasses.replace(model, **mf)
        ld = dataclasses.replace(loads, **lf)
        new, overflow = _preload(m, state, ld, *a, mode=mode)
        return _fields(new, STATE_FLOATS), (new, overflow)

    primals = (_fields(model, SMOOTH_MODEL), _fields(loads, LOAD_FLOATS), args)
    _, lin, (new, overflow) = jax.linearize(pre, *primals, has_aux=True)
    return new, overflow, jax.vmap(lin)(dmodel, dloads, dargs)


class _Driver:
    """Host loop over stages and load steps; collects the records of a Result.

    With derivatives (``data.p > 0``) it carries ``dstate``, the derivatives
    of the state's :data:`STATE_FLOATS` with respect to the p parameters.
    """

    def __init__(self, model, state, layout, data: Data, progress):
        self.model, self.state, self.layout = model, state, layout
        self.data, self.progress = data, progress
        self.compile_s = self.solve_s = 0.0
        self.records, self.history = [], []
        self.info = None
        self.ref = None  # the state displacements are measured from (None: the start)
        self.dref = None
        self.status = Status.CONVERGED
        self.bolt_active = np.zeros(model.n_bolts, bool)
        self.water_y = data.water_y
        self.approximate = False
        p = data.p
        self.dstate = None if p == 0 else {
            k: jnp.zeros((p,) + getattr(state, k).shape, getattr(state, k).dtype)
            for k in STATE_FLOATS}

    def loads(self, force, water_y=None, water_scale=1.0):
        """Loads of an increment from (1 + p, ...) stacks, and their derivatives (or None)."""
        wy = self.water_y if water_y is None else water_y
        loads = make_loads(self.model, force[0], self.data.water_x, wy[0], self.bolt_active,
                           water_scale)
        if self.dstate is None:
            return loads, None
        dtype = loads.force.dtype
        return loads, dict(force=jnp.asarray(force[1:], dtype), water_y=jnp.asarray(wy[1:], dtype))

    def step(self, stage, k, n, loads):
        from jaxdem.results import monitor_values

        loads, dloads = loads
        tangents = None if dloads is None else dict(model=self.data.dmodel, state=self.dstate,
                                                    loads=dloads)
        t1 = time.perf_counter()
        self.model, self.state, info, dt = run_increment(self.model, self.state, loads, tangents)
        jax.block_until_ready(self.state.verts)
        self.compile_s += dt
        self.solve_s += time.perf_counter() - t1 - dt
        self.info = info
        if tangents is not None:
            self.dstate = info["dstate"]
            self.approximate |= bool(info["approximate"])
        self.status = Status(int(info["status"]))
        bal, jm = info["balance"], info["joints"]
        rec = dict(stage=stage, step=k, load_factor=k / n, status=self.status,
                   iterations=int(info["iterations"]), substeps=int(info["substeps"]),
                   residual=float(info["residual"]), imbalance=_imbalance(bal),
                   overlap=float(bal["overlap"]), overlap_rel=float(bal["overlap_rel"]),
                   strength_excess=float(bal["excess"]),
                   slip=float(jm["slip"]), slip_rel=float(jm["slip_rel"]),
                   slip_blocks=[int(x) for x in np.asarray(jm["slip_blocks"])],
                   opening=float(jm["opening"]),
                   opening_blocks=[int(x) for x in np.asarray(jm["opening_blocks"])])
        self.records.append(rec)
        self.history.append(dict(stage=stage, step=k, load_factor=k / n,
                                 monitors=monitor_values(self.layout, self.state, self.ref)))
        if self.progress is not None:
            self.progress(dict(stage=stage, step=k, n_steps=n, status=self.status.label,
                               iterations=rec["iterations"], substeps=rec["substeps"],
                               residual=rec["residual"]))
        return self.status == Status.CONVERGED

    def release(self, removed):
        """Forces (1 + p, N, D) of the blocks being removed on the rest, from the last contacts."""
        N, D = self.model.n_blocks, self.model.ndof
        out = np.zeros((1 + self.data.p, N, D))
        if not removed.any() or self.info is None:
            return out
        snap, rm = self.info["snapshot"], jnp.asarray(removed)
        if self.dstate is None:
            out[0] = np.asarray(_release_jit(self.state.centroid, snap, rm, D))
            return out
        value, tangent = _release_with_tangent(self.state.centroid, snap, rm,
                                               self.dstate["centroid"], self.info["dsnapshot"], D)
        out[0], out[1:] = np.asarray(value), np.asarray(tangent)
        return out

    def preload(self, scene, base):
        """The in-situ state (contact forces of the in-situ stress at zero displacement)."""
        data, mode = self.data, scene.in_situ.mode
        stacks = (data.sigma, data.surface, data.gamma, data.k0)
        args = tuple(jnp.asarray(x[0], self.layout.dtype) for x in stacks)
        loads, dloads = self.loads(base)
        while True:
            if self.dstate is None:
                pre, dt = _compiled(_preload, self.model, self.state, loads, *args, mode=mode)
                self.compile_s += dt
                st, overflow = pre(self.model, self.state, loads, *args)
            else:
                dargs = tuple(jnp.asarray(x[1:], self.layout.dtype) for x in stacks)
                st, overflow, self.dstate = _preload_tangent(
                    self.model, self.state, loads, args, data.dmodel, dloads, dargs, mode=mode)
            if not bool(overflow):
                break
            self.state = grow_capacity(self.state, model_mod.bucket(2 * self.state.capacity))
        self.state = st


def solve(scene, set: dict | None = None, progress=None):
    """Solve a scene: load steps, in-situ stress and stages, each to static equilibrium.

    Without ``[in_situ]`` the scene starts unloaded and self-weight and
    tractions are applied over ``solver.load_steps`` increments. With it, the
    contacts start with the in-situ stress (zero displacement). Then each
    stage (``[[stages]]``, or one stage when the scene has excavations,
    supports or bolts but no stages) removes its excavations, whose forces on
    the remaining rock are released over the stage's load steps, installs its
    bolts, ramps its support pressures and moves the water table.
    Displacements are reported from the state before the first stage.

    Args:
      scene: a validated :class:`jaxdem.scene.Scene` (from :func:`jaxdem.load_scene`).
      set: parameter overrides by dotted path, e.g. ``{"joints.set1.kn": 2e6}``.
      progress: optional callable, called after each increment with a dict
        (``stage``, ``step``, ``n_steps``, ``status``, ``iterations``,
        ``substeps``, ``residual``).
    Returns:
      a :class:`jaxdem.results.Result`.

    Example::

        scene = jaxdem.load_scene("examples/block_on_incline.toml")
        result = jaxdem.solve(scene, set={"joints.base.friction_deg": 25.0})
        print(result.stable, result.monitors)
    """
    from jaxdem.results import build_result

    if set:
        scene = scene.with_overrides(set)
    t0 = time.perf_counter()
    model, state, layout = model_mod.build(scene)
    jax.block_until_ready(state.verts)
    build_s = time.perf_counter() - t0
    d = run(scene, model, state, layout, scene_data(scene, layout), progress)
    timing = dict(build_s=build_s, compile_s=d.compile_s, solve_s=d.solve_s)
    return build_result(scene, d.model, layout, d.state, d.ref, d.info, d.records, d.history,
                        timing)


def run(scene, model: Model, state: State, layout, data: Data, progress=None,
        stage_end=None, driver=None) -> _Driver:
    """Run a built scene through its loading and stages; returns the finished driver.

    ``data`` gives the loads (and, with p > 0, their derivatives, which the
    driver then carries: :class:`Data`). ``stage_end``, if given, is called
    with the driver and the stage name at the end of each stage ("initial"
    for the state before the first stage). ``driver``, if given, replaces the
    single-solve :class:`_Driver` (``jaxdem.batch`` passes one that solves a
    batch of samples, with ``data`` stacked over the samples).
    """
    d = driver if driver is not None else _Driver(model, state, layout, data, progress)
    in_situ = scene.in_situ
    N, D = model.n_blocks, model.ndof
    zero = np.zeros((1 + data.p, N, D))
    pending = zero  # applied over the first stage (uniform in-situ mode)
    plan = _stage_plan(scene)
    if in_situ is None and not plan:
        # Without in-situ stress and with nothing after the loading (no stage, no
        # excavation, no support), a bolt is part of the scene the loading builds: it
        # acts from the first load step. Otherwise it is installed in its stage (the
        # first, when it names none).
        d.bolt_active[:] = True
    if in_situ is None:
        n = layout.load_steps
        base = data.weight + data.traction
        for k in range(1, n + 1):
            # Pore pressure grows with the weight: a saturated slope is loaded
            # as a whole, not by full water pressure on a weightless mass.
            if not d.step("loading", k, n, d.loads(k / n * base, water_scale=k / n)):
                break
    else:
        if in_situ.mode == "gravity":
            base = data.weight + data.traction
        else:
            base, pending = data.traction, data.weight
        d.preload(scene, base)
        d.step("initial", 1, 1, d.loads(base))
    # Displacements count from the state before the first stage, once there
    # is one and the loading before it found equilibrium.
    started = (plan or in_situ is not None) and d.status == Status.CONVERGED
    d.ref, d.dref = (d.state, d.dstate) if started else (None, None)
    if stage_end is not None:
        stage_end(d, "initial")
    for stage in plan:
        if d.status != Status.CONVERGED:
            break
        removed = np.zeros(N, bool)
        removed[:layout.n_rock] = [e is not None and e in stage["excavations"]
                                   for e in layout.excavation]
        release = d.release(removed)
        if removed.any():
            alive = np.asarray(d.state.alive) & ~removed
            d.state = dataclasses.replace(d.state, alive=jnp.asarray(alive))
        for b, bs in enumerate(layout.bolt_stages):
            if bs == stage["name"] or (bs is None and stage["first"]):
                d.bolt_active[b] = True
        support = sum((f for sp, f in zip(layout.supports, data.supports, strict=True)
                       if sp["stage"] == stage["name"] or (sp["stage"] is None and stage["first"])),
                      zero)
        y_old = d.water_y
        y_new = data.stage_water.get(stage["name"], y_old)
        n = stage["load_steps"] or layout.load_steps
        for k in range(1, n + 1):
            lam = k / n
            force = base + (1 - lam) * release + lam * (pending + support)
            if not d.step(stage["name"], k, n, d.loads(force, (1 - lam) * y_old + lam * y_new)):
                break
        base, pending = base + pending + support, zero
        d.water_y = y_new
        if stage_end is not None and d.status == Status.CONVERGED:
            stage_end(d, stage["name"])
    return d


def _stage_plan(scene) -> list[dict]:
    """The stages after the initial state, in order, with what each one does."""
    excavations = scene.excavations
    stages = list(scene.stages)
    bolts_later = scene.bolts and scene.in_situ is not None
    if not stages and (excavations or scene.supports or bolts_later):
        return [dict(name="excavation", first=True, load_steps=None, water_table=None,
                     excavations={e.name for e in excavations})]
    if not stages and scene.in_situ is not None and scene.in_situ.mode == "uniform":
        # A uniform in-situ stress leaves self-weight to the first stage; with
        # no stage, it is applied over the load steps of a "loading" stage.
        return [dict(name="loading", first=True, load_steps=None, water_table=None,
                     excavations=set())]
    first = stages[0].name if stages else None
    return [dict(name=st.name, first=st.name == first, load_steps=st.load_steps,
                 water_table=st.water_table,
                 excavations={e.name for e in excavations
                              if e.stage == st.name or (e.stage is None and st.name == first)})
            for st in stages]
