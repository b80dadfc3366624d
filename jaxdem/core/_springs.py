"""The springs of one geometry sub-step: forces, states, residual and stiffness terms.

Owns :class:`Sub` (everything fixed during a sub-step, a pytree inside jit, with its
:class:`Bolts` and :class:`Packing`), the contact springs' and bolts' forces and states
for a trial increment du (:func:`evaluate`, a :class:`Springs`, through the contact law
of :mod:`jaxdem.core.laws`), the
residual and the per-block force scale of the equilibrium test, and the
iteration matrix written as rank-one terms (a, b, B, k)
(:func:`stiffness_terms`, :func:`_bolt_terms`, :func:`with_slip_coupling`).

Data flow: takes kinematics (:mod:`jaxdem.core.kinematics`) and laws; its terms go
to the linear solves (:mod:`jaxdem.core._linsolve`), and the Newton iteration
(:mod:`jaxdem.core._substep`) and the sensitivities call it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdem.core._contact import Slots
from jaxdem.core.kinematics import (
    bolt_hessian,
    bolt_length_derivatives,
    gather_pairs,
    scatter_pairs,
)
from jaxdem.core.laws import SlotLaw, forces_in_state, held_elastic, mohr_coulomb
from jaxdem.core.state import OPEN, SLIP, STICK, Model

#: A slipping spring whose strength is below this fraction of its trial shear force has
#: no shear spring in the secant matrix (:func:`stiffness_terms`).
SLIP_SECANT = 0.01


class Bolts(NamedTuple):
    """The bolts during a sub-step (nb,): blocks ``a``, ``b`` (their anchors' blocks),
    ``free_a``, ``free_b`` (those blocks have degrees of freedom), ``f_old`` the committed
    axial force (kN/m), ``active`` (installed, both blocks alive), ``d0`` (nb, 2) anchor a
    minus anchor b (m), ``ra``, ``rb`` (nb, 2) the anchors from their blocks' centroids (m),
    ``rest`` the rest length (m; grows with plastic elongation)."""

    a: jax.Array
    b: jax.Array
    free_a: jax.Array
    free_b: jax.Array
    f_old: jax.Array
    active: jax.Array
    d0: jax.Array
    ra: jax.Array
    rb: jax.Array
    rest: jax.Array


class Packing(NamedTuple):
    """Where the touching slots of a sub-step lie (:func:`jaxdem.core._substep.pack_slots`):
    ``slot`` (C,) the index of each among the detection's P x 2 x V (P x 2 x V for an empty
    place), ``first`` and ``second`` (Pt,) the two blocks of each touching pair, ``grid``
    (Pt, m) the places of each pair's slots in the packed list (C where it has fewer)."""

    slot: jax.Array
    first: jax.Array
    second: jax.Array
    grid: jax.Array


class Springs(NamedTuple):
    """The springs at a trial increment du (:func:`evaluate`); per slot (S,) unless said.

    ``fn``, ``fs`` the forces carried (kN/m, compression positive), ``state`` (OPEN,
    STICK, SLIP), ``gap`` (m), ``total_n`` the normal force with the water's, ``fn_trial``,
    ``fs_trial`` the elastic trial forces, ``law_state`` the law's state (where a slot is
    held frozen in another), ``misfit`` (kN/m) how far a frozen slot's forces are from the
    law's, ``dfs_dfn`` d fs / d fn_trial in the states held; per block (N, D): ``internal``
    the springs' (and cells', bolts') forces, ``R`` the residual (load + internal on the
    free blocks), ``R_law`` the residual with the law's forces everywhere; ``stress`` (N, 3)
    of deformable cells (None for rigid blocks); of the bolts (nb, ..., None without):
    ``bolt_force`` (kN/m), ``bolt_state`` (0 elastic; :func:`_bolt_law`'s codes),
    ``bolt_length`` (m), ``bolt_g`` its gradient in the anchors' motions and its Hessian
    as rank-one terms ``bolt_Hv``, ``bolt_Hc``
    (:func:`jaxdem.core.kinematics.bolt_length_derivatives`), ``bolt_rows`` its forces on
    the blocks. What
    :func:`jaxdem.core._substep.commit_substep` reads of an evaluation on packed slots is
    laid out over all slots, the rest None (:func:`jaxdem.core._substep._unpacked`).
    """

    fn: jax.Array
    fs: jax.Array
    state: jax.Array
    gap: jax.Array
    total_n: jax.Array
    fn_trial: jax.Array | None = None
    fs_trial: jax.Array | None = None
    law_state: jax.Array | None = None
    misfit: jax.Array | None = None
    dfs_dfn: jax.Array | None = None
    internal: jax.Array | None = None
    R: jax.Array | None = None
    R_law: jax.Array | None = None
    stress: jax.Array | None = None
    bolt_force: jax.Array | None = None
    bolt_state: jax.Array | None = None
    bolt_length: jax.Array | None = None
    bolt_g: jax.Array | None = None
    bolt_Hv: jax.Array | None = None
    bolt_Hc: jax.Array | None = None
    bolt_rows: jax.Array | None = None


