"""The jitted increment: geometry sub-steps until equilibrium under one load step.

One increment applies the loads of one load step (block forces, water table,
installed bolts) and looks for static equilibrium with large displacements:

  repeat (geometry sub-steps: a ``lax.fori_loop`` to ``max_substeps`` whose body is
  skipped once the increment has ended, a ``lax.while_loop`` in a batch):
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
  force scale, with the springs' forces of the law) with a negligible du, or a block has
  travelled its ``travel_limit`` (mechanism: ``max_displacement``, or by default its own
  size, or its group's where blocks move together:
  :func:`jaxdem.core.kinematics.group_limits`).

Owns :func:`increment` and :func:`increment_tangent` (jitted), the loop of
sub-steps :func:`substeps_to_equilibrium` that sets the :class:`jaxdem.core.status.Status` of
the increment, and :func:`_joint_motion` (largest joint slip and opening); it hands the
host's loop ``bounded_factorisations`` (:mod:`jaxdem.core._linsolve`), which holds
sparsax's memory while an increment runs.

Data flow: takes one sub-step from :mod:`jaxdem.core._substep` (and its
derivatives from :mod:`jaxdem.core.sensitivities`) and the tolerances of
:mod:`jaxdem.core.status`; the host driver (:mod:`jaxdem.solver`) and
:mod:`jaxdem.batch` compile and call it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxdem.core._linsolve import bounded_factorisations  # noqa: F401 (for the host's loop)
from jaxdem.core._substep import Unbalanced, substep
from jaxdem.core.compile_cache import on_disk
from jaxdem.core.kinematics import block_travel, group_limits, rotate_vectors
from jaxdem.core.sensitivities import substep_tangent
from jaxdem.core.state import Balance, Loads, Model, Snapshot, State, float_part
from jaxdem.core.status import (
    IMBALANCE_FACTOR,
    OVERLAP_TOL,
    STRENGTH_TOL,
    Status,
    global_imbalance_jax,
)


class JointMotion(NamedTuple):
    """The largest joint slip and opening of an increment (:func:`_joint_motion`): ``slip``
    (m), ``slip_rel`` (relative to the smaller block's size), ``slip_blocks`` (2,) the
    blocks where it is; ``opening`` (m), ``opening_blocks`` (2,)."""

    slip: jax.Array
    slip_rel: jax.Array
    slip_blocks: jax.Array
    opening: jax.Array
    opening_blocks: jax.Array


@on_disk("increment")
@jax.jit
def increment(model: Model, state: State, loads: Loads):
    """One load increment: geometry sub-steps until equilibrium under ``loads``.

    Returns (state, report): the report is the loop's :class:`Progress` at its end,
    its ``state`` taken out (returned apart) and its ``joints`` in.
    """
    return substeps_to_equilibrium(model, state, loads)


@on_disk("increment_tangent")
@jax.jit
def increment_tangent(model: Model, state: State, loads: Loads, tangents: dict):
    """:func:`increment` with forward-mode sensitivities of the state to p parameters.

    ``tangents`` holds ``model`` ({field: (p, ...)} for
    :data:`jaxdem.core.sensitivities.SMOOTH_MODEL`),
    ``loads`` ({field: (p, ...)} for :data:`jaxdem.core.sensitivities.LOAD_FLOATS`) and ``state``
    ({field: (p, ...)} for :data:`jaxdem.core.sensitivities.STATE_FLOATS`): the derivatives of those
    inputs with respect to each parameter. The report then also holds
    ``dstate``, the derivatives of the new state, and ``dsnapshot``, those of the final
    contact snapshot.

    Each sub-step that ends in equilibrium, R(du*; geometry, history,
    theta) = 0, is differentiated implicitly with its contact states held
    (stick, slip, open and the bolts' states as found): du*' = K^-1 dR/dtheta,
    with K = -dR/d(du) the exact tangent of the held states (unsymmetric where
    slots slip). Geometry, detection and the committed history are chained
    through exactly, so the result is the derivative of the discrete solution
    wherever no state changes under a small change of theta. A sub-step cut
    short by the step length (a large motion on the way to equilibrium) is
    held fixed, and the report's ``approximate`` says that one was.
    """
    return substeps_to_equilibrium(model, state, loads, tangents)


def travelled_too_far(model: Model, snap: Snapshot, travel):
    """Whether a block's path in this increment passed its limit (a mechanism), its
    group's where blocks move together (:func:`jaxdem.core.kinematics.group_limits`,
    worked out only once a block has passed its own limit)."""
    past_own = jnp.any(travel > model.travel_limit)
    return past_own & jax.lax.cond(
        past_own, lambda: jnp.any(travel > group_limits(model, snap, travel)[0]),
        lambda: jnp.array(False))


_substep_once = jax.jit(substep)
"""``substep`` behind a jit of its own: traced once for its abstract arguments (the
loop's shapes and its body share that trace; XLA inlines the call)."""


class Progress(NamedTuple):
    """The carry of an increment's loop of sub-steps (:func:`substeps_to_equilibrium`), and
    at its end the increment's report to the host (``state`` None there: it is returned
    apart; ``joints`` the :class:`JointMotion`, None in the loop).

    ``state`` the blocks and springs now; ``status`` the outcome's code (-1 while it goes
    on: :class:`jaxdem.core.status.Status`); ``substeps``, ``iterations`` (Newton's, summed)
    and ``stuck`` (sub-steps in a row that neither converged, nor moved a step length, nor
    brought the residual below a tenth of ``best``, the least since the last that did one
    of the first two);
    ``travel`` (N,) each block's travel so far; ``residual`` the last sub-step's relative
    residual; ``balance`` and ``snapshot`` those of the last sub-step
    (:func:`jaxdem.core._substep.commit_substep`); ``pairs_needed``, ``cell_full``,
    ``slots_full`` and ``touch_needed`` what the contact list needed (the host grows what
    overflowed); ``approximate`` a sub-step ended without equilibrium, cut by the step
    length (see :func:`increment_tangent`); ``unbalanced`` the last sub-step's blocks furthest
    out of balance (:class:`jaxdem.core._substep.Unbalanced`).
    With sensitivities, ``dstate`` and ``dsnapshot`` their derivatives (else None;
    ``dsnapshot`` has the snapshot's float fields alone: :func:`jaxdem.core.state.float_part`).
    """

    state: State | None
    status: jax.Array
    substeps: jax.Array
    stuck: jax.Array
    best: jax.Array
    iterations: jax.Array
    travel: jax.Array
    residual: jax.Array
    balance: Balance
    snapshot: Snapshot
    pairs_needed: jax.Array
    cell_full: jax.Array
    slots_full: jax.Array
    touch_needed: jax.Array
    approximate: jax.Array
    unbalanced: Unbalanced
    dstate: Any = None
    dsnapshot: Snapshot | None = None
    joints: JointMotion | None = None


def substeps_to_equilibrium(model: Model, state: State, loads: Loads, tangents=None, skip=None):
    """Geometry sub-steps until equilibrium; with ``tangents``, their sensitivities too.

    ``skip`` (a bool scalar) returns ``state`` untouched: a batch member that has
    already failed, or one that need not be redone, costs no iterations.
    """
    N = model.n_blocks
    dtype = state.verts.dtype
    # The shapes of the balance and snapshot carried by the loop. ``substep`` is
    # jitted so that this trace is the one the loop body uses, not a second one: with
    # the body's abstract arguments (``warm`` a traced bool, as the body makes it).
    _, _, newton0, _, balance0, snap0 = jax.eval_shape(_substep_once, model, state, loads,
                                                       jnp.zeros((), bool))
    zeros_like = lambda t: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), t)  # noqa: E731

    def body(c: Progress) -> Progress:
        # A sub-step after a balanced one only corrects for the geometry that one moved.
        warm = (c.substeps > 0) & (c.residual <= model.tol)
        if tangents is None:
            st_new, du, newton, need, balance, snap = _substep_once(model, c.state, loads, warm)
            dstate = dsnap = None
        else:
            (st_new, du, newton, need, balance, snap), (dstate, dsnap) = substep_tangent(
                model, c.state, loads, tangents["model"], c.dstate, tangents["loads"], warm=warm)
        overflow = need.overflowed(model, state)
        travel = c.travel + block_travel(model, du)
        small = jnp.max(block_travel(model, du)) <= model.touch_tol
        # A sub-step cut by the iteration limit that brought the residual below a
        # tenth of the least one since the last converged or clipped sub-step is
        # progress too (a block pressed into a corner contact that has just closed
        # settles over a few sub-steps), not stuck; a residual that goes up and down
        # is not, and a tenth at a time it comes down a few times at most.
        moved = newton.converged | newton.clipped
        settling = newton.rnorm < 0.1 * c.best
        stuck = jnp.where(moved | settling, 0, c.stuck + 1)
        best = jnp.where(moved, newton.rnorm, jnp.minimum(c.best, newton.rnorm))
        substeps = c.substeps + 1
        # The first outcome that holds ends the increment; -1 goes on. An
        # equilibrium counts only if it is admissible (no overlap, no law broken,
        # the whole in balance): else the status says which check failed.
        done = newton.converged & small & ~need.new_failures
        status = jnp.select(
            [overflow, ~newton.finite, done & (balance.overlap_rel > OVERLAP_TOL),
             done & (balance.excess > STRENGTH_TOL),
             done & (global_imbalance_jax(balance) > IMBALANCE_FACTOR * model.tol), done,
             travelled_too_far(model, snap, travel),
             (stuck >= 3) | (substeps >= model.max_substeps)],
            [s.code for s in (Status.CAPACITY_OVERFLOW, Status.NON_FINITE, Status.OVERLAP,
                              Status.LAW_VIOLATION, Status.IMBALANCE, Status.CONVERGED,
                              Status.MECHANISM, Status.ITERATION_LIMIT)],
            -1).astype(jnp.int32)
        keep = overflow | ~newton.finite
        hold = lambda old, new: jax.tree.map(lambda o, n: jnp.where(keep, o, n), old, new)  # noqa: E731
        return Progress(state=hold(c.state, st_new), status=status, substeps=substeps,
                        stuck=stuck, best=best, iterations=c.iterations + newton.it,
                        travel=travel,
                        residual=newton.rnorm, balance=balance, snapshot=snap,
                        pairs_needed=jnp.maximum(c.pairs_needed, need.pairs.astype(jnp.int32)),
                        cell_full=c.cell_full | need.cell_full,
                        slots_full=c.slots_full | need.slots_full,
                        touch_needed=jnp.maximum(c.touch_needed,
                                                 need.touching.astype(jnp.int32)),
                        approximate=c.approximate | ~newton.converged,
                        unbalanced=newton.unbalanced,
                        dstate=None if tangents is None else hold(c.dstate, dstate),
                        dsnapshot=dsnap)

    status0 = jnp.array(-1) if skip is None else jnp.where(skip, Status.CONVERGED.code, -1)
    dstate0 = dsnap0 = None
    if tangents is not None:
        dstate0 = tangents["state"]
        p = jax.tree.leaves(tangents["state"])[0].shape[0]
        dsnap0 = jax.tree.map(lambda s: jnp.zeros((p,) + s.shape, dtype), float_part(snap0))
    # Counters int32, as the body makes them (a weakly typed jnp.array(0) that the body
    # turns into int32 makes JAX trace the body twice).
    zero = jnp.zeros((), jnp.int32)
    init = Progress(state=state, status=status0.astype(jnp.int32), substeps=zero, stuck=zero,
                    best=jnp.array(jnp.inf, dtype),
                    iterations=zero, travel=jnp.zeros(N, dtype),
                    residual=jnp.array(jnp.inf, dtype), balance=zeros_like(balance0),
                    snapshot=zeros_like(snap0), pairs_needed=zero,
                    cell_full=jnp.array(False), slots_full=jnp.array(False),
                    touch_needed=zero,
                    approximate=jnp.array(False),
                    unbalanced=zeros_like(newton0.unbalanced),
                    dstate=dstate0, dsnapshot=dsnap0)
    if model.lanes is None:
        # A loop whose condition does not depend on its body, the body skipped once the
        # increment has ended: XLA compiles it in about a third less time than a
        # while_loop that ends on the status (the demo's increment 6.3-7.2 s -> 4.1-4.8 at
        # LLVM level 0; the same answers, to round-off; the skipped iterations cost nothing
        # measurable: BENCHMARKS.md, "Twenty-fourth session"). Not in a batch: under vmap
        # the cond on a member's status would become a select, and every member would
        # run all max_substeps sub-steps.
        c = jax.lax.fori_loop(0, model.max_substeps,
                              lambda _, c: jax.lax.cond(c.status < 0, body, lambda c: c, c), init)
    else:
        c = jax.lax.while_loop(lambda c: c.status < 0, body, init)
    return c.state, c._replace(state=None, joints=_joint_motion(model, state, c.state, c.snapshot))


