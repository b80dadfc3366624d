"""Travel limits of blocks that move together (:mod:`jaxdem.core.kinematics`):
:func:`connected_groups` and :func:`group_limits` under jit and vmap against a plain
union-find loop on random contact graphs. The mechanisms they decide are checked in
tests/test_hard_cases.py (a pair of blocks that falls together) and
tests/verification/test_admissible_mechanism.py (a wedge of seven cells)."""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdem.core.kinematics import connected_groups, group_limits

N, S = 12, 30


def _union_find(moving, a, b, link) -> np.ndarray:
    """The least index of each moving block's group over the links between moving
    blocks, N for a block that does not move: a loop, the reference."""
    parent = list(range(len(moving)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for i, j, on in zip(a, b, link, strict=True):
        if on and moving[i] and moving[j]:
            ri, rj = root(i), root(j)
            parent[max(ri, rj)] = min(ri, rj)
    least = {}
    for i in range(len(moving)):
        if moving[i]:
            least.setdefault(root(i), i)
    return np.array([least[root(i)] if moving[i] else len(moving) for i in range(len(moving))])


def _graphs(seed: int, count: int):
    rng = np.random.default_rng(seed)
    return (rng.random((count, N)) < 0.7, rng.integers(0, N, (count, S)),
            rng.integers(0, N, (count, S)), rng.random((count, S)) < 0.5)


@pytest.mark.parametrize("seed", range(5))
def test_groups_match_a_union_find_eager_jitted_and_batched(seed):
    moving, a, b, link = _graphs(seed, 8)
    expected = np.stack([_union_find(*g) for g in zip(moving, a, b, link, strict=True)])
    eager = np.stack([np.asarray(connected_groups(*map(jnp.asarray, g)))
                      for g in zip(moving, a, b, link, strict=True)])
    jitted = np.stack([np.asarray(jax.jit(connected_groups)(*map(jnp.asarray, g)))
                       for g in zip(moving, a, b, link, strict=True)])
    batched = np.asarray(jax.vmap(connected_groups)(*map(jnp.asarray, (moving, a, b, link))))
    np.testing.assert_array_equal(eager, expected)
    np.testing.assert_array_equal(jitted, expected)
    np.testing.assert_array_equal(batched, expected)


def test_a_chain_is_one_group():
    """A chain 0-1-2-...-11 linked end to end in reverse order (the worst order for one
    sweep of propagation) is one group labelled 0; with the middle link cut, two."""
    a, b = jnp.arange(N - 1)[::-1], jnp.arange(1, N)[::-1]
    moving = jnp.ones(N, bool)
    assert np.all(np.asarray(connected_groups(moving, a, b, jnp.ones(N - 1, bool))) == 0)
    cut = jnp.ones(N - 1, bool).at[N - 1 - 6].set(False)  # the link 5-6
    lab = np.asarray(connected_groups(moving, a, b, cut))
    np.testing.assert_array_equal(lab, [0] * 6 + [6] * 6)


@pytest.mark.parametrize("seed", range(3))
def test_group_limits_are_the_size_of_each_group_between_the_bounds(seed):
    """Each moving block's limit is sqrt(its group's area), clipped to the travel range
    and never below its own; a block that does not move keeps its own; under jit and
    vmap (a batch of travels) as eager."""
    rng = np.random.default_rng(10 + seed)
    area = rng.uniform(0.01, 2.0, N)
    lo, hi = 0.2, 1.0
    own = np.clip(np.sqrt(area), lo, hi)
    free = rng.random(N) < 0.9
    model = types.SimpleNamespace(
        n_blocks=N, free=jnp.asarray(free), max_displacement=jnp.asarray(hi),
        area=jnp.asarray(area), travel_limit=jnp.asarray(own),
        travel_range=jnp.asarray([lo, hi]))
    a, b = rng.integers(0, N, S), rng.integers(0, N, S)
    active = rng.random(S) < 0.4
    snap = types.SimpleNamespace(a=jnp.asarray(a), b=jnp.asarray(b), active=jnp.asarray(active))
    travel = rng.uniform(0.0, 0.5, (4, N))

    def reference(t):
        moving = free & (t > 0.1 * hi)
        lab = _union_find(moving, a, b, active)
        out = own.copy()
        for i in np.flatnonzero(moving):
            shared = np.clip(np.sqrt(area[lab == lab[i]].sum()), lo, hi)
            out[i] = max(shared, own[i])
        return out, lab

    run = jax.jit(lambda t: group_limits(model, snap, t))
    batched = jax.vmap(run)(jnp.asarray(travel))
    for k, t in enumerate(travel):
        want, lab = reference(t)
        for limit, groups in (group_limits(model, snap, jnp.asarray(t)), run(jnp.asarray(t)),
                              (batched[0][k], batched[1][k])):
            np.testing.assert_allclose(np.asarray(limit), want, rtol=1e-12)
            np.testing.assert_array_equal(np.asarray(groups), lab)
