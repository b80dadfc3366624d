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


def test_find_overlapping_pairs_agrees_with_all_pairs():
    rng = np.random.default_rng(0)
    polys = [SQUARE * rng.uniform(0.2, 1.0) + rng.uniform(0, 5, size=2) for _ in range(60)]
    brute = [
        (i, j)
        for i in range(len(polys))
        for j in range(i + 1, len(polys))
        if g.overlap_area(polys[i], polys[j]) > 1e-12
    ]
    assert g.find_overlapping_pairs(polys, 1e-12) == brute