@functools.partial(jax.tree_util.register_dataclass, meta_fields=[], data_fields=[
    "geo", "prop", "Bn", "Bs", "fs_old", "fn0", "failed", "pw", "bolt", "load", "free", "stress",
    "Kc", "packed"])
@dataclasses.dataclass(frozen=True)
class Sub:
    """Everything fixed during one geometry sub-step (a pytree that lives inside jit).

    Contacts: ``geo`` (the detection's :class:`jaxdem.core._contact.Slots`), ``prop``
    (their springs and strengths, :class:`jaxdem.core.laws.SlotLaw`), rows ``Bn``, ``Bs``
    (S, 2 D; None where a sub-step's detection left them to
    :func:`jaxdem.core._substep.pack_slots`, which forms them for the touching slots),
    committed shear force ``fs_old``, initial normal force ``fn0``, ``failed``, water
    force ``pw`` (S,) (pore pressure x share, on joint slots). Bolts
    (when the scene has them): ``bolt``, :class:`Bolts`. ``load``: (N, D) external
    load. ``free``: (N,) blocks with degrees of freedom (not fixed, not excavated).
    ``stress``: (N, 3) committed stress of deformable blocks (tension positive);
    ``Kc``: their (N, 6, 6) stiffness (None for rigid blocks). ``packed``: None where
    the slots are the detection's P x 2 x V, in its order; else the touching slots
    alone, :class:`Packing` (:func:`jaxdem.core._substep.pack_slots`).
    """

    geo: Slots
    prop: SlotLaw
    Bn: jax.Array | None
    Bs: jax.Array | None
    fs_old: jax.Array
    fn0: jax.Array
    failed: jax.Array
    pw: jax.Array
    bolt: Bolts | None
    load: jax.Array
    free: jax.Array
    stress: jax.Array
    Kc: jax.Array | None
    packed: Packing | None = None


def cell_stiffness(model: Model, free):
    """(N, 6, 6) block-diagonal stiffness of deformable blocks: A D on the strains."""
    K = jnp.zeros((model.n_blocks, 6, 6), model.area.dtype)
    kc = (model.area * free)[:, None, None] * model.cell_D
    return K.at[:, 3:, 3:].set(kc)


def _bolt_kinematics(model: Model, sub: Sub, du):
    """Length L (B,), its gradient g (B, 2 D) and Hessian H in (du_a, du_b), as rank-one
    terms H = sum_t c_t v_t v_t^T: v (B, T, 2 D), c (B, T).

    g is the bolt's row (the elongation of a small move, which turns with the
    anchor-to-anchor line) and H its change: F H is the bolt's geometric
    stiffness, the string stiffness F / L across its line and the lever-arm
    terms of its anchors' rotations. Parts of blocks without degrees of freedom
    are zero.
    """
    bolt = sub.bolt
    D = model.ndof
    mask = jnp.concatenate([jnp.repeat(bolt.free_a[:, None], D, 1),
                            jnp.repeat(bolt.free_b[:, None], D, 1)], 1).astype(du.dtype)
    x = gather_pairs(du, bolt.a, bolt.b) * mask
    L, g, v, c = bolt_length_derivatives(D, bolt.d0, bolt.ra, bolt.rb, x)
    return L, g * mask, v * mask[:, None, :], c


