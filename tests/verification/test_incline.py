"""A block on an inclined plane: limit equilibrium and elastic closed forms.

Stability: a cohesionless block on a plane inclined at alpha with joint friction
phi slides when alpha > phi (Goodman & Bray; Hoek & Bray, Rock Slope
Engineering, ch. 2); cohesion c adds c * L to the resistance.
Elastic displacement: two point springs at the ends of the contact (Le = face
length, eq. 8), each of normal stiffness kn * Le / 2 and shear stiffness
ks * Le / 2, with kn, ks from eqs. 6-7. The block is loaded by its weight W at
its centroid, a height hc above the contact face; see _closed_form below.
"""

import math

import numpy as np
import pytest
from scenes import block_on_incline

import jaxdem
from jaxdem.core.laws import equivalent_stiffness, intact_stiffness
from jaxdem.scene import parse_scene


def _solve(alpha, phi, **kw):
    return jaxdem.solve(parse_scene(block_on_incline(alpha, phi, **kw)))


@pytest.mark.parametrize(
    "alpha, phi",
    [(10, 20), (20, 30), (29, 30), (31, 30), (35, 30), (25, 40), (45, 40), (40, 30)],
)
def test_stable_below_friction_angle_sliding_above(alpha, phi):
    r = _solve(alpha, phi)
    assert r.stable == (alpha < phi)
    if alpha < phi:
        assert r.converged and r.status == "converged"
        assert np.linalg.norm(r.monitors["block"]["displacement"]) < 1e-3
    else:
        assert r.status == "mechanism" and r.moving_blocks == [1]
        # It moved down the slope, not through it.
        ux, uy = r.monitors["block"]["displacement"]
        assert ux < 0 and uy < 0
        assert math.isclose(math.degrees(math.atan2(-uy, -ux)), alpha, abs_tol=3.0)


def test_cohesion_holds_a_block_that_friction_alone_would_not():
    # W = 25 kN/m on a 1 m face: W sin 35 = 14.3 > W cos 35 tan 30 = 11.8, so
    # friction alone fails; with c = 10 kPa the capacity is 21.8 kN/m.
    assert not _solve(35, 30).stable
    r = _solve(35, 30, cohesion=10.0)
    assert r.stable and r.converged
    # Just below the cohesion needed it fails: (14.34 - 11.82) / 1 m = 2.52 kPa
    # is the global limit; the back spring carries less normal force and slips
    # first, so 1 kPa is well inside the failing range.
    assert not _solve(35, 30, cohesion=1.0).stable


def _closed_form(alpha, kn0, ks0, width, height, E=1e7, nu=0.25, gamma=25.0):
    """Displacement (along slope t, normal n, rotation) of the block centroid."""
    kn_i, ks_i = intact_stiffness(E, nu)
    a = math.radians(alpha)
    # Distance of the fixed base's centroid from the slope line (see scenes.slope_base).
    base = np.array(parse_scene(block_on_incline(alpha, 20.0)).blocks[0].vertices)
    from jaxdem.geometry import centroid

    cb = centroid(base)
    h_base = abs(-math.sin(a) * cb[0] + math.cos(a) * cb[1])
    hc = height / 2.0
    Le = width
    kn = equivalent_stiffness(hc, h_base, 1 / kn_i, 1 / kn_i, 1 / kn0)
    ks = equivalent_stiffness(hc, h_base, 1 / ks_i, 1 / ks_i, 1 / ks0)
    W = gamma * width * height
    Ft = -W * math.sin(a)  # along +t (up-slope): the weight pulls down-slope
    Fn = -W * math.cos(a)
    # Normal: 2 (kn Le / 2) u_n = Fn.
    u_n = Fn / (kn * Le)
    # Moment about the centroid: normal springs at x = +-Le/2 resist rotation
    # with kn Le^3 / 4; the shear force acts at the face, hc below the centroid.
    theta = -Ft * hc / (kn * Le**3 / 4.0)
    # Shear: the face point moves u_t + theta * hc; ks Le (u_t + theta hc) = Ft.
    u_t = Ft / (ks * Le) - theta * hc
    return u_t, u_n, theta


@pytest.mark.parametrize("alpha, kn, ks, width, height", [
    (10.0, 1e6, 5e5, 1.0, 1.0),
    (20.0, 2e5, 1e5, 2.0, 1.0),
    (25.0, 5e6, 1e6, 1.0, 0.5),
])
def test_elastic_translation_and_rotation_match_eqs_6_7(alpha, kn, ks, width, height):
    r = _solve(alpha, 45.0, kn=kn, ks=ks, width=width, height=height)
    assert r.converged
    u_t, u_n, theta = _closed_form(alpha, kn, ks, width, height)
    a = math.radians(alpha)
    t = np.array([math.cos(a), math.sin(a)])
    n = np.array([-math.sin(a), math.cos(a)])
    ux, uy, rot = r.blocks[1]["u"]
    u = np.array([ux, uy])
    assert u @ t == pytest.approx(u_t, rel=0.01)
    assert u @ n == pytest.approx(u_n, rel=0.01)
    assert rot == pytest.approx(theta, rel=0.01)


def test_threshold_does_not_depend_on_load_steps():
    for steps in (1, 4):
        assert _solve(29, 30, load_steps=steps).stable
        assert not _solve(31, 30, load_steps=steps).stable


def test_shear_history_is_carried_across_increments_and_redetection():
    """Elastic: the same displacement whether the weight comes in 1 or 4 steps.

    Each increment re-detects the contacts; if the accumulated shear force of
    a spring were lost, the later increments would rebuild it from zero and
    the block would end further down the slope.
    """
    one = _solve(20, 45, load_steps=1).blocks[1]["u"]
    four = _solve(20, 45, load_steps=4).blocks[1]["u"]
    np.testing.assert_allclose(four, one, rtol=1e-6)


def test_the_iteration_limit_names_the_block_out_of_balance():
    # One Newton iteration a sub-step cannot settle the block's springs: the analysis
    # stops at the iteration limit and says where the blocks do not balance. The named
    # block's ratio is the increment's residual (the largest over the free blocks,
    # computed apart), and its force scale (force / ratio) is at least the weight it
    # carries in the increment that stopped, W = 25 kN/m3 x 1 m2 = 25 kN/m times its load
    # factor: the load step was cut three times (solver.max_step_cuts) before it stopped.
    r = _solve(25, 30, max_iterations=1)
    assert r.status == "iteration_limit" and not r.converged
    assert r.stages[-1]["step_cuts"] == 3
    factor = r.stages[-1]["load_factor"][-1]
    assert factor <= 1 / 8
    assert [b["id"] for b in r.unbalanced_blocks] == [1]
    worst = r.unbalanced_blocks[0]
    assert math.isclose(worst["relative"], r.stages[-1]["residual"][-1], rel_tol=1e-9)
    assert worst["relative"] > 1e-6  # beyond the default solver.tolerance
    assert worst["force"] / worst["relative"] >= 25.0 * factor * (1 - 1e-9)
    assert "Out of balance: block 1 at (" in r.message
    assert np.allclose(worst["centroid"], r.blocks[1]["centroid"])
    assert r.to_dict()["unbalanced_blocks"] == r.unbalanced_blocks
    # An equilibrium names none.
    assert _solve(25, 30).unbalanced_blocks == []
