"""Large displacements: the seed's example 1 (slide and stop) and toppling.

Example 1 (Hataf & Baharloo, fig. 11): a block on a slope steeper than its
friction angle slides until it meets a fixed block and comes to rest; it
travels the gap between them (plus an elastic compression of order W / k).
Toppling (Goodman & Bray 1976; Hoek & Bray, Rock Slope Engineering): a block
of width b and height h on a plane inclined at alpha, with friction angle
phi > alpha, topples when b / h < tan(alpha) and stands when b / h > tan(alpha).
"""

import math

import numpy as np
import pytest
from scenes import slide_and_stop, tall_block

import jaxdem
from jaxdem.scene import parse_scene


@pytest.mark.parametrize("gap", [0.5, 1.0, 2.0])
def test_seed_example_1_slides_the_gap_and_comes_to_rest(gap):
    r = jaxdem.solve(parse_scene(slide_and_stop(gap)))
    assert r.converged and r.stable
    travel = np.linalg.norm(r.monitors["block"]["displacement"])
    assert travel == pytest.approx(gap, rel=0.02)
    # It came to rest against the stop: its front face now carries load.
    assert r.contacts["total"] >= 3
    assert r.equilibrium["imbalance"] < 1e-8


@pytest.mark.parametrize("width, height, topples", [
    (0.30, 1.0, True),   # b/h = 0.30 < tan 20 = 0.364
    (0.34, 1.0, True),   # b/h = 0.34 < 0.364, close to the threshold
    (0.39, 1.0, False),  # b/h = 0.39 > 0.364
    (0.60, 1.0, False),
])
def test_toppling_when_width_over_height_below_tan_slope(width, height, topples):
    assert (width / height < math.tan(math.radians(20.0))) == topples
    r = jaxdem.solve(parse_scene(tall_block(width, height)))
    if topples:
        assert r.status == "mechanism" and not r.stable and r.moving_blocks == [1]
        # The slope rises to the right, so the block tips down-slope to the
        # left about its lower corner: a counter-clockwise (positive) rotation.
        assert r.blocks[1]["u"][2] > 0.1
    else:
        assert r.converged and r.stable
        assert abs(r.blocks[1]["u"][2]) < 1e-3