def _bolt_law(model: Model, sub: Sub, L):
    """Bolt axial forces (kN/m, tension positive) and states from the current length L (m).

    Elastic, k (L - rest), between the compression it may carry (``bolt_comp``; 0: it
    goes slack, state 3) and its tension capacity min(yield, anchor capacity),
    where it is plastic (state 1 yielded, 2 pulled out; 4 yielded in compression):
    the plastic elongation is kept at commit (:func:`jaxdem.core._substep.commit_substep`),
    so that unloading is elastic from the yielded length.
    """
    bolt = sub.bolt
    trial = model.bolt_k * (L - bolt.rest)
    cap, comp = model.bolt_cap, model.bolt_comp
    force = jnp.where(bolt.active, jnp.clip(trial, -comp, cap), 0.0)
    state = jnp.select([trial > cap, (trial < 0) & (comp <= 0), trial < -comp],
                       [jnp.where(model.bolt_pullout, 2, 1), 3, 4], 0)
    state = jnp.where(bolt.active, state, 0)
    return force, state.astype(jnp.int32)


def bolt_rest_length(model: Model, sub: Sub, L, force, state):
    """The rest length after the step: plastic elongation or shortening kept."""
    k = model.bolt_k
    plastic = (state == 1) | (state == 2) | (state == 4)
    return jnp.where(sub.bolt.active & plastic, L - force / k, sub.bolt.rest)


