"""Host polygon utilities against hand-computed cases (jaxdem.geometry)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxdem import geometry as g

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
TRIANGLE = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0]])
BOWTIE = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
L_SHAPE = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)


def test_unit_square_area_and_centroid():
    assert g.signed_area(SQUARE) == pytest.approx(1.0)
    assert g.signed_area(SQUARE[::-1]) == pytest.approx(-1.0)
    np.testing.assert_allclose(g.centroid(SQUARE), [0.5, 0.5])
    assert g.characteristic_length(SQUARE) == pytest.approx(1.0)
    assert g.bbox(SQUARE) == (0.0, 0.0, 1.0, 1.0)


def test_triangle_area_and_centroid():
    # Right triangle with legs 4 and 3: area 6, centroid at the vertex mean (4/3, 1).
    assert g.signed_area(TRIANGLE) == pytest.approx(6.0)
    np.testing.assert_allclose(g.centroid(TRIANGLE), [4.0 / 3.0, 1.0])


def test_l_shape_centroid_far_from_origin():
    # L of three unit squares: centroid (5/6, 5/6); shifted to UTM-like coordinates.
    shift = np.array([5.0e5, 4.0e6])
    assert g.signed_area(L_SHAPE + shift) == pytest.approx(3.0)
    np.testing.assert_allclose(g.centroid(L_SHAPE + shift) - shift, [5 / 6, 5 / 6], atol=1e-9)


def test_is_convex():
    assert g.is_convex(SQUARE)
    assert g.is_convex(TRIANGLE)
    assert not g.is_convex(SQUARE[::-1])  # clockwise
    assert not g.is_convex(L_SHAPE)
    assert not g.is_convex(BOWTIE)
    collinear = np.array([[0, 0], [1, 0], [2, 0], [2, 1], [0, 1]], dtype=float)
    assert not g.is_convex(collinear)
    # A pentagram turns left at every vertex but winds twice.
    k = np.arange(5)
    star = np.stack([np.cos(4 * np.pi * k / 5), np.sin(4 * np.pi * k / 5)], axis=1)
    assert not g.is_convex(star)


def test_corner_sines_marks_reflex_and_collinear():
    s = g.corner_sines(L_SHAPE)
    assert s[3] < 0 and np.all(np.delete(s, 3) > 0)
    collinear = np.array([[0, 0], [1, 0], [2, 0], [2, 1], [0, 1]], dtype=float)
    assert g.corner_sines(collinear)[1] == 0.0


def test_self_intersects():
    assert g.self_intersects(BOWTIE)
    assert not g.self_intersects(SQUARE)
    assert not g.self_intersects(L_SHAPE)
    # A vertex touching a non-adjacent edge.
    touching = np.array([[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]], dtype=float)
    assert g.self_intersects(touching)
    # An edge folding back over its neighbour.
    spike = np.array([[0, 0], [2, 0], [1, 0], [1, 1]], dtype=float)
    assert g.self_intersects(spike)


def test_has_repeated_points():
    assert not g.has_repeated_points(SQUARE, 1e-9)
    rep = np.array([[0, 0], [1, 0], [1, 1], [1, 1 + 1e-12], [0, 1]], dtype=float)
    assert g.has_repeated_points(rep, 1e-9)
    assert not g.has_repeated_points(rep, 1e-13)


def test_point_on_segment():
    assert g.point_on_segment([0.5, 0.0], [0, 0], [1, 0], 0.0)
    assert g.point_on_segment([1.0, 1e-10], [0, 0], [1, 0], 1e-9)
    assert not g.point_on_segment([1.5, 0.0], [0, 0], [1, 0], 1e-9)
    assert g.point_on_segment([0, 0], [0, 0], [0, 0], 0.0)  # degenerate segment


def test_segments_intersect():
    assert g.segments_intersect([0, 0], [1, 1], [0, 1], [1, 0])
    assert g.segments_intersect([0, 0], [1, 0], [1, 0], [2, 1])  # touching at an end
    assert not g.segments_intersect([0, 0], [1, 0], [0, 1], [1, 1])


@pytest.mark.parametrize(
    ("p", "inside"),
    [
        ((0.5, 0.5), True),
        ((0.0, 0.5), True),  # on an edge
        ((1.0, 1.0), True),  # on a vertex
        ((1.5, 0.5), False),
        ((-1e-12, 0.5), False),
    ],
)
def test_point_in_square(p, inside):
    assert g.point_in_polygon(np.array(p), SQUARE) is inside


def test_point_in_polygon_nonconvex_and_tolerance():
    assert g.point_in_polygon([0.5, 1.5], L_SHAPE)
    assert not g.point_in_polygon([1.5, 1.5], L_SHAPE)  # in the notch
    assert g.point_in_polygon([1.0 + 1e-10, 1.5], L_SHAPE, tol=1e-9)
    assert g.point_in_polygon([0.5, 0.5], SQUARE[::-1])  # either orientation


def test_overlap_of_offset_squares():
    assert g.overlap_area(SQUARE, SQUARE + 0.5) == pytest.approx(0.25)
    inter = g.convex_clip(SQUARE, SQUARE + 0.5)
    assert g.bbox(inter) == pytest.approx((0.5, 0.5, 1.0, 1.0))


def test_overlap_touching_and_disjoint():
    assert g.overlap_area(SQUARE, SQUARE + [1.0, 0.0]) == 0.0
    assert g.overlap_area(SQUARE, SQUARE + [3.0, 0.0]) == 0.0
    assert g.convex_clip(SQUARE, SQUARE + [3.0, 0.0]).shape == (0, 2)
    assert g.overlap_area(SQUARE, SQUARE) == pytest.approx(1.0)
    # A triangle inside a square: the overlap is the triangle.
    tri = np.array([[0.2, 0.2], [0.8, 0.2], [0.5, 0.7]])
    assert g.overlap_area(SQUARE, tri) == pytest.approx(g.signed_area(tri))


@settings(max_examples=50, deadline=None)
@given(
    dx=st.floats(-2.0, 2.0),
    dy=st.floats(-2.0, 2.0),
)
def test_overlap_of_shifted_squares_matches_closed_form(dx, dy):
    expected = max(0.0, 1.0 - abs(dx)) * max(0.0, 1.0 - abs(dy))
    assert g.overlap_area(SQUARE, SQUARE + [dx, dy]) == pytest.approx(expected, abs=1e-12)
    assert g.overlap_area(SQUARE + [dx, dy], SQUARE) == pytest.approx(expected, abs=1e-12)


def _grid(n: int) -> list[np.ndarray]:
    return [SQUARE + [i, j] for i in range(n) for j in range(n)]


def test_find_overlapping_pairs_small():
    polys = [SQUARE, SQUARE + [1.0, 0.0], SQUARE + [0.5, 0.5], SQUARE + [5.0, 5.0]]
    assert g.find_overlapping_pairs(polys, 1e-12) == [(0, 2), (1, 2)]
    assert g.find_overlapping_pairs([SQUARE], 0.0) == []
    assert g.find_overlapping_pairs([], 0.0) == []


def test_find_overlapping_pairs_touching_grid_and_one_shifted():
    polys = _grid(100)
    t0 = time.perf_counter()
    assert g.find_overlapping_pairs(polys, 1e-9) == []
    elapsed = time.perf_counter() - t0
    assert elapsed < 5.0, f"10,000 touching squares took {elapsed:.2f} s"
    # Shift block (3, 7) by a quarter to the right: it overlaps its right neighbour (4, 7).
    k = 3 * 100 + 7
    polys[k] = polys[k] + [0.25, 0.0]
    assert g.find_overlapping_pairs(polys, 1e-9) == [(k, 4 * 100 + 7)]


@pytest.mark.parametrize("pair_slice", [2**22, 7])
def test_find_overlapping_pairs_agrees_with_all_pairs(monkeypatch, pair_slice):
    monkeypatch.setattr(g, "_PAIR_SLICE", pair_slice)  # 7: candidates in many slices
    rng = np.random.default_rng(0)
    polys = [SQUARE * rng.uniform(0.2, 1.0) + rng.uniform(0, 5, size=2) for _ in range(60)]
    brute = [
        (i, j)
        for i in range(len(polys))
        for j in range(i + 1, len(polys))
        if g.overlap_area(polys[i], polys[j]) > 1e-12
    ]
    assert g.find_overlapping_pairs(polys, 1e-12) == brute


# --------------------------------------------------------------------------- many polygons at once
# The vectorised functions against their scalar definitions, polygon by polygon.


@st.composite
def star_polygons(draw, convex: bool = True) -> np.ndarray:
    """A random simple CCW polygon of 3 to 24 vertices: sorted angles around a centre up to
    1e5 m from (0, 0) (a convex one: on a circle; otherwise radii vary, star-shaped)."""
    n = draw(st.integers(3, 24))
    gaps = np.array(draw(st.lists(st.floats(0.05, 1.0), min_size=n, max_size=n)))
    angles = 2.0 * np.pi * np.cumsum(gaps) / np.sum(gaps) + draw(st.floats(0.0, 6.3))
    r = draw(st.floats(1e-3, 1e2))
    radii = r * (np.ones(n) if convex else
                 np.array(draw(st.lists(st.floats(0.3, 1.0), min_size=n, max_size=n))))
    centre = np.array([draw(st.floats(-1e5, 1e5)), draw(st.floats(-1e5, 1e5))])
    return centre + radii[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)


polygon_lists = st.lists(st.one_of(star_polygons(), star_polygons(convex=False)),
                         min_size=1, max_size=12)


@settings(max_examples=60, deadline=None)
@given(polys=polygon_lists)
def test_areas_centroids_moments_agree_with_scalar(polys):
    areas = g.signed_areas(polys)
    cents = g.centroids(polys)
    rg2 = g.polar_moments(polys, cents)
    for i, v in enumerate(polys):
        a, c = g.signed_area(v), g.centroid(v)
        size = np.sqrt(abs(a))
        assert abs(areas[i] - a) <= 1e-12 * abs(a)
        assert np.hypot(*(cents[i] - c)) <= 1e-12 * size
        assert abs(rg2[i] - g.polar_moment(v, c)) <= 1e-12 * abs(g.polar_moment(v, c))
        np.testing.assert_array_equal(g.bboxes(polys)[i], g.bbox(v))


def test_polar_moment_of_rectangle_and_square_grid():
    # Rectangle b x h about its centroid: J / A = (b^2 + h^2) / 12.
    rect = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]]) + [3e5, -2e4]
    assert g.polar_moment(rect, g.centroid(rect)) == pytest.approx(20.0 / 12.0, rel=1e-12)
    polys = _grid(30)
    np.testing.assert_allclose(g.polar_moments(polys, g.centroids(polys)), 1.0 / 6.0,
                               rtol=1e-12)
    np.testing.assert_allclose(g.centroids(polys), [p.mean(axis=0) for p in polys], rtol=1e-12)


def test_centroids_of_degenerate_polygons_as_scalar():
    polys = [np.array([[1.0, 2.0]]), np.array([[0.0, 0.0], [2.0, 2.0]]),
             np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), TRIANGLE]
    np.testing.assert_array_equal(g.centroids(polys), [g.centroid(p) for p in polys])
    np.testing.assert_array_equal(g.signed_areas(polys), [g.signed_area(p) for p in polys])
    with pytest.raises(ValueError):
        g.centroids([np.zeros((0, 2))])


@settings(max_examples=60, deadline=None)
@given(polys=polygon_lists, data=st.data())
def test_points_in_polygons_agrees_with_scalar(polys, data):
    # Points inside, outside, on vertices, near edges: every pair against point_in_polygon.
    pts = []
    for v in polys:
        c = v.mean(axis=0)
        r = float(np.max(np.hypot(*(v - c).T)))
        u = data.draw(st.lists(st.floats(-1.3, 1.3), min_size=2, max_size=2))
        pts += [c, v[0], 0.5 * (v[0] + v[1]), c + r * np.array(u)]
    tol = data.draw(st.sampled_from([0.0, 1e-9, 1e-3]))
    inside = g.points_in_polygons(np.array(pts), polys, tol)
    expected = [[g.point_in_polygon(p, v, tol) for v in polys] for p in pts]
    np.testing.assert_array_equal(inside, expected)


def test_points_in_polygons_grid_and_shapes():
    polys = _grid(100)
    pts = np.array([[50.5, 50.5], [0.0, 0.0], [100.5, 3.0], [99.5, 99.5]])
    inside = g.points_in_polygons(pts, polys, 1e-9)
    assert [np.nonzero(row)[0].tolist() for row in inside] == [[5050], [0], [], [9999]]
    assert g.points_in_polygons(np.zeros((0, 2)), polys).shape == (0, 10_000)
    assert g.points_in_polygons(pts, []).shape == (4, 0)


@settings(max_examples=40, deadline=None)
@given(polys=polygon_lists, data=st.data())
def test_drop_collinear_all_agrees_with_scalar(polys, data):
    # Put a 180-degree vertex and a repeated vertex into some polygons.
    polys = list(polys)
    v = polys[0]
    polys[0] = np.vstack([v[:1], 0.5 * (v[0] + v[1]), v[1:]])
    polys.append(np.vstack([v[:1], v[:1] + 1e-12, v[1:]]))
    tol = data.draw(st.sampled_from([0.0, 1e-9, 1e-6]))
    for got, p in zip(g.drop_collinear_all(polys, tol), polys, strict=True):
        np.testing.assert_array_equal(got, g.drop_collinear(p, tol))


@pytest.mark.parametrize("pair_slice", [2**22, 5])
@pytest.mark.parametrize("tol", [0.0, 0.05])
def test_near_box_pairs_agrees_with_all_pairs(monkeypatch, pair_slice, tol):
    monkeypatch.setattr(g, "_PAIR_SLICE", pair_slice)  # 5: candidates in many slices
    rng = np.random.default_rng(1)
    lo = np.round(rng.uniform(0, 6, size=(80, 2)), 1)  # rounded: boxes that touch exactly
    boxes = np.concatenate([lo, lo + np.round(rng.uniform(0.1, 1.5, size=(80, 2)), 1)], axis=1)
    brute = [(i, j) for i in range(80) for j in range(i + 1, 80)
             if boxes[j, 0] <= boxes[i, 2] + tol and boxes[i, 0] <= boxes[j, 2] + tol
             and boxes[j, 1] <= boxes[i, 3] + tol and boxes[i, 1] <= boxes[j, 3] + tol]
    i, j = g.near_box_pairs(boxes, tol)
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == brute
    assert [len(a) for a in g.near_box_pairs(np.zeros((0, 4)), tol)] == [0, 0]
