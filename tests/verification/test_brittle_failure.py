"""Brittle intact rock: springs fail event by event.

A spring with cohesion or tensile strength is elastic until it is loaded beyond them;
at the end of a geometry update the springs whose excess over their strength is at
least half the worst fail (they lose both, SPEC), and the next update carries their
load elsewhere (jaxdem.core._substep.breaking). Seed example 3's rock without its
tunnels, loaded by its own weight (tests/data/rock_box_gravity.toml: 882 cells, a joint
set at 10 degrees with cohesion, roller sides, a fixed base), breaks bonds where its
joints run into the base at a quarter of its weight. When every spring beyond its
strength slipped on with its cohesion to the end of the update and all of them failed
together, the steps to 25% of the weight stopped at the iteration limit (939-954
iterations) until the load step had been cut three times (28 increments, 174 s of
solve; BENCHMARKS.md "Nineteenth session").
"""

from pathlib import Path

import numpy as np
import pytest

import jaxdem

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def box():
    return jaxdem.solve(jaxdem.load_scene(DATA / "rock_box_gravity.toml"))


def test_the_rock_loaded_by_its_weight_converges_in_its_own_load_steps(box):
    assert box.converged and box.stable and box.admissibility["admissible"]
    (loading,) = box.stages
    # Its 4 load steps, none cut, each within issue 30's 100 Newton iterations.
    assert loading["step_cuts"] == 0 and len(loading["iterations"]) == 4
    assert max(loading["iterations"]) <= 100


def test_its_vertical_stress_is_the_weight_above(box):
    """Roller sides carry no shear: each horizontal slice of the box carries the weight of
    the rock above it, sigma_v = gamma (20 - y) (statics alone, whatever the joints' and
    cells' stiffness). The cells' stress, their median in 2 m bands 15 m and more below
    the surface (nearer it the band is a large part of the depth), within 2%."""
    c = np.array([b["centroid"] for b in box.blocks])
    syy = np.array([b["stress"][1] for b in box.blocks])
    for y in (5.0, -5.0, -15.0, -24.0):
        band = np.abs(c[:, 1] - y) < 1.0
        assert band.sum() > 30
        assert np.median(syy[band]) == pytest.approx(26.0 * (20.0 - y), rel=0.02)
