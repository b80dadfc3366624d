"""Generated rock mass: tiling, convexity, labels, openings, mesh, slivers (jaxdem.rockmass)."""

from __future__ import annotations

import math
import time
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxdem import geometry
from jaxdem.rockmass import RockMass, generate
from jaxdem.rockmass._mesh import graded_squares
from jaxdem.scene import SceneError, parse_scene

ROCK = {"E": 1.0e7, "nu": 0.25, "unit_weight": 25.0}
SOFT = {"E": 1.0e6, "nu": 0.3, "unit_weight": 22.0}


def joint_set(dip: float, spacing: float, **extra) -> dict:
    return {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0, "dip_deg": dip, "spacing": spacing, **extra}


def square(size: float) -> list[list[float]]:
    return [[0.0, 0.0], [size, 0.0], [size, size], [0.0, size]]


def rock_scene(outline=None, joints=None, mesh_size=None, **sections):
    domain = {"outline": outline or square(10.0), "material": "rock"}
    if mesh_size is not None:
        domain["mesh_size"] = mesh_size
    data = {
        "scene": {"name": "rock mass"},
        "materials": {"rock": ROCK, "soft": SOFT},
        "joints": joints or {},
        "domain": domain,
        **sections,
    }
    return parse_scene(data)


def total_area(rm: RockMass) -> float:
    return sum(geometry.signed_area(v) for v in rm.polygons())


def edges(rm: RockMass):
    """(a, b, label) for every edge of every piece."""
    for p in rm.pieces:
        v = p.vertices
        for k, label in enumerate(p.edge_labels):
            yield v[k], v[(k + 1) % len(v)], label


def assert_valid(rm: RockMass, area: float) -> None:
    assert rm.pieces
    for p in rm.pieces:
        assert geometry.is_convex(p.vertices), p.vertices  # strictly convex, CCW
        assert len(p.edge_labels) == len(p.vertices)
    assert total_area(rm) == pytest.approx(area, rel=1e-9)
    polys = rm.polygons()
    assert geometry.find_overlapping_pairs(polys, 1e-9 * area) == []


def test_two_orthogonal_persistent_sets_give_unit_squares():
    rm = generate(rock_scene(joints={"a": joint_set(0.0, 1.0), "b": joint_set(90.0, 1.0)}))
    assert len(rm.pieces) == 100
    assert_valid(rm, 100.0)
    for v in rm.polygons():
        assert geometry.signed_area(v) == pytest.approx(1.0, rel=1e-12)
    for a, b, (kind, name) in edges(rm):
        on_outline = (a[0] == b[0] and a[0] in (0.0, 10.0)) or (
            a[1] == b[1] and a[1] in (0.0, 10.0)
        )
        if on_outline:
            assert (kind, name) == ("outer", None)
        else:
            assert kind == "joint"
            assert name == ("a" if a[1] == pytest.approx(b[1]) else "b")
    counts = Counter(label for *_, label in edges(rm))
    assert counts == {("joint", "a"): 180, ("joint", "b"): 180, ("outer", None): 40}


def test_inclined_set_tiles_the_domain_and_labels_its_traces():
    rm = generate(rock_scene(joints={"s": joint_set(30.0, 1.0)}))
    assert_valid(rm, 100.0)
    d = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    n = np.array([-d[1], d[0]])
    c0 = n @ np.array([5.0, 5.0])  # origin defaults to the domain centroid
    n_joint = 0
    for a, b, (kind, name) in edges(rm):
        pa, pb = (n @ a - c0), (n @ b - c0)
        on_trace = abs(pa - round(pa)) < 1e-9 and abs(pb - round(pb)) < 1e-9
        on_trace &= round(pa) == round(pb)
        if kind == "outer":
            continue
        assert on_trace and (kind, name) == ("joint", "s")
        n_joint += 1
    assert n_joint > 0


