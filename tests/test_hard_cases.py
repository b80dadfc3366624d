"""Hard cases: every run converges to a checked equilibrium or reports the mechanism.

Each test names its case, the outcome it expects and the closed form or the
geometry it checks, and runs in float64 and float32 (``dtype``). Both must
meet the same closed forms (``close``): float64 to 1e-5 relative (the closed
forms hold the geometry fixed, the model updates the lever arms h and the
lengths Le as the blocks settle: a change of the order of the strain times
the rock's share of the compliance, 5e-6 at most here), float32 to 1e-3
relative or 5e-7 m (it resolves a coordinate of a few metres to 2.4e-7 m,
against elastic displacements of 1e-5 to 1e-2 m here). The float32 run must
also agree with the float64 one: the same verdict and displacements within
1e-3 of the largest (``assert_matches_float64``).

Closed forms:
- Series springs (paper eqs. 6-7): a contact of effective length Le between
  blocks whose centroids are h1, h2 from it has the normal stiffness
  k Le, k = 1 / (h1 / kn_1 + h2 / kn_2 + 1 / kn_0), kn_i = E / (1 - nu^2); a
  column of blocks settles by sum_k W_k / (k_k Le_k), W_k the weight above
  joint k (Wang & Garga 1993; Hataf & Baharloo).
- A block of weight W on a plane inclined at alpha (Goodman & Bray; Hoek &
  Bray, Rock Slope Engineering ch. 2): stable when tan(phi) > tan(alpha);
  elastic displacements u_n = -W cos(alpha) / (kn Le), rotation
  theta = W sin(alpha) hc / (kn Le^3 / 4) and u_t = -W sin(alpha) / (ks Le)
  - theta hc, hc the centroid's height over the face.
- Toppling (Goodman & Bray 1976): a block of width b and height h on a plane
  at alpha < phi topples when b / h < tan(alpha), about its down-slope corner.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from scenes import ROCK, block_on_incline, incline_frame, rect_on_slope, slope_base, stack
from test_properties import strength_violations

import jaxdem
from jaxdem import solver
from jaxdem.core import model as model_mod
from jaxdem.core.laws import equivalent_stiffness, intact_stiffness
from jaxdem.core.status import Status
from jaxdem.geometry import centroid
from jaxdem.scene import parse_scene

DTYPES = ["float64", "float32"]
TOL = {"float64": {"rel": 1e-5, "abs": 0.0}, "float32": {"rel": 1e-3, "abs": 5e-7}}
E, NU, GAMMA = ROCK["E"], ROCK["nu"], ROCK["unit_weight"]
KN_I = intact_stiffness(E, NU)[0]  # kPa, eq. 4
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DATA = Path(__file__).resolve().parent / "data"


@functools.cache
def _solve_json(text: str, dtype: str):
    d = json.loads(text)
    d["solver"] = {**d.get("solver", {}), "dtype": dtype}
    t0 = time.perf_counter()
    r = jaxdem.solve(parse_scene(d))
    r.timing["wall_s"] = time.perf_counter() - t0
    return r


def solve(d: dict, dtype: str):
    """Solve a scene dictionary in ``dtype`` (cached: the float32 test reuses float64's run)."""
    return _solve_json(json.dumps(d, sort_keys=True), dtype)


def close(expected, dtype):
    """``expected`` to the tolerance of ``dtype`` (module docstring)."""
    return pytest.approx(expected, **TOL[dtype])


def u_of(r) -> np.ndarray:
    return np.array([b["u"] for b in r.blocks], float)


def assert_sane(r):
    """Finite everywhere; a converged run is balanced; a failed one says why."""
    assert np.isfinite(u_of(r)).all()
    assert all(np.isfinite(x) for s in r.stages for x in s["residual"] + s["imbalance"])
    if r.converged:
        assert r.status == "converged" and r.stable
        assert r.equilibrium["imbalance"] < 1e-4
    else:
        assert r.status != "converged" and len(r.message) > 20


def assert_matches_float64(d: dict, dtype: str, r):
    """float32: the same verdict as float64, displacements within 1e-3 of the largest."""
    if dtype == "float64":
        return
    r64 = solve(d, "float64")
    assert (r.status, r.stable, r.moving_blocks) == (r64.status, r64.stable, r64.moving_blocks)
    u32, u64 = u_of(r), u_of(r64)
    assert np.abs(u32 - u64).max() <= 1e-3 * np.abs(u64).max()


def rect(x0: float, y0: float, w: float, h: float) -> list:
    return [[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]]


def blocks_scene(name: str, blocks: list, *, kn=1e6, ks=5e5, phi=35.0, materials=None,
                 **solver) -> dict:
    """Explicit blocks (``(vertices, fixed[, material])``) with one joint ``j``."""
    return {
        "scene": {"name": name},
        "solver": {"load_steps": 1, **solver},
        "materials": materials or {"rock": dict(ROCK)},
        "joints": {"j": {"kn": kn, "ks": ks, "friction_deg": phi}},
        "blocks": [{"vertices": b[0], "fixed": b[1], "material": b[2] if len(b) > 2 else "rock"}
                   for b in blocks],
    }


BASE = (rect(-2, -1, 5, 1), True)  # fixed, top face y = 0, h = 0.5 below it


def k_eq(h1, h2, kn0=1e6, kn1=KN_I, kn2=KN_I):
    """Normal stiffness per unit length of a joint (eqs. 6-7), kPa/m."""
    return equivalent_stiffness(h1, h2, 1 / kn1, 1 / kn2, 1 / kn0)


# ---------------------------------------------------------------------------
# Stiffness contrasts


def _incline_closed_form(alpha, kn0, ks0, width=1.0, height=1.0):
    """(u_t, u_n, theta) of a block on a slope (module docstring), eqs. 6-7 with Le = width."""
    a = math.radians(alpha)
    _, n = incline_frame(alpha)
    h_base = abs(centroid(np.array(slope_base(alpha))) @ n)  # the slope runs through 0
    ks_i = intact_stiffness(E, NU)[1]
    kn = k_eq(height / 2, h_base, kn0)
    ks = equivalent_stiffness(height / 2, h_base, 1 / ks_i, 1 / ks_i, 1 / ks0)
    W = GAMMA * width * height
    hc = height / 2
    theta = W * math.sin(a) * hc / (kn * width**3 / 4)
    return -W * math.sin(a) / (ks * width) - theta * hc, -W * math.cos(a) / (kn * width), theta


@pytest.mark.parametrize("dtype", DTYPES)
def test_kn_over_ks_1e4_on_an_incline_gives_the_spring_displacements(dtype):
    """kn / ks = 1e4 (kn = 1e7, ks = 1e3 kPa/m), alpha = 20 < phi = 45: stable, and the
    block moves by the closed-form spring displacements (8 mm down the slope, 2 um into
    it); at alpha = 35 > phi = 30 the same springs slide (mechanism, block 1 named)."""
    d = block_on_incline(20.0, 45.0, kn=1e7, ks=1e3)
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged and r.stable
    u_t, u_n, theta = _incline_closed_form(20.0, 1e7, 1e3)
    t, n = incline_frame(20.0)
    ux, uy, rot = r.blocks[1]["u"]
    assert np.dot([ux, uy], t) == close(u_t, dtype)
    # u_n (2 um) and theta (6 urad) are small: float32 resolves them to its coordinate
    # resolution near x = 4 m (5e-7 m, and 5e-7 rad over the 1 m face).
    res = {"float64": 0.0, "float32": 1e-6}[dtype]
    assert np.dot([ux, uy], n) == pytest.approx(u_n, rel=1e-5, abs=res)
    assert rot == pytest.approx(theta, rel=1e-4, abs=res)
    assert_matches_float64(d, dtype, r)
    slide = solve(block_on_incline(35.0, 30.0, kn=1e7, ks=1e3, max_displacement=0.5), dtype)
    assert_sane(slide)
    assert slide.status == "mechanism" and not slide.stable and slide.moving_blocks == [1]


def _column(n_blocks, h_base, height, width, kn0, kn_blocks):
    """Settlement of the top of a column (series springs, module docstring)."""
    W = GAMMA * width * height
    settle = 0.0
    for k in range(n_blocks):
        below = (h_base, KN_I) if k == 0 else (height / 2, kn_blocks[k - 1])
        kk = k_eq(height / 2, below[0], kn0, kn_blocks[k], below[1])
        settle += W * (n_blocks - k) / (kk * width)
    return settle


@pytest.mark.parametrize("dtype", DTYPES)
def test_joint_stiffness_1e6_times_softer_than_rock_settles_as_series_springs(dtype):
    """Joints 1e-6 of the rock's stiffness (kn_0 = 1e-6 kn_i / h, E = 1e11 kPa): a column
    of three blocks settles by sum W_k / (k Le), the rock's 1e-6 share of the compliance
    included, and without any rotation or sideways drift."""
    E_rock = 1e11
    kn_rock = intact_stiffness(E_rock, NU)[0]
    kn0 = 1e-6 * kn_rock / 0.5
    d = stack(3, kn=kn0, ks=kn0)
    d["materials"]["rock"]["E"] = E_rock
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged
    # The fixed base is rock of the same E, its centroid 0.5 m below the joint.
    W = GAMMA
    expected = sum(W * (3 - k) / equivalent_stiffness(0.5, 0.5, 1 / kn_rock, 1 / kn_rock, 1 / kn0)
                   for k in range(3))
    ux, uy = r.monitors["top"]["displacement"]
    assert -uy == close(expected, dtype)
    assert abs(ux) < 1e-6 * expected and np.abs(u_of(r)[:, 2]).max() < 1e-9
    assert_matches_float64(d, dtype, r)


@pytest.mark.parametrize("dtype", DTYPES)
def test_materials_with_E_ratio_1e4_settle_as_series_springs(dtype):
    """E = 1e7 kPa under E = 1e3 kPa (ratio 1e4): the soft block's own compliance
    h / kn_i (0.5 / 1067 kPa) dominates its joint: 11.8 mm against 0.05 mm below it."""
    d = stack(2)
    d["materials"]["soft"] = dict(ROCK, E=1e3)
    d["blocks"][2]["material"] = "soft"
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged
    soft = intact_stiffness(1e3, NU)[0]
    expected = _column(2, 0.5, 1.0, 1.0, 1e6, [KN_I, soft])
    assert -r.monitors["top"]["displacement"][1] == close(expected, dtype)
    lower = 2 * GAMMA / k_eq(0.5, 0.5)
    assert -r.blocks[1]["u"][1] == close(lower, dtype)
    assert_matches_float64(d, dtype, r)


# ---------------------------------------------------------------------------
# Scales


def _big_and_small(small_block):
    return blocks_scene("sizes 1e3", [(rect(-600, -20, 1200, 20), True),
                                      (rect(-500, 0, 1000, 10), False),
                                      (small_block, False)])


@pytest.mark.parametrize("dtype", DTYPES)
def test_small_block_on_a_block_1000_times_larger_carries_its_weight(dtype):
    """A 1 m block on a free 1000 m x 10 m block (size ratio 1e3, weight ratio 1e-4), both
    on a fixed base: the small block's contact forces add up to its weight, and it settles
    into the big one by W / (k Le) with h = 5 m of the big block (eq. 7). Each block is
    balanced to the tolerance of its own forces, not of the scene's largest load."""
    d = _big_and_small(rect(0, 10, 1, 1))
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged
    c = r.geometry["contacts"]
    top = (c["state"] > 0) & (c["points"][:, 1] > 5.0)  # the small block's base
    assert top.sum() == 2
    assert c["fn"][top].sum() == close(GAMMA, dtype)
    sink = r.blocks[1]["u"][1] - r.blocks[2]["u"][1]
    assert sink == close(GAMMA / k_eq(0.5, 5.0), dtype)
    big = (GAMMA * 1e4 + GAMMA) / (k_eq(5.0, 10.0) * 1000.0)
    assert -r.blocks[1]["u"][1] == pytest.approx(big, rel=1e-3)
    assert_matches_float64(d, dtype, r)


@pytest.mark.parametrize("dtype", DTYPES)
def test_small_block_sliding_on_a_block_1000_times_larger_is_a_mechanism(dtype):
    """The same pair with the big block's top a 35 degree slope, phi = 30: the small block
    slides (its out-of-balance force, 2.5 kN/m, is 1e-7 of the big block's weight, which a
    scene-wide tolerance would have let pass as equilibrium)."""
    a = 35.0
    top = 100.0 + 1000.0 * math.tan(math.radians(a))
    big = [[-500, 0], [500, 0], [500, top], [-500, 100]]
    small = (np.array(rect_on_slope(a, 500.0, 1.0, 1.0)) + [-500.0, 100.0]).tolist()
    d = blocks_scene("slides on a big block", [(rect(-600, -20, 1200, 20), True),
                                               (big, False), (small, False)],
                     phi=30.0, max_displacement=5.0)
    r = solve(d, dtype)
    assert_sane(r)
    assert r.status == "mechanism" and not r.stable and r.moving_blocks == [2]
    # It slid down the big block's face, not through it: its base stays on that face
    # (within 1 mm) and it went more than half of max_displacement down it.
    big_now = np.asarray(r.geometry["final_vertices"][1])
    face_t = (big_now[2] - big_now[3]) / np.linalg.norm(big_now[2] - big_now[3])
    face_n = np.array([-face_t[1], face_t[0]])
    base_now = np.asarray(r.geometry["final_vertices"][2])[:2]
    assert np.abs((base_now - big_now[3]) @ face_n).max() < 1e-3
    s0 = (np.array(small[0]) - big[3]) @ incline_frame(a)[0]
    assert (base_now[0] - big_now[3]) @ face_t < s0 - 2.5


# ---------------------------------------------------------------------------
# Degenerate geometry


@pytest.mark.parametrize("dtype", DTYPES)
def test_faces_1e6_rad_from_parallel_settle_flat(dtype):
    """A block whose base is tilted 1e-6 rad against the base's top face (one corner
    touching, the other 1 um up): it settles onto both corners and ends where a flat
    block does (the springs carry equal forces: the base ends parallel to the support)."""
    tilt = 1e-6
    c, s = math.cos(tilt), math.sin(tilt)
    tilted = blocks_scene("near-parallel", [BASE, ([[0, 0], [c, s], [c - s, s + c], [-s, c]],
                                                   False)])
    flat = blocks_scene("flat", [BASE, (rect(0, 0, 1, 1), False)])
    r, r_flat = solve(tilted, dtype), solve(flat, dtype)
    for x in (r, r_flat):
        assert_sane(x)
        assert x.converged
    settle = GAMMA / k_eq(0.5, 0.5)
    assert -r_flat.blocks[1]["u"][1] == close(settle, dtype)
    # Final positions: the same block in the same place, to the resolution of the dtype.
    final = np.asarray(r.geometry["final_vertices"][1])
    final_flat = np.asarray(r_flat.geometry["final_vertices"][1])
    assert np.abs(final - final_flat).max() <= TOL[dtype]["rel"] * settle + TOL[dtype]["abs"]
    assert r.blocks[1]["u"][2] == pytest.approx(-tilt, rel=1e-3 if dtype == "float64" else 0.1)
    assert_matches_float64(tilted, dtype, r)


@pytest.mark.parametrize("dtype", DTYPES)
def test_corners_meeting_corners_carry_no_spurious_force(dtype):
    """Vertex-to-vertex contacts. (1) A block flush with the end of its base (its corner on
    the base's corner): an edge-to-edge contact of Le = 1 m, settlement W / (k Le), no tilt.
    (2) A 2 x 2 grid of blocks on a base: the four meet corner to corner at the centre
    node; each column settles as two springs in series, 2 W / k and 3 W / k, and
    nothing moves sideways or turns."""
    flush = blocks_scene("flush corners", [(rect(-2, -1, 3, 1), True), (rect(0, 0, 1, 1), False)])
    r = solve(flush, dtype)
    assert_sane(r)
    assert r.converged
    k = k_eq(0.5, 0.5)
    ux, uy, rot = r.blocks[1]["u"]
    assert -uy == close(GAMMA / k, dtype)
    assert abs(ux) < 1e-6 * GAMMA / k and abs(rot) < 1e-6 * GAMMA / k
    assert_matches_float64(flush, dtype, r)

    grid = blocks_scene("2x2 grid", [BASE] + [(rect(i, j, 1, 1), False)
                                              for j in range(2) for i in range(2)])
    r = solve(grid, dtype)
    assert_sane(r)
    assert r.converged
    u = u_of(r)[1:]
    assert -u[:, 1] == close([2 * GAMMA / k] * 2 + [3 * GAMMA / k] * 2, dtype)
    assert np.abs(u[:, [0, 2]]).max() < 1e-6 * GAMMA / k
    assert_matches_float64(grid, dtype, r)


@pytest.mark.parametrize("dtype", DTYPES)
def test_exactly_touching_and_1e9_gap_settle_to_the_same_equilibrium(dtype):
    """A block exactly on its base, and one 1e-9 m above it (below the touch tolerance,
    1e-6 of the block size): both settle to the same place, W / (k Le) into the base."""
    touching = blocks_scene("touching", [BASE, (rect(0, 0, 1, 1), False)])
    gap = blocks_scene("gap 1e-9", [BASE, (rect(0, 1e-9, 1, 1), False)])
    r0, r1 = solve(touching, dtype), solve(gap, dtype)
    settle = GAMMA / k_eq(0.5, 0.5)
    for r in (r0, r1):
        assert_sane(r)
        assert r.converged
        y_base = np.asarray(r.geometry["final_vertices"][1])[:2, 1]
        assert -y_base == close([settle, settle], dtype)
    # The same place: u differs by the gap (float32 cannot see 1e-9 m at all).
    assert r1.blocks[1]["u"][1] == close(r0.blocks[1]["u"][1] - 1e-9, dtype)
    assert_matches_float64(gap, dtype, r1)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("thickness", [1e-2, 1e-3])
def test_long_thin_sliver_between_two_close_joints(dtype, thickness):
    """A 10 m sliver 1 cm or 1 mm thick (two joints that close apart) under a 1 m block:
    the sliver settles by (W + W_sliver) / (k 10 m) with its own h = t / 2 (eq. 7: a
    floor on h at a tenth of the 5 m radius made it 100 times too soft), and the block by
    W / (k 1 m) more."""
    d = blocks_scene("sliver", [(rect(-6, -1, 12, 1), True), (rect(-5, 0, 10, thickness), False),
                                (rect(-0.5, thickness, 1, 1), False)])
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged
    w_sliver = GAMMA * 10 * thickness
    sliver = (GAMMA + w_sliver) / (k_eq(thickness / 2, 0.5) * 10)
    block = sliver + GAMMA / k_eq(0.5, thickness / 2)
    assert -r.blocks[1]["u"][1] == close(sliver, dtype)
    assert -r.blocks[2]["u"][1] == close(block, dtype)
    assert np.abs(u_of(r)[:, 2]).max() < 1e-6
    assert_matches_float64(d, dtype, r)


# ---------------------------------------------------------------------------
# Limit states and mechanisms


@pytest.mark.parametrize("dtype", DTYPES)
def test_friction_equal_to_the_slope_angle_is_limit_equilibrium(dtype):
    """alpha = phi = 30: limit equilibrium. The solver reports it stable (the out-of-balance
    force W (sin alpha - cos alpha tan phi) is round-off), with the base at the limit:
    sum Fs / sum Fn = tan(phi). The verdict switches at the friction angle to within the
    tolerance: a slope steeper by delta, sin(delta) = 3 tol cos(phi), whose excess force
    is 3 tol W (tol = 1e-6; float32's floor 2.4e-5), slides (mechanism: it must move, not
    creep by R / (eps k) per iteration until the iteration limit); as much flatter stands."""
    d = block_on_incline(30.0, 30.0, max_displacement=0.5)
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged and r.stable
    c = r.geometry["contacts"]
    on = c["state"] > 0
    assert c["fs"][on].sum() / c["fn"][on].sum() == pytest.approx(
        math.tan(math.radians(30.0)), rel=10 * TOL[dtype]["rel"])
    assert c["fn"][on].sum() == pytest.approx(GAMMA * math.cos(math.radians(30.0)),
                                              rel=10 * TOL[dtype]["rel"])
    tol = {"float64": 1e-6, "float32": 200 * float(np.finfo(np.float32).eps)}[dtype]
    delta = math.degrees(math.asin(3 * tol * math.cos(math.radians(30.0))))
    steeper = solve(block_on_incline(30.0 + delta, 30.0, max_displacement=0.5), dtype)
    assert_sane(steeper)
    assert steeper.status == "mechanism" and steeper.moving_blocks == [1]
    ux, uy = steeper.monitors["block"]["displacement"]
    assert math.degrees(math.atan2(-uy, -ux)) == pytest.approx(30.0, abs=0.5)  # down-slope
    flatter = solve(block_on_incline(30.0 - delta, 30.0, max_displacement=0.5), dtype)
    assert_sane(flatter)
    assert flatter.converged and flatter.stable


@pytest.mark.parametrize("dtype", DTYPES)
def test_free_falling_block_is_reported_at_once(dtype):
    """A block with nothing under it (no other block in the scene): a mechanism, block 0
    named, after falling max_displacement (1 m, its size) in sub-steps of a twentieth of
    it, one Newton iteration each; the remaining four load steps are not attempted."""
    d = blocks_scene("free fall", [(rect(0, 0, 1, 1), False)], load_steps=5)
    r = solve(d, dtype)
    assert_sane(r)
    assert r.status == "mechanism" and not r.stable and r.moving_blocks == [0]
    assert "mechanism" in r.message
    stage = r.stages[0]
    assert len(stage["iterations"]) == 1
    assert stage["substeps"][0] <= 25 and stage["iterations"][0] <= stage["substeps"][0] + 2
    ux, uy, rot = r.blocks[0]["u"]
    assert uy < -1.0 and ux == 0.0 and rot == 0.0
    assert_matches_float64(d, dtype, r)


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_small_block_is_a_mechanism_once_it_has_fallen_its_own_size(dtype):
    """Two 2 m blocks at rest on a fixed base and a 0.5 m block with nothing under it:
    the median block size L is 2 m, but where the scene leaves max_displacement out each
    block's limit is its own size (between L / 5 and L), so the small block is a
    mechanism once it has fallen 0.5 m (sub-steps of at most a quarter of its 0.35 m
    radius), not 2 m; given, max_displacement is every block's limit (it falls 2 m)."""
    blocks = [(rect(-1, -1, 8, 1), True), (rect(0, 0, 2, 2), False),
              (rect(4, 0, 2, 2), False), (rect(10, 5, 0.5, 0.5), False)]
    d = blocks_scene("a small block falls", blocks)
    r = solve(d, dtype)
    assert_sane(r)
    assert r.status == "mechanism" and r.moving_blocks == [3]
    assert "block 3 travelled over its own limit, 0.5 m" in r.message
    ux, uy, rot = r.blocks[3]["u"]
    assert -0.5 - 0.25 * math.hypot(0.25, 0.25) <= uy < -0.5 and ux == 0.0 and rot == 0.0
    for b in r.blocks[1:3]:  # the large blocks rest on the base
        assert np.abs(b["u"][:2]).max() < 1e-4
    assert_matches_float64(d, dtype, r)
    given = solve(blocks_scene("a small block falls", blocks, max_displacement=2.0), dtype)
    assert given.status == "mechanism" and given.moving_blocks == [3]
    assert "travel over 2 m" in given.message
    assert given.blocks[3]["u"][1] < -2.0


@pytest.mark.parametrize("dtype", DTYPES)
def test_blocks_that_fall_together_share_the_limit_of_their_group(dtype):
    """Two 0.5 m blocks side by side with nothing under them, among three 2 m blocks at
    rest (L = 2 m): each one's own limit is 0.5 m, but they fall together (in contact
    along their common side), so their limit is the size of the pair, sqrt(2 x 0.25) =
    0.707 m: a mechanism once they have fallen that far, both named. With a fixed ledge
    0.6 m below them they land on it after 0.6 m and come to rest: an equilibrium, where
    each block's own limit would have called it a mechanism at 0.5 m."""
    blocks = [(rect(-1, -1, 14, 1), True), (rect(0, 0, 2, 2), False),
              (rect(3, 0, 2, 2), False), (rect(6, 0, 2, 2), False),
              (rect(10, 5, 0.5, 0.5), False), (rect(10.5, 5, 0.5, 0.5), False)]
    d = blocks_scene("a pair falls", blocks)
    r = solve(d, dtype)
    assert_sane(r)
    assert r.status == "mechanism" and r.moving_blocks == [4, 5]
    assert "blocks 4, 5 moved together" in r.message and "their limit, 0.707 m" in r.message
    for i in (4, 5):
        ux, uy, rot = r.blocks[i]["u"]
        assert -math.sqrt(0.5) - 0.25 * math.hypot(0.25, 0.25) <= uy < -math.sqrt(0.5)
        # Straight down in exact arithmetic. In float32 the LU of the iteration matrix
        # (the pair's stiff contact springs beside eps M) turned the pair by 0.002 rad
        # (17,000 eps) on an AVX2 CPU; refined in float64
        # (jaxdem.core._linsolve.refined_solve), by 6e-9.
        small = {"float64": 1e-6, "float32": 1000 * float(np.finfo(np.float32).eps)}[dtype]
        assert abs(ux) < small and abs(rot) < small
    ledge = blocks + [(rect(9.5, 3.9, 2.0, 0.5), True)]  # its top 0.6 m below the pair
    landed = solve(blocks_scene("a pair lands", ledge), dtype)
    assert_sane(landed)
    assert landed.converged and landed.stable
    for i in (4, 5):
        assert landed.blocks[i]["u"][1] == pytest.approx(-0.6, abs=1e-3)


# The simplest draw of tests/test_properties.py that ended at the iteration limit: a 6 m
# square of soft rock (no cohesion on intact cuts, the material default) between roller
# walls on a fixed base, one joint segment across the middle; the rock-mass generation
# cuts it into 3 columns x 2 rows (intact cuts through the joint's ends).
SIX_BLOCKS_IN_A_BOX = {
    "scene": {"name": "six blocks in a box"},
    "solver": {"load_steps": 1},
    "materials": {"rock": {"E": 1e6, "nu": 0.15, "unit_weight": 18.0}},
    "joints": {"fault": {"kn": 1e5, "ks": 1e5, "friction_deg": 15.0}},
    "domain": {"outline": [[0, 0], [6, 0], [6, 6], [0, 6]], "material": "rock"},
    "discontinuities": [{"from": [2.46, 3.0], "to": [3.54, 3.0], "joint": "fault"}],
    "boundaries": [{"side": "bottom", "condition": "fixed"},
                   {"side": "left", "condition": "roller"},
                   {"side": "right", "condition": "roller"}],
}


@pytest.mark.parametrize("dtype", DTYPES)
def test_columns_slipping_past_each_other_at_zero_normal_force_converge(dtype):
    """Six blocks under self-weight: the middle column settles more on its soft joint
    (kn 1e5 kPa/m) than its neighbours on intact rock, so the vertical interfaces slip,
    at zero normal force (nothing pushes sideways). With the elastic (secant) matrix,
    in which slipping slots keep their shear spring, Newton converged at a rate of 0.96
    an iteration and every sub-step ran into max_iterations (60); with the slip tangent
    once the states hold, in fewer than 60 in all. Closed forms: the base carries the
    weight (gamma x 36 m2); the vertical interfaces carry nothing; each column settles
    as series springs (module docstring): the bottom blocks by W_col h / kn_i on the
    fixed base (h = 1.5 m, a wall adds no joint term), the outer top blocks by
    W_top / k_intact more, the middle one by W_top / k_joint more (W per m of width).
    To 1e-3: the model updates h as the blocks settle, and the strain here is 1e-4."""
    r = solve(SIX_BLOCKS_IN_A_BOX, dtype)
    assert_sane(r)
    assert r.converged and r.stable
    assert len(r.blocks) == 6
    iterations = sum(r.stages[0]["iterations"])
    assert iterations < 60  # the default max_iterations of a single sub-step
    gamma, kn_i = 18.0, intact_stiffness(1e6, 0.15)[0]
    assert r.equilibrium["reaction"][1] == pytest.approx(gamma * 36.0, rel=1e-6)
    c = r.geometry["contacts"]
    vertical = np.abs(c["normals"][:, 0]) > 0.99
    tol = {"float64": 1e-6, "float32": 200 * float(np.finfo(np.float32).eps)}[dtype]
    assert vertical.sum() > 0
    assert np.abs(c["fn"][vertical]).max() <= 10 * tol * gamma * 36.0
    base = gamma * 6.0 * 1.5 / kn_i
    top = {"intact": gamma * 3.0 / k_eq(1.5, 1.5, np.inf, kn_i, kn_i),
           "joint": gamma * 3.0 / k_eq(1.5, 1.5, 1e5, kn_i, kn_i)}
    for b in r.blocks:
        x, y = b["centroid"]
        expected = base if y < 3.0 else base + top["joint" if 2.46 < x < 3.54 else "intact"]
        ux, uy, rot = b["u"]
        assert -uy == pytest.approx(expected, rel=1e-3)
        assert abs(ux) < 1e-6 * expected and abs(rot) < 1e-6 * expected


@pytest.mark.parametrize("name", ["frozen_slots_opening", "frozen_slots_water"])
def test_frozen_chattering_slots_never_give_a_converged_answer_beyond_strength(name):
    """Two rock masses drawn by tests/test_properties.py (tests/data/NAME.toml) in which
    slots chatter between states and Newton freezes them. A frozen slot stuck beyond its
    strength or closed in tension was once accepted as converged. Now every stage that
    ends converged satisfies every contact's strength law (the property tests'
    ``strength_violations``), and
    one that does not reach equilibrium says so (mechanism or iteration limit), never
    "converged". The opening's loading stage (self-weight, frozen slots on the way)
    reaches a lawful equilibrium. The water scene converges: its slots chattered because
    water pressed only on closed joints (the force jumped by pw where one opened); it now
    presses on open ones too. float64 only: these are the property test's draws."""
    scene = jaxdem.load_scene(DATA / f"{name}.toml")
    model, state, layout = model_mod.build(scene)
    checked = {}

    def stage_end(driver, stage):
        if driver.status == Status.CONVERGED:
            checked[stage] = strength_violations(driver, float(driver.model.tol))

    driver = solver.run(scene, model, state, layout, solver.scene_data(scene, layout),
                        stage_end=stage_end)
    assert all(not bad for bad in checked.values()), checked
    if driver.status == Status.CONVERGED:
        assert not strength_violations(driver, float(driver.model.tol))
    else:
        assert driver.status in (Status.MECHANISM, Status.ITERATION_LIMIT)
    if name == "frozen_slots_opening":
        assert "initial" in checked
    else:
        assert driver.status == Status.CONVERGED


def _toppling_example(dtype, **overrides):
    """examples/toppling.toml in ``dtype``, with ``solver`` overrides."""
    scene = jaxdem.load_scene(EXAMPLES / "toppling.toml")
    scene = scene.with_overrides({f"solver.{k}": v for k, v in overrides.items()})
    return dataclasses.replace(scene, solver=dataclasses.replace(scene.solver, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_toppling_example_is_a_mechanism_within_its_max_displacement(dtype):
    """examples/toppling.toml (0.3 x 1 m block, alpha 20, phi 40: b / h = 0.3 < tan 20)
    allows 0.3 m of travel: the block tips down-slope about its lower corner (positive
    rotation) past that, so the answer is a mechanism naming block 1, not a bug."""
    r = jaxdem.solve(_toppling_example(dtype))
    assert_sane(r)
    assert r.status == "mechanism" and r.moving_blocks == [1]
    assert r.blocks[1]["u"][2] > 0.1


@pytest.mark.parametrize("dtype", DTYPES)
def test_toppling_block_turns_over_and_lands_on_its_side(dtype):
    """The same block with room to move (max_displacement 3 m) topples through 90 degrees
    about its down-slope corner and comes to rest on its long face (b / h = 3.3 > tan 20,
    tan 40 > tan 20): stable, rotation pi / 2, that face flat on the slope, the pivot
    corner where it started (within 1 cm: the sub-steps' linearised rotation lets it creep
    by 0.8 mm per 10 degrees)."""
    r = jaxdem.solve(_toppling_example(dtype, max_displacement=3.0))
    assert_sane(r)
    assert r.converged and r.stable
    assert r.blocks[1]["u"][2] == pytest.approx(math.pi / 2, abs=1e-3)
    t, n = incline_frame(20.0)
    final = np.asarray(r.geometry["final_vertices"][1])
    start = np.asarray(_toppling_example(dtype).blocks[1].vertices)
    # The slope is y = x tan 20 through the origin: the long face (vertices 3 and 0) is on it.
    assert np.abs(final[[3, 0]] @ n).max() < 1e-4
    assert np.abs(final[[1, 2]] @ n - 0.3).max() < 1e-4
    assert np.linalg.norm(final[0] - start[0]) < 0.01


def _topple_onto_stop(lean=30.0, h=0.6):
    """A tall block on a 20 degree slope with a fixed stop down-slope, whose upper corner C
    lies where the block's down-slope face passes after turning ``lean`` degrees."""
    d_along = h * math.tan(math.radians(lean))
    d = block_on_incline(20.0, 40.0, width=0.3, height=1.0, max_displacement=1.0)
    d["blocks"].insert(1, {"vertices": rect_on_slope(20.0, 4.0 - d_along - 1.0, 1.0, h),
                           "material": "rock", "fixed": True})
    t, n = incline_frame(20.0)
    return d, (4.0 - d_along) * t + h * n


@pytest.mark.parametrize("dtype", DTYPES)
def test_toppling_block_turns_30_degrees_and_lands_on_a_stop(dtype):
    """The toppling block with a fixed block 0.35 m down-slope, 0.6 m high: it turns about
    its lower corner until its face lands on the stop's corner C, at tan(theta) = 0.35 /
    0.6 (30 degrees), and rests there: stable, C on the block's face, the angle that of
    the face through the final pivot and C, friction within Mohr-Coulomb at both points."""
    d, C = _topple_onto_stop()
    r = solve(d, dtype)
    assert_sane(r)
    assert r.converged and r.stable
    final = np.asarray(r.geometry["final_vertices"][2])
    pivot, top = final[0], final[3]
    face = (top - pivot) / np.linalg.norm(top - pivot)
    # C lies on the face (within the elastic overlap of the corner spring, < 0.1 mm).
    offset = C - pivot
    assert abs(offset[0] * face[1] - offset[1] * face[0]) < 1e-4
    _, n = incline_frame(20.0)
    lean = math.atan2(-(face[0] * n[1] - face[1] * n[0]), face @ n)
    assert r.blocks[2]["u"][2] == pytest.approx(lean, abs=1e-4)
    assert math.degrees(lean) == pytest.approx(30.0, abs=0.2)
    c = r.geometry["contacts"]
    on = c["state"] > 0
    assert on.sum() == 2
    assert (np.abs(c["fs"][on]) <= c["fn"][on] * math.tan(math.radians(40.0)) * (1 + 1e-6)).all()


# ---------------------------------------------------------------------------
# Many load steps


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_thousand_load_steps_give_the_answer_of_five(dtype):
    """load_steps = 1000 on a stack of three: the same settlement as 5 steps and as the
    closed form (elastic: the path does not matter), a bounded amount of work (at most 4
    Newton iterations a step) and time. In float32 a step's move (1.6e-7 m) is below the
    resolution of a coordinate near y = 2.5 m (2.4e-7 m): positions are rebuilt from the
    start geometry and the accumulated displacement, so it is not lost step by step."""
    five = solve(stack(3, load_steps=5), dtype)
    d = stack(3, load_steps=1000)
    many = solve(d, dtype)
    for r in (five, many):
        assert_sane(r)
        assert r.converged
    expected = _column(3, 0.5, 1.0, 1.0, 1e6, [KN_I] * 3)
    u5 = five.monitors["top"]["displacement"][1]
    u1000 = many.monitors["top"]["displacement"][1]
    assert -u1000 == close(expected, dtype)
    # float32: the two paths' round-off differ by 2.7e-4 (measured); monitors read from
    # the accumulated displacement show it (read as differences of positions, both were
    # rounded to the same multiple of a coordinate's resolution, 2.4e-7 m).
    assert u1000 == pytest.approx(u5, rel={"float64": 1e-8, "float32": 1e-3}[dtype])
    iterations = many.stages[0]["iterations"]
    assert len(iterations) == 1000 and max(iterations) <= 4
    assert many.timing["solve_s"] < 20.0
    assert_matches_float64(d, dtype, many)
