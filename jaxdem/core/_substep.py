"""One geometry sub-step: detect contacts, Newton iteration at fixed geometry, commit.

Owns :func:`prepare_substep` (contacts and their history at the current geometry:
the :class:`jaxdem.core._springs.Sub`, from its slots' part :func:`slot_fields_of` and
its blocks' part :func:`block_fields_of`, and the :class:`Detection`; what a sub-step
needed, :class:`Needs`), :func:`pack_slots` (the touching slots that
the iteration works on, and in a sub-step their rows Bn, Bs, which only those need:
:func:`slot_rows`), :func:`_newton` (the iteration on du),
:func:`breaking` (with ``solver.bond_failure = "events"``, the springs that fail: elastic
in the iteration until loaded beyond their strength, event by event),
:func:`commit_substep` (move the blocks, commit the springs, global balance),
:func:`_admissibility` and :func:`substep`, which chains them. The increment
(:mod:`jaxdem.core.increment`) repeats sub-steps until one converges.


eps M only shapes the path: the converged answer solves R = 0 whatever eps
is, and where K_t is singular (a free block, a sliding mechanism) it turns
the step into a finite move along the mechanism, which the step length
bounds. Where slots slip, the elastic (secant) matrix converges only
linearly; once it has reduced R twice with the states held, the slip tangent
is tried (on the direct paths the exact one, with the coupling of shear to
normal force), its steps shortened by a backtracking line search on the
squared residuals, and kept while it reduces R. A tried step that would
leave the step length is not taken, and the secant takes over for the rest of
the sub-step. When the secant iteration stalls (R stays put: a block just
past limit equilibrium, whose small residual would move it only by
R / (eps k) an iteration), the slip tangent is used and the step goes the
whole step length along the mechanism, so that it is followed and reported,
not left to creep into the iteration limit; where R stood still in the stall (a
block sliding free) and that slip-tangent step did not reduce it, at the next stall
at once. A slot whose state flips
:data:`FREEZE_AFTER` times in one sub-step is frozen in its last state for
the rest of that sub-step, which ends open/close chatter. Frozen slots only
shape the path: a sub-step converges only if every block also balances with
the forces the contact law gives (a frozen slot at its limit: within the
tolerance), and returns those. A frozen slot that breaks its law there (stuck
beyond its strength, closed in tension, held open with a block inside it)
takes the law's state and the iteration goes on.

Data flow: takes spring forces and stiffness (:mod:`jaxdem.core._springs`), the
linear solves (:mod:`jaxdem.core._linsolve`), kinematics, contact detection and
loads from below; used by :mod:`jaxdem.core.increment` and
:mod:`jaxdem.core.sensitivities`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdem.core._contact import (
    CORNER_PASS,
    Corners,
    History,
    Slots,
    block_steps,
    broad_phase,
    narrow_phase,
    remap_history,
)
from jaxdem.core._linsolve import CG_RTOL_MAX, CG_RTOL_MIN, linear_solve, sparse_pattern
from jaxdem.core._springs import (
    Bolts,
    Packing,
    Springs,
    Sub,
    block_residual,
    block_scale,
    bolt_rest_length,
    cell_stiffness,
    evaluate,
    slip_coupling,
    stiffness_terms,
)
from jaxdem.core.kinematics import (
    b_rows,
    block_travel,
    bolt_geometry,
    cross,
    gather_pairs,
    move_blocks,
)
from jaxdem.core.laws import excess_ratio, has_strength, overload, slot_properties
from jaxdem.core.loads import water_force
from jaxdem.core.state import OPEN, SLIP, STICK, Balance, Loads, Model, Snapshot, State


def force_scales(model: Model, sub: Sub):
    """Force scale (N,) of each block's equilibrium test and hysteresis band (S,) of each slot.

    The scale (:func:`jaxdem.core._springs.block_scale`) is a block's load or the
    largest force on it (an in-situ state has large contact forces and no net
    load). No block is asked to balance below 1000 round-offs of the scene's
    largest force scale (nor is a scene without loads below 1e-3 f_ref), which
    is all that a block without load or contacts has. The band by which a
    slot's trial force must pass a threshold of the law to change its state
    (open/closed, stuck/slipping: :func:`jaxdem.core.laws.mohr_coulomb`) is a tenth
    of the tolerance of the smaller free block it touches.
    """
    s0 = block_scale(model, sub)
    biggest = jnp.maximum(jnp.max(jnp.where(sub.free, s0, 0.0)), model.f_ref * 1e-3)
    floor = 1e3 * jnp.finfo(sub.load.dtype).eps * biggest
    s0 = jnp.maximum(s0, floor)
    s_slot = jnp.minimum(jnp.where(sub.free, s0, jnp.inf)[sub.geo.a],
                         jnp.where(sub.free, s0, jnp.inf)[sub.geo.b])
    return s0, 0.1 * model.tol * jnp.where(jnp.isfinite(s_slot), s_slot, biggest)


#: A slot whose state flips this many times in one sub-step is held in its last state
#: for the rest of it (open/close and stick/slip chatter). 4 froze slots on their way
#: to an answer: with the line search and the pierced slots below, seed example 4 (wet)
#: takes 685 iterations with 12 and 816 with 4 (721 before all three), BENCHMARKS.md
#: "Issue 30, Newton".
FREEZE_AFTER = 12
#: Of the springs loaded beyond their strength at the end of a sub-step, those whose excess
#: (:func:`jaxdem.core.laws.excess_ratio`) is at least this share of the worst fail
#: together; the rest wait for the next sub-step (:func:`breaking`). Near 1 is the
#: sequentially linear ideal, one failure at a time, and costs a sub-step per failure:
#: at 0.9 (the springs over their strength committed as the iteration left them) seed
#: example 3 at k0 = 1/3 spent its 131 sub-steps at 56% of the excavation's release
#: failing two springs at a time (iteration limit, 822 s of solve); at 0.5 it reaches an
#: answer (BENCHMARKS.md "Twentieth session"). At 0 (every spring over its strength at
#: once) seed example 3's rock loaded by its weight broke 607 springs in one sub-step at a
#: quarter of its weight, and its sub-steps stopped converging.
FAIL_TOGETHER = 0.5
#: The dtype of Newton's increment du in every scene (see :func:`_newton`).
WIDE = jnp.float64
#: A persisting slot keeps its last gap where a new detection differs from it by less
#: than this many round-offs of the scene's largest coordinate (float32:
#: :func:`slot_fields_of`).
GAP_ROUND_OFF = 16
#: The slip tangent is tried once the secant has reduced the residual TRY_AFTER times in
#: a row with the states held; a try that failed (did not reduce the residual), after
#: RETRY_AFTER more such iterations per failure, and not after RETRY_LIMIT failures in
#: a sub-step (:func:`_newton`). Trying after one such iteration took seed example 4
#: from a median of 23.5 iterations an increment to 20.5 and the demo from 71 to 56 in
#: all, but took the two-set staged tunnel's heading (tests/verification/
#: test_admissible_mechanism.py) to the iteration limit: a tried step there left a
#: crown sliver held by slots at almost no normal force, and the secant threw it 18 mm.
TRY_AFTER = 2
RETRY_AFTER = 8
RETRY_LIMIT = 3
#: A stall whose residual changes by less than this (relative) an iteration is flat: a
#: block that slides free, its out-of-balance force the same wherever it is.
FLAT = 1e-4
#: An open slot whose spring, closed over its gap, would carry less than this many
#: hysteresis bands (a band is a tenth of the tolerance of the smaller block it touches)
#: keeps its normal spring in the secant matrix (:func:`_newton`).
NEAR = 10.0
#: Halvings of a Newton step that the line search tries before it takes the whole step.
LINE_SEARCH_HALVINGS = 8
#: Armijo's sufficient decrease of the merit, per unit of step.
ARMIJO = 1e-4
#: How many of the blocks furthest out of balance a sub-step reports (:class:`Iterate`):
#: where the analysis stops at the iteration limit, the result names them.
UNBALANCED_NAMED = 5


class Unbalanced(NamedTuple):
    """The K = min(:data:`UNBALANCED_NAMED`, N) free blocks with the largest out-of-balance
    force relative to their force scale, largest first, at one evaluation: ``ids`` (K,),
    ``force`` (K,) that force (kN/m, measured as :func:`jaxdem.core._springs.block_residual`)
    and ``rel`` (K,) the same over the block's force scale (-1 for a block that is not
    free)."""

    ids: jax.Array
    force: jax.Array
    rel: jax.Array


class Iterate(NamedTuple):
    """The carry of the Newton loop of one sub-step, and its record when it ends.

    Per slot (S,): ``st`` the states of the last evaluation, ``flips`` how often each
    changed, ``frozen`` and ``frozen_state`` the slots held in a state. Scalars:
    ``it`` the iterations, ``done`` / ``converged`` / ``clipped`` (the step length or a
    closing slot ended the sub-step before equilibrium) / ``finite``, ``rnorm`` the
    largest residual of a free block relative to its force scale, ``rprev`` the same
    relative to its tolerance at the previous iteration, ``rbest`` the least of those
    since the states last changed, ``stall`` how many iterations in a row made no
    progress with the states held, ``settled`` how many reduced the residual below
    ``rbest`` with the states held, ``trying`` the slip tangent is being tried,
    ``tangent`` the last step used it, ``untried`` no tried step has overshot, nor
    failed :data:`RETRY_LIMIT` times (``fails``), in this sub-step, ``flat`` how many
    stalled iterations in a row left the residual as it was (to :data:`FLAT`),
    ``lost`` the slip-tangent step of such a flat stall did not reduce the residual in
    this sub-step (a stall is then followed as a mechanism at once). ``unbalanced`` the
    blocks furthest out of balance at the last evaluation (:class:`Unbalanced`). The last
    step: ``scale`` the share of Newton's step taken (0 where none was), ``cut_by`` the
    slot whose closing bounded it (the whole step would have sunk it deeper than its
    spring's compression under its blocks' forces; its index among ``sub``'s slots, the
    packed ones in a sub-step: :func:`pack_slots`), -1 where nothing did, or the step
    length or the line search did (for ``benchmarks/newton_trace.py``).
    """

    du: jax.Array
    st: jax.Array
    flips: jax.Array
    frozen: jax.Array
    frozen_state: jax.Array
    it: jax.Array
    done: jax.Array
    converged: jax.Array
    clipped: jax.Array
    finite: jax.Array
    rnorm: jax.Array
    rprev: jax.Array
    rbest: jax.Array
    stall: jax.Array
    settled: jax.Array
    trying: jax.Array
    tangent: jax.Array
    untried: jax.Array
    lost: jax.Array
    flat: jax.Array
    fails: jax.Array
    unbalanced: Unbalanced
    scale: jax.Array
    cut_by: jax.Array


class Detection(NamedTuple):
    """What a sub-step's detection found beside its slots (:func:`prepare_substep`):
    ``pairs`` the candidate pairs it needed (to compare with the state's capacity),
    ``cell_full`` (the broad phase's cells overflowed), ``corners``
    (:class:`jaxdem.core._contact.Corners`, for :func:`corner_bound`)."""

    pairs: jax.Array
    cell_full: jax.Array
    corners: Corners


class Needs(NamedTuple):
    """What a sub-step needed of the fixed capacities, and whether it failed a spring
    (:func:`substep`): ``pairs`` the candidate pairs, ``cell_full`` (the broad phase's
    cells), ``slots_full`` (more touching slots, or watched vertices, than their places),
    ``touching`` the touching pairs (to compare with ``model.touch_capacity``) and
    ``new_failures`` (a spring with cohesion or tensile strength failed: the increment
    cannot end with this sub-step)."""

    pairs: jax.Array
    cell_full: jax.Array
    slots_full: jax.Array
    touching: jax.Array
    new_failures: jax.Array

    def overflowed(self, model: Model, state: State):
        """Whether the sub-step needed more than ``state``'s and ``model``'s capacities
        (the increment then ends, and the host grows them and runs it again)."""
        return ((self.pairs > state.capacity) | self.cell_full | self.slots_full
                | (self.touching > model.touch_capacity))


def _newton(model: Model, sub: Sub, st0, warm=False, loop=None):
    """Newton iteration on du at fixed geometry (one sub-step).

    The elastic (secant) matrix first; the slip tangent (with the slip coupling on
    the direct paths: :func:`jaxdem.core._springs.slip_coupling`) once the
    secant has reduced the residual twice with the states held and slots slip,
    kept while it reduces the residual; on the direct paths a backtracking line
    search on the merit sum((|R_b| / tol_b)^2) over the free blocks takes the first
    of 1, 1/2, 1/4, ... that meets Armijo's condition (the whole step where none
    does within :data:`LINE_SEARCH_HALVINGS`: the merit is not smooth where states
    change). A tried step that would leave the step length is not taken. The slip
    tangent, without line search, once the iteration stalls (a mechanism).

    ``warm`` (a bool scalar): the sub-step before this one, in this increment, ended in
    balance (its residual within the tolerance), so that this one only corrects for the
    geometry it moved, from the states of an equilibrium nearby: the slip tangent is
    tried from its second iteration on (below).

    ``loop``: what runs the iteration, a function of :func:`jax.lax.while_loop`'s
    signature (cond, body, init), which it is by default. A diagnostic passes a
    ``while_loop`` whose body also hands each :class:`Iterate` to the host
    (``benchmarks/newton_trace.py``).

    Returns the :class:`Iterate` at the end (its ``du`` the sub-step's increment).
    """
    S = st0.shape[0]
    N = model.n_blocks
    dtype = sub.load.dtype
    s0, band = force_scales(model, sub)
    zeros_s = jnp.zeros(S, jnp.int32)
    step = block_steps(model)
    direct = model.linear_solver != "cg"
    named = min(UNBALANCED_NAMED, N)

    def merit(ev, tol):
        return jnp.sum(jnp.where(sub.free, (block_residual(model, ev.R) / tol) ** 2, 0.0))

    # What the sparse solve's matrices share in every iteration of the sub-step (their
    # triplets' indices, the springs' rows laid out by pair), formed once.
    pattern = sparse_pattern(model, sub) if model.linear_solver == "sparse" else None

    def body(c: Iterate) -> Iterate:
        ev = evaluate(model, sub, c.du, c.frozen, c.frozen_state, c.st, band)
        changed = (ev.state != c.st) & sub.geo.active
        scale_b = jnp.maximum(s0, block_scale(model, sub, ev))
        tol = model.tol * scale_b
        # Largest residual of a free block relative to its own tolerance.
        r_block = block_residual(model, ev.R)
        rnorm = jnp.max(jnp.where(sub.free, r_block / tol, 0.0))
        rel, worst = jax.lax.top_k(jnp.where(sub.free, r_block / scale_b, -1.0), named)
        # Frozen slots only shape the path: the answer must balance every
        # block with the forces of the contact law itself (R_law), within the
        # same tolerance, so that no state against the law is returned. Where
        # it does not, the frozen slots with a misfit on an unbalanced block
        # were frozen on the way to an answer elsewhere (stuck beyond their
        # strength, closed in tension): they take the law's state, and the
        # iteration goes on with it (an active-set update). The states of ev
        # are the law's at du given the previous states and the hysteresis
        # band, and a fixed point of it (evaluated again with them as the
        # previous states they come out the same), so a state that changed in
        # this iteration does not stop a balanced iterate: slots at zero force
        # (joints between columns that carry nothing) chatter between stick,
        # slip and open at round-off forever, and kept a 70 x 70 grid iterating
        # at 0.3 tolerances (114 iterations, 16 without the condition).
        balanced = rnorm <= 1.0
        off = sub.free & (block_residual(model, ev.R_law) > tol)
        converged = balanced & ~jnp.any(off)
        a, b = sub.geo.a, sub.geo.b
        reassign = balanced & c.frozen & (ev.misfit > 0) & (off[a] | off[b])
        # How deep a slot may sink in one step: its spring's own compression
        # under the larger force scale of its two blocks.
        s_slot = jnp.where(sub.free, scale_b, 0.0)
        s_slot = jnp.maximum(s_slot[a], s_slot[b])
        sink = s_slot / jnp.maximum(sub.prop.kn, jnp.finfo(dtype).tiny)
        # A slot frozen open that a block has entered deeper than that is not
        # open: held open, every step would stop at its face (the closing
        # bound below) and the iteration would cycle there. It takes the law's
        # state.
        pierced = (c.frozen & (c.frozen_state == OPEN) & sub.geo.active
                   & (ev.gap < -sink) & (ev.law_state != OPEN))
        reassign = reassign | pierced
        flips = c.flips + changed.astype(jnp.int32)
        newly = (flips >= FREEZE_AFTER) & ~c.frozen
        frozen = c.frozen | newly
        frozen_state = jnp.where(newly, ev.state,
                                 jnp.where(reassign, ev.law_state, c.frozen_state))
        # The secant matrix (slipping slots keep their shear spring) converges
        # only linearly where slots slip (a rate of 0.96 an iteration is common).
        # Once it has reduced the residual twice in a row with the states held and
        # slots slipping, the slip tangent is tried, and kept while it reduces the
        # residual and no state changes: on the direct paths with the slip
        # coupling (the exact tangent of the held states), on the cg path its
        # symmetric part. A tried step that would leave the step length (not taken)
        # hands back to the secant for the rest of the sub-step, one that does not
        # reduce the residual until the secant has settled again. Three iterations
        # without progress with the states held (stall) mean a mechanism or slip the
        # secant cannot settle: the slip tangent, and ``creeping`` below follows the
        # mechanism. A slot held (frozen) stuck beyond its strength carries the limit
        # but keeps its shear spring in the tangent until a tried step has failed in
        # this sub-step; the tries after that drop it (``exact``: the tangent of the
        # forces the slot carries). With the exact tangent everywhere seed example 4
        # took 397 iterations instead of 410, but a roof prism's strength-reduction
        # trial just past its limit and the two-set staged tunnel's heading ran to the
        # iteration limit; in every tried step, that heading too. After a failure only:
        # seed example 4 wet 406 -> 379, its worst increment 84 -> 65 (where the tangent
        # failed at 1.2e3 tolerances, the exact one, computed at that iterate,
        # converges in one step), the other bundled scenes the same.
        still = ~jnp.any(changed)
        progress = rnorm <= 0.98 * c.rprev
        # With the states held, progress (settled) and its absence (stall) are
        # measured against the least residual since the states last changed, not the
        # last one: the secant can swing between two iterates with the states held,
        # each "progress" on the one before (seed example 3's excavation at k0 = 1/3:
        # 8.2e5 and 9.0e5 tolerances in turn, iteration after iteration, to the
        # iteration limit). Such a swing is a stall: its step is damped (the line
        # search below) and, if it persists, the slip tangent takes over.
        gain = rnorm <= 0.98 * c.rbest
        rbest = jnp.where(still, jnp.minimum(c.rbest, rnorm), rnorm)
        settled = jnp.where(still & gain, c.settled + 1, 0)
        failed = c.trying & ~progress
        stall = jnp.where(still & ~gain & ~failed, c.stall + 1, 0)
        flat = jnp.where((stall > 0) & (jnp.abs(rnorm - c.rprev) <= FLAT * rnorm), c.flat + 1, 0)
        slipping = jnp.any(sub.geo.active & (ev.state == SLIP))
        if model.n_bolts:
            slipping |= jnp.any(sub.bolt.active & (ev.bolt_state != 0))
        # A tried step that failed is tried again once the secant has held the states
        # for RETRY_AFTER more iterations of progress per failure, up to RETRY_LIMIT
        # failures: the first try often comes while the states are still settling,
        # and the secant alone then crawled on at 0.83 an iteration (seed example 4's
        # first sub-step: 48 iterations after the tangent's only try).
        fails = c.fails + failed.astype(jnp.int32)
        untried = c.untried & (fails < RETRY_LIMIT)
        due = settled >= TRY_AFTER + RETRY_AFTER * fails
        # A warm sub-step tries the slip tangent from its second iteration on (the first
        # gives the newly detected slots their states), while a few slots still change
        # state, until a try fails; then as any sub-step. The secant crawled there
        # (0.75 an iteration) for 6-10 iterations, its slots flipping one or two at a
        # time, before the states held still twice: seed example 4 wet 353 -> 309
        # iterations (median 23.5 -> 19.5 an increment), the demo 67 -> 51, seed
        # example 2 77 -> 64, the staged tunnel 279 -> 208 (its worst increment 114 ->
        # 94: warm after any balanced sub-step, not only where all before it were),
        # the answers the same to 3e-7.
        eager = warm & (c.it >= 1) & (fails == 0)
        trying = untried & slipping & (eager | (still & ((c.trying & ~failed) | due
                                                          | (c.tangent & progress))))
        # A flat stall (the residual the same to FLAT, iteration after iteration: a
        # block sliding free, its out-of-balance force the same wherever it is)
        # whose slip-tangent step did not reduce the residual is a mechanism: the
        # next stall is followed at once (``creeping``), before the states the
        # tangent step disturbs reset it. Else the secant walked back to the same
        # stall and the tangent threw the block again, a cycle of 10 iterations into
        # the iteration limit (seed example 4 wet, saturation: 300 of the
        # increment's 310). A stall in which the residual still falls slowly (1% an
        # iteration, seed example 2's last increment) is not flat: followed at once,
        # it threw that tunnel's blocks a step length each sub-step (1,200
        # iterations).
        lost = c.lost | (c.tangent & ~c.trying & ~progress & (c.flat >= 2))
        tangent = trying | (stall >= 3)

        # Joints between the columns of a stack carry nothing: their slots touch at
        # gaps of the order of the iteration's own error, and hundreds of them opened
        # and closed in every iteration of a 100 x 100 grid. Each opening let its
        # blocks move sideways on nothing stiffer than eps M, the next step closed it
        # again, and the residual hovered at 1-5 tolerances (iteration limit, or
        # converged only as round-off allowed: 36 iterations, the same matrix summed in
        # another order 242). An open slot within NEAR bands of closing keeps its
        # normal spring in the secant matrix (not in its force: the residual is the
        # law's): a step then opens it no further than the forces ask. 100 x 100: 18
        # iterations, 70 x 70 15 -> 9; the tangent (a mechanism, tried slip) keeps
        # open slots open.
        near = (sub.geo.active & (ev.state == OPEN) & ~tangent
                & (ev.gap >= 0.0) & (sub.prop.kn * ev.gap < NEAR * band))

        def newton_step():
            terms = stiffness_terms(model, sub, ev, tangent, near,
                                    exact=trying & (c.fails > 0))
            if not direct:
                # Inexact Newton (Eisenstat-Walker, choice 2): solve as accurately
                # as Newton's own progress warrants, and no more accurately than
                # the tolerance needs (the residual test below still decides).
                ratio = jnp.where(jnp.isfinite(c.rprev), rnorm / c.rprev, jnp.inf)
                tol_min = jnp.min(jnp.where(sub.free, tol, jnp.inf))
                need = 0.1 * tol_min / jnp.maximum(jnp.linalg.norm(ev.R),
                                                   jnp.finfo(tol.dtype).tiny)
                eta = jnp.clip(jnp.maximum(0.9 * ratio**2, need),
                               CG_RTOL_MIN[tol.dtype == jnp.float64], CG_RTOL_MAX)
                return linear_solve(model, sub, terms, ev.R, rtol=eta)
            # The secant matrix is symmetric positive definite (CHOLMOD on the
            # sparse path), the slip tangent with its coupling is not.
            return linear_solve(model, sub, terms, ev.R, active=~c.done & ~converged,
                                symmetric=~tangent, coupling=slip_coupling(sub, ev, tangent),
                                pattern=pattern)

        # The iterate that converged takes no step: its matrix is not
        # assembled nor factorised (one factorisation a sub-step). Under vmap
        # a cond on a per-member flag would run both branches, so a batch
        # (model.lanes) skips only when none of its members needs a step; the
        # sparse path's SciPy fallback also skips the host solve of each member
        # that does not (sparsax's batched call solves them all).
        idle = converged
        if model.lanes is not None:
            idle = jax.lax.psum(jnp.where(converged | c.done, 0, 1), model.lanes) == 0
        ddu = jax.lax.cond(idle, lambda: jnp.zeros(c.du.shape, dtype), newton_step)
        # Still no progress: a mechanism whose residual is small (a block just
        # past limit equilibrium) would only creep, by R / (eps k) an
        # iteration, and run out of iterations instead of showing that it
        # moves. Along the mechanism R does not change, so go the whole step
        # along it (the elastic part of ddu, eps times smaller, stays
        # negligible) and let the next sub-step follow it.
        creeping = (c.stall >= 5) | (lost & (stall >= 3))
        t_now = block_travel(model, c.du)
        t_step = block_travel(model, ddu)
        room = jnp.maximum(step - t_now, 0.0)
        fit = jnp.min(jnp.where(t_step > 0, room / jnp.where(t_step > 0, t_step, 1.0), jnp.inf))
        # A mechanism moves where its out-of-balance forces push it (they do work
        # on the step, R . ddu > 0). The slip tangent is not definite near one, and
        # a stall's step that goes beyond the step length (Newton's step reaches no
        # equilibrium within it: a mechanism is followed) could point back up the
        # slope: a sidewall wedge went down one step length and up the next,
        # sub-step after sub-step, until its path (not its displacement) passed
        # max_displacement and it was reported as a mechanism. A step within the
        # step length is Newton's, whatever its sign.
        following = creeping | (tangent & ~trying & (fit < 1.0))
        work = jnp.sum(jnp.where(sub.free[:, None], ev.R * ddu, 0.0))
        ddu = jnp.where(following & (work < 0), -ddu, ddu)
        s_travel = jnp.where(creeping & jnp.isfinite(fit), fit, jnp.minimum(fit, 1.0))
        # No step lands a block inside another. A slot may close during the step
        # but not sink deeper than its spring's own compression under the forces
        # in play (``sink``): a falling block lands on its support, it does not
        # plunge a step length into it. Newton's own step (scale <= 1) compresses
        # a closed spring as its law says, so closed slots bound only a step
        # scaled beyond it (``creeping``); every step actually taken is checked.
        dn_step = jnp.sum(sub.Bn * gather_pairs(ddu, a, b), axis=1)
        closing = sub.geo.active & (dn_step < 0)
        depth = jnp.maximum(ev.gap, 0.0) + sink
        s_slots = jnp.where(closing, depth / jnp.where(closing, -dn_step, 1.0), jnp.inf)
        is_open = ev.state == OPEN
        s_slots = jnp.where(is_open, s_slots, jnp.maximum(s_slots, 1.0))
        s_gap = jnp.min(s_slots, initial=jnp.inf)
        scale = jnp.minimum(s_travel, s_gap)
        clipped = (s_travel <= s_gap) & ((s_travel < 1.0) | creeping)
        # A tried tangent step that would leave the step length is not taken: near
        # a mechanism the slip tangent is nearly singular, and its slip of a large
        # trial step can show a mechanism that is not there (a toppling block's
        # stuck pivot, slipping under the linearised rotation).
        overshoot = trying & clipped
        untried = untried & ~overshoot
        scale = jnp.where(overshoot, 0.0, scale)
        clipped = clipped & ~overshoot
        # The line search: on a tried tangent step, and on a secant step after one
        # that gained nothing (a swing between two iterates is halved back towards
        # its middle). Seed example 4 wet: 379 -> 353 iterations, its worst increment
        # 65 -> 50, the answers the same to 3e-11; the other bundled scenes the same.
        search = (trying | ((stall > 0) & ~tangent)) & ~converged & ~clipped & (scale <= 1.0)
        if direct:
            scale = _line_search(lambda x: merit(evaluate(model, sub, x, frozen, frozen_state,
                                                          ev.state, band), tol),
                                 c.du, ddu, scale, merit(ev, tol), search)
        du = jnp.where(converged, c.du, c.du + scale * ddu)
        cut_by = jnp.where(jnp.isfinite(s_gap) & (s_gap < s_travel) & (scale >= s_gap)
                           & ~overshoot & ~converged, jnp.argmin(s_slots), -1).astype(jnp.int32)
        finite = jnp.all(jnp.isfinite(du))
        it = c.it + 1
        done = converged | clipped | ~finite | (it >= model.max_iterations)
        return Iterate(du=du, st=ev.state, flips=flips, frozen=frozen,
                       frozen_state=frozen_state, it=it, done=done, converged=converged,
                       clipped=clipped & ~converged, finite=finite, rnorm=rnorm * model.tol,
                       rprev=rnorm, rbest=rbest, stall=stall, settled=settled, trying=trying,
                       tangent=tangent, untried=untried, lost=lost, flat=flat, fails=fails,
                       unbalanced=Unbalanced(worst.astype(jnp.int32), r_block[worst], rel),
                       scale=jnp.where(converged, 0.0, scale).astype(dtype), cut_by=cut_by)

    inf = jnp.array(jnp.inf, dtype)
    # Counters int32 (a weakly typed jnp.array(0) plus an int32, as ``fails`` gets, comes
    # back int32, and JAX then traced the body a second time: 0.3 s of every compilation).
    zero = jnp.zeros((), jnp.int32)
    # The increment du is carried in float64 whatever the scene's dtype: a spring's
    # force follows the difference of its two blocks' motions, and where they are large
    # (a tall column settling as a whole: 22 mm at the top of a 40 x 40 grid) float32
    # would keep eps |du| of it, about 4 times a top block's tolerance in round-off
    # force: the float32 grid iterated 60 times at that level, 11 with du in float64
    # (BENCHMARKS.md, "Fourteenth session"). The springs' motions are formed from it in
    # float64 (jaxdem.core._springs.evaluate), everything else stays in the scene's dtype.
    init = Iterate(du=jnp.zeros((N, model.ndof), WIDE), st=st0, flips=zeros_s,
                   frozen=jnp.zeros(S, bool), frozen_state=zeros_s, it=zero,
                   done=jnp.array(False), converged=jnp.array(False),
                   clipped=jnp.array(False), finite=jnp.array(True), rnorm=inf, rprev=inf,
                   rbest=inf, stall=zero, settled=zero, trying=jnp.array(False),
                   tangent=jnp.array(False), untried=jnp.array(True), lost=jnp.array(False),
                   flat=zero, fails=zero,
                   unbalanced=Unbalanced(jnp.zeros(named, jnp.int32), jnp.zeros(named, dtype),
                                         jnp.full(named, -1.0, dtype)),
                   scale=jnp.zeros((), dtype), cut_by=jnp.array(-1, jnp.int32))
    return (jax.lax.while_loop if loop is None else loop)(lambda c: ~c.done, body, init)


def _line_search(merit_at, du, ddu, scale, m0, on):
    """The step scale that the backtracking line search takes (see :func:`_newton`).

    Tries ``scale``, scale / 2, ... (at most :data:`LINE_SEARCH_HALVINGS` halvings)
    and returns the first whose merit meets Armijo's condition; ``scale`` itself
    where none does or where ``on`` is false.
    """
    def sufficient(s, m):
        return m <= (1.0 - ARMIJO * s / jnp.maximum(scale, jnp.finfo(m0.dtype).tiny)) * m0

    # k halvings so far; -1: ``scale`` itself not yet tried (one evaluation of the merit
    # in the program, not two).
    def cond(q):
        s, k, m = q
        return on & ((k < 0) | (~sufficient(s, m) & (k < LINE_SEARCH_HALVINGS)))

    def body(q):
        s, k, _ = q
        s = jnp.where(k < 0, s, 0.5 * s)
        return s, k + 1, merit_at(du + s * ddu)

    s, _, m = jax.lax.while_loop(cond, body, (scale, jnp.array(-1), m0))
    return jnp.where(on & sufficient(s, m), s, scale)


def _snap_gaps(geo: Slots, carried) -> Slots:
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
    eps = jnp.finfo(geo.gap.dtype).eps
    resolution = 8.0 * eps * jnp.max(jnp.abs(geo.point), axis=1)
    small = (jnp.abs(geo.gap) <= resolution) & (carried == 0)
    return geo._replace(gap=geo.gap - jax.lax.stop_gradient(jnp.where(small, geo.gap, 0.0)))


def prepare_substep(model: Model, state: State, loads: Loads, rows: bool = True):
    """Detect contacts at the current geometry and carry their history: a sub-step's data.

    Returns (mdl, sub, st0, pairs, found): the model with ``free`` restricted to
    the blocks alive now, the :class:`jaxdem.core._springs.Sub`, the slots' starting states, the
    pair list and the :class:`Detection` (what the contact list needed, and the vertices
    that bear on nothing near another block's node, for :func:`corner_bound`).
    ``rows=False`` leaves the sub's ``Bn`` and ``Bs`` None, for :func:`pack_slots` to form
    on the touching slots alone (see :func:`substep`).
    """
    N = model.n_blocks
    free = model.free & state.alive
    mdl = dataclasses.replace(model, free=free)
    pairs, count, cell_full = broad_phase(mdl, state.verts, state.capacity, state.alive)
    hist = jax.tree.map(lambda v: v.reshape(-1), remap_history(state, pairs, N))
    geo, corners = narrow_phase(mdl, state.verts, state.centroid, pairs)
    geo, slots, st0 = slot_fields_of(mdl, state, loads, geo, hist, rows)
    sub = Sub(geo=geo, **slots, **block_fields_of(model, state, loads, free))
    return mdl, sub, st0, pairs, Detection(pairs=count, cell_full=cell_full, corners=corners)


def slot_fields_of(mdl: Model, state: State, loads: Loads, geo: Slots, hist: History,
                   rows: bool = True):
    """The slots' part of a sub-step's data, from their contacts and carried history.

    ``geo``: :func:`jaxdem.core._contact.narrow_phase`'s slots (or any subset of them, as
    the sensitivities take the active ones); ``hist``: their history
    (:func:`jaxdem.core._contact.remap_history`, flat: one entry per slot); ``mdl``: the model
    with ``free`` restricted to the live blocks. Returns (geo with round-off
    gaps snapped, the :class:`jaxdem.core._springs.Sub` fields prop, Bn, Bs (None
    without ``rows``: :func:`slot_rows`), fs_old, fn0, failed and pw, the slots'
    starting states).
    """
    prop = slot_properties(mdl, geo)
    carried = jnp.where(hist.present, jnp.abs(hist.fn) + jnp.abs(hist.fs), 0.0)
    geo = _snap_gaps(geo, carried)
    same = hist.present & (hist.edge == geo.edge) & geo.active
    if geo.gap.dtype != jnp.float64:
        # A gap is a difference of absolute coordinates: in float32 a detection resolves
        # it to eps |x| (3e-6 m 28 m from the origin), and a bonded cell's penalty spring
        # (1e9 kN/m per m) turns each new detection's rounding into 3e3 kN/m of force.
        # A slot that persists keeps the gap it ended the last sub-step with where the
        # geometry agrees with it to that round-off, measured on the scene's largest
        # coordinate for every slot alike (per slot, mirror-image slots at x and -x + 1
        # made different choices, and a symmetric column drifted sideways).
        eps = jnp.finfo(geo.gap.dtype).eps
        extent = jnp.max(jnp.where(state.alive[:, None, None], jnp.abs(state.verts), 0.0))
        keep = same & (jnp.abs(geo.gap - hist.gap) <= GAP_ROUND_OFF * eps * extent)
        geo = geo._replace(gap=jnp.where(keep, hist.gap, geo.gap))
    failed = jnp.where(same, hist.failed, geo.gap > mdl.touch_tol)
    fs_old = jnp.where(same, hist.fs, 0.0)
    fn0 = jnp.where(same, hist.fn0, 0.0)
    # A new slot starts closed where its faces touch: round-off in a gap of
    # zero must not leave a block resting on its support without springs.
    st0 = jnp.where(same, hist.cstate,
                    jnp.where(geo.gap <= mdl.touch_tol, STICK, OPEN)).astype(jnp.int32)
    Bn, Bs = slot_rows(mdl, geo, state.centroid) if rows else (None, None)
    if mdl.has_water:
        pw = water_force(mdl, geo, prop, loads.water_x, loads.water_y, loads.water_scale)
    else:
        pw = jnp.zeros_like(fs_old)
    return geo, dict(prop=prop, Bn=Bn, Bs=Bs, fs_old=fs_old, fn0=fn0, failed=failed, pw=pw), st0


def slot_rows(mdl: Model, geo: Slots, centroid):
    """The rows (Bn, Bs) (S, 2 D) of the slots of ``geo``: their blocks' motions to the
    relative displacement along the normal and the tangent (:func:`jaxdem.core.kinematics.
    b_rows`); ``mdl.free`` the live free blocks."""
    D = mdl.ndof
    return tuple(b_rows(mdl.free, geo.a, geo.b, geo.point, geo.point, d, centroid, D)
                 for d in (geo.normal, geo.tangent))


def block_fields_of(model: Model, state: State, loads: Loads, free) -> dict:
    """The blocks' and bolts' part of a sub-step's data (``free``: the live free blocks)."""
    bolt = None
    if model.n_bolts:
        bg = bolt_geometry(model, state)
        alive_b = state.alive[bg.a] & state.alive[bg.b] & loads.bolt_active
        d0 = bg.point_a - bg.point_b
        # A bolt is installed unstressed: its rest length is its length when it
        # first acts (bolt_rest 0 until then), and grows with its plastic elongation.
        length0 = jnp.linalg.norm(d0, axis=1)
        rest = jnp.where(state.bolt_rest > 0, state.bolt_rest, length0)
        bolt = Bolts(a=bg.a, b=bg.b, free_a=free[bg.a], free_b=free[bg.b],
                     f_old=state.bolt_force, active=alive_b, d0=d0,
                     ra=bg.point_a - state.centroid[bg.a], rb=bg.point_b - state.centroid[bg.b],
                     rest=rest)
    return dict(bolt=bolt, load=jnp.where(free[:, None], loads.force, 0.0), free=free,
                stress=state.stress, Kc=cell_stiffness(model, free) if model.ndof == 6 else None)


def breaking(sub: Sub, ev: Springs, band):
    """(S,) the springs that fail at the end of a sub-step, from its evaluation ``ev`` in
    the iteration's law (:func:`jaxdem.core.laws.held_elastic`): of the springs loaded
    beyond their strength, those whose excess (:func:`jaxdem.core.laws.excess_ratio`) is
    at least :data:`FAIL_TOGETHER` of the worst. The others are judged again after the
    next sub-step has carried the failed ones' load elsewhere."""
    ratio = jnp.where(sub.geo.active, excess_ratio(ev.fn, ev.fs, sub.prop, sub.failed, band),
                      -1.0)
    worst = jnp.max(ratio, initial=-1.0)
    return (ratio > 0) & (ratio >= FAIL_TOGETHER * worst)


def commit_substep(model: Model, state: State, sub: Sub, pairs, du, ev: Springs, breaks=None,
                   touching: tuple[Sub, Springs] | None = None):
    """Move the blocks by du and commit the springs' forces and states.

    ``ev``: the forces and states to commit (:func:`newton_and_commit`); ``breaks``
    (S,): with ``model.events``, the springs with strength to lose that fail now
    (:func:`breaking`); None: those that slipped or opened. ``touching``: the packed
    sub-step data and its evaluation (:func:`pack_slots`), which hold every slot that
    carries a force: the balance and admissibility are summed over them alone (the
    same sums: the other slots add zeros); None: over ``sub`` and ``ev``, which then
    need the rows ``Bn``, ``Bs``.

    Returns (state, balance, snapshot): the new state, the global balance of the free
    blocks (:class:`jaxdem.core.state.Balance`) and the contact snapshot (forces at the
    sub-step's points, :class:`jaxdem.core.state.Snapshot`).
    """
    N, D = model.n_blocks, model.ndof
    geo, free = sub.geo, sub.free
    st = ev.state
    active = geo.active
    # A spring fails where it slips or opens (one without strength to lose, a clean
    # joint, loses nothing: a contact that forms later is failed from the start,
    # slot_fields_of). Event by event (``breaks`` given, :func:`breaking`), a spring with
    # strength to lose fails where ``breaks`` says.
    opened = (st == OPEN) & ((sub.prop.tension > 0) | (ev.gap > model.touch_tol))
    slipped = active & ~sub.prop.bonded & ((st == SLIP) | opened)
    if breaks is None:
        failed_new = sub.failed | slipped
    else:
        failed_new = sub.failed | (slipped & ~has_strength(sub.prop)) | breaks
    moved = move_blocks(model, state, du, ev.stress)
    shape = state.fs.shape
    new_state = dataclasses.replace(
        moved, pairs=pairs, fs=ev.fs.reshape(shape), fn=ev.fn.reshape(shape),
        fn0=sub.fn0.reshape(shape), failed=failed_new.reshape(shape),
        edge=geo.edge.reshape(shape), cstate=st.reshape(shape),
        present=active.reshape(shape), gap=ev.gap.reshape(shape))
    if model.n_bolts:
        rest = bolt_rest_length(model, sub, ev.bolt_length, ev.bolt_force, ev.bolt_state)
        new_state = dataclasses.replace(
            new_state, bolt_force=ev.bolt_force, bolt_state=ev.bolt_state,
            bolt_rest=jnp.where(sub.bolt.active, rest, state.bolt_rest))
    # Global balance (about the origin) of the free blocks: applied loads and
    # the forces from blocks without degrees of freedom (bolts anchored in
    # them included).
    c_xy = state.centroid
    moment = lambda F: F[:, 2] + cross(c_xy, F[:, :2])  # noqa: E731
    tsub, tev = (sub, ev) if touching is None else touching
    ta, tb = tsub.geo.a, tsub.geo.b
    f_row = tsub.Bn * tev.total_n[:, None] - tsub.Bs * tev.fs[:, None]
    reaction = (jax.ops.segment_sum(jnp.where((~free[tb])[:, None], f_row[:, :3], 0.0), ta, N)
                + jax.ops.segment_sum(jnp.where((~free[ta])[:, None], f_row[:, D:D + 3], 0.0),
                                      tb, N))
    if model.n_bolts:
        bolt = sub.bolt
        rows = ev.bolt_rows
        reaction = reaction + (
            jax.ops.segment_sum(jnp.where((~free[bolt.b])[:, None], rows[:, :3], 0.0),
                                bolt.a, N)
            + jax.ops.segment_sum(jnp.where((~free[bolt.a])[:, None], rows[:, D:D + 3], 0.0),
                                  bolt.b, N))
    # The imbalance is relative to the forces in play: the summed loads and
    # reactions, or, where both are nil (an in-situ stress that balances
    # itself, with no load), the largest spring force carried at the start or
    # the end of the sub-step (the forces the convergence test, block_scale,
    # was relative to: an in-situ force released to nothing is still the
    # scale its block was balanced to), and at least the convergence test's
    # floor (1e-3 f_ref), so that round-off over round-off does not read as
    # an imbalance of 1.
    carried = jnp.maximum(jnp.abs(tev.total_n) + jnp.abs(tev.fs),
                          jnp.abs(tsub.fn0) + jnp.abs(tsub.fs_old) + jnp.abs(tsub.pw))
    carried = jnp.max(jnp.where(tsub.geo.active, carried, 0.0), initial=0.0)
    carried = jnp.maximum(carried, 1e-3 * model.f_ref)
    overlap, overlap_rel, excess = _admissibility(model, tsub, tev)
    balance = Balance(
        overlap=overlap, overlap_rel=overlap_rel, excess=excess,
        applied=jnp.stack([sub.load[:, 0].sum(), sub.load[:, 1].sum(), moment(sub.load).sum()]),
        reaction=jnp.stack([reaction[:, 0].sum(), reaction[:, 1].sum(), moment(reaction).sum()]),
        scale=jnp.maximum(jnp.maximum(jnp.sum(jnp.linalg.norm(reaction[:, :2], axis=1)),
                                      jnp.sum(jnp.linalg.norm(sub.load[:, :2], axis=1))),
                          carried),
    )
    joint = active & ~sub.prop.bonded & ~model.joint_intact[geo.joint]
    snapshot = Snapshot(point=geo.point, normal=geo.normal, a=geo.a, b=geo.b, active=active,
                        fn=ev.fn, fs=ev.fs, pw=ev.total_n - ev.fn, state=st, joint=joint)
    return new_state, balance, snapshot


def _admissibility(model: Model, sub: Sub, ev: Springs):
    """How far the sub-step's answer is from admissible (:data:`jaxdem.core.status.OVERLAP_TOL`):
    (overlap, overlap_rel, excess).

    ``overlap`` (m): the deepest interpenetration at a contact; ``overlap_rel``: the
    same relative to the smaller block's size; ``excess``: the largest excess of a
    contact's forces over its strength (Mohr-Coulomb, tension cut-off), relative
    to the force scale of its blocks. The contact law itself never exceeds its
    strength; a slot held frozen in its state may, by up to the tolerance.
    """
    geo, prop = sub.geo, sub.prop
    a, b, active = geo.a, geo.b, geo.active
    size = jnp.where(sub.free, model.radius, jnp.inf)
    size = jnp.minimum(size[a], size[b])
    size = jnp.where(jnp.isfinite(size), size, jnp.maximum(model.radius[a], model.radius[b]))
    depth = jnp.where(active, jnp.maximum(-ev.gap, 0.0), 0.0)
    bonded = prop.bonded & ~sub.failed
    over = overload(ev.fn, ev.fs, prop, sub.failed)
    scale = jnp.where(sub.free, block_scale(model, sub, ev), 0.0)
    scale = jnp.maximum(jnp.maximum(scale[a], scale[b]), model.f_ref * 1e-3)
    excess = jnp.where(active & ~bonded & (ev.state != OPEN), jnp.maximum(over, 0.0) / scale,
                       0.0)
    return (jnp.max(depth, initial=0.0), jnp.max(depth / size, initial=0.0),
            jnp.max(excess, initial=0.0))


def substep(model: Model, state: State, loads: Loads, warm=False, loop=None):
    """Detect contacts, iterate to equilibrium at fixed geometry, commit the motion.

    ``need.new_failures`` says whether a spring with cohesion or tensile strength
    failed in this sub-step (first slipped or opened; with ``model.events``, loaded
    beyond its strength in the iteration, which holds it elastic until then:
    :func:`breaking`): it loses them from the next sub-step on, so the increment
    cannot end here (a slot that failed would be reported with its intact strength). A
    clean joint's spring has nothing to lose: its slip asks for no further sub-step.
    ``warm`` and ``loop``: see :func:`_newton`.
    """
    # The rows Bn, Bs are formed for the touching slots alone (pack_slots), and the
    # balance summed over them: formed for all the detection's slots, gathered and summed
    # over, they cost seed example 3 with D 69 ms of a 313 ms sub-step (294,912 slots,
    # 8,370 touching; BENCHMARKS.md, "Thirty-eighth session").
    mdl, sub, st0, pairs, found = prepare_substep(model, state, loads, rows=False)
    return newton_and_commit(mdl, state, sub, st0, pairs, found, warm, loop)


def pack_slots(model: Model, sub: Sub, st0, centroid=None):
    """The touching slots of ``sub`` packed into C = ``model.slots_per_pair`` x Pt places,
    and their pairs into Pt = ``model.touch_capacity`` (at most the P candidate pairs).

    Of the S = P x 2 x V slots of the detection only the touching ones (``active``, within
    the contact margin) carry springs, and the geometry does not change during a
    sub-step's Newton iteration: it works on them alone (a tenth of S on the demo tunnel:
    4,478 of 36,864), which makes its evaluations and its assembly that much cheaper.
    Of the P candidate pairs, only those with a touching slot couple their blocks (seed
    example 2: 2,529 of 8,678): the assembly sums those pairs' slots alone, into that many
    blocks of the matrix. Empty places are inactive with zero rows. The packed list keeps
    the detection's order, so each pair's slots lie side by side: ``grid`` (touch_capacity,
    m) gives their places, m = :func:`pair_places`, for the assembly's sum over a pair's
    springs (:func:`jaxdem.core._linsolve.stiffness_blocks`), ``first`` and ``second`` the
    pair's blocks. Returns (packed sub, its starting states, the (C,) slot indices, S for
    an empty place; too many: more touching slots than C, or a pair with more than m, so
    that the increment ends with a capacity overflow and the driver doubles
    ``slots_per_pair``; the number of touching pairs, which the driver compares with
    ``touch_capacity``). Where C >= S, ``sub`` itself and None. Where ``sub`` has no rows
    (``prepare_substep(rows=False)``) they are formed here, at the blocks' ``centroid``.
    """
    S = st0.shape[0]
    two_v = 2 * model.n_vertices
    P = S // two_v
    Pt = min(model.touch_capacity, P)
    C = model.slots_per_pair * Pt
    if C >= S:
        if sub.Bn is None:
            Bn, Bs = slot_rows(model, sub.geo, centroid)
            sub = dataclasses.replace(sub, Bn=Bn, Bs=Bs)
        return sub, st0, None, jnp.array(False), jnp.array(0)
    active = sub.geo.active
    count = jnp.sum(active)
    touching = jnp.any(active.reshape(P, two_v), axis=1)
    pair = jnp.nonzero(touching, size=Pt, fill_value=P)[0]
    sid = jnp.nonzero(active, size=C, fill_value=S)[0]
    # Each touching pair's run of places [start, end) in the packed list.
    owner = sid // two_v
    start = jnp.searchsorted(owner, pair, side="left")
    end = jnp.where(pair < P, jnp.searchsorted(owner, pair, side="right"), start)
    m = pair_places(model)
    grid = start[:, None] + jnp.arange(m)
    grid = jnp.where(grid < end[:, None], grid, C)
    real = sid < S
    at = jnp.minimum(sid, S - 1)

    def take(x):
        x = x[at]
        return jnp.where(real.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.zeros_like(x))

    geo = jax.tree.map(lambda v: v[at], sub.geo)
    if sub.Bn is None:
        Bn, Bs = (jnp.where(real[:, None], r, 0.0) for r in slot_rows(model, geo, centroid))
    else:
        Bn, Bs = take(sub.Bn), take(sub.Bs)
    geo = geo._replace(active=geo.active & real)
    of_pair = lambda x: x.reshape(P, -1)[jnp.minimum(pair, P - 1), 0]  # noqa: E731
    packed = Sub(geo=geo, prop=jax.tree.map(lambda v: v[at], sub.prop), Bn=Bn,
                 Bs=Bs, fs_old=take(sub.fs_old), fn0=take(sub.fn0),
                 failed=take(sub.failed), pw=take(sub.pw), bolt=sub.bolt, load=sub.load,
                 free=sub.free, stress=sub.stress, Kc=sub.Kc,
                 packed=Packing(slot=sid, first=of_pair(sub.geo.a), second=of_pair(sub.geo.b),
                                grid=grid))
    too_many = (count > C) | jnp.any(end - start > m)
    return packed, st0[at], sid, too_many, jnp.sum(touching)


def pair_places(model: Model) -> int:
    """How many touching slots of one pair the assembly sums (:func:`pack_slots`'s grid):
    twice ``slots_per_pair``, at most 2 V. Two convex blocks touch at one or two points
    (a corner, the ends of a face against a face), each seen from one side or both: four
    slots, a fifth where a third vertex lies within the contact margin (the bundled
    examples: 146 of 14,117 touching pairs of seed example 2, none with six). A pair with
    more flags a capacity overflow, and the places double with ``slots_per_pair``."""
    return min(2 * model.slots_per_pair, 2 * model.n_vertices)


def corner_bound(model: Model, sub: Sub, centroid, corners: Corners, du, capacity: int):
    """The largest scale s <= 1 of ``du`` at which no corner has passed into another block,
    and whether more vertices were watched than ``capacity`` (the bound is over
    ``capacity`` of them at most: an overflow, which doubles the places).

    A vertex that comes to another block at one of its nodes, outside the span of both
    faces that meet there (corner to corner), or at the end of a face that meets its
    own end to end, has no spring (:func:`jaxdem.core._contact.narrow_phase`), so nothing
    in the Newton step stops it: it would pass a whole step length into the other block
    before the next detection saw it. Near the node that block is the intersection of
    the two faces' half-planes, so the vertex is inside once it is behind both lines.
    Along the step (linearised, the rows of :func:`jaxdem.core.kinematics.b_rows`) its
    distance from face i is d_i + s delta_i; each face keeps it out on an interval of
    s, and the bound is where their union, from s = 0, ends: the vertex behind both
    faces by :data:`CORNER_PASS` of the smaller block's step length (elastic
    compression of the blocks around a node of a grid, whose diagonal corners meet,
    stays far below it). A vertex already behind both is left to its spring, which the
    next detection gives it.
    """
    geo = sub.geo
    a, b, p = geo.a, geo.b, geo.point
    S = a.shape[0]
    watch = corners.watch
    if capacity < S:
        # The watched vertices alone (seed example 2: 9,261 of 196,608 slots; the rows of
        # all of them cost 23 ms a sub-step).
        at = jnp.nonzero(watch, size=capacity, fill_value=S)[0]
        full = jnp.sum(watch) > capacity
        watch = at < S
        at = jnp.minimum(at, S - 1)
        a, b, p = a[at], b[at], p[at]
        corners = jax.tree.map(lambda v: v[at], corners)
    else:
        full = jnp.array(False)
    step = block_steps(model)
    tol = CORNER_PASS * jnp.minimum(step[a], step[b])
    rel = gather_pairs(du, a, b)
    d = corners.node_gap
    inf = jnp.inf
    # Both faces at once, the second's vertices after the first's (one copy of the rows
    # in the program).
    K = a.shape[0]
    two = lambda x: jnp.concatenate([x, x])  # noqa: E731
    rows = b_rows(sub.free, two(a), two(b), two(p), two(p),
                  jnp.concatenate([corners.node_normal[:, 0], corners.node_normal[:, 1]]),
                  centroid, model.ndof)
    delta = jnp.sum(rows * two(rel), axis=1).reshape(2, K)
    # Out of the block on [start, end): from 0 until it crosses the line going
    # in; or, behind the line now, from when it comes back out. s at which the
    # vertex is tol behind the line (inf where it never gets there):
    safe = jnp.where(delta != 0, delta, 1.0)
    crossing = jnp.where(delta != 0, -(d.T + tol) / safe, inf)
    out = d.T > -tol
    end = jnp.where(out & (delta < 0), crossing, inf)
    start = jnp.where(out, 0.0, jnp.where(delta > 0, crossing, inf))
    reach = jnp.maximum(jnp.where(start[0] <= 0, end[0], 0.0),
                        jnp.where(start[1] <= 0, end[1], 0.0))
    for i in range(2):
        reach = jnp.where(start[i] <= reach, jnp.maximum(reach, end[i]), reach)
    # Half the pass behind both: the narrow phase gives it a spring (round-off leaves a
    # vertex cut at the whole pass a little short of it).
    inside = (d[:, 0] <= -0.5 * tol) & (d[:, 1] <= -0.5 * tol)
    reach = jnp.where(watch & ~inside, reach, inf)
    return jnp.minimum(jnp.min(reach, initial=inf), 1.0), full


def _unpacked(model: Model, sub: Sub, ev: Springs, sid) -> Springs:
    """What :func:`commit_substep` reads of an evaluation on the packed slots
    (:func:`pack_slots`), laid out over all of ``sub``'s: the rest carry no spring
    (forces 0, OPEN, their gaps and water forces as detected), as an evaluation of all
    of them gives; the blocks' and bolts' fields as they are, the slots' others None."""
    def put(x, rest):
        return rest.at[sid].set(x, mode="drop")

    zero = jnp.zeros_like(sub.fn0)
    return Springs(
        fn=put(ev.fn, zero), fs=put(ev.fs, zero), gap=put(ev.gap, sub.geo.gap),
        state=put(ev.state, jnp.full(sub.fn0.shape, OPEN, jnp.int32)),
        total_n=put(ev.total_n, sub.pw if model.has_water else zero), stress=ev.stress,
        bolt_force=ev.bolt_force, bolt_state=ev.bolt_state, bolt_length=ev.bolt_length,
        bolt_g=ev.bolt_g, bolt_Hv=ev.bolt_Hv, bolt_Hc=ev.bolt_Hc,
        bolt_rows=ev.bolt_rows)


def newton_and_commit(mdl: Model, state: State, sub: Sub, st0, pairs, found: Detection,
                      warm=False, loop=None):
    """The rest of :func:`substep` once contacts are detected (``found``): Newton (on the
    touching slots: :func:`pack_slots`), then commit. Returns (the new state, du, the
    :class:`Iterate` at the end, the :class:`Needs`, the balance, the snapshot).

    The step is cut where a corner without a spring would pass into another block
    (:func:`corner_bound`): the sub-step then ends short of equilibrium, and the next
    detection gives that corner its spring. ``warm`` and ``loop``: see :func:`_newton`.
    """
    packed, st0_packed, sid, too_many, touching = pack_slots(mdl, sub, st0, state.centroid)
    c = _newton(mdl, packed, st0_packed, warm, loop)
    scale, watch_full = corner_bound(mdl, sub, state.centroid, found.corners, c.du,
                                     packed.geo.a.shape[0])
    too_many = too_many | watch_full
    cut = scale < 1.0
    c = c._replace(du=jnp.where(cut, scale * c.du, c.du), converged=c.converged & ~cut,
                   clipped=c.clipped | cut)
    du = c.du
    # A converged sub-step returns (and commits) the law's own forces and
    # states, which balance the blocks; one cut short keeps the frozen ones. Event by
    # event, the springs that fail are found on the iteration's forces (elastic until
    # they fail), and every spring is committed with the law's: one over its strength
    # carries that strength (cohesion included: it fails now, or is judged again after
    # the next sub-step). Committed elastic beyond their strength instead, seed example
    # 3's rock loaded by its weight took up to 356 Newton iterations an increment
    # instead of 75 (BENCHMARKS.md "Twentieth session").
    band = force_scales(mdl, packed)[1]
    frozen = c.frozen & ~c.converged
    ev = evaluate(mdl, packed, du, frozen, c.frozen_state, c.st, band)
    breaks = None
    if mdl.events:
        breaks = breaking(packed, ev, band)
        ev = evaluate(mdl, packed, du, frozen, c.frozen_state, c.st, band, held=False)
    du = du.astype(sub.load.dtype)  # the blocks move in the scene's dtype
    touching_ev = (packed, ev)  # the rows are the packed slots' (sub may have none)
    if sid is not None:
        ev = _unpacked(mdl, sub, ev, sid)
        if breaks is not None:
            breaks = jnp.zeros(sub.fn0.shape, bool).at[sid].set(breaks, mode="drop")
    new_state, balance, snapshot = commit_substep(mdl, state, sub, pairs, du, ev, breaks,
                                                  touching_ev)
    # Only a failure that takes strength away is one: a slot without cohesion or
    # tensile strength (a clean joint) that slips or opens carries the same law after.
    weakened = new_state.failed.reshape(-1) & ~sub.failed & has_strength(sub.prop)
    need = Needs(pairs=found.pairs, cell_full=found.cell_full, slots_full=too_many,
                 touching=touching, new_failures=jnp.any(weakened))
    return new_state, du, c, need, balance, snapshot
