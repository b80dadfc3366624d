"""Forward-mode sensitivities of a sub-step, the in-situ preload and the release.

Owns the lists of smooth fields (:data:`SMOOTH_MODEL`, :data:`STATE_FLOATS`,
:data:`LOAD_FLOATS`, :data:`jaxdem.core.state.SNAPSHOT_FLOATS`), :func:`substep_tangent` (each
converged sub-step differentiated implicitly with its contact states held),
:func:`_sub_tangents` (the derivatives of a sub-step's data, from its active
slots alone),
the solve with the exact tangent (:func:`_tangent_solve`), and the
derivatives of :func:`jaxdem.core.loads.in_situ_preload` and
:func:`jaxdem.core.loads.release_forces`.

Data flow: takes the sub-step (:mod:`jaxdem.core._substep`), the springs, the
assembly of :mod:`jaxdem.core._linsolve` and the loads; used by
:func:`jaxdem.core.increment.increment_tangent`, the host driver
(:mod:`jaxdem.solver`) and :mod:`jaxdem.differentiable`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.core._contact import remap_history, slot_geometry
from jaxdem.core._linsolve import (
    assemble_dense,
    blocks_times,
    host_matrix,
    sparse_lu,
    stiffness_blocks,
)
from jaxdem.core._springs import Sub, evaluate, stiffness_terms, with_slip_coupling
from jaxdem.core._substep import (
    block_fields_of,
    commit_substep,
    force_scales,
    newton_and_commit,
    prepare_substep,
    slot_fields_of,
)
from jaxdem.core.laws import has_strength
from jaxdem.core.loads import in_situ_preload, release_forces
from jaxdem.core.state import (
    SNAPSHOT_FLOATS,
    STICK,
    Loads,
    Model,
    Snapshot,
    State,
    float_part,
)

# Model fields that scene parameters change smoothly (see jaxdem.differentiable).
SMOOTH_MODEL = ("joint_kn", "joint_ks", "joint_c", "joint_t", "joint_tanphi", "kn_inv", "ks_inv",
                "cell_D", "bolt_k", "bolt_cap", "bolt_comp", "gamma_w")
STATE_FLOATS = ("verts", "centroid", "u", "rot", "fs", "fn", "fn0", "bolt_force", "bolt_rest",
                "strain", "stress")
LOAD_FLOATS = ("force", "water_y")


def _fields(obj, names) -> dict:
    return {k: getattr(obj, k) for k in names}


def _tangent_terms(model: Model, sub: Sub, ev):
    """The exact tangent K = -dR/d(du) with the slots' states held, as terms (a, b, L, R, k).

    The slip tangent (:func:`jaxdem.core._springs.stiffness_terms` with ``consistent``: both
    springs of a sticking slot, the normal one of a slipping slot, none of an
    open one; elastic bolts) with the slip law's coupling d fs / d fn_trial =
    sign(fs) tan(phi), which makes K unsymmetric (:func:`jaxdem.core._springs.with_slip_coupling`):
    the matrix Newton's tried tangent uses on the direct paths.
    """
    terms = stiffness_terms(model, sub, ev, True)
    return with_slip_coupling(model, sub, ev, terms, jnp.ones((), bool))


TANGENT_REFINEMENTS = 2
"""Refinement steps of the sensitivity solve on its regularised factorisation (see
:func:`_tangent_solve`): each multiplies the regularisation's error by eps / lambda."""


def _host_tangent_solve(rows, cols, blocks, pm, rhs):
    """:func:`_tangent_solve` on the host: SuperLU of K + eps M, refined on K; NaN if singular."""
    import scipy.sparse
    import scipy.sparse.linalg

    pm, rhs = np.asarray(pm), np.asarray(rhs)
    K = host_matrix(rows, cols, blocks, rhs.shape[0])
    try:
        lu = scipy.sparse.linalg.splu(K + scipy.sparse.diags(pm, format="csc"),
                                      permc_spec="MMD_AT_PLUS_A")
    except RuntimeError:  # "Factor is exactly singular": no derivative here
        return np.full_like(rhs, np.nan)
    x = lu.solve(rhs)
    for _ in range(TANGENT_REFINEMENTS):
        x = x + lu.solve(rhs - K @ x)
    return np.where(np.all(np.isfinite(x)), x, np.nan).astype(rhs.dtype)


