"""The Newton iteration on the touching slots alone (jaxdem.core._substep.pack_slots).

Of the P x 2 x V slots of a sub-step's detection only the touching ones carry springs,
and the geometry does not change during the sub-step's Newton iteration, so the iteration
on those slots packed into ``slots_per_pair`` x ``touch_capacity`` places (the touching
pairs' slots) is the iteration on all of them:
the same iterates, states and answer, to the round-off of a different order of summation.
Where more slots touch than there are places, the increment ends with a capacity
overflow and the driver doubles the places and redoes it: nothing is left out.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from scenes import jointed_tunnel

from jaxdem import solver
from jaxdem.core import model as model_mod
from jaxdem.core._springs import evaluate
from jaxdem.core._substep import (
    _newton,
    _unpacked,
    commit_substep,
    force_scales,
    pack_slots,
    pair_places,
    prepare_substep,
)
from jaxdem.core.loads import make_loads
from jaxdem.scene import parse_scene


def _solve(scene, slots_per_pair: int):
    """The finished driver of a solve with ``slots_per_pair`` places per candidate pair."""
    model, state, layout = model_mod.build(scene)
    model = dataclasses.replace(model, slots_per_pair=slots_per_pair)
    return solver.run(scene, model, state, layout, solver.scene_data(scene, layout))


def _tunnel(linear_solver: str):
    d = jointed_tunnel(load_steps=2)
    d["solver"]["linear_solver"] = linear_solver
    return parse_scene(d)


@pytest.mark.parametrize("linear_solver", ["dense", "sparse", "cg"])
def test_packed_newton_gives_the_answer_of_all_slots(linear_solver):
    """A jointed tunnel with water, a bolt and a support: packed (3 places a pair) and
    unpacked (2 V places a pair: every slot) take the same Newton iterations in every
    increment and end with the same contact states, forces and displacements (1e-9 of
    the largest; the tunnel's tolerance is 1e-9)."""
    scene = _tunnel(linear_solver)
    packed = _solve(scene, 3)
    full = _solve(scene, 2 * packed.model.n_vertices)
    assert packed.status == full.status and packed.status.value == "converged"
    assert [r["iterations"] for r in packed.records] == [r["iterations"] for r in full.records]
    a, b = packed.state, full.state
    np.testing.assert_array_equal(np.asarray(a.cstate), np.asarray(b.cstate))
    for name in ("u", "rot", "fn", "fs", "bolt_force"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-9 * max(np.abs(y).max(), 1e-30),
                                   err_msg=name)


def test_more_touching_slots_than_places_grow_the_places_and_redo_the_increment():
    """With one place per candidate pair the tunnel's sub-steps have more touching slots
    than places (a face-to-face contact touches with two slots): the increment overflows,
    the driver doubles ``slots_per_pair`` until they fit, and the answer is that of all
    slots."""
    scene = _tunnel("dense")
    grown = _solve(scene, 1)
    full = _solve(scene, 2 * grown.model.n_vertices)
    assert grown.model.slots_per_pair >= 2
    assert grown.status == full.status
    assert [r["iterations"] for r in grown.records] == [r["iterations"] for r in full.records]
    np.testing.assert_allclose(np.asarray(grown.state.u), np.asarray(full.state.u), rtol=0,
                               atol=1e-9 * np.abs(np.asarray(full.state.u)).max())


def test_more_touching_pairs_than_places_grow_them_and_redo_the_increment():
    """With places for 8 touching pairs (``touch_capacity``) the tunnel has more: the
    increment overflows, the driver grows the places, and the answer is that of all
    slots, in the same iterations."""
    scene = _tunnel("sparse")
    model, state, layout = model_mod.build(scene)
    tight = solver.run(scene, dataclasses.replace(model, touch_capacity=8), state, layout,
                       solver.scene_data(scene, layout))
    full = _solve(scene, 2 * tight.model.n_vertices)
    assert tight.model.touch_capacity > 8
    assert tight.status == full.status and tight.status.value == "converged"
    assert [r["iterations"] for r in tight.records] == [r["iterations"] for r in full.records]
    np.testing.assert_allclose(np.asarray(tight.state.u), np.asarray(full.state.u), rtol=0,
                               atol=1e-9 * np.abs(np.asarray(full.state.u)).max())


def test_each_pairs_places_hold_its_touching_slots_and_one_more_overflows():
    """The assembly sums each touching pair's slots from ``pack_slots``'s grid: row q of
    the grid is the q-th touching pair (in the detection's order), every entry of it a
    packed place of that pair, and together they are all its touching slots; the rows
    past the touching pairs are empty. A pair with more touching slots than its places
    (m = 4 with two places per touching pair) flags the overflow that doubles the places,
    although the packed list itself has room."""
    model, state, _ = model_mod.build(parse_scene(jointed_tunnel(water=False, bolts=False)))
    model = dataclasses.replace(model, slots_per_pair=2)
    loads = make_loads(model, model.f_ext)
    mdl, sub, st0, _, _ = prepare_substep(model, state, loads)
    packed, _, sid, too_many, touching = pack_slots(mdl, sub, st0)
    assert not bool(too_many)
    two_v = 2 * model.n_vertices
    active = np.asarray(sub.geo.active)
    pairs = np.flatnonzero(active.reshape(-1, two_v).any(axis=1))
    assert int(touching) == len(pairs) > 0
    grid, sid = np.asarray(packed.packed.grid), np.asarray(sid)
    assert grid.shape[1] == pair_places(model) == 4 and grid.shape[0] >= len(pairs)
    first = np.asarray(packed.packed.first)
    for q in range(grid.shape[0]):
        places = grid[q][grid[q] < sid.shape[0]]
        if q >= len(pairs):
            assert places.size == 0
            continue
        p = pairs[q]
        assert first[q] == np.asarray(sub.geo.a)[p * two_v]
        assert sorted(sid[places]) == list(np.flatnonzero(active[p * two_v:(p + 1) * two_v])
                                           + p * two_v)
    # Five touching slots on one pair (the list has room).
    crowded = active.copy()
    crowded[:5] = True
    assert crowded.sum() <= 2 * grid.shape[0]
    sub5 = dataclasses.replace(sub, geo=sub.geo._replace(active=jnp.asarray(crowded)))
    assert bool(pack_slots(mdl, sub5, st0)[3])
    crowded[4] = False
    crowded[5:two_v] = False
    sub4 = dataclasses.replace(sub, geo=sub.geo._replace(active=jnp.asarray(crowded)))
    assert not bool(pack_slots(mdl, sub4, st0)[3])


def test_touching_pairs_at_the_start_are_those_that_bear_or_meet():
    """The estimate of the touching pairs (``model._touching``, which sizes the places):
    a square resting on another (faces anti-parallel, overlapping) and one meeting it
    corner to corner (faces anti-parallel, end to end: they come to touch as the blocks
    settle) touch; one 0.5 m away does not (margin 0.1 m), nor one whose vertex is inside
    the margin of a face's line but beyond its end."""
    def square(x, y):
        return [[x, y], [x + 1, y], [x + 1, y + 1], [x, y + 1]]

    blocks = [square(0, 0), square(1, 0), square(1.5, 1.0), square(1, 1.05), square(-1.05, 1.5)]
    verts = np.array(blocks, float)
    nv = np.full(len(blocks), 4)
    pairs = (np.array([0, 0, 1, 0, 0]), np.array([1, 2, 2, 3, 4]))
    touching = model_mod._touching(verts, nv, pairs, 0.1, 1e-3)
    # 0-1 side by side; 0-2 0.5 m apart; 1-2 (1.5, 1) rests on 1's top face; 0-3 corner
    # to corner 0.05 m apart (within the margin, faces meeting end to end); 0-4 beyond
    # the end of 0's top face, 0.05 m to the side of its left face's line but above it.
    np.testing.assert_array_equal(touching, [True, False, True, True, False])
    assert model_mod._touch_capacity(verts, nv, pairs, 0.1, 1e-3) == model_mod.bucket(
        int(1.5 * 3) + 16)


def test_rows_formed_for_the_touching_slots_and_the_balance_over_them_are_all_slots():
    """A sub-step forms the rows Bn, Bs of the touching slots alone (``prepare_substep``
    leaves them out, ``pack_slots`` forms them on its places) and sums the balance over
    those places: the same rows as the detection's for every slot, taken to the places
    (zero rows on empty ones), and the same balance and admissibility as summed over all
    the P x 2 V slots (a slot that touches nothing carries no force: it adds zeros). The
    jointed tunnel with water and a bolt, 3 places a pair, at the first sub-step's
    answer."""
    model, state, _ = model_mod.build(parse_scene(jointed_tunnel(water=True, bolts=True)))
    model = dataclasses.replace(model, slots_per_pair=3)
    loads = make_loads(model, model.f_ext)
    mdl, whole, st0, pairs, _ = prepare_substep(model, state, loads)
    lean = prepare_substep(model, state, loads, rows=False)[1]
    assert lean.Bn is None and lean.Bs is None
    packed, st0p, sid, _, _ = pack_slots(mdl, lean, st0, state.centroid)
    taken = pack_slots(mdl, whole, st0)[0]
    assert sid is not None and packed.Bn.shape[0] < whole.Bn.shape[0]
    for name in ("Bn", "Bs"):
        np.testing.assert_array_equal(np.asarray(getattr(packed, name)),
                                      np.asarray(getattr(taken, name)), err_msg=name)
    assert np.abs(np.asarray(packed.Bn)).max() > 0
    c = _newton(mdl, packed, st0p)
    assert bool(c.converged)
    band = force_scales(mdl, packed)[1]
    ev = evaluate(mdl, packed, c.du, jnp.zeros(st0p.shape, bool), c.frozen_state, c.st, band)
    laid = _unpacked(mdl, whole, ev, sid)
    du = c.du.astype(whole.load.dtype)
    _, over_all, _ = commit_substep(mdl, state, whole, pairs, du, laid)
    _, over_touching, _ = commit_substep(mdl, state, lean, pairs, du, laid, None, (packed, ev))
    assert float(jnp.linalg.norm(over_all.reaction)) > 0
    for name in over_all._fields:
        np.testing.assert_allclose(np.asarray(getattr(over_touching, name)),
                                   np.asarray(getattr(over_all, name)), rtol=1e-13, atol=0,
                                   err_msg=name)


@pytest.mark.parametrize("places", ["packed", "all slots"])
def test_sparse_pattern_formed_once_is_every_iterations_triplet_indices(places):
    """The sparse path forms its triplets' indices and the springs' rows laid out by pair
    once a sub-step (``_linsolve.sparse_pattern``), and every iteration the values alone:
    the indices are those that each iteration's matrix forms for itself: the secant, the
    slip tangent's symmetric part and the whole slip tangent (a third group of terms,
    its coupling, summed into the pairs' blocks), upper triangle and whole, bolts
    included; the blocks summed from the rows laid out before are the same, bit for bit.
    The jointed tunnel with water and a bolt, 3 places a pair or every slot, at the first
    sub-step's answer."""
    from jaxdem.core import _linsolve
    from jaxdem.core._springs import slip_coupling, stiffness_terms, with_coupling

    model, state, _ = model_mod.build(parse_scene(jointed_tunnel(water=True, bolts=True)))
    assert model.n_bolts > 0
    model = dataclasses.replace(model, slots_per_pair=3)
    loads = make_loads(model, model.f_ext)
    mdl, sub, st0, _, _ = prepare_substep(model, state, loads)
    if places == "packed":
        sub, st0 = pack_slots(mdl, sub, st0)[:2]
        assert sub.packed is not None
    c = _newton(mdl, sub, st0)
    band = force_scales(mdl, sub)[1]
    ev = evaluate(mdl, sub, c.du, jnp.zeros(st0.shape, bool), c.frozen_state, c.st, band)
    diag = _linsolve.pseudo_mass_diagonal(mdl, sub)
    up, both, paired = _linsolve.sparse_pattern(mdl, sub)
    for tangent in (False, True):
        a, b, B, k = stiffness_terms(mdl, sub, ev, tangent, None)
        sym = _linsolve.stiffness_blocks(mdl, sub, a, b, B, B, k, diag)
        # The springs' rows laid out by pair once a sub-step: the same blocks, bit for bit.
        for x, y in zip(_linsolve.stiffness_blocks(mdl, sub, a, b, B, B, k, diag, paired), sym,
                        strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        coupling = slip_coupling(sub, ev, jnp.asarray(tangent))
        whole = _linsolve.stiffness_blocks(mdl, sub, *with_coupling((a, b, B, k), coupling,
                                                                     sub.geo.a.shape[0]), diag)
        for blocks, upper, index in ((sym, True, up), (sym, False, both), (whole, False, both)):
            formed = _linsolve.coo_of_blocks(mdl, *blocks, upper=upper)
            given = _linsolve.coo_of_blocks(mdl, *blocks, upper=upper, index=index)
            for x, y in zip(formed, given, strict=True):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
