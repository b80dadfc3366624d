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
  until a sub-step converges (|R| <= tol F_ref, no state change) with a
  negligible du, or a block has travelled ``max_displacement`` (mechanism).

eps M only shapes the path: the converged answer solves R = 0 whatever eps
is, and where K_t is singular (a free block, a sliding mechanism) it turns
the step into a finite move along the mechanism, which the step length
bounds. A slot whose state flips four times in one sub-step is frozen in its
last state for the rest of that sub-step, which ends open/close chatter.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.contact import broad_phase, narrow_phase, remap_history
from jaxdem.laws import forces_in_state, mohr_coulomb, slot_properties
from jaxdem.state import OPEN, SLIP, STICK, Loads, Model, State, grow_capacity


class Status(enum.IntEnum):
    """Outcome of an increment, with the message shown to the user."""

    CONVERGED = 0
    MECHANISM = 1
    ITERATION_LIMIT = 2
    CAPACITY_OVERFLOW = 3
    NON_FINITE = 4

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


@dataclasses.dataclass(frozen=True)
class _Sub:
    """Everything fixed during one geometry sub-step (not a pytree: lives inside jit).

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


def _bolt_law(model: Model, sub: _Sub, du):
    """Bolt axial forces, tension positive: elastic to min(yield, anchor capacity), then plastic."""
    bolt = sub.bolt
    elong = jnp.sum(bolt["B"] * _gather(du, bolt["a"], bolt["b"]), axis=1)
    trial = bolt["f_old"] + model.bolt_k * elong
    over = jnp.abs(trial) > model.bolt_cap
    force = jnp.where(bolt["active"], jnp.clip(trial, -model.bolt_cap, model.bolt_cap), 0.0)
    state = jnp.where(bolt["active"] & over, jnp.where(model.bolt_pullout, 2, 1), 0)
    return force, state.astype(jnp.int32)


def _evaluate(model: Model, sub: _Sub, du, frozen, frozen_state, prev, band):
    """Spring forces, states and the residual for a trial increment du.

    The springs carry the effective normal force fn (compression positive):
    fn0 - kn * gap, through the tension cut-off and Mohr-Coulomb; the blocks
    also receive the water force pw on closed joint faces. ``prev`` is the
    previous iterate's state and ``band`` the open/close hysteresis (kN/m) of
    :func:`jaxdem.laws.mohr_coulomb`.
    """
    geo = sub.geo
    x = _gather(du, geo["a"], geo["b"])
    dn = jnp.sum(sub.Bn * x, axis=1)
    ds = jnp.sum(sub.Bs * x, axis=1)
    gap = geo["gap"] + dn
    fn_trial = sub.fn0 - sub.prop["kn"] * gap
    fs_trial = sub.fs_old + sub.prop["ks"] * ds
    active = geo["active"]
    fn, fs, st = mohr_coulomb(fn_trial, fs_trial, sub.prop, sub.failed, active, prev, band)
    fn_f, fs_f = forces_in_state(fn_trial, fs_trial, sub.prop, sub.failed, frozen_state)
    fn = jnp.where(frozen, fn_f, fn)
    fs = jnp.where(frozen, fs_f, fs)
    st = jnp.where(frozen, frozen_state, st)
    total_n = fn + jnp.where(st != OPEN, sub.pw, 0.0) if model.has_water else fn
    internal = _scatter(model.n_blocks, geo["a"], geo["b"],
                        sub.Bn * total_n[:, None] - sub.Bs * fs[:, None])
    out = dict(fn=fn, fs=fs, state=st, gap=gap, fn_trial=fn_trial, total_n=total_n)
    if model.n_bolts:
        bf, bst = _bolt_law(model, sub, du)
        bolt = sub.bolt
        internal = internal + _scatter(model.n_blocks, bolt["a"], bolt["b"],
                                       -bolt["B"] * bf[:, None])
        out.update(bolt_force=bf, bolt_state=bst)
    if model.ndof == 6:
        # Deformable blocks: the stress (committed + D d_eps) resists the strains.
        dsig = jnp.einsum("nij,nj->ni", model.cell_D, du[:, 3:])
        internal = internal.at[:, 3:].add(-model.area[:, None] * (sub.stress + dsig))
        out["stress"] = sub.stress + dsig
    out["internal"] = internal
    out["R"] = jnp.where(sub.free[:, None], sub.load + internal, 0.0)
    return out


def _residual_norm(model: Model, free, R):
    """max over blocks of max(|Rx|, |Ry|, |M| / radius, |R_strain| / radius) (kN/m)."""
    r = jnp.maximum(jnp.abs(R[:, 0]), jnp.abs(R[:, 1]))
    r = jnp.maximum(r, jnp.max(jnp.abs(R[:, 2:]), axis=1) / model.radius)
    return jnp.max(jnp.where(free, r, 0.0))


def _stiffness_terms(model: Model, sub: _Sub, ev, consistent):
    """The iteration matrix K_t = sum_m k_m B_m B_m^T as rank-one terms (a, b, B, k).

    Closed slots carry both springs: for a slipping slot this is the elastic
    (secant) stiffness, which keeps every step of the order of the elastic
    compliance. With ``consistent``, slipping slots lose their shear spring
    (and yielded bolts theirs): the tangent of the slip law, used once the
    elastic iteration has stalled, so that a sliding mechanism makes a finite
    move (bounded by the step length) instead of creeping at elastic speed.
    """
    st = ev["state"]
    closed = sub.geo["active"] & (st != OPEN)
    kn = jnp.where(closed, sub.prop["kn"], 0.0)
    ks = jnp.where(closed & ((st == STICK) | ~consistent), sub.prop["ks"], 0.0)
    a, b = sub.geo["a"], sub.geo["b"]
    terms = [(a, b, sub.Bn, kn), (a, b, sub.Bs, ks)]
    if model.n_bolts:
        bolt = sub.bolt
        kb = jnp.where(bolt["active"] & ((ev["bolt_state"] == 0) | ~consistent), model.bolt_k, 0.0)
        terms.append((bolt["a"], bolt["b"], bolt["B"], kb))
    return [jnp.concatenate(x) for x in zip(*terms, strict=True)]


def _solve_dense(model: Model, sub: _Sub, terms, R):
    """(K_t + eps M)^-1 R by Cholesky on the assembled (D N, D N) matrix."""
    N, D = model.n_blocks, model.ndof
    a, b, B, k = terms
    Ke = k[:, None, None] * B[:, :, None] * B[:, None, :]
    dofs = jnp.concatenate([D * a[:, None] + jnp.arange(D), D * b[:, None] + jnp.arange(D)],
                           axis=1)
    K = jnp.zeros((D * N, D * N), R.dtype).at[dofs[:, :, None], dofs[:, None, :]].add(Ke)
    if sub.Kc is not None:
        own = D * jnp.arange(N)[:, None] + jnp.arange(D)
        K = K.at[own[:, :, None], own[:, None, :]].add(sub.Kc)
    freeD = jnp.repeat(sub.free, D)
    diag = jnp.where(freeD, model.pseudo_mass.reshape(-1), 1.0)
    K = K + jnp.diag(diag)
    c = jax.scipy.linalg.cho_factor(K)
    return jax.scipy.linalg.cho_solve(c, R.reshape(-1)).reshape(N, D)


def _host_sparse_solve(a, b, B, k, Kc, diag, rhs):
    """Assemble K = sum_m k_m B_m B_m^T + blockdiag(Kc) + diag(diag) on the host and solve.

    Only springs with k != 0 enter, so the padded slot list costs nothing.
    The factorisation is SciPy's SuperLU (minimum-degree ordering of K + K^T).
    CPU only: on a GPU the matrix would travel to the host (use "cg" there).
    """
    import scipy.sparse
    import scipy.sparse.linalg

    a, b, B, k, Kc, diag, rhs = (np.asarray(x) for x in (a, b, B, k, Kc, diag, rhs))
    n = rhs.shape[-1]
    D = B.shape[1] // 2
    on = k != 0
    a, b, B, k = a[on], b[on], B[on], k[on]
    dofs = np.concatenate([D * a[:, None] + np.arange(D), D * b[:, None] + np.arange(D)], axis=1)
    rows = [np.repeat(dofs, 2 * D, axis=1).ravel()]
    cols = [np.tile(dofs, (1, 2 * D)).ravel()]
    vals = [(k[:, None, None] * B[:, :, None] * B[:, None, :]).ravel()]
    if Kc.size:
        own = D * np.arange(n // D)[:, None] + np.arange(D)
        rows.append(np.repeat(own, D, axis=1).ravel())
        cols.append(np.tile(own, (1, D)).ravel())
        vals.append(Kc.ravel())
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals.append(diag)
    K = scipy.sparse.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    # K is symmetric positive definite: symmetric ordering, no pivoting (ten
    # times faster than SuperLU's default partial pivoting).
    lu = scipy.sparse.linalg.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                  options=dict(SymmetricMode=True))
    return lu.solve(rhs).astype(rhs.dtype)


def _solve_sparse(model: Model, sub: _Sub, terms, R):
    """(K_t + eps M)^-1 R by a sparse direct solve (SciPy's SuperLU through a host callback).

    Fill-in of a 2D contact graph is mild, so cost and memory grow about
    linearly with the number of blocks, and a direct solve does not slow down
    near a mechanism as an iterative one does. The springs go to the host as
    rank-one terms (12 numbers each, not their 144 matrix entries) and are
    assembled there; vmap solves batch members one after another.
    """
    a, b, B, k = terms
    D = model.ndof
    Kc = sub.Kc if sub.Kc is not None else jnp.zeros((0, D, D), R.dtype)
    diag = jnp.where(jnp.repeat(sub.free, D), model.pseudo_mass.reshape(-1), 1.0)
    rhs = R.reshape(-1)
    x = jax.pure_callback(_host_sparse_solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                          a, b, B, k, Kc, diag, rhs, vmap_method="sequential")
    return x.reshape(R.shape)


def _solve_cg(model: Model, sub: _Sub, terms, R):
    """(K_t + eps M)^-1 R by conjugate gradients, matrix-free, block-Jacobi preconditioned.

    The product K x is a gather/scatter over the springs: cost and memory
    linear in the number of contacts.
    """
    N, nd = model.n_blocks, model.ndof
    a, b, B, k = terms
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
    D = D + jax.vmap(jnp.diag)(pm)
    Dinv = jnp.linalg.inv(D)

    def precond(x):
        return jnp.einsum("nij,nj->ni", Dinv, x)

    # Inexact Newton: the outer iteration corrects what CG leaves; float32
    # cannot resolve 1e-10.
    rtol = 1e-10 if R.dtype == jnp.float64 else 1e-5
    x, _ = jax.scipy.sparse.linalg.cg(matvec, R, M=precond, tol=rtol, maxiter=4 * N + 200)
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
    solve = dict(dense=_solve_dense, sparse=_solve_sparse, cg=_solve_cg)[model.linear_solver]
    # Force scale of the convergence test: the largest block load, or the
    # largest carried spring force (an in-situ state has large contact forces
    # and no net load), whichever is larger.
    load = jnp.where(sub.free, jnp.linalg.norm(sub.load[:, :2], axis=1), 0.0)
    carried = jnp.max(jnp.abs(sub.fn0) + jnp.abs(sub.fs_old), initial=0.0)
    tol = model.tol * jnp.maximum(jnp.maximum(jnp.max(load), carried), model.f_ref * 1e-3)
    band = 0.1 * tol
    zeros_s = jnp.zeros(S, jnp.int32)
    allow = 0.02 * model.step_length
    # A small block moves at most a quarter of its radius per sub-step.
    step = jnp.minimum(model.step_length, 0.25 * model.radius)

    def cond(c):
        return ~c["done"]

    def body(c):
        ev = _evaluate(model, sub, c["du"], c["frozen"], c["frozen_state"], c["st"], band)
        changed = (ev["state"] != c["st"]) & sub.geo["active"]
        rnorm = _residual_norm(model, sub.free, ev["R"])
        converged = (rnorm <= tol) & ~jnp.any(changed)
        flips = c["flips"] + changed.astype(jnp.int32)
        newly = (flips >= 4) & ~c["frozen"]
        frozen = c["frozen"] | newly
        frozen_state = jnp.where(newly, ev["state"], c["frozen_state"])
        # Three iterations in a row without progress or state change: the
        # secant iteration has stalled on a mechanism; take the slip tangent.
        slow = (rnorm > 0.98 * c["rprev"]) & ~jnp.any(changed)
        stall = jnp.where(slow, c["stall"] + 1, 0)
        ddu = solve(model, sub, _stiffness_terms(model, sub, ev, stall >= 3), ev["R"])
        t_now = _travel(model, c["du"])
        t_step = _travel(model, ddu)
        room = jnp.maximum(step - t_now, 0.0)
        s_travel = jnp.min(jnp.where(t_step > room, room / jnp.where(t_step > 0, t_step, 1.0), 1.0))
        # An open slot may close during the step, but not sink deeper than a
        # small allowance: a free block lands on its support, it does not
        # plunge a whole step length into it.
        dn_step = jnp.sum(sub.Bn * _gather(ddu, sub.geo["a"], sub.geo["b"]), axis=1)
        g_pred = ev["gap"] + dn_step
        landing = sub.geo["active"] & (ev["state"] == OPEN) & (ev["gap"] > 0) & (g_pred < -allow)
        drop = jnp.where(landing, ev["gap"] - g_pred, 1.0)
        s_gap = jnp.min(jnp.where(landing, (ev["gap"] + allow) / drop, 1.0))
        scale = jnp.minimum(s_travel, s_gap)
        clipped = (s_travel <= s_gap) & (s_travel < 1.0)
        du = jnp.where(converged, c["du"], c["du"] + scale * ddu)
        finite = jnp.all(jnp.isfinite(du))
        it = c["it"] + 1
        done = converged | clipped | ~finite | (it >= model.max_iterations)
        return dict(du=du, st=ev["state"], flips=flips, frozen=frozen, frozen_state=frozen_state,
                    it=it, done=done, converged=converged, clipped=clipped & ~converged,
                    finite=finite, rnorm=rnorm / tol * model.tol, rprev=rnorm, stall=stall)

    init = dict(du=jnp.zeros((N, model.ndof), sub.load.dtype), st=st0, flips=zeros_s,
                frozen=jnp.zeros(S, bool), frozen_state=zeros_s, it=jnp.array(0),
                done=jnp.array(False), converged=jnp.array(False), clipped=jnp.array(False),
                finite=jnp.array(True), rnorm=jnp.array(jnp.inf, sub.load.dtype),
                rprev=jnp.array(jnp.inf, sub.load.dtype), stall=jnp.array(0))
    c = jax.lax.while_loop(cond, body, init)
    ev = _evaluate(model, sub, c["du"], c["frozen"], c["frozen_state"], c["st"], band)
    return c["du"], ev, c


def _rotate(r, angle):
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([cos * r[..., 0] - sin * r[..., 1], sin * r[..., 0] + cos * r[..., 1]], -1)


def _move(state: State, du, stress=None):
    """Move every block by du: exact rigid motion (ux, uy, theta) about its centroid.

    A deformable block is first strained by (eps_x, eps_y, gamma_xy) about its
    centroid (which stays its centroid); its strain and ``stress`` (the new
    stress, tension positive) then turn with the block.
    """
    th = du[:, 2]
    r = state.verts - state.centroid[:, None, :]
    strain, new_stress = state.strain, state.stress
    if du.shape[1] == 6:
        e = du[:, 3:]
        r = r + strain_times(e[:, None, :], r)
        tensor = lambda v: v * jnp.array([1.0, 1.0, 0.5], v.dtype)  # noqa: E731
        engineering = lambda v: v * jnp.array([1.0, 1.0, 2.0], v.dtype)  # noqa: E731
        strain = engineering(_rotate_tensor(tensor(state.strain + e), th))
        new_stress = _rotate_tensor(stress, th)
    centroid = state.centroid + du[:, :2]
    verts = centroid[:, None, :] + _rotate(r, th[:, None])
    return dataclasses.replace(state, verts=verts, centroid=centroid,
                               u=state.u + du[:, :2], rot=state.rot + th, strain=strain,
                               stress=new_stress)


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


def _substep(model: Model, state: State, loads: Loads):
    """Detect contacts, iterate to equilibrium at fixed geometry, commit the motion."""
    N = model.n_blocks
    free = model.free & state.alive
    mdl = dataclasses.replace(model, free=free)
    pairs, count, cell_full = broad_phase(mdl, state.verts, state.capacity, state.alive)
    hist = remap_history(state, pairs, N)
    geo = narrow_phase(mdl, state.verts, state.centroid, pairs)
    prop = slot_properties(mdl, geo)
    flat = lambda x: x.reshape(-1)  # noqa: E731
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
        bolt = dict(a=bg["a"], b=bg["b"], f_old=state.bolt_force, active=alive_b,
                    B=b_rows(free, bg["a"], bg["b"], bg["point_a"], bg["point_b"], bg["e"],
                             state.centroid, D))
    sub = _Sub(geo=geo, prop=prop, Bn=Bn, Bs=Bs, fs_old=fs_old, fn0=fn0, failed=failed, pw=pw,
               bolt=bolt, load=jnp.where(free[:, None], loads.force, 0.0), free=free,
               stress=state.stress, Kc=_cell_stiffness(model, free) if D == 6 else None)
    du, ev, c = _newton(mdl, sub, st0)
    st = ev["state"]
    active = geo["active"]
    opened = (st == OPEN) & ((prop["tension"] > 0) | (ev["gap"] > model.touch_tol))
    failed_new = failed | (active & ~prop["bonded"] & ((st == SLIP) | opened))
    moved = _move(state, du, ev.get("stress"))
    shape = state.fs.shape
    new_state = dataclasses.replace(
        moved, pairs=pairs, fs=ev["fs"].reshape(shape), fn=ev["fn"].reshape(shape),
        fn0=fn0.reshape(shape), failed=failed_new.reshape(shape),
        edge=geo["edge"].reshape(shape), cstate=st.reshape(shape),
        present=active.reshape(shape))
    if model.n_bolts:
        new_state = dataclasses.replace(new_state, bolt_force=ev["bolt_force"],
                                        bolt_state=ev["bolt_state"])
    # Global balance (about the origin) of the free blocks: applied loads and
    # the forces from blocks without degrees of freedom (bolts anchored in
    # them included).
    c_xy = state.centroid
    moment = lambda F: F[:, 2] + _cross(c_xy, F[:, :2])  # noqa: E731
    a, b = geo["a"], geo["b"]
    f_row = Bn * ev["total_n"][:, None] - Bs * ev["fs"][:, None]
    reaction = (jax.ops.segment_sum(jnp.where((~free[b])[:, None], f_row[:, :3], 0.0), a, N)
                + jax.ops.segment_sum(jnp.where((~free[a])[:, None], f_row[:, D:D + 3], 0.0),
                                      b, N))
    if model.n_bolts:
        rows = -bolt["B"] * ev["bolt_force"][:, None]
        reaction = reaction + (
            jax.ops.segment_sum(jnp.where((~free[bolt["b"]])[:, None], rows[:, :3], 0.0),
                                bolt["a"], N)
            + jax.ops.segment_sum(jnp.where((~free[bolt["a"]])[:, None], rows[:, D:D + 3], 0.0),
                                  bolt["b"], N))
    balance = dict(
        applied=jnp.stack([sub.load[:, 0].sum(), sub.load[:, 1].sum(), moment(sub.load).sum()]),
        reaction=jnp.stack([reaction[:, 0].sum(), reaction[:, 1].sum(), moment(reaction).sum()]),
        scale=jnp.maximum(jnp.sum(jnp.linalg.norm(reaction[:, :2], axis=1)),
                          jnp.sum(jnp.linalg.norm(sub.load[:, :2], axis=1))),
    )
    snapshot = dict(point=geo["point"], normal=geo["normal"], a=a, b=b, active=active,
                    fn=ev["fn"], fs=ev["fs"], pw=ev["total_n"] - ev["fn"], state=st)
    need = dict(pairs=count, cell_full=cell_full)
    return new_state, du, c, need, balance, snapshot


@jax.jit
def increment(model: Model, state: State, loads: Loads):
    """One load increment: geometry sub-steps until equilibrium under ``loads``.

    Returns (state, info): info holds ``status`` (a Status value), ``iterations``
    (Newton iterations), ``substeps``, ``residual`` (relative), ``travel``
    (N,) path length of each block in this increment (m), ``balance`` and the
    final contact ``snapshot``.
    """
    N = model.n_blocks
    dtype = state.verts.dtype
    _, _, _, _, balance0, snap0 = jax.eval_shape(_substep, model, state, loads)
    zeros_like = lambda t: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), t)  # noqa: E731

    def cond(c):
        return c["status"] < 0

    def body(c):
        st_new, du, newton, need, balance, snap = _substep(model, c["state"], loads)
        overflow = (need["pairs"] > state.capacity) | need["cell_full"]
        travel = c["travel"] + _travel(model, du)
        small = jnp.max(_travel(model, du)) <= model.touch_tol
        stuck = jnp.where(newton["converged"] | newton["clipped"], 0, c["stuck"] + 1)
        substeps = c["substeps"] + 1
        # The first outcome that holds ends the increment; -1 goes on.
        status = jnp.select(
            [overflow, ~newton["finite"], newton["converged"] & small,
             jnp.max(travel) > model.max_displacement,
             (stuck >= 3) | (substeps >= model.max_substeps)],
            [Status.CAPACITY_OVERFLOW, Status.NON_FINITE, Status.CONVERGED, Status.MECHANISM,
             Status.ITERATION_LIMIT],
            -1)
        keep = overflow | ~newton["finite"]
        new = jax.tree.map(lambda o, n: jnp.where(keep, o, n), c["state"], st_new)
        return dict(state=new, status=status, substeps=substeps, stuck=stuck,
                    iterations=c["iterations"] + newton["it"], travel=travel,
                    residual=newton["rnorm"], balance=balance, snapshot=snap,
                    pairs_needed=jnp.maximum(c["pairs_needed"], need["pairs"]),
                    cell_full=c["cell_full"] | need["cell_full"])

    init = dict(state=state, status=jnp.array(-1), substeps=jnp.array(0), stuck=jnp.array(0),
                iterations=jnp.array(0), travel=jnp.zeros(N, dtype),
                residual=jnp.array(jnp.inf, dtype), balance=zeros_like(balance0),
                snapshot=zeros_like(snap0), pairs_needed=jnp.array(0), cell_full=jnp.array(False))
    c = jax.lax.while_loop(cond, body, init)
    info = {k: c[k] for k in ("status", "substeps", "iterations", "travel", "residual",
                              "balance", "snapshot", "pairs_needed", "cell_full")}
    return c["state"], info


# ---------------------------------------------------------------------------
# Host driver

_COMPILED: dict = {}


def _compiled_increment(model: Model, state: State, loads: Loads):
    """The compiled increment for these shapes and static settings, and its compile time (s)."""
    leaves, tree = jax.tree.flatten((model, state, loads))
    key = (tree, tuple((x.shape, str(x.dtype)) for x in leaves))
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    fn = increment.lower(model, state, loads).compile()
    _COMPILED[key] = fn
    return fn, time.perf_counter() - t0


def run_increment(model: Model, state: State, loads: Loads):
    """One increment with capacity growth: on overflow, grow and redo from ``state``.

    Returns (model, state, info, compile_s): the model changes only when a
    grid cell capacity grew. Growing recompiles; nothing is ever truncated.
    """
    compile_s = 0.0
    while True:
        fn, dt = _compiled_increment(model, state, loads)
        compile_s += dt
        new, info = fn(model, state, loads)
        if int(info["status"]) != Status.CAPACITY_OVERFLOW:
            return model, new, info, compile_s
        if bool(info["cell_full"]):
            model = dataclasses.replace(model, cell_capacity=2 * model.cell_capacity)
        need = int(info["pairs_needed"])
        if need > state.capacity:
            state = grow_capacity(state, max(2 * state.capacity, int(1.3 * need) + 16))


def _imbalance(balance) -> float:
    """Global force balance of the free blocks, relative.

    |applied + reaction| over the larger of the summed magnitudes of the
    block loads and of the reactions (forces from fixed blocks, walls and
    their bolts), so that it stays meaningful when the loads cancel out (an
    in-situ state held by walls on all sides).
    """
    applied = np.asarray(balance["applied"][:2])
    reaction = np.asarray(balance["reaction"][:2])
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
    dtype = model.radius.dtype
    no_water = jnp.array([0.0, 1.0], dtype), jnp.array([-1e30, -1e30], dtype)
    return Loads(
        force=jnp.asarray(force, dtype),
        water_x=no_water[0] if water_x is None else jnp.asarray(water_x, dtype),
        water_y=no_water[1] if water_y is None else jnp.asarray(water_y, dtype),
        water_scale=jnp.asarray(water_scale, dtype),
        bolt_active=(jnp.ones(model.n_bolts, bool) if bolt_active is None
                     else jnp.asarray(bolt_active)))


class _Driver:
    """Host loop over stages and load steps; collects the records of a Result."""

    def __init__(self, model, state, layout, scene, progress):
        self.model, self.state, self.layout = model, state, layout
        self.scene, self.progress = scene, progress
        self.compile_s = self.solve_s = 0.0
        self.records, self.history = [], []
        self.info = None
        self.ref = None  # the state displacements are measured from (None: the start)
        self.status = Status.CONVERGED
        nb = model.n_bolts
        self.bolt_active = np.zeros(nb, bool)
        water = scene.water
        tables = ([water.table] if water is not None else []) + [
            st.water_table for st in scene.stages if st.water_table is not None]
        xs = np.unique(np.concatenate([np.asarray(t, float)[:, 0] for t in tables])) \
            if tables else np.array([0.0, 1.0])
        self.water_x = xs
        self.water_y = (np.interp(xs, *np.asarray(water.table, float).T)
                        if water is not None else np.full(xs.shape, -1e30))

    def loads(self, force, water_y=None, water_scale=1.0):
        wy = self.water_y if water_y is None else water_y
        return make_loads(self.model, force, self.water_x, wy, self.bolt_active, water_scale)

    def step(self, stage, k, n, loads):
        from jaxdem.results import monitor_values

        t1 = time.perf_counter()
        self.model, self.state, info, dt = run_increment(self.model, self.state, loads)
        jax.block_until_ready(self.state.verts)
        self.compile_s += dt
        self.solve_s += time.perf_counter() - t1 - dt
        self.info = info
        self.status = Status(int(info["status"]))
        rec = dict(stage=stage, step=k, load_factor=k / n, status=self.status,
                   iterations=int(info["iterations"]), substeps=int(info["substeps"]),
                   residual=float(info["residual"]), imbalance=_imbalance(info["balance"]))
        self.records.append(rec)
        self.history.append(dict(stage=stage, step=k, load_factor=k / n,
                                 monitors=monitor_values(self.layout, self.state, self.ref)))
        if self.progress is not None:
            self.progress(dict(stage=stage, step=k, n_steps=n, status=self.status.label,
                               iterations=rec["iterations"], substeps=rec["substeps"],
                               residual=rec["residual"]))
        return self.status == Status.CONVERGED


def _excavation_release(model, state, snapshot, removed):
    """Forces (N, D) that the blocks being removed exert on the others (from the snapshot)."""
    snap = {k: np.asarray(v) for k, v in snapshot.items()}
    cen = np.asarray(state.centroid)
    out = np.zeros((cen.shape[0], model.ndof))
    act = snap["active"]
    a, b, p, n = snap["a"][act], snap["b"][act], snap["point"][act], snap["normal"][act]
    t = np.stack([-n[:, 1], n[:, 0]], axis=1)
    F = (snap["fn"][act] + snap["pw"][act])[:, None] * n - snap["fs"][act][:, None] * t
    for on, by, sign in ((a, b, 1.0), (b, a, -1.0)):
        sel = removed[by] & ~removed[on]
        f = sign * F[sel]
        # |f| times the row of its unit direction: the generalised force of f.
        mag = np.linalg.norm(f, axis=1)
        unit = f / np.maximum(mag, 1e-300)[:, None]
        row = np.asarray(point_row(p[sel] - cen[on[sel]], unit, model.ndof))
        np.add.at(out, on[sel], mag[:, None] * row)
    return out


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
    from jaxdem import model as model_mod
    from jaxdem.results import build_result

    if set:
        scene = scene.with_overrides(set)
    t0 = time.perf_counter()
    model, state, layout = model_mod.build(scene)
    jax.block_until_ready(state.verts)
    build_s = time.perf_counter() - t0
    d = _Driver(model, state, layout, scene, progress)
    n_rock = layout.n_rock
    N = model.n_blocks
    in_situ = scene.in_situ
    D = model.ndof
    base = np.zeros((N, D))
    pending = np.zeros((N, D))  # applied over the first stage (uniform in-situ mode)
    if in_situ is None:
        n = layout.load_steps
        for k in range(1, n + 1):
            # Pore pressure grows with the weight: a saturated slope is loaded
            # as a whole, not by full water pressure on a weightless mass.
            loads = d.loads(k / n * (layout.weight + layout.traction), water_scale=k / n)
            if not d.step("loading", k, n, loads):
                break
        base = layout.weight + layout.traction
    else:
        if in_situ.mode == "gravity":
            base = layout.weight + layout.traction
            mats = [layout.materials[i] for i in range(n_rock) if layout.excavation[i] is None]
            gamma = scene.materials[scene.domain.material if scene.domain else mats[0]].unit_weight
            surface = in_situ.surface_y
        else:
            base, pending = layout.traction, layout.weight
            gamma = surface = 0.0
        sigma = jnp.asarray([in_situ.sigma_xx, in_situ.sigma_yy, in_situ.sigma_xy], layout.dtype)
        while True:
            st, overflow = _preload(d.model, d.state, d.loads(base), sigma, surface, gamma,
                                    in_situ.k0, mode=in_situ.mode)
            if not bool(overflow):
                break
            d.state = grow_capacity(d.state, 2 * d.state.capacity)
        d.state = st
        d.step("initial", 1, 1, d.loads(base))
    plan = _stage_plan(scene)
    # Displacements count from the state before the first stage, once there
    # is one and the loading before it found equilibrium.
    started = (plan or in_situ is not None) and d.status == Status.CONVERGED
    d.ref = d.state if started else None
    for stage in plan:
        if d.status != Status.CONVERGED:
            break
        removed = np.zeros(N, bool)
        removed[:n_rock] = [e is not None and e in stage["excavations"] for e in layout.excavation]
        release = _excavation_release(d.model, d.state, d.info["snapshot"], removed) \
            if removed.any() and d.info is not None else np.zeros((N, D))
        if removed.any():
            alive = np.asarray(d.state.alive) & ~removed
            d.state = dataclasses.replace(d.state, alive=jnp.asarray(alive))
        for b, bs in enumerate(layout.bolt_stages):
            if bs == stage["name"] or (bs is None and stage["first"]):
                d.bolt_active[b] = True
        support = sum((sp["force"] for sp in layout.supports
                       if sp["stage"] == stage["name"] or (sp["stage"] is None and stage["first"])),
                      np.zeros((N, D)))
        y_old, y_new = d.water_y, d.water_y
        if stage["water_table"] is not None:
            y_new = np.interp(d.water_x, *np.asarray(stage["water_table"], float).T)
        n = stage["load_steps"] or layout.load_steps
        for k in range(1, n + 1):
            lam = k / n
            force = base + (1 - lam) * release + lam * (pending + support)
            if not d.step(stage["name"], k, n, d.loads(force, (1 - lam) * y_old + lam * y_new)):
                break
        base, pending = base + pending + support, np.zeros((N, D))
        d.water_y = y_new
    timing = dict(build_s=build_s, compile_s=d.compile_s, solve_s=d.solve_s)
    return build_result(scene, d.model, layout, d.state, d.ref, d.info, d.records, d.history,
                        timing)


def _stage_plan(scene) -> list[dict]:
    """The stages after the initial state, in order, with what each one does."""
    excavations = scene.excavations
    stages = list(scene.stages)
    if not stages and (excavations or scene.supports
                       or scene.bolts):
        return [dict(name="excavation", first=True, load_steps=None, water_table=None,
                     excavations={e.name for e in excavations})]
    first = stages[0].name if stages else None
    return [dict(name=st.name, first=st.name == first, load_steps=st.load_steps,
                 water_table=st.water_table,
                 excavations={e.name for e in excavations
                              if e.stage == st.name or (e.stage is None and st.name == first)})
            for st in stages]
