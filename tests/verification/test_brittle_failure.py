"""Brittle intact rock: springs failing event by event (``solver.bond_failure = "events"``).

A spring with cohesion or tensile strength is elastic until it is loaded beyond them;
at the end of a geometry update the springs whose excess over their strength is at
least half the worst fail (they lose both: README, "Strength"), and the next update
carries their load elsewhere (jaxdem.core._substep.breaking). Seed example 3's rock without its
tunnels, loaded by its own weight (tests/data/rock_box_gravity.toml, in that mode: 882
cells, a joint set at 10 degrees with cohesion, roller sides, a fixed base), breaks bonds
where its joints run into the base at a quarter of its weight. By default ("substep":
every spring that reaches its strength slips on with its cohesion to the end of the
update, and all of them then fail together) its steps to 25% of the weight stop at the
iteration limit (939-954 iterations) until the load step has been cut three times (28
increments, 174 s of solve; BENCHMARKS.md "Nineteenth session").
"""

from pathlib import Path

import numpy as np
import pytest
from scenes import block_on_incline

import jaxdem
from jaxdem.scene import parse_scene

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


@pytest.mark.parametrize("mode", ["substep", "events"])
@pytest.mark.parametrize("cohesion, holds", [(5.2, True), (4.9, False)])
def test_a_cohesive_contact_fails_spring_by_spring_as_statics_says(mode, cohesion, holds):
    """A 1 m block (W = 25 kN/m) on a 35-degree plane, friction 30 degrees, cohesion c:
    two springs, 0.5 m either side of the face's middle, share the shear equally (S =
    W sin 35 / 2 = 7.17 kN/m each) and, about the centroid 0.5 m above the face, the
    normal force unequally: N = W cos 35 / 2 -/+ W sin 35 x 0.5 / 1 m = 3.07 (upslope)
    and 17.41 kN/m. The upslope spring fails first (7.17 > 0.5 c + 3.07 tan 30 for
    c < 10.8 kPa) and keeps its friction, 1.77 kN/m; the other then holds the block
    while W sin 35 - 1.77 = 12.57 <= 0.5 c + 17.41 tan 30, c >= 5.04 kPa (twice the
    2.52 kPa of limit equilibrium on the whole face, where the cohesion of both would
    count). Both modes of failure agree on it, within 3% either side (measured: held
    at 5.15, slid at 4.95)."""
    r = jaxdem.solve(parse_scene(block_on_incline(35, 30, cohesion=cohesion,
                                                  bond_failure=mode)))
    assert r.stable == holds
    if holds:
        assert r.converged
    else:
        assert r.status == "mechanism" and r.moving_blocks == [1]