def test_non_persistent_set_is_jointed_on_half_of_each_line():
    rm = generate(rock_scene(joints={"s": joint_set(0.0, 1.0, persistence=0.5)}))
    assert_valid(rm, 100.0)
    counts = Counter(label[0] for *_, label in edges(rm))
    assert counts["intact"] > 0 and counts["joint"] > 0
    joint_length: dict[float, float] = {}
    for a, b, (kind, _) in edges(rm):
        if kind == "joint":
            y = round(float(a[1]), 6)
            joint_length[y] = joint_length.get(y, 0.0) + float(np.hypot(*(b - a)))
    # Interior lines y = 1..9, each 10 m long; every edge counted from both sides.
    assert sorted(joint_length) == [float(k) for k in range(1, 10)]
    for y, length in joint_length.items():
        assert length / 2.0 == pytest.approx(5.0, rel=0.05), y


def test_gap_sets_the_bridge_and_lines_stagger():
    rm = generate(
        rock_scene(joints={"s": joint_set(0.0, 2.0, persistence=0.75, gap=1.0, origin=[0, 0])})
    )
    assert_valid(rm, 100.0)

    # Trace segments 3 m long, bridges 1 m: on even lines centred at x = 0, 4, 8, on odd
    # lines (y = 2, 6, ...) shifted by half a period, 2 m.
    def joint_intervals(y: float) -> list[tuple[float, float]]:
        parts = sorted(
            (round(float(min(a[0], b[0])), 6), round(float(max(a[0], b[0])), 6))
            for a, b, (kind, _) in edges(rm)
            if kind == "joint" and a[1] == pytest.approx(y) and b[1] == pytest.approx(y)
        )
        merged: list[list[float]] = []
        for lo, hi in parts:
            if merged and lo <= merged[-1][1] + 1e-9:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        return [(lo, hi) for lo, hi in merged]

    assert joint_intervals(4.0) == [(0.0, 1.5), (2.5, 5.5), (6.5, 9.5)]
    assert joint_intervals(2.0) == [(0.5, 3.5), (4.5, 7.5), (8.5, 10.0)]


def test_circular_excavation_in_jointed_rock():
    scene = rock_scene(
        outline=square(20.0),
        joints={"a": joint_set(0.0, 1.0), "b": joint_set(90.0, 1.0)},
        excavations=[{"name": "tunnel", "shape": "circle", "center": [10.3, 10.2], "radius": 2.0}],
    )
    rm = generate(scene)
    assert_valid(rm, 400.0)
    inside = [p for p in rm.pieces if p.excavation == "tunnel"]
    outside = [p for p in rm.pieces if p.excavation is None]
    assert len(inside) + len(outside) == len(rm.pieces)
    circle = scene.excavations[0].vertices
    assert sum(geometry.signed_area(p.vertices) for p in inside) == pytest.approx(
        geometry.signed_area(circle), rel=1e-9
    )
    for p in inside:
        assert geometry.point_in_polygon(geometry.centroid(p.vertices), circle)
    for p in outside:
        assert not geometry.point_in_polygon(geometry.centroid(p.vertices), circle)
    # The opening's outline is cut through intact rock, except where it runs along a joint.
    assert any(label == ("intact", None) for *_, label in edges(rm))


def test_horseshoe_and_polygon_excavations():
    scene = rock_scene(
        outline=square(20.0),
        joints={"a": joint_set(30.0, 0.7), "b": joint_set(100.0, 1.3)},
        excavations=[
            {"name": "h", "shape": "horseshoe", "center": [6, 4], "width": 4, "height": 5},
            {
                "name": "p",
                "shape": "polygon",
                "vertices": [[12, 3], [16, 3], [16, 8], [14, 6], [12, 8]],
            },
        ],
    )
    h = scene.excavations[0].vertices
    assert h[:, 1].min() == 4.0 and h[:, 1].max() == pytest.approx(9.0)
    assert h[:, 0].min() == 4.0 and h[:, 0].max() == 8.0
    # Area: 4 x 3 rectangle plus a half disc of radius 2 (discretised: slightly less).
    assert geometry.signed_area(h) == pytest.approx(12 + 2 * math.pi, rel=5e-3)
    rm = generate(scene)
    assert_valid(rm, 400.0)
    for e in scene.excavations:
        got = sum(geometry.signed_area(p.vertices) for p in rm.pieces if p.excavation == e.name)
        assert got == pytest.approx(geometry.signed_area(e.vertices), rel=1e-9)