def evaluate(model: Model, sub: Sub, du, frozen, frozen_state, prev, band,
             held=True) -> Springs:
    """Spring forces, states and the residual for a trial increment du (:class:`Springs`).

    The springs carry the effective normal force fn (compression positive):
    fn0 - kn * gap, through the tension cut-off and Mohr-Coulomb; the blocks
    also receive the water force pw on the faces of joint slots, open or
    closed (:func:`jaxdem.core.loads.water_force`). ``prev`` is the
    previous iterate's state and ``band`` the open/close hysteresis (kN/m) of
    :func:`jaxdem.core.laws.mohr_coulomb`. A ``frozen`` slot carries the forces of
    ``frozen_state`` (:func:`jaxdem.core.laws.forces_in_state`); ``misfit`` (kN/m)
    is how far they are from the law's, |d fn| + |d fs| (zero where not
    frozen), and ``R_law`` the residual with the law's forces everywhere. ``held`` (with
    ``model.events``): a spring with strength to lose that has not failed is elastic,
    the law of the Newton iteration (:func:`jaxdem.core.laws.held_elastic`); without
    it, the law itself (what a sub-step commits: a spring over its strength carries it).
    """
    geo = sub.geo
    dtype = sub.load.dtype
    # du may be wider than the scene's dtype (float64 in a float32 scene: _newton): the
    # springs' relative motions are formed in it, then rounded.
    x = gather_pairs(du, geo.a, geo.b)
    dn = jnp.sum(sub.Bn * x, axis=1).astype(dtype)
    ds = jnp.sum(sub.Bs * x, axis=1).astype(dtype)
    du = du.astype(dtype)
    gap = geo.gap + dn
    fn_trial = sub.fn0 - sub.prop.kn * gap
    fs_trial = sub.fs_old + sub.prop.ks * ds
    active = geo.active
    law = held_elastic(sub.prop) if held and model.events else sub.prop
    fn_l, fs_l, st_l = mohr_coulomb(fn_trial, fs_trial, law, sub.failed, active, prev, band)
    fn_f, fs_f = forces_in_state(fn_trial, fs_trial, law, sub.failed, frozen_state, band)
    fn = jnp.where(frozen, fn_f, fn_l)
    fs = jnp.where(frozen, fs_f, fs_l)
    st = jnp.where(frozen, frozen_state, st_l)
    # d fs / d fn_trial in the states held, with the same band as the forces
    # (forces_in_state gives the law's forces in the law's own states): the slip
    # coupling's (:func:`slip_coupling`). Taken without the band, a slot stuck within
    # the band above its strength got a coupling though its force is its trial force.
    def shear(fn_t):
        return forces_in_state(fn_t, fs_trial, law, sub.failed, st, band)[1]

    dfs_dfn = jax.jvp(shear, (fn_trial,), (jnp.ones_like(fn_trial),))[1]
    # Water presses on a joint's faces whether it is closed or open (within
    # the contact margin, where the slot is active): the springs carry only
    # the effective force. Tying pw to the closed state would make the force
    # jump by pw where a joint opens, and a slot whose water lifts its faces
    # apart would chatter open/closed with no equilibrium in either state.
    total_n = fn + sub.pw if model.has_water else fn
    d_n = jnp.where(frozen & active, fn_l - fn, 0.0)
    d_s = jnp.where(frozen & active, fs_l - fs, 0.0)
    internal = scatter_pairs(model.n_blocks, geo.a, geo.b,
                             sub.Bn * total_n[:, None] - sub.Bs * fs[:, None])
    to_law = scatter_pairs(model.n_blocks, geo.a, geo.b,
                           sub.Bn * d_n[:, None] - sub.Bs * d_s[:, None])
    bolts = {}
    if model.n_bolts:
        L, g, Hv, Hc = _bolt_kinematics(model, sub, du)
        bf, bst = _bolt_law(model, sub, L)
        bolt = sub.bolt
        bolt_rows = -g * bf[:, None]
        internal = internal + scatter_pairs(model.n_blocks, bolt.a, bolt.b, bolt_rows)
        bolts = dict(bolt_force=bf, bolt_state=bst, bolt_length=L, bolt_g=g, bolt_Hv=Hv,
                     bolt_Hc=Hc, bolt_rows=bolt_rows)
    stress = None
    if model.ndof == 6:
        # Deformable blocks: the stress (committed + D d_eps) resists the strains.
        dsig = jnp.einsum("nij,nj->ni", model.cell_D, du[:, 3:])
        internal = internal.at[:, 3:].add(-model.area[:, None] * (sub.stress + dsig))
        stress = sub.stress + dsig
    R = jnp.where(sub.free[:, None], sub.load + internal, 0.0)
    return Springs(fn=fn, fs=fs, state=st, gap=gap, total_n=total_n, fn_trial=fn_trial,
                   fs_trial=fs_trial, law_state=st_l, misfit=jnp.abs(d_n) + jnp.abs(d_s),
                   dfs_dfn=dfs_dfn, internal=internal, R=R,
                   R_law=jnp.where(sub.free[:, None], R + to_law, 0.0), stress=stress,
                   **bolts)


def block_residual(model: Model, R):
    """(N,) max(|Rx|, |Ry|, |M| / radius, |R_strain| / radius) of each block (kN/m)."""
    r = jnp.maximum(jnp.abs(R[:, 0]), jnp.abs(R[:, 1]))
    return jnp.maximum(r, jnp.max(jnp.abs(R[:, 2:]), axis=1) / model.radius)


