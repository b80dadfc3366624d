"""Intact rock as deformable constant-strain triangles (``domain.mesh_size``).

Closed forms:
- Patch test: a plane-strain square under a uniform vertical traction p, on
  rollers at the left and bottom, has the uniform strain eps_y = -p (1 - nu^2) / E,
  eps_x = p nu (1 + nu) / E. Rigid cells would give eps_x = 0 (no Poisson effect).
- Kirsch (1898; Jaeger, Cook & Zimmerman, Fundamentals of Rock Mechanics, 8.4): a
  circular opening of radius a excavated under hydrostatic in-situ stress p closes
  by 2 u = 2 p a (1 + nu) / E across a diameter in plane strain. The model's roller
  walls at 16 a make the answer about 1% smaller (Lame, thick cylinder).
"""

import sys
from pathlib import Path

import numpy as np
import pytest

import jaxdem
from jaxdem.scene import parse_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_kirsch import scene as kirsch_scene  # noqa: E402  (the benchmark's scene)

E, NU, P = 1e7, 0.25, 1000.0


def _patch(solver=None, size=4.0, h=1.0):
    return {
        "scene": {"name": "patch test"},
        "solver": {"load_steps": 1, **(solver or {})},
        "materials": {"rock": {"E": E, "nu": NU, "unit_weight": 0.0, "cohesion": 1e5,
                               "tensile_strength": 1e5, "friction_deg": 45.0}},
        "domain": {"outline": [[0, 0], [size, 0], [size, size], [0, size]], "material": "rock",
                   "mesh_size": h},
        "boundaries": [{"side": "left", "condition": "roller"},
                       {"side": "bottom", "condition": "roller"},
                       {"side": "top", "condition": "traction", "traction": [0.0, -P]}],
        "monitors": [{"name": "right", "point": [size, size / 2]},
                     {"name": "top", "point": [size / 2, size]},
                     {"name": "corner", "point": [size, size]}],
    }


def test_patch_test_gives_the_plane_strain_poisson_effect():
    r = jaxdem.solve(parse_scene(_patch()))
    assert r.converged
    ex = P * NU * (1 + NU) / E
    ey = -P * (1 - NU**2) / E
    # Bond springs add about 1/100 of the cells' compliance (BOND_PENALTY).
    assert r.monitors["right"]["displacement"][0] == pytest.approx(4.0 * ex, rel=0.02)
    assert r.monitors["top"]["displacement"][1] == pytest.approx(4.0 * ey, rel=0.02)
    assert r.monitors["corner"]["displacement"] == pytest.approx([4.0 * ex, 4.0 * ey], rel=0.02)
    # Every cell carries the applied stress (compression positive): syy = p, sxx = 0.
    s = np.array([b["stress"] for b in r.to_dict()["blocks"]])
    assert np.allclose(s[:, 1], P, rtol=0.02) and np.allclose(s[:, [0, 2]], 0.0, atol=0.02 * P)


@pytest.mark.parametrize("solver", ["sparse", "cg"])
def test_linear_solvers_agree_with_dense_cholesky(solver):
    # Both converged far below the 1e-7 they are compared at: at the default
    # tolerance (1e-6) each answer is only that close to the equilibrium, and
    # the cg path's inexact Newton stops wherever its own round-off takes it.
    ref = jaxdem.solve(parse_scene(_patch({"linear_solver": "dense", "tolerance": 1e-10})))
    other = jaxdem.solve(parse_scene(_patch({"linear_solver": solver, "tolerance": 1e-10})))
    assert other.converged
    a = np.array(ref.monitors["corner"]["displacement"])
    b = np.array(other.monitors["corner"]["displacement"])
    assert np.abs(a - b).max() <= 1e-7 * np.abs(a).max()


def test_circular_opening_converges_to_kirsch():
    closed = 2 * P * 1.0 * (1 + NU) / E
    errors = []
    for h in (1.0, 0.5):
        r = jaxdem.solve(parse_scene(kirsch_scene(h, half_width=16.0)))
        assert r.converged
        d = r.to_dict()
        initial = d["stages"][0]
        # The in-situ state is in equilibrium at zero displacement.
        assert initial["name"] == "initial" and initial["imbalance"][-1] < 1e-8
        assert abs(initial["monitors"]["h"][-1]) < 1e-6 * closed
        conv = 0.5 * (r.monitors["h"]["convergence"] + r.monitors["v"]["convergence"])
        errors.append(abs(conv / closed - 1.0))
    assert errors[1] < errors[0]
    assert errors[1] < 0.05


def test_float32_patch_test_matches_float64():
    r64 = jaxdem.solve(parse_scene(_patch()))
    r32 = jaxdem.solve(parse_scene(_patch({"dtype": "float32"})))
    assert r32.converged
    a = np.array(r64.monitors["corner"]["displacement"])
    b = np.array(r32.monitors["corner"]["displacement"])
    # float32 holds the vertex coordinates (up to 4 m here) to eps32 * 4 m = 4.8e-7 m,
    # 1.3e-3 of the 0.38 mm displacement: the answer can be no closer than a few of
    # those units (measured: 0.85 of one).
    ulp = np.finfo(np.float32).eps * 4.0
    assert np.abs(a - b).max() <= 4 * ulp


def test_gravity_in_situ_state_of_jointed_triangles_is_in_equilibrium():
    # Triangles cut by a joint set dipping 25 degrees, gravity stress with K0 = 0.5
    # and an overburden traction on top: the consistent nodal forces of the linear
    # stress field balance every block (force, moment and strains) at zero displacement.
    d = {
        "scene": {"name": "in-situ, jointed triangles"},
        "solver": {"load_steps": 1},
        "materials": {"rock": {"E": E, "nu": NU, "unit_weight": 27.0, "cohesion": 1e4,
                               "tensile_strength": 1e4, "friction_deg": 45.0}},
        "joints": {"set": {"kn": 1e6, "ks": 1e5, "friction_deg": 30.0, "dip_deg": 25.0,
                           "spacing": 3.0}},
        "domain": {"outline": [[0, 0], [20, 0], [20, 20], [0, 20]], "material": "rock",
                   "mesh_size": 2.0},
        "in_situ": {"mode": "gravity", "k0": 0.5, "surface_y": 40.0},
        "boundaries": [{"side": "bottom", "condition": "fixed"}]
        + [{"side": s, "condition": "roller"} for s in ("left", "right")]
        + [{"side": "top", "condition": "traction", "traction": [0.0, -540.0]}],
        # The opening's outline cuts the cells into irregular triangles (it is
        # excavated afterwards; only the state before that is checked here).
        "excavations": [{"name": "hole", "shape": "circle", "center": [10.0, 10.0],
                         "radius": 3.0}],
        "monitors": [{"name": "roof", "point": [10.0, 15.0]}],
    }
    r = jaxdem.solve(parse_scene(d))
    initial = r.stages[0]
    assert initial["name"] == "initial" and initial["converged"]
    assert initial["imbalance"][-1] < 1e-8
    # Stress 540 kPa at the top to 1,080 kPa at the base: an unbalanced quadrature
    # (trapezoidal end forces) moves the rock by about 1e-6 m here; measured with
    # the consistent forces: below 1e-12 m.
    roof = initial["monitors"]["roof"][-1]  # |u| of the point (m)
    assert roof < 1e-9