def test_l_shaped_domain_is_split_into_convex_pieces():
    rm = generate(rock_scene(outline=[[0, 0], [4, 0], [4, 2], [2, 2], [2, 4], [0, 4]]))
    assert len(rm.pieces) == 2
    assert_valid(rm, 12.0)
    counts = Counter(label for *_, label in edges(rm))
    assert counts == {("outer", None): 6, ("intact", None): 2}


def test_mesh_without_joints_gives_squares_split_into_triangles():
    rm = generate(rock_scene(outline=square(4.0), mesh_size=0.5))
    assert len(rm.pieces) == 128
    assert all(len(v) == 3 for v in rm.polygons())
    assert_valid(rm, 16.0)
    # Diagonals alternate from square to square (no preferred direction).
    slopes = Counter(_hyp_slope(v) for v in rm.polygons())
    assert slopes[1.0] == slopes[-1.0] == 64
    for a, b, (kind, _) in edges(rm):
        on_outline = (a[0] == b[0] and a[0] in (0.0, 4.0)) or (a[1] == b[1] and a[1] in (0.0, 4.0))
        assert kind == ("outer" if on_outline else "intact")


def _hyp_slope(tri):
    """Slope sign of a right triangle's hypotenuse (its longest edge)."""
    e = np.roll(tri, -1, axis=0) - tri
    k = int(np.argmax(np.hypot(e[:, 0], e[:, 1])))
    return float(np.sign(e[k, 0] * e[k, 1]))


def test_graded_mesh_is_fine_at_the_opening_and_coarse_far_away():
    scene = rock_scene(outline=square(16.0), mesh_size=0.25,
                       excavations=[{"name": "hole", "shape": "circle", "center": [8.0, 8.0],
                                     "radius": 1.0}])
    data = scene.data
    data["domain"]["mesh_max_size"] = 2.0
    rm = generate(parse_scene(data))
    assert_valid(rm, 256.0)
    rock = [v for v, pc in zip(rm.polygons(), rm.pieces, strict=True) if pc.excavation is None]
    assert all(len(v) == 3 for v in rock)
    size = lambda v: float(np.sqrt(2.0 * geometry.signed_area(v)))  # noqa: E731
    dist = lambda v: float(np.linalg.norm(geometry.centroid(v) - 8.0)) - 1.0  # noqa: E731
    near = [size(v) for v in rock if dist(v) < 0.3]
    far = [size(v) for v in rock if dist(v) > 6.0]
    assert max(near) <= 0.25 * 1.01
    assert np.median(far) > 4 * np.median(near)
    # The quadtree behind it: 0.25 m squares at the opening, 2 m ones (the
    # largest power-of-two multiple of 0.25 up to mesh_max_size) far from it, and
    # no square larger than h + GROWTH * (its distance to the opening).
    sq = graded_squares((0.0, 0.0, 16.0, 16.0), 0.25, 2.0, [scene.excavations[0].vertices])
    assert np.sum(sq[:, 2] ** 2) == pytest.approx(256.0)
    centre = sq[:, :2] + 0.5 * sq[:, 2:3]
    gap = np.maximum(np.linalg.norm(centre - 8.0, axis=1) - 1.0 - sq[:, 2] / math.sqrt(2), 0)
    assert set(np.round(sq[:, 2], 9)) == {0.25, 0.5, 1.0, 2.0}
    assert np.all(sq[:, 2] <= 0.25 + 0.25 * gap + 1e-6)
    assert np.all(sq[gap < 0.01, 2] == 0.25)


def test_mesh_conforms_to_joints_and_merges_slivers():
    # Grid lines 1e-4 m from the joint traces would leave slivers: they are merged.
    scene = rock_scene(
        outline=square(4.0), mesh_size=0.5, joints={"s": joint_set(0.0, 1.0, origin=[0, 1e-4])}
    )
    rm = generate(scene)
    assert_valid(rm, 16.0)
    for v in rm.polygons():
        e = np.roll(v, -1, axis=0) - v
        emax = float(np.max(np.hypot(e[:, 0], e[:, 1])))
        assert geometry.signed_area(v) >= 1e-3 * emax**2
    assert 120 <= len(rm.pieces) <= 150
    joint_length = sum(float(np.hypot(*(b - a))) for a, b, (k, _) in edges(rm) if k == "joint")
    # Traces at y = 1.0001, 2.0001, 3.0001 (both sides); the one at y = 0.0001 left a
    # sliver against the outline, merged across it.
    assert joint_length == pytest.approx(2 * 3 * 4.0)