def block_scale(model: Model, sub: Sub, ev: Springs | None = None):
    """(N,) force scale (kN/m) of each block's equilibrium test.

    The largest of the block's load and of the forces on it: spring forces
    (committed, in-situ and water; with ``ev`` also the current ones, |fn| +
    |fs|), bolt forces, and for a deformable block its stress times area over
    radius, measured like :func:`block_residual`. Each block is balanced to
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
        c = jnp.maximum(c, jnp.abs(ev.total_n) + jnp.abs(ev.fs))
    s = jnp.maximum(jnp.linalg.norm(sub.load[:, :2], axis=1),
                    jnp.max(jnp.abs(sub.load[:, 2:]), axis=1) / model.radius)
    s = jnp.maximum(s, per_block(jnp.where(sub.geo.active, c, 0.0), sub.geo.a,
                                 sub.geo.b))
    if model.n_bolts:
        bolt = sub.bolt
        f = jnp.abs(bolt.f_old)
        if ev is not None:
            f = jnp.maximum(f, jnp.abs(ev.bolt_force))
        s = jnp.maximum(s, per_block(jnp.where(bolt.active, f, 0.0), bolt.a, bolt.b))
    if model.ndof == 6:
        stress = jnp.abs(sub.stress) if ev is None else jnp.abs(ev.stress)
        s = jnp.maximum(s, jnp.max(stress, axis=1) * model.area / model.radius)
    return s


def stiffness_terms(model: Model, sub: Sub, ev: Springs, consistent, near=None, exact=False):
    """The iteration matrix K_t = sum_m k_m B_m B_m^T as rank-one terms (a, b, B, k).

    Closed slots carry both springs: for a slipping slot this is the elastic
    (secant) stiffness, which keeps every step of the order of the elastic
    compliance, unless its strength is under :data:`SLIP_SECANT` of its trial
    shear force (a joint at zero normal force: no shear spring). With
    ``consistent``, slipping slots lose their shear spring (and yielded bolts
    theirs): the tangent of the slip law (its symmetric part; the direct solvers
    add the coupling d fs / d fn = tan(phi) while it is tried,
    :func:`slip_coupling`; the cg path does without),
    tried once the states hold so that slip settles in a few iterations, and
    used once the elastic iteration stalls so that a sliding mechanism makes
    a finite move (bounded by the step length) instead of creeping at
    elastic speed. ``near`` (S,): open slots that keep their normal spring (an open
    slot within a few hysteresis bands of closing, :data:`jaxdem.core._substep.NEAR`).
    ``exact`` (with ``consistent``): a slot held stuck beyond its strength (frozen
    STICK, :func:`jaxdem.core.laws.forces_in_state`) carries the limit, which does not
    follow its shear displacement, and loses its shear spring too; without ``exact`` it
    keeps it (the stiffness of the state it is held in).
    """
    st = ev.state
    closed = sub.geo.active & (st != OPEN)
    kn = jnp.where(closed if near is None else closed | near, sub.prop.kn, 0.0)
    ks = jnp.where(closed & ((st == STICK) | ~consistent), sub.prop.ks, 0.0)
    # A slipping spring whose strength is under a hundredth of its trial shear
    # force (a joint at zero normal force) carries none of the shear that its
    # elastic spring would: it keeps no shear spring in the secant either.
    # Kept, it tied blocks that slide freely past each other (columns of a
    # grid whose vertices touch the next column's blocks across a joint):
    # a 4 x 100 grid took 72 iterations, a 100 x 100 one none within 240.
    free_slip = (closed & (st == SLIP)
                 & (jnp.abs(ev.fs) < SLIP_SECANT * jnp.abs(ev.fs_trial)))
    ks = jnp.where(free_slip, 0.0, ks)
    capped = closed & (st == STICK) & (jnp.abs(ev.fs) < jnp.abs(ev.fs_trial))
    ks = jnp.where(exact & consistent & capped, 0.0, ks)
    a, b = sub.geo.a, sub.geo.b
    terms = [(a, b, sub.Bn, kn), (a, b, sub.Bs, ks)]
    if model.n_bolts:
        terms.append(_bolt_terms(model, sub, ev, consistent))
    return [jnp.concatenate(x) for x in zip(*terms, strict=True)]


def _bolt_terms(model: Model, sub: Sub, ev: Springs, consistent):
    """The bolts' tangent as rank-one terms (a, b, v, lambda): 2 D a bolt.

    K_b = k g g^T + F H (:func:`_bolt_kinematics`): the axial spring (none for a
    plastic or slack bolt in the consistent tangent; the elastic one in the
    secant) and the geometric stiffness of its force, which holds a block hung
    on a bolt sideways (F / L) and in rotation. Symmetric, and written as rank-one
    terms already: g's and those of H (3 for rigid blocks, 7 for deformable ones, the
    rest of the 2 D places zero), so that every linear solver takes it as it takes the
    springs. Its negative part (a block hung below its centroid is unstable in rotation)
    is kept for the direct solvers and left out of the conjugate-gradient iteration,
    which needs a positive definite matrix (Newton then converges linearly there): for
    it, K_b's eigen-pairs with the negative eigenvalues set to zero.
    """
    bolt = sub.bolt
    D = model.ndof
    g, F = ev.bolt_g, ev.bolt_force
    axial = jnp.where(bolt.active & ((ev.bolt_state == 0) | ~consistent), model.bolt_k, 0.0)
    vec = jnp.concatenate([g[:, None, :], ev.bolt_Hv], 1)  # (B, T + 1, 2 D)
    lam = jnp.concatenate([axial[:, None], F[:, None] * ev.bolt_Hc], 1)
    lam = jnp.where(bolt.active[:, None], lam, 0.0)
    if model.linear_solver == "cg":
        lam, vec = jnp.linalg.eigh(bolt_hessian(vec, lam))
        lam, vec = jnp.maximum(lam, 0.0), jnp.swapaxes(vec, 1, 2)
    else:
        pad = 2 * D - vec.shape[1]
        vec = jnp.pad(vec, ((0, 0), (0, pad), (0, 0)))
        lam = jnp.pad(lam, ((0, 0), (0, pad)))
    nb = g.shape[0]
    return (*bolt_term_blocks(model, bolt), vec.reshape(nb * 2 * D, 2 * D), lam.reshape(-1))


def n_bolt_terms(model: Model) -> int:
    """Rank-one terms of the bolts at the end of a term list (:func:`_bolt_terms`)."""
    return model.n_bolts * 2 * model.ndof


def bolt_term_blocks(model: Model, bolt: Bolts):
    """The blocks (a, b) of the bolts' rank-one terms (:func:`_bolt_terms`): each bolt's
    two blocks once for each of its 2 D terms, in the bolts' order."""
    return jnp.repeat(bolt.a, 2 * model.ndof), jnp.repeat(bolt.b, 2 * model.ndof)


