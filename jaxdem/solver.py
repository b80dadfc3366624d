"""Incremental static solver: increment (jitted), load steps, and the host driver.

One increment applies the load factor ``lam`` and looks for static
equilibrium with large displacements:

  repeat (geometry sub-steps, ``lax.while_loop``):
    detect contacts at the current geometry, carry each slot's history;
    Newton iteration on the increment du of the free blocks
    (``lax.while_loop``): trial spring forces from the gaps and the
    committed shear forces, tension cut-off and Mohr-Coulomb, residual
    R = lam F_ext + sum B^T f; solve (K_t + eps M) ddu = R, where K_t is the
    tangent of the current states (open: none; slipping: normal spring only,
    which keeps K_t symmetric) and eps M a small pseudo-mass;
    the step is shortened so that no block travels more than
    ``step_length`` in one sub-step;
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
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.contact import broad_phase, narrow_phase, remap_history
from jaxdem.laws import forces_in_state, mohr_coulomb, slot_properties
from jaxdem.state import OPEN, SLIP, STICK, Model, State, grow_capacity


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


def b_rows(model: Model, geo: dict, centroid):
    """Rows of B mapping (du_a, du_b) to the relative normal and shear displacement.

    For direction v at contact point p: v . (u_a + theta_a x r_a) - v . (u_b + theta_b x r_b),
    r = p - centroid. Parts of blocks without degrees of freedom are zeroed.
    Returns Bn, Bs: (S, 6).
    """
    a, b, p = geo["a"], geo["b"], geo["point"]
    ra, rb = p - centroid[a], p - centroid[b]
    fa = model.free[a][:, None].astype(p.dtype)
    fb = model.free[b][:, None].astype(p.dtype)

    def row(v):
        pa = jnp.concatenate([v, _cross(ra, v)[:, None]], axis=1) * fa
        pb = -jnp.concatenate([v, _cross(rb, v)[:, None]], axis=1) * fb
        return jnp.concatenate([pa, pb], axis=1)

    return row(geo["normal"]), row(geo["tangent"])


def _gather(du, geo):
    return jnp.concatenate([du[geo["a"]], du[geo["b"]]], axis=1)


def _scatter(model: Model, geo, x6):
    """Sum (S, 6) slot vectors into (N, 3) block vectors."""
    N = model.n_blocks
    return (jax.ops.segment_sum(x6[:, :3], geo["a"], N)
            + jax.ops.segment_sum(x6[:, 3:], geo["b"], N))


@dataclasses.dataclass(frozen=True)
class _Sub:
    """Everything fixed during one geometry sub-step (not a pytree: lives inside jit)."""

    geo: dict
    prop: dict
    Bn: jax.Array
    Bs: jax.Array
    fs_old: jax.Array
    failed: jax.Array
    load: jax.Array


def _evaluate(model: Model, sub: _Sub, du, frozen, frozen_state, prev, band):
    """Spring forces, states and the residual for a trial increment du.

    ``prev`` is the previous iterate's state and ``band`` the open/close
    hysteresis (kN/m) of :func:`jaxdem.laws.mohr_coulomb`.
    """
    x = _gather(du, sub.geo)
    dn = jnp.sum(sub.Bn * x, axis=1)
    ds = jnp.sum(sub.Bs * x, axis=1)
    gap = sub.geo["gap"] + dn
    fn_trial = -sub.prop["kn"] * gap
    fs_trial = sub.fs_old + sub.prop["ks"] * ds
    active = sub.geo["active"]
    fn, fs, st = mohr_coulomb(fn_trial, fs_trial, sub.prop, sub.failed, active, prev, band)
    fn_f, fs_f = forces_in_state(fn_trial, fs_trial, sub.prop, sub.failed, frozen_state)
    fn = jnp.where(frozen, fn_f, fn)
    fs = jnp.where(frozen, fs_f, fs)
    st = jnp.where(frozen, frozen_state, st)
    internal = _scatter(model, sub.geo, sub.Bn * fn[:, None] - sub.Bs * fs[:, None])
    R = jnp.where(model.free[:, None], sub.load + internal, 0.0)
    return dict(fn=fn, fs=fs, state=st, R=R, gap=gap, fn_trial=fn_trial, internal=internal)


def _residual_norm(model: Model, R):
    """max over blocks of max(|Rx|, |Ry|, |M| / radius) (kN/m)."""
    r = jnp.maximum(jnp.abs(R[:, 0]), jnp.abs(R[:, 1]))
    r = jnp.maximum(r, jnp.abs(R[:, 2]) / model.radius)
    return jnp.max(jnp.where(model.free, r, 0.0))


def _tangent_springs(sub: _Sub, st, consistent):
    """Normal and shear springs of the iteration matrix K_t.

    Closed slots carry both springs: for a slipping slot this is the elastic
    (secant) stiffness, which keeps every step of the order of the elastic
    compliance. With ``consistent``, slipping slots lose their shear spring:
    the tangent of the slip law, used once the elastic iteration has stalled,
    so that a sliding mechanism makes a finite move (bounded by the step
    length) instead of creeping at elastic speed.
    """
    closed = sub.geo["active"] & (st != OPEN)
    kn = jnp.where(closed, sub.prop["kn"], 0.0)
    ks = jnp.where(closed & ((st == STICK) | ~consistent), sub.prop["ks"], 0.0)
    return kn, ks


def _solve_dense(model: Model, sub: _Sub, st, consistent, R):
    """(K_t + eps M)^-1 R by Cholesky on the assembled (3N, 3N) matrix."""
    N = model.n_blocks
    kn, ks = _tangent_springs(sub, st, consistent)
    Ke = (kn[:, None, None] * sub.Bn[:, :, None] * sub.Bn[:, None, :]
          + ks[:, None, None] * sub.Bs[:, :, None] * sub.Bs[:, None, :])
    a, b = sub.geo["a"], sub.geo["b"]
    dofs = jnp.concatenate([3 * a[:, None] + jnp.arange(3), 3 * b[:, None] + jnp.arange(3)], axis=1)
    K = jnp.zeros((3 * N, 3 * N), R.dtype).at[dofs[:, :, None], dofs[:, None, :]].add(Ke)
    free3 = jnp.repeat(model.free, 3)
    diag = jnp.where(free3, model.pseudo_mass.reshape(-1), 1.0)
    K = K + jnp.diag(diag)
    c = jax.scipy.linalg.cho_factor(K)
    return jax.scipy.linalg.cho_solve(c, R.reshape(-1)).reshape(N, 3)


def _solve_cg(model: Model, sub: _Sub, st, consistent, R):
    """(K_t + eps M)^-1 R by conjugate gradients, matrix-free, block-Jacobi preconditioned.

    The product K x is a gather/scatter over the slots: cost and memory linear
    in the number of contacts.
    """
    kn, ks = _tangent_springs(sub, st, consistent)
    pm = jnp.where(model.free[:, None], model.pseudo_mass, 1.0)

    def matvec(x):
        xs = _gather(x, sub.geo)
        y6 = (sub.Bn * (kn * jnp.sum(sub.Bn * xs, 1))[:, None]
              + sub.Bs * (ks * jnp.sum(sub.Bs * xs, 1))[:, None])
        y = _scatter(model, sub.geo, y6)
        return jnp.where(model.free[:, None], y, 0.0) + pm * x

    def block(B, k, part):
        Bp = B[:, part]
        return k[:, None, None] * Bp[:, :, None] * Bp[:, None, :]

    N = model.n_blocks
    D = (jax.ops.segment_sum(block(sub.Bn, kn, slice(0, 3)) + block(sub.Bs, ks, slice(0, 3)),
                             sub.geo["a"], N)
         + jax.ops.segment_sum(block(sub.Bn, kn, slice(3, 6)) + block(sub.Bs, ks, slice(3, 6)),
                               sub.geo["b"], N))
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
    """Largest vertex displacement of each block for a rigid increment du (m), bounded above."""
    return jnp.sqrt(du[:, 0] ** 2 + du[:, 1] ** 2) + jnp.abs(du[:, 2]) * model.radius


def _newton(model: Model, sub: _Sub, st0):
    """Newton iteration on du at fixed geometry (one sub-step).

    Returns du, the final evaluation, whether it converged, whether the step
    length cut it short, and the iteration count.
    """
    S = st0.shape[0]
    N = model.n_blocks
    solve = _solve_dense if model.dense else _solve_cg
    load = jnp.where(model.free, jnp.linalg.norm(sub.load[:, :2], axis=1), 0.0)
    tol = model.tol * jnp.maximum(jnp.max(load), model.f_ref * 1e-3)
    band = 0.1 * tol
    zeros_s = jnp.zeros(S, jnp.int32)
    allow = 0.02 * model.step_length

    def cond(c):
        return ~c["done"]

    def body(c):
        ev = _evaluate(model, sub, c["du"], c["frozen"], c["frozen_state"], c["st"], band)
        changed = (ev["state"] != c["st"]) & sub.geo["active"]
        rnorm = _residual_norm(model, ev["R"])
        converged = (rnorm <= tol) & ~jnp.any(changed)
        flips = c["flips"] + changed.astype(jnp.int32)
        newly = (flips >= 4) & ~c["frozen"]
        frozen = c["frozen"] | newly
        frozen_state = jnp.where(newly, ev["state"], c["frozen_state"])
        stalled = (rnorm > 0.9 * c["rprev"]) & ~jnp.any(changed)
        ddu = solve(model, sub, ev["state"], stalled, ev["R"])
        t_now = _travel(model, c["du"])
        t_step = _travel(model, ddu)
        room = jnp.maximum(model.step_length - t_now, 0.0)
        s_travel = jnp.min(jnp.where(t_step > room, room / jnp.where(t_step > 0, t_step, 1.0), 1.0))
        # An open slot may close during the step, but not sink deeper than a
        # small allowance: a free block lands on its support, it does not
        # plunge a whole step length into it.
        dn_step = jnp.sum(sub.Bn * _gather(ddu, sub.geo), axis=1)
        g_pred = ev["gap"] + dn_step
        landing = sub.geo["active"] & (ev["state"] == OPEN) & (ev["gap"] > 0) & (g_pred < -allow)
        drop = jnp.where(landing, ev["gap"] - g_pred, 1.0)
        s_gap = jnp.min(jnp.where(landing, (ev["gap"] + allow) / drop, 1.0))
        scale = jnp.minimum(s_travel, s_gap)
        clipped = s_travel <= s_gap
        clipped = clipped & (s_travel < 1.0)
        du = jnp.where(converged, c["du"], c["du"] + scale * ddu)
        finite = jnp.all(jnp.isfinite(du))
        it = c["it"] + 1
        done = converged | clipped | ~finite | (it >= model.max_iterations)
        return dict(du=du, st=ev["state"], flips=flips, frozen=frozen, frozen_state=frozen_state,
                    it=it, done=done, converged=converged, clipped=clipped & ~converged,
                    finite=finite, rnorm=rnorm / tol * model.tol, rprev=rnorm)

    init = dict(du=jnp.zeros((N, 3), sub.load.dtype), st=st0, flips=zeros_s,
                frozen=jnp.zeros(S, bool), frozen_state=zeros_s, it=jnp.array(0),
                done=jnp.array(False), converged=jnp.array(False), clipped=jnp.array(False),
                finite=jnp.array(True), rnorm=jnp.array(jnp.inf, sub.load.dtype),
                rprev=jnp.array(jnp.inf, sub.load.dtype))
    c = jax.lax.while_loop(cond, body, init)
    ev = _evaluate(model, sub, c["du"], c["frozen"], c["frozen_state"], c["st"], band)
    return c["du"], ev, c


def _move(state: State, du):
    """Exact rigid motion of every block by (ux, uy, theta) about its centroid."""
    th = du[:, 2]
    cos, sin = jnp.cos(th), jnp.sin(th)
    r = state.verts - state.centroid[:, None, :]
    rx = cos[:, None] * r[..., 0] - sin[:, None] * r[..., 1]
    ry = sin[:, None] * r[..., 0] + cos[:, None] * r[..., 1]
    centroid = state.centroid + du[:, :2]
    verts = centroid[:, None, :] + jnp.stack([rx, ry], axis=-1)
    return dataclasses.replace(state, verts=verts, centroid=centroid,
                               u=state.u + du[:, :2], rot=state.rot + th)


def _substep(model: Model, state: State, lam):
    """Detect contacts, iterate to equilibrium at fixed geometry, commit the motion."""
    N = model.n_blocks
    pairs, count, cell_full = broad_phase(model, state.verts, state.capacity)
    hist = remap_history(state, pairs, N)
    geo = narrow_phase(model, state.verts, state.centroid, pairs)
    prop = slot_properties(model, geo)
    flat = lambda x: x.reshape(-1)  # noqa: E731
    same = flat(hist["present"]) & (flat(hist["edge"]) == geo["edge"]) & geo["active"]
    failed = jnp.where(same, flat(hist["failed"]), geo["gap"] > model.touch_tol)
    fs_old = jnp.where(same, flat(hist["fs"]), 0.0)
    # A new slot starts closed where its faces touch: round-off in a gap of
    # zero must not leave a block resting on its support without springs.
    st0 = jnp.where(same, flat(hist["cstate"]),
                    jnp.where(geo["gap"] <= model.touch_tol, STICK, OPEN))
    Bn, Bs = b_rows(model, geo, state.centroid)
    sub = _Sub(geo=geo, prop=prop, Bn=Bn, Bs=Bs, fs_old=fs_old, failed=failed,
               load=lam * model.f_ext)
    du, ev, c = _newton(model, sub, st0)
    st = ev["state"]
    active = geo["active"]
    opened = (st == OPEN) & ((prop["tension"] > 0) | (ev["gap"] > model.touch_tol))
    failed_new = failed | (active & ~prop["bonded"] & ((st == SLIP) | opened))
    moved = _move(state, du)
    shape = state.fs.shape
    new_state = dataclasses.replace(
        moved, pairs=pairs, fs=ev["fs"].reshape(shape), fn=ev["fn"].reshape(shape),
        failed=failed_new.reshape(shape), edge=geo["edge"].reshape(shape),
        cstate=st.reshape(shape), present=active.reshape(shape))
    # Global balance (about the origin) of the free blocks: applied loads and
    # the forces from blocks without degrees of freedom.
    c_xy = state.centroid
    moment = lambda F: F[:, 2] + _cross(c_xy, F[:, :2])  # noqa: E731
    applied = jnp.where(model.free[:, None], sub.load, 0.0)
    a, b = geo["a"], geo["b"]
    f_on_a = Bn[:, :3] * ev["fn"][:, None] - Bs[:, :3] * ev["fs"][:, None]
    f_on_b = Bn[:, 3:] * ev["fn"][:, None] - Bs[:, 3:] * ev["fs"][:, None]
    from_fixed_a = jnp.where((~model.free[b])[:, None], f_on_a, 0.0)
    from_fixed_b = jnp.where((~model.free[a])[:, None], f_on_b, 0.0)
    reaction = (jax.ops.segment_sum(from_fixed_a, a, N) + jax.ops.segment_sum(from_fixed_b, b, N))
    balance = dict(
        applied=jnp.stack([applied[:, 0].sum(), applied[:, 1].sum(), moment(applied).sum()]),
        reaction=jnp.stack([reaction[:, 0].sum(), reaction[:, 1].sum(), moment(reaction).sum()]),
    )
    snapshot = dict(point=geo["point"], normal=geo["normal"], a=a, b=b, active=active,
                    fn=ev["fn"], fs=ev["fs"], state=st)
    need = dict(pairs=count, cell_full=cell_full)
    return new_state, du, c, need, balance, snapshot


@jax.jit
def increment(model: Model, state: State, lam):
    """One load increment at load factor ``lam``: geometry sub-steps until equilibrium.

    Returns (state, info): info holds ``status`` (a Status value), ``iterations``
    (Newton iterations), ``substeps``, ``residual`` (relative), ``travel``
    (N,) path length of each block in this increment (m), ``balance`` and the
    final contact ``snapshot``.
    """
    N = model.n_blocks
    dtype = state.verts.dtype
    _, _, _, _, balance0, snap0 = jax.eval_shape(_substep, model, state, lam)
    zeros_like = lambda t: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), t)  # noqa: E731

    def cond(c):
        return c["status"] < 0

    def body(c):
        st_new, du, newton, need, balance, snap = _substep(model, c["state"], lam)
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


def _compiled_increment(model: Model, state: State, lam):
    """The compiled increment for these shapes and static settings, and its compile time (s)."""
    leaves, tree = jax.tree.flatten((model, state, lam))
    key = (tree, tuple((x.shape, str(x.dtype)) for x in leaves))
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    fn = increment.lower(model, state, lam).compile()
    _COMPILED[key] = fn
    return fn, time.perf_counter() - t0


def run_increment(model: Model, state: State, lam):
    """One increment with capacity growth: on overflow, grow and redo from ``state``.

    Returns (model, state, info, compile_s): the model changes only when a
    grid cell capacity grew. Growing recompiles; nothing is ever truncated.
    """
    compile_s = 0.0
    lam = jnp.asarray(lam, state.verts.dtype)
    while True:
        fn, dt = _compiled_increment(model, state, lam)
        compile_s += dt
        new, info = fn(model, state, lam)
        if int(info["status"]) != Status.CAPACITY_OVERFLOW:
            return model, new, info, compile_s
        if bool(info["cell_full"]):
            model = dataclasses.replace(model, cell_capacity=2 * model.cell_capacity)
        need = int(info["pairs_needed"])
        if need > state.capacity:
            state = grow_capacity(state, max(2 * state.capacity, int(1.3 * need) + 16))


def _imbalance(balance) -> float:
    """|applied + reaction| / |applied| of the forces on the free blocks (relative)."""
    applied = np.asarray(balance["applied"][:2])
    reaction = np.asarray(balance["reaction"][:2])
    return float(np.linalg.norm(applied + reaction) / max(np.linalg.norm(applied), 1e-300))


def solve(scene, set: dict | None = None, progress=None):
    """Solve a scene: load steps of self-weight and tractions, each to static equilibrium.

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
    from jaxdem.results import build_result, monitor_values

    if set:
        scene = scene.with_overrides(set)
    t0 = time.perf_counter()
    model, state, layout = model_mod.build(scene)
    jax.block_until_ready(state.verts)
    build_s = time.perf_counter() - t0
    compile_s = solve_s = 0.0
    n = layout.load_steps
    history, increments = [], []
    info = None
    for k in range(1, n + 1):
        lam = k / n
        t1 = time.perf_counter()
        model, state, info, dt = run_increment(model, state, lam)
        status = Status(int(info["status"]))
        jax.block_until_ready(state.verts)
        compile_s += dt
        solve_s += time.perf_counter() - t1 - dt
        increments.append(dict(step=k, load_factor=lam, status=status,
                               iterations=int(info["iterations"]),
                               substeps=int(info["substeps"]),
                               residual=float(info["residual"]),
                               imbalance=_imbalance(info["balance"])))
        history.append(dict(stage="loading", step=k, load_factor=lam,
                            monitors=monitor_values(layout, state)))
        if progress is not None:
            progress(dict(stage="loading", step=k, n_steps=n, status=status.label,
                          iterations=int(info["iterations"]), substeps=int(info["substeps"]),
                          residual=float(info["residual"])))
        if status != Status.CONVERGED:
            break
    timing = dict(build_s=build_s, compile_s=compile_s, solve_s=solve_s)
    return build_result(scene, model, layout, state, info, increments, history, timing)