def test_zone_takes_its_material():
    scene = rock_scene(
        outline=square(20.0),
        joints={"a": joint_set(0.0, 1.0), "b": joint_set(90.0, 1.0)},
        zones=[
            {
                "name": "shear",
                "vertices": [[-5, 8], [25, 14], [25, 16], [-5, 10]],
                "material": "soft",
            }
        ],
    )
    rm = generate(scene)
    assert_valid(rm, 400.0)
    soft = sum(geometry.signed_area(p.vertices) for p in rm.pieces if p.material == "soft")
    assert soft == pytest.approx(40.0, rel=1e-9)


def test_discontinuity_is_jointed_only_along_its_segment():
    joints = {"d": {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0}}
    rm = generate(
        rock_scene(joints=joints, discontinuities=[{"from": [2, 5], "to": [6, 5], "joint": "d"}])
    )
    assert_valid(rm, 100.0)
    length = {"joint": 0.0, "intact": 0.0}
    for a, b, (kind, _) in edges(rm):
        if kind != "outer" and a[1] == 5.0 and b[1] == 5.0:
            length[kind] += float(np.hypot(*(b - a))) / 2.0
    assert length == pytest.approx({"joint": 4.0, "intact": 6.0})


def test_near_coincident_discontinuity_is_merged():
    joints = {"a": joint_set(0.0, 1.0), "b": joint_set(90.0, 1.0)}
    joints["d"] = {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0}
    rm = generate(
        rock_scene(
            joints=joints,
            discontinuities=[{"from": [0, 5.0005], "to": [10, 5.0005], "joint": "d"}],
        )
    )
    assert_valid(rm, 100.0)
    assert len(rm.pieces) == 100  # the 0.5 mm slivers went into their neighbours


def test_unmergeable_sliver_is_refused_with_the_traces_named():
    # A 0.5 mm band of another material between a set trace and a discontinuity has no
    # neighbour of its own kind to merge into.
    joints = {"a": joint_set(0.0, 1.0), "d": {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0}}
    scene = rock_scene(
        joints=joints,
        discontinuities=[{"from": [0, 5.0005], "to": [10, 5.0005], "joint": "d"}],
        zones=[
            {
                "name": "z",
                "vertices": [[0, 5], [10, 5], [10, 5.0005], [0, 5.0005]],
                "material": "soft",
            }
        ],
    )
    with pytest.raises(SceneError) as info:
        generate(scene)
    assert info.value.path in ("joints.a", "discontinuities.0")
    assert "nearly coincide" in str(info.value) and "sliver" in str(info.value)


def test_small_well_shaped_piece_that_cannot_be_merged_is_kept():
    # A joint along the floor and a circular opening 0.25 m above it: the piece between
    # the opening's lowest edge and the floor (0.086 m2, 0.24 m wide) is small against
    # the 20 m domain and cannot be merged convexly, but it is a block, not a sliver
    # (found by tests/test_properties.py: it used to be refused as a sliver).
    joints = {"d": {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0}}
    rm = generate(
        rock_scene(
            outline=[[0, 0], [20, 0], [20, 15], [0, 15]],
            joints=joints,
            discontinuities=[{"from": [0, 0], "to": [4, 0], "joint": "d"}],
            excavations=[{"name": "t", "shape": "circle", "center": [5, 1.5], "radius": 1.25}],
        )
    )
    assert_valid(rm, 300.0)
    small = min(rm.pieces, key=lambda p: geometry.signed_area(p.vertices))
    assert geometry.signed_area(small.vertices) == pytest.approx(0.0862, rel=1e-3)
    assert small.excavation is None


