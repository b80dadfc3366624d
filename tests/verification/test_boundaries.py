"""Boundary walls and tractions against closed forms of eqs. 6-7.

A rigid wall contact has no joint term and no block on the other side, so its
stiffness per unit length is k = kn_i / h (h: distance from the face to the
block centroid, kn_i = E / (1 - nu^2), eq. 4). A traction q on a face of
length L is a force q L on that block.
"""

import numpy as np
import pytest
from scenes import ROCK

import jaxdem
from jaxdem.core.laws import equivalent_stiffness, intact_stiffness
from jaxdem.scene import parse_scene


def _block_on_wall(traction=None, width=2.0, height=1.0):
    d = {
        "scene": {"name": "block on a fixed boundary"},
        "solver": {"load_steps": 2, "tolerance": 1e-9},  # the test checks balance to 1e-8
        "materials": {"rock": dict(ROCK)},
        "joints": {"j": {"kn": 1e6, "ks": 1e6, "friction_deg": 30.0}},
        "blocks": [{"vertices": [[0, 0], [width, 0], [width, height], [0, height]],
                    "material": "rock"}],
        "boundaries": [{"side": "bottom", "condition": "fixed"}],
        "monitors": [{"name": "c", "point": [width / 2, height / 2]}],
    }
    if traction is not None:
        d["boundaries"].append({"side": "top", "condition": "traction", "traction": traction})
    return d


def test_block_on_a_fixed_boundary_settles_by_weight_over_wall_stiffness():
    r = jaxdem.solve(parse_scene(_block_on_wall()))
    assert r.converged
    kn_i, _ = intact_stiffness(1e7, 0.25)
    W = 25.0 * 2.0
    k = kn_i / 0.5  # h = half the height, no joint term
    assert -r.monitors["c"]["displacement"][1] == pytest.approx(W / (k * 2.0), rel=1e-3)
    assert r.equilibrium["imbalance"] < 1e-8


def test_top_traction_adds_q_times_face_length():
    q = 100.0
    r = jaxdem.solve(parse_scene(_block_on_wall(traction=[0.0, -q])))
    kn_i, _ = intact_stiffness(1e7, 0.25)
    W = 25.0 * 2.0 + q * 2.0
    assert -r.monitors["c"]["displacement"][1] == pytest.approx(W / (kn_i / 0.5 * 2.0), rel=1e-3)
    assert r.equilibrium["applied"][1] == pytest.approx(-W, rel=1e-12)


def test_fixed_wall_holds_a_horizontal_traction_in_shear_and_roller_does_not():
    # Horizontal traction on the top face: the fixed base resists it in shear
    # (bonded: no slip whatever the load); on a roller base the block runs away.
    fixed = _block_on_wall(traction=[50.0, 0.0])
    r = jaxdem.solve(parse_scene(fixed))
    assert r.converged and r.stable
    _, ks_i = intact_stiffness(1e7, 0.25)
    # Shear stiffness of the base: ks_i / h over 2 m; the block also rotates,
    # so only check the order of magnitude and the direction.
    ux = r.monitors["c"]["displacement"][0]
    assert ux > 0 and ux < 10 * 100.0 / (ks_i / 0.5 * 2.0)
    roller = _block_on_wall(traction=[50.0, 0.0])
    roller["boundaries"][0]["condition"] = "roller"
    roller["solver"]["max_displacement"] = 0.5
    r = jaxdem.solve(parse_scene(roller))
    assert r.status == "mechanism" and r.moving_blocks == [0]
    # It runs off along the wall; near the end of the wall the overhanging
    # block starts to tip over the wall's corner, hence a small uy.
    ux, uy = r.monitors["c"]["displacement"]
    assert ux > 0.5 and abs(uy) < 0.1 * ux


def test_confined_column_between_roller_walls():
    """Rows of blocks between roller sides on a fixed base: springs in series."""
    rows, cols = 3, 3
    blocks = [{"vertices": [[c, r], [c + 1, r], [c + 1, r + 1], [c, r + 1]], "material": "rock"}
              for r in range(rows) for c in range(cols)]
    d = {
        "scene": {"name": "confined column"},
        "solver": {"load_steps": 1},
        "materials": {"rock": dict(ROCK)},
        "joints": {"j": {"kn": 1e6, "ks": 1e6, "friction_deg": 30.0}},
        "blocks": blocks,
        "boundaries": [{"side": "bottom", "condition": "fixed"},
                       {"side": "left", "condition": "roller"},
                       {"side": "right", "condition": "roller"}],
        "monitors": [{"name": "top", "point": [1.5, 2.5]}],
    }
    r = jaxdem.solve(parse_scene(d))
    assert r.converged
    kn_i, _ = intact_stiffness(1e7, 0.25)
    k_joint = equivalent_stiffness(0.5, 0.5, 1 / kn_i, 1 / kn_i, 1e-6)
    settle = 25.0 * rows / (kn_i / 0.5) + sum(25.0 * (rows - k) / k_joint for k in (1, 2))
    ux, uy = r.monitors["top"]["displacement"]
    assert -uy == pytest.approx(settle, rel=1e-3)
    assert abs(ux) < 1e-9
    # The roller walls carry no shear: the base wall carries all the weight.
    assert r.equilibrium["reaction"][1] == pytest.approx(25.0 * rows * cols, rel=1e-8)
    assert np.isfinite([b["stress"] for b in r.blocks]).all()


def test_a_stage_applies_its_traction_and_displacements_count_from_before_it():
    # The block settles under its weight while loading; the stage "surcharge"
    # then adds q on the top face: the reported settlement is q L / (k L) only.
    q = 100.0
    d = _block_on_wall(traction=[0.0, -q])
    d["boundaries"][-1]["stage"] = "surcharge"
    d["stages"] = [{"name": "surcharge", "load_steps": 2}]
    r = jaxdem.solve(parse_scene(d))
    assert r.converged
    kn_i, _ = intact_stiffness(1e7, 0.25)
    assert -r.monitors["c"]["displacement"][1] == pytest.approx(q / (kn_i / 0.5), rel=1e-3)
    assert r.equilibrium["applied"][1] == pytest.approx(-(25.0 + q) * 2.0, rel=1e-12)
    assert [s["name"] for s in r.stages] == ["loading", "surcharge"]