def _joint_motion(model: Model, start: State, end: State, snap: Snapshot) -> JointMotion:
    """Largest joint slip and opening (m) of an increment, and the blocks where they are.

    At each joint contact of the final geometry (open or closed, walls included,
    intact bonds not), the relative displacement over the increment of the two
    blocks' material points now at the contact point: its tangential part is the
    slip, its normal part the opening (positive apart). ``slip_rel`` is the slip
    relative to the smaller block's size, which the command line warns about
    above :data:`jaxdem.core.status.LARGE_SLIP`.
    """
    p, n = snap.point, snap.normal
    t = jnp.stack([-n[:, 1], n[:, 0]], axis=1)

    def moved(i):
        back = rotate_vectors(p - end.centroid[i], -(end.rot[i] - start.rot[i]))
        return p - (start.centroid[i] + back)

    a, b = snap.a, snap.b
    rel = moved(a) - moved(b)
    joint = snap.joint
    slip = jnp.where(joint, jnp.abs(jnp.sum(rel * t, axis=1)), 0.0)
    opening = jnp.where(joint, jnp.sum(rel * n, axis=1), 0.0)
    size = jnp.where(model.free, model.radius, jnp.inf)
    size = jnp.minimum(size[a], size[b])
    size = jnp.where(jnp.isfinite(size), size, 1.0)
    i, j = jnp.argmax(slip), jnp.argmax(opening)
    return JointMotion(slip=slip[i], slip_rel=slip[i] / size[i],
                       slip_blocks=jnp.stack([a[i], b[i]]), opening=jnp.maximum(opening[j], 0.0),
                       opening_blocks=jnp.stack([a[j], b[j]]))