def slip_coupling(sub: Sub, ev: Springs, on):
    """The slip law's coupling where ``on``, as rank-one terms (a, b, L, Rt, k) = (a, b,
    Bs, Bn, kc): one a slot, zero but where it is closed and slipping.

    A slipping slot's shear force follows its normal force, d fs / d fn_trial =
    sign(fs) tan(phi) (:func:`jaxdem.core.laws.forces_in_state`), so the exact
    tangent has the unsymmetric terms -(d fs / d fn_trial) kn Bs Bn^T. With
    them Newton converges quadratically once the states hold, where the slip
    tangent's symmetric part converges linearly (about 0.7 an iteration).
    """
    closed = sub.geo.active & (ev.state != OPEN)
    kc = jnp.where(on & closed, -ev.dfs_dfn * sub.prop.kn, 0.0)
    return sub.geo.a, sub.geo.b, sub.Bs, sub.Bn, kc


def with_coupling(terms, coupling, S: int):
    """Symmetric terms (a, b, B, k) and a :func:`slip_coupling` group as one list (a, b,
    L, Rt, k): the coupling after the slots' two groups (2 S terms) and before the
    bolts, as :func:`jaxdem.core._linsolve.assemble_dense` expects."""
    a, b, B, k = terms
    cat = jnp.concatenate
    return tuple(cat([x[:2 * S], c, x[2 * S:]])
                 for x, c in zip((a, b, B, B, k), coupling, strict=True))


def with_slip_coupling(model: Model, sub: Sub, ev: Springs, terms, on):
    """``terms`` (a, b, B, k) with the slip law's coupling added where ``on``: (a, b, L, Rt, k)
    (:func:`slip_coupling`, :func:`with_coupling`)."""
    return with_coupling(terms, slip_coupling(sub, ev, on), sub.geo.a.shape[0])
