"""A column of blocks on a fixed base: settlement from eqs. 6-7 with Le.

Each joint carries the weight of the blocks above it, W_k = gamma A (n - k).
Its equivalent stiffness per unit length is k = 1 / (h1/kn_i + h2/kn_i + 1/kn0)
(eq. 7, h = half the block height, kn_i = E / (1 - nu^2), eq. 4) over the
contact length Le = width (eq. 8). The top settles by sum_k W_k / (k Le).
"""

import pytest
from scenes import stack

import jaxdem
from jaxdem.core.laws import equivalent_stiffness, intact_stiffness
from jaxdem.scene import parse_scene


@pytest.mark.parametrize("n, kn, width, height", [(1, 1e6, 1.0, 1.0), (3, 1e6, 1.0, 1.0),
                                                   (4, 2e5, 2.0, 0.5)])
def test_stack_settlement_matches_closed_form(n, kn, width, height):
    r = jaxdem.solve(parse_scene(stack(n, kn=kn, width=width, height=height)))
    assert r.converged
    kn_i, _ = intact_stiffness(1e7, 0.25)
    W = 25.0 * width * height
    base_h = 0.5  # the fixed base is 1 m high
    settle = 0.0
    for k in range(n):
        h_below = base_h if k == 0 else height / 2
        k_eq = equivalent_stiffness(height / 2, h_below, 1 / kn_i, 1 / kn_i, 1 / kn)
        settle += W * (n - k) / (k_eq * width)
    ux, uy = r.monitors["top"]["displacement"]
    assert -uy == pytest.approx(settle, rel=0.01)
    assert abs(ux) < 1e-6 * settle


def test_settlement_scales_with_load_steps_only_through_the_path():
    # Elastic: the answer does not depend on how the weight is applied.
    a = jaxdem.solve(parse_scene(stack(3, load_steps=1))).monitors["top"]["displacement"][1]
    b = jaxdem.solve(parse_scene(stack(3, load_steps=5))).monitors["top"]["displacement"][1]
    assert a == pytest.approx(b, rel=1e-6)


def _grid(n: int, m: int | None = None) -> dict:
    """n columns of m (default n) square 1 m blocks on a fixed base 1 m high
    (benchmarks/bench_time_to_answer.py)."""
    m = n if m is None else m
    blocks = [{"vertices": [[-1.0, -1.0], [n + 1.0, -1.0], [n + 1.0, 0.0], [-1.0, 0.0]],
               "material": "rock", "fixed": True}]
    blocks += [{"vertices": [[i, j], [i + 1, j], [i + 1, j + 1], [i, j + 1]], "material": "rock"}
               for i in range(n) for j in range(m)]
    return {"scene": {"name": "grid"}, "solver": {"load_steps": 1},
            "materials": {"rock": {"E": 1e7, "nu": 0.25, "unit_weight": 25.0}},
            "joints": {"j": {"kn": 1e6, "ks": 1e6, "friction_deg": 35.0}},
            "blocks": blocks, "monitors": [{"name": "top", "point": [n // 2 + 0.5, m - 0.5]}]}


def _grid_settlement(m: int) -> float:
    """The top of a column of m 1 m blocks (the stack's closed form above)."""
    kn_i, _ = intact_stiffness(1e7, 0.25)
    return sum(25.0 * (m - k) / equivalent_stiffness(0.5, 0.5, 1 / kn_i, 1 / kn_i, 1 / 1e6)
               for k in range(m))


def test_a_grid_of_columns_settles_as_stacks_in_few_iterations():
    """A 6 x 6 grid: rigid columns side by side settle alike, so each is the stack
    above (same closed form) and the side contacts carry no force. Cohesionless,
    their strength is zero, and round-off shear (1e-13 kN) is not a slip: a stuck
    slot slips only when its shear passes the strength by the hysteresis band (a
    tenth of the tolerance). Without the band the side contacts flipped
    stick/slip at round-off and the secant iteration took 143 Newton iterations
    on a 10 x 10 grid; it is a linear problem, which Newton solves in a few."""
    n = 6
    r = jaxdem.solve(parse_scene(_grid(n)))
    assert r.converged
    settle = _grid_settlement(n)
    ux, uy = r.monitors["top"]["displacement"]
    assert -uy == pytest.approx(settle, rel=1e-4)
    assert abs(ux) < 1e-6 * settle
    assert sum(r.to_dict()["stages"][0]["iterations"]) <= 10


def test_a_tall_grid_settles_in_few_iterations_over_several_geometry_updates():
    """4 columns of 100 blocks settle 138 mm, about three step lengths (50 mm), so the
    load goes on over several geometry updates. Once a column's joints are compressed
    by the weight above them (up to 2.5 mm), each block's top corners reach past the
    next column's joint and touch the block above it there at zero normal force: such
    a side contact slips at once (zero strength) and carries nothing. Its elastic
    shear spring kept in the secant matrix tied every block to the next column's
    block above, and the iteration took 72 Newton iterations (a 100 x 100 grid found
    no equilibrium within 240); with no shear spring where a slipping slot's strength
    is under a hundredth of its trial force it takes 9. The answer is the stack's
    closed form (module docstring)."""
    r = jaxdem.solve(parse_scene(_grid(4, 100)))
    assert r.converged
    settle = _grid_settlement(100)
    assert settle > 2.5 * 0.05   # several step lengths: the case described above
    ux, uy = r.monitors["top"]["displacement"]
    assert -uy == pytest.approx(settle, rel=1e-6)
    assert abs(ux) < 1e-6 * settle
    assert sum(r.to_dict()["stages"][0]["iterations"]) <= 20


def test_a_wide_grid_settles_without_side_contacts_chattering():
    """A 70 x 70 grid (4,901 blocks) settles 68 mm in one load step: the stack's closed
    form (1e-6) in at most 12 Newton iterations. The joints between its columns carry
    nothing and touch at gaps of the order of the iteration's own error; hundreds of
    their slots opened and closed in every iteration, each opening let two columns
    part on nothing stiffer than eps M, and the residual hovered at 1-5 tolerances
    (15 iterations here, a 100 x 100 grid 36 or the iteration limit depending on the
    order in which its matrix was summed). An open slot within a few hysteresis bands
    of closing now keeps its normal spring in the secant matrix (9 iterations; the 100
    x 100 grid 18)."""
    r = jaxdem.solve(parse_scene(_grid(70)))
    assert r.converged
    settle = _grid_settlement(70)
    ux, uy = r.monitors["top"]["displacement"]
    assert -uy == pytest.approx(settle, rel=1e-6)
    assert abs(ux) < 1e-6 * settle
    assert sum(r.to_dict()["stages"][0]["iterations"]) <= 12
