"""Contact kernels on tiny named cases, against hand-worked geometry.

Cases: "face" (aligned faces: two points, Le = face length, eq. 8), "offset"
(partly overlapping faces: Le = the overlap), "corner" (a corner on a face:
one point, Le = corner_share x shorter adjacent face), "apart" (beyond the
margin: nothing), "touching" (exactly touching faces are in contact), "deep"
(overlapping blocks: negative gap), plus the broad phase (grid cells against
all pairs) and the kernels under jit and vmap.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import ROCK

from jaxdem.core import model as model_mod
from jaxdem.core._contact import broad_phase, narrow_phase
from jaxdem.scene import parse_scene


def _scene(blocks, **solver):
    return parse_scene({
        "scene": {"name": "contact case"},
        "solver": solver,
        "materials": {"rock": dict(ROCK)},
        "joints": {"j": {"kn": 1e6, "ks": 1e6, "friction_deg": 30.0}},
        "blocks": [{"vertices": v, "material": "rock"} for v in blocks],
    })


def _square(x, y, w=1.0, h=1.0):
    return [[x, y], [x + w, y], [x + w, y + h], [x, y + h]]


def _rotated_square(cx, cy, angle_deg, side=1.0):
    a = math.radians(angle_deg)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    half = side / 2
    pts = np.array([[-half, -half], [half, -half], [half, half], [-half, half]]) @ R.T
    return (pts + [cx, cy]).tolist()


def _slots(blocks, **solver):
    model, state, _ = model_mod.build(_scene(blocks, **solver))
    pairs, count, _ = broad_phase(model, state.verts, state.capacity, state.alive)
    geo, _ = narrow_phase(model, state.verts, state.centroid, pairs)
    act = np.asarray(geo.active)
    return jax.tree.map(lambda v: np.asarray(v)[act], geo), model


def _ends(g, decimals=9):
    """{contact point: summed share (m)}: a point where both blocks have a corner is a
    slot on each side, with half the share each (order-independent)."""
    out = {}
    for p, s in zip(np.round(g.point, decimals), g.share, strict=True):
        out[tuple(p)] = out.get(tuple(p), 0.0) + float(s)
    return out


def test_face_gives_two_points_sharing_the_face_length():
    g, _ = _slots([_square(0, 0, 2, 1), _square(0, 1, 2, 1)])
    # The corners coincide: each end is found from both blocks, half the share each.
    assert len(g.gap) == 4
    np.testing.assert_allclose(g.share, 0.5)
    ends = _ends(g)
    assert sorted(ends) == [(0.0, 1.0), (2.0, 1.0)]
    np.testing.assert_allclose(list(ends.values()), [1.0, 1.0])  # Le = 2 m, half each
    np.testing.assert_allclose(np.abs(g.normal[:, 1]), 1.0)
    np.testing.assert_allclose(g.gap, 0.0, atol=1e-12)
    # Distances from the contact line to both centroids (eqs. 6-7).
    np.testing.assert_allclose(g.h_a, 0.5)
    np.testing.assert_allclose(g.h_b, 0.5)


def test_offset_faces_share_the_overlap():
    # Upper block shifted 0.6 m: the faces overlap over 1.4 m, from x = 0.6 to 2.0.
    g, _ = _slots([_square(0, 0, 2, 1), _square(0.6, 1, 2, 1)])
    assert len(g.gap) == 2
    np.testing.assert_allclose(np.sort(g.point[:, 0]), [0.6, 2.0], atol=1e-12)
    np.testing.assert_allclose(g.share, [0.7, 0.7])


def test_corner_on_a_face_gives_one_point():
    # A square standing on its corner (45 degrees) on a wide block.
    h = math.sqrt(2) / 2
    g, model = _slots([_square(-2, -1, 4, 1), _rotated_square(0.0, h, 45.0)])
    assert len(g.gap) == 1
    np.testing.assert_allclose(g.point[0], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(g.normal[0], [0.0, 1.0], atol=1e-12)
    assert g.share[0] == pytest.approx(float(model.corner_share) * 1.0)


def test_blocks_beyond_the_margin_have_no_contact():
    g, model = _slots([_square(0, 0), _square(0, 1.5)], step_length=0.05)
    assert len(g.gap) == 0


def test_gap_within_the_margin_is_an_open_slot_with_positive_gap():
    g, _ = _slots([_square(0, 0), _square(0, 1.05)], step_length=0.05)
    # Each end seen from both blocks (corners 5 cm apart), half the share each.
    assert len(g.gap) == 4
    np.testing.assert_allclose(g.gap, 0.05, rtol=1e-12)
    np.testing.assert_allclose(g.share, 0.25)


def test_overlapping_blocks_have_negative_gap_on_the_right_face():
    # The upper block sinks 1 mm into the lower one: the face is the horizontal
    # one (anti-parallel), not the vertical sides the corners also lie on.
    model, state, _ = model_mod.build(_scene([_square(0, 0), _square(0, 1)]))
    verts = state.verts.at[1, :, 1].add(-0.001)  # scenes refuse overlaps: move it here
    pairs, _, _ = broad_phase(model, verts, state.capacity, state.alive)
    geo, _ = narrow_phase(model, verts, state.centroid.at[1, 1].add(-0.001), pairs)
    act = np.asarray(geo.active)
    g = jax.tree.map(lambda v: np.asarray(v)[act], geo)
    # Each end is found from both blocks (their corners 1 mm apart): half the share each.
    assert len(g.gap) == 4
    np.testing.assert_allclose(g.gap, -0.001, rtol=1e-9)
    np.testing.assert_allclose(np.abs(g.normal[:, 1]), 1.0)
    np.testing.assert_allclose(g.share, 0.25)
    np.testing.assert_allclose(sorted(_ends(g, 2).values()), [0.5, 0.5])


def test_side_by_side_blocks_touch_on_the_vertical_face():
    g, _ = _slots([_square(0, 0), _square(1, 0)])
    assert len(g.gap) == 4 and len(_ends(g)) == 2
    np.testing.assert_allclose(np.abs(g.normal[:, 0]), 1.0)


def _grid(n, jitter=0.0, size=0.9, seed=0):
    rng = np.random.default_rng(seed)
    blocks = []
    for i in range(n):
        for j in range(n):
            blocks.append(_square(i + jitter * rng.uniform(), j * 1.0001, size, size))
    return blocks


def test_cell_broad_phase_finds_the_same_pairs_as_all_pairs():
    scene = _scene(_grid(22, jitter=0.1))  # 484 blocks: the grid path
    model, state, _ = model_mod.build(scene)
    assert model.use_cells
    cap = 20 * model.n_blocks
    pairs_cells, count_c, full = broad_phase(model, state.verts, cap, state.alive)
    pairs_all, count_a, _ = broad_phase(dataclasses.replace(model, use_cells=False),
                                        state.verts, cap, state.alive)
    assert not bool(full) and int(count_c) == int(count_a) > 0
    as_set = lambda p: {tuple(x) for x in np.asarray(p) if x[0] < model.n_blocks}  # noqa: E731
    assert as_set(pairs_cells) == as_set(pairs_all)


def test_dead_blocks_neither_size_nor_fill_the_cells():
    """A model past 7 blocks carries dead copies of its first block up to its size
    class. Here the first block is a big base (20 m wide): were its copies taken into
    the cells, the cell would be as wide as the base, every block would share one,
    and the cells would fill (the 20 x 20 grid grew its cell capacity from 12 to 768,
    recompiling six times). Same pairs as the all-pairs search, and no cell full."""
    base = [[-1.0, -1.0], [23.0, -1.0], [23.0, -0.05], [-1.0, -0.05]]
    model, state, _ = model_mod.build(_scene([base] + _grid(22, jitter=0.1)))
    assert model.use_cells and not bool(np.asarray(state.alive)[-1])
    cap = 20 * model.n_blocks
    pairs_cells, count_c, full = broad_phase(model, state.verts, cap, state.alive)
    pairs_all, count_a, _ = broad_phase(dataclasses.replace(model, use_cells=False),
                                        state.verts, cap, state.alive)
    assert not bool(full) and int(count_c) == int(count_a) > 0
    as_set = lambda p: {tuple(x) for x in np.asarray(p) if x[0] < model.n_blocks}  # noqa: E731
    assert as_set(pairs_cells) == as_set(pairs_all)


def test_broad_phase_flags_overflow_instead_of_truncating():
    scene = _scene(_grid(22, size=1.0))
    model, state, _ = model_mod.build(scene)
    _, count, _ = broad_phase(model, state.verts, 10, state.alive)
    assert int(count) > 10
    tight = dataclasses.replace(model, cell_capacity=1)
    _, _, full = broad_phase(tight, state.verts, 10 * model.n_blocks, state.alive)
    assert bool(full)


def test_narrow_phase_jit_matches_eager_and_vmaps_over_positions():
    model, state, _ = model_mod.build(_scene([_square(0, 0, 2, 1), _square(0.3, 1, 1, 1)]))
    pairs, _, _ = broad_phase(model, state.verts, state.capacity, state.alive)
    eager = narrow_phase(model, state.verts, state.centroid, pairs)
    jitted = jax.jit(narrow_phase)(model, state.verts, state.centroid, pairs)
    for x, y in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y))
    shifts = jnp.array([0.0, 0.001, -0.002])
    verts = state.verts[None].repeat(3, 0).at[:, 1, :, 1].add(shifts[:, None])
    batched, _ = jax.vmap(narrow_phase, in_axes=(None, 0, None, None))(
        model, verts, state.centroid, pairs)
    for k in range(3):
        one, _ = narrow_phase(model, verts[k], state.centroid, pairs)
        np.testing.assert_allclose(np.asarray(batched.gap[k]), np.asarray(one.gap))
    act = np.asarray(batched.active[1])
    np.testing.assert_allclose(np.asarray(batched.gap[1])[act], 0.001, rtol=1e-9)


def test_gap_gradient_matches_finite_differences():
    """d(gap)/d(vertical position of the upper block) = 1 for a horizontal face."""
    model, state, _ = model_mod.build(_scene([_square(0, 0, 2, 1), _square(0.3, 1, 1, 1)]))
    pairs, _, _ = broad_phase(model, state.verts, state.capacity, state.alive)
    act = np.asarray(narrow_phase(model, state.verts, state.centroid, pairs)[0].active)

    def total_gap(dy):
        v = state.verts.at[1, :, 1].add(dy)
        return jnp.sum(jnp.where(act, narrow_phase(model, v, state.centroid, pairs)[0].gap, 0.0))

    g = jax.grad(total_gap)(0.0)
    fd = (total_gap(1e-6) - total_gap(-1e-6)) / 2e-6
    assert float(g) == pytest.approx(float(fd), rel=1e-6)
    assert float(g) == pytest.approx(2.0)


def _triangles_under_octagons():
    """Ten unit squares, each cut on its diagonal into two triangles, and three regular
    octagons (flat side down) resting on them: most blocks have 3 vertices, V = 8."""
    blocks = []
    for i in range(10):
        blocks += [[[i, 0], [i + 1, 0], [i + 1, 1]], [[i, 0], [i + 1, 1], [i, 1]]]
    side = 1.0 / (1 + math.sqrt(2))
    for cx in (1.5, 4.5, 7.5):
        r = 0.5 / math.cos(math.pi / 8)
        blocks.append([[cx + r * math.cos(math.pi / 8 * (2 * k - 5)),
                        1.5 + r * math.sin(math.pi / 8 * (2 * k - 5))] for k in range(8)])
    assert abs(blocks[-1][1][0] - blocks[-1][0][0] - side) < 1e-12
    return blocks


def test_narrow_phase_tests_most_pairs_with_their_own_vertex_count():
    """Triangles under octagons (V = 8): the pairs of triangles are tested with their 3
    vertices, those with an octagon with all 8 (``model.narrow_vertices``,
    ``wide_capacity``: :func:`jaxdem.core.model._narrow_split`). The slots are those of
    testing every pair with 8: the same touching slots, and their gaps, points, normals,
    shares and centroid distances to 1e-12 (round-off of a different order of operations).
    Too few places for the wide pairs are an overflow of the detection, not a truncation.
    (So small a scene is not split: it would save too few tests to pay for a second copy
    of the narrow phase in the program. With room for 100,000 pairs it is.)"""
    model, state, _ = model_mod.build(_scene(_triangles_under_octagons()))
    assert model.n_vertices == 8 and model.narrow_vertices == 8
    real = np.asarray(state.alive)  # the dead blocks of the size class left out
    pairs = model_mod._candidate_pairs(np.asarray(state.verts)[real],
                                       np.asarray(model.free)[real], float(model.margin))
    v, wide = model_mod._narrow_split(np.asarray(model.nv)[real], pairs, 100_000)
    assert v == 3 and wide > 0
    model = dataclasses.replace(model, narrow_vertices=v, wide_capacity=wide)
    pairs, _, full = broad_phase(model, state.verts, state.capacity, state.alive)
    assert not bool(full)
    split, _ = narrow_phase(model, state.verts, state.centroid, pairs)
    whole, _ = narrow_phase(dataclasses.replace(model, narrow_vertices=8), state.verts,
                            state.centroid, pairs)
    act = np.asarray(whole.active)
    np.testing.assert_array_equal(np.asarray(split.active), act)
    # Each octagon's two bottom corners bear on the triangle under it, face to face.
    on_octagons = act & (np.asarray(whole.a) >= 20) | act & (np.asarray(whole.b) >= 20)
    assert on_octagons.sum() >= 6
    for k in ("gap", "point", "normal", "share", "h_a", "h_b", "far_gap"):
        np.testing.assert_allclose(np.asarray(getattr(split, k))[act],
                                   np.asarray(getattr(whole, k))[act],
                                   rtol=0, atol=1e-12, err_msg=k)
    for k in ("edge", "own_edge", "joint", "halved", "a", "b"):
        np.testing.assert_array_equal(np.asarray(getattr(split, k))[act],
                                      np.asarray(getattr(whole, k))[act])
    tight = dataclasses.replace(model, wide_capacity=1)
    assert bool(broad_phase(tight, state.verts, state.capacity, state.alive)[2])