def _tangent_solve(model: Model, sub: Sub, terms, rhs):
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
    The dense path factorises with LU in the program, the others with KLU in the
    program (sparsax; SciPy's SuperLU on the host where sparsax is not installed).
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
        K = assemble_dense(model, sub, a, b, L, Rt, k, diag)
        lu = jax.scipy.linalg.lu_factor(K + jnp.diag(pm))
        x = jax.scipy.linalg.lu_solve(lu, B)
        for _ in range(TANGENT_REFINEMENTS):
            x = x + jax.scipy.linalg.lu_solve(lu, B - K @ x)
        x = jnp.where(jnp.all(jnp.isfinite(x)), x, jnp.nan)
    else:
        rows, cols, blocks = stiffness_blocks(model, sub, a, b, L, Rt, k, diag)
        # K + eps M: the pseudo-mass added to K's own diagonal blocks (the last N).
        pm_blocks = pm.reshape(N, D)[:, :, None] * jnp.eye(D, dtype=blocks.dtype)
        solve = sparse_lu(model, rows, cols, blocks.at[-N:].add(pm_blocks))
        if solve is None:  # without sparsax: SciPy's SuperLU on the host
            x = jax.pure_callback(_host_tangent_solve, jax.ShapeDtypeStruct(B.shape, B.dtype),
                                  rows, cols, blocks, pm, B, vmap_method="sequential")
        else:
            x = solve(B)
            for _ in range(TANGENT_REFINEMENTS):
                x = x + solve(B - blocks_times(model, rows, cols, blocks, x))
            x = jnp.where(jnp.all(jnp.isfinite(x)), x, jnp.nan)
    return x.T.reshape(rhs.shape)


ACTIVE_SHARE = 4
"""The sensitivities differentiate the active slots gathered into S / ACTIVE_SHARE places
(all of them where there are more: :func:`_sub_tangents`)."""


def _sub_tangents(model: Model, state: State, loads: Loads, sub: Sub, pairs, primals, tangents,
                  active_share: int = ACTIVE_SHARE):
    """Derivatives (p, ...) of the float leaves of a sub-step's data (:func:`prepare_substep`).

    ``primals`` are the smooth fields (model, state, loads) and ``tangents`` their
    derivatives. Only the active slots carry forces, so only theirs matter: an
    inactive slot's spring is open whatever its geometry (the held state of
    :func:`substep_tangent`), and its force and derivative are zero. The active
    slots are few of the S = P x 2 V (most candidate pairs are near but not
    touching, most vertices of a touching pair touch nothing: 598 of 4608 in the
    back-analysis benchmark's tunnel), so they are
    gathered into S / ``active_share`` places and differentiated there
    (:func:`jaxdem.core._contact.slot_geometry`, the same expressions as the
    detection), at the price of their primal; the rest get zeros (so do the
    derivatives of their points and normals in the contact snapshot, which
    carry no force and which the release masks out). A sub-step with more
    active slots differentiates all of them (the whole detection, linearised).
    The two agree (tests/test_differentiable.py); on the back-analysis benchmark's
    tunnel this cut a solve with 6 sensitivities from 1.77 to 1.46 plain solves.
    """
    N, V = model.n_blocks, model.n_vertices
    S = sub.geo.active.shape[0]
    C = -(-S // active_share)
    slot_fields = ("geo", "prop", "Bn", "Bs", "fs_old", "fn0", "failed", "pw")

    def rebuilt(mf, sf, lf):
        """The model, state and loads with these smooth fields."""
        return (dataclasses.replace(model, **mf), dataclasses.replace(state, **sf),
                dataclasses.replace(loads, **lf))

    def compact():
        sid = jnp.nonzero(sub.geo.active, size=C, fill_value=S)[0]
        at = jnp.minimum(sid, S - 1)
        # The slots' choices (the geometry's values are evaluated again below).
        chosen = jax.tree.map(lambda v: v[at], sub.geo)
        vertex = (at % V).astype(jnp.int32)

        def part(mf, sf, lf):
            m, s, ld = rebuilt(mf, sf, lf)
            free = m.free & s.alive
            mdl = dataclasses.replace(m, free=free)
            hist = jax.tree.map(lambda v: v.reshape(-1)[at], remap_history(s, pairs, N))
            geo = slot_geometry(mdl, s.verts, s.centroid, chosen, vertex)
            geo, slots, _ = slot_fields_of(mdl, s, ld, geo, hist)
            return floats_of(Sub(geo=geo, **slots, **block_fields_of(m, s, ld, free)))

        _, lin = jax.linearize(part, *primals)
        d = jax.vmap(lin)(*tangents)
        out = []
        for (name, full), x in zip(_named_floats(sub), d, strict=True):
            if name in slot_fields:
                x = jnp.zeros(x.shape[:1] + full.shape, x.dtype).at[:, sid].set(x, mode="drop")
            out.append(x)
        return out

    def whole():
        _, lin = jax.linearize(lambda *f: floats_of(prepare_substep(*rebuilt(*f))[1]), *primals)
        return jax.vmap(lin)(*tangents)

    return jax.lax.cond(jnp.sum(sub.geo.active) <= C, compact, whole)


def _named_floats(sub: Sub) -> list:
    """(field, leaf) for the float leaves of a sub-step's data, in tree order."""
    return [(path[0].name, x) for path, x in jax.tree_util.tree_leaves_with_path(sub)
            if jnp.issubdtype(x.dtype, jnp.inexact)]


def floats_of(sub: Sub) -> list:
    """The float leaves of a sub-step's data, in tree order (the smooth ones)."""
    return [x for _, x in _named_floats(sub)]


def substep_tangent(model: Model, state: State, loads: Loads, dmodel, dstate, dloads,
                    active_share: int = ACTIVE_SHARE, warm=False):
    """:func:`jaxdem.core._substep.substep` and the derivatives of its new state and snapshot.

    Returns (the outputs of :func:`jaxdem.core._substep.substep`, (dstate, dsnapshot)); see
    :func:`jaxdem.core.increment.increment_tangent`. ``active_share``: see
    :func:`_sub_tangents`; ``warm``: see :func:`jaxdem.core._substep._newton`.
    """
    mf0, sf0, lf0 = (_fields(model, SMOOTH_MODEL), _fields(state, STATE_FLOATS),
                     _fields(loads, LOAD_FLOATS))

    # Geometry, detection and history: the candidate pairs and each slot's choices
    # (face, state) are integers, with no derivative. The forward sub-step iterates
    # on the primal; the derivatives of its data are those of the active slots
    # alone (:func:`_sub_tangents`).
    mdl, sub, st0, pairs, found = prepare_substep(model, state, loads)
    forward = newton_and_commit(mdl, state, sub, st0, pairs, found, warm)
    new_state, du, converged = forward[0], forward[1], forward[2].converged
    held = new_state.cstate.reshape(-1)
    all_held = jnp.ones(held.shape, bool)
    # Event by event (``model.events``) the iteration balanced the blocks with the
    # springs that have strength to lose held elastic (stuck: :func:`jaxdem.core.laws.
    # held_elastic`), and committed the law's forces: one loaded beyond its strength
    # carries it (in ``held``, slipping or open). The equilibrium is differentiated in the
    # iteration's states, the commit in the law's. Both in the committed states, the
    # equilibrium was another one: a jointed tunnel's derivatives were 8.6e-4 off (a
    # joint's normal stiffness) to 76% (its cohesion; tests/test_differentiable.py).
    iterated = held
    if model.events:
        iterated = jnp.where(has_strength(sub.prop) & ~sub.failed & sub.geo.active, STICK,
                             held)
    leaves, tree = jax.tree.flatten(sub)
    smooth = [jnp.issubdtype(x.dtype, jnp.inexact) for x in leaves]

    def with_floats(fl):
        it = iter(fl)
        return tree.unflatten([next(it) if f else x for x, f in zip(leaves, smooth, strict=True)])

    dsub = _sub_tangents(model, state, loads, sub, pairs, (mf0, sf0, lf0), (dmodel, dstate, dloads),
                         active_share)

    # Equilibrium and commit at fixed geometry, in the held states.
    def settle(mf, fl, sf, x):
        m = dataclasses.replace(model, **mf)
        sb = with_floats(fl)
        mdl = dataclasses.replace(m, free=sb.free)
        s = dataclasses.replace(state, **sf)
        # The held states with the forward's band: a slot stuck within the band
        # above its strength carries its trial force there, and here too.
        band = jax.lax.stop_gradient(force_scales(mdl, sb)[1])
        ev = evaluate(mdl, sb, x, all_held, iterated, iterated, band)
        committed = ev
        if model.events:
            committed = evaluate(mdl, sb, x, all_held, held, held, band, held=False)
        new, _, snap = commit_substep(mdl, s, sb, pairs, x, committed)
        return (ev.R, _fields(new, STATE_FLOATS), float_part(snap)), ev

    # Linearised apart in the parameters (at the converged du) and in du: each
    # evaluates only its own tangent paths, where one linearisation in all four
    # would carry zero tangents through the other's.
    fl0 = floats_of(sub)
    _, lin_p, ev = jax.linearize(lambda mf, fl, sf: settle(mf, fl, sf, du), mf0, fl0, sf0,
                                 has_aux=True)
    dR, ds1, dsnap1 = jax.vmap(lin_p)(dmodel, dsub, dstate)
    # Out here, its primal is the one above (XLA computes it once).
    _, lin_x = jax.linearize(lambda x: settle(mf0, fl0, sf0, x)[0][1:], du)

    def implicit():
        ddu = _tangent_solve(mdl, sub, _tangent_terms(mdl, sub, ev), dR)
        ds2, dsnap2 = jax.vmap(lin_x)(ddu)
        add = lambda x, y: jax.tree.map(jnp.add, x, y)  # noqa: E731
        return add(ds1, ds2), add(dsnap1, dsnap2)

    # A sub-step cut short by the step length is held fixed (its du has no
    # derivative): it needs neither the tangent's factorisation nor the chain
    # through du (17 of the 26 sub-steps of the back-analysis benchmark's solve).
    return forward, jax.lax.cond(converged, implicit, lambda: (ds1, dsnap1))


@functools.partial(jax.jit, static_argnames=("mode",))
def preload_tangent(model: Model, state: State, loads: Loads, args, dmodel, dloads, dargs,
                    mode: str):
    """:func:`jaxdem.core.loads.in_situ_preload` (its state and overflow flag) and its state's
    derivatives.

    The derivatives are (p, ...), one per parameter.

    args = (sigma, surface_y, gamma, k0) and dargs their derivatives (p, ...).
    One compiled call: the plain :func:`jaxdem.core.loads.in_situ_preload` runs op by op
    (compiling it
    would cost seconds for a millisecond saved in a single solve), and the
    linearisation gives its values with the derivatives.
    """
    def pre(mf, lf, a):
        m = dataclasses.replace(model, **mf)
        ld = dataclasses.replace(loads, **lf)
        new, overflow = in_situ_preload(m, state, ld, *a, mode=mode)
        return _fields(new, STATE_FLOATS), (new, overflow)

    primals = (_fields(model, SMOOTH_MODEL), _fields(loads, LOAD_FLOATS), args)
    _, lin, (new, overflow) = jax.linearize(pre, *primals, has_aux=True)
    return new, overflow, jax.vmap(lin)(dmodel, dloads, dargs)


@functools.partial(jax.jit, static_argnames=("ndof",))
def release_with_tangent(centroid, snap: Snapshot, removed, dcentroid, dsnap: Snapshot, ndof):
    """:func:`jaxdem.core.loads.release_forces` (N, D) and its derivatives (p, N, D)."""
    def rel(c, floats):
        merged = snap._replace(**{k: getattr(floats, k) for k in SNAPSHOT_FLOATS})
        return release_forces(c, merged, removed, ndof)

    floats = float_part(snap)
    value = rel(centroid, floats)
    tangent = jax.vmap(lambda dc, ds: jax.jvp(rel, (centroid, floats), (dc, ds))[1])(
        dcentroid, dsnap)
    return value, tangent