def test_no_domain_gives_an_empty_rock_mass():
    scene = parse_scene(
        {
            "scene": {"name": "one"},
            "materials": {"rock": ROCK},
            "blocks": [{"vertices": square(1.0), "material": "rock"}],
        }
    )
    assert generate(scene).pieces == []


def test_a_scene_is_cut_once_and_each_caller_gets_its_own_copy(monkeypatch):
    """The command line counts the blocks, the solver lays them out and the figures draw
    them: one cut of the scene, and a copy for each (a change to one is not the next's)."""
    from jaxdem.rockmass import _generate

    cuts = []
    cut = _generate._cut
    monkeypatch.setattr(_generate, "_cut", lambda sc: cuts.append(sc) or cut(sc))
    scene = rock_scene(outline=square(4.0), joints={"a": joint_set(0.0, 1.0)})
    first = generate(scene)
    first.pieces[0].vertices[:] = 0.0
    first.pieces[0].edge_labels.clear()
    again = generate(scene)
    assert len(cuts) == 1
    assert total_area(again) == pytest.approx(16.0, rel=1e-12)
    assert len(again.pieces[0].edge_labels) == len(again.pieces[0].vertices)
    other = rock_scene(outline=square(4.0), joints={"a": joint_set(0.0, 2.0)})
    assert len(generate(other).pieces) == 2 and len(cuts) == 2  # another scene: its own cut


def test_ten_thousand_blocks_generate_quickly():
    scene = rock_scene(
        outline=square(100.0), joints={"a": joint_set(0.0, 1.0), "b": joint_set(90.0, 1.0)}
    )
    t0 = time.perf_counter()
    rm = generate(scene)
    elapsed = time.perf_counter() - t0
    assert len(rm.pieces) == 10_000
    assert elapsed < 10.0, f"generating 10,000 blocks took {elapsed:.1f} s"
    assert total_area(rm) == pytest.approx(1e4, rel=1e-9)


def test_inclined_sets_at_scale():
    scene = rock_scene(
        outline=square(100.0), joints={"a": joint_set(30.0, 1.0), "b": joint_set(120.0, 1.0)}
    )
    t0 = time.perf_counter()
    rm = generate(scene)
    assert time.perf_counter() - t0 < 10.0
    assert 9_500 <= len(rm.pieces) <= 11_000
    assert total_area(rm) == pytest.approx(1e4, rel=1e-9)


# --------------------------------------------------------------------------- clipping in one pass
# _cutting.clip passes over the half-planes that hold a piece whole and stops at one that
# holds nothing of it, decided for all half-planes at once: the answer is that of clipping
# by every half-plane in turn, bit for bit.


def _clip_in_turn(v, planes, tol):
    for n, off, below in planes:
        lo, hi = geometry.split_by_line(v, n, off, tol)
        v = lo if below else hi
        if v is None:
            return None
    return v


@settings(max_examples=80, deadline=None)
@given(
    n=st.integers(3, 12),
    k=st.integers(1, 40),
    seed=st.integers(0, 2**32 - 1),
    centre=st.floats(-1e5, 1e5),
    tol=st.sampled_from([0.0, 1e-9, 1e-4]),
)
def test_clip_agrees_with_half_planes_in_turn(n, k, seed, centre, tol):
    from jaxdem.rockmass._cutting import clip

    rng = np.random.default_rng(seed)
    a = np.sort(rng.uniform(0.0, 2.0 * np.pi, n))
    v = centre + rng.uniform(0.5, 5.0) * np.stack([np.cos(a), np.sin(a)], axis=1)
    planes = []
    for _ in range(k):
        t = rng.uniform(0.0, 2.0 * np.pi)
        nrm = np.array([math.cos(t), math.sin(t)])
        # Offsets through the polygon, beyond it, and through a vertex (grazing).
        off = float(nrm @ v[rng.integers(n)]) + rng.choice([0.0, rng.normal(0.0, 3.0), 10.0])
        planes.append((nrm, off, bool(rng.integers(2))))
    got, want = clip(v, planes, tol), _clip_in_turn(v, planes, tol)
    assert (got is None) == (want is None)
    if want is not None:
        np.testing.assert_array_equal(got, want)
