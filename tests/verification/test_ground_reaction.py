"""Ground reaction curve (jaxdem.grc, ``jaxdem grc``): all support pressures in one batch.

Closed forms:
- Circular opening of radius a in intact linear elastic rock under a hydrostatic
  in-situ stress p0, plane strain, with a support pressure p on its wall (Lame;
  Panet 1995; Carranza-Torres & Fairhurst 2000, eq. 7 in the elastic range): the wall
  moves in by u(p) = (1 + nu) a (p0 - p) / E, linear in p, so a diameter shortens by
  2 u(p). A support line p_s = k (u_s - u0) on that convergence u_s meets it at
  u_s = (p0 + k u0) / (K_s + k) with K_s = E / (2 (1 + nu) a). The rock is the
  deformable triangles of the Kirsch benchmark (benchmarks/bench_kirsch.py) in a
  32 a square with roller walls (about 1% stiffer than the infinite medium,
  tests/verification/test_deformable_cells.py).
- The in-situ normal stress on a square opening of side s centred at depth
  H = surface_y - y_c under gravity stress (sigma_yy = gamma (surface_y - y),
  sigma_xx = K0 sigma_yy): its roof and floor carry gamma (H -+ s/2), its walls K0
  gamma H on average, so the mean is p0 = gamma H (1 + K0) / 2.
- Jointed rock has no closed form: each level is the single solve of the scene with
  that support pressure (jaxdem.solve), which the batch must reproduce.
"""

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxdem
from jaxdem import grc as grc_module
from jaxdem.cli import main
from jaxdem.geometry import centroid, signed_area
from jaxdem.grc import SupportLine, grc_scene, in_situ_pressure, intersect, inward
from jaxdem.scene import SceneError, load_scene, parse_scene

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
from bench_kirsch import scene as kirsch_scene  # noqa: E402  (the benchmark's scene)
from bench_time_to_answer import to_toml  # noqa: E402
from scenes import jointed_tunnel  # noqa: E402

E, NU, A, P0 = 1e7, 0.25, 1.0, 1000.0


def roof_wedge() -> dict:
    """A 2 m square opening at 20 m depth whose roof is a wedge between two frictionless,
    cohesionless joints (apex 2 m above the roof); ``max_displacement`` 0.1 m, so that a
    wedge that drops is a mechanism rather than coming to rest on the floor."""
    return {
        "scene": {"name": "roof wedge"},
        "solver": {"load_steps": 2, "max_displacement": 0.1},
        "materials": {"rock": {"E": 1e7, "nu": 0.25, "unit_weight": 26.0, "cohesion": 1e4,
                               "friction_deg": 45.0, "tensile_strength": 1e4}},
        "joints": {"j": {"kn": 1e6, "ks": 1e5, "friction_deg": 5.0, "cohesion": 0.0,
                         "tensile_strength": 0.0}},
        "domain": {"outline": [[-5, -5], [5, -5], [5, 5], [-5, 5]], "material": "rock"},
        "discontinuities": [{"from": [-1.0, 1.0], "to": [0.0, 3.0]},
                            {"from": [1.0, 1.0], "to": [0.0, 3.0]}],
        "excavations": [{"name": "opening", "shape": "polygon",
                         "vertices": [[-1, -1], [1, -1], [1, 1], [-1, 1]]}],
        "in_situ": {"mode": "gravity", "k0": 0.3, "surface_y": 20.0},
        "boundaries": [{"side": "bottom", "condition": "fixed"}]
        + [{"side": s, "condition": "roller"} for s in ("left", "right", "top")],
        "monitors": [{"name": "span", "from": [-1.0, 0.0], "to": [1.0, 0.0]},
                     {"name": "roof", "point": [0.0, 1.0]}],
    }


def test_elastic_circular_opening_follows_the_closed_form():
    scene = parse_scene(kirsch_scene(0.5, half_width=16.0))
    k_support = 5e5   # kPa per m of the section's convergence
    curve = jaxdem.ground_reaction(scene, "hole", levels=4,
                                   support=dict(stiffness=k_support, capacity=400.0))
    # Hydrostatic: the mean normal stress on the outline is p0 itself.
    assert curve.p0 == pytest.approx(P0, rel=1e-12) and curve.p0_from == "in_situ"
    assert curve.parameter == "supports.0.pressure"        # a support was added
    np.testing.assert_allclose(curve.pressure, [1000.0, 2000.0 / 3, 1000.0 / 3, 0.0])
    assert curve.status == ["converged"] * 4 and curve.mechanism is None
    u_closed = (1 + NU) * A * (P0 - curve.pressure) / E
    for name in ("h", "v"):
        u = curve.monitors[name] / 2          # a diameter's shortening = 2 u
        # At p = p0 the support balances what the excavation releases.
        assert abs(u[0]) <= 1e-9 * u_closed[-1]
        np.testing.assert_allclose(u[1:], u_closed[1:], rtol=0.05)
        # Linear in p: the straight line through the levels misses none by 1%.
        fit = np.polyval(np.polyfit(curve.pressure, u, 1), curve.pressure)
        assert np.abs(u - fit).max() <= 0.01 * u[-1]
    # The support line meets the curve where the closed forms meet.
    k_rock = E / (2 * (1 + NU) * A)
    u_eq = P0 / (k_rock + k_support)
    eq = curve.equilibrium
    assert eq["status"] == "equilibrium"
    assert eq["convergence"] == pytest.approx(u_eq, rel=0.05)
    assert eq["pressure"] == pytest.approx(k_support * u_eq, rel=0.05)
    assert eq["factor_of_safety"] == pytest.approx(400.0 / eq["pressure"], rel=1e-12)


def test_jointed_rock_levels_equal_single_solves():
    """The small jointed tunnel (two joint sets, a bolt, water, a 100 kPa support on the
    tunnel): each level is the single solve with that support pressure."""
    scene = parse_scene(jointed_tunnel(spacing=3.5, top="roller"))
    curve = jaxdem.ground_reaction(scene, "tunnel", levels=4)
    # The scene's own support carries the level's pressure.
    assert curve.parameter == "supports.0.pressure" and "replaced" in curve.supports_note
    for i, p in enumerate(curve.pressure):
        single = jaxdem.solve(scene, set={"supports.0.pressure": float(p)})
        assert single.status == curve.status[i]
        assert curve.monitors["span"][i] == pytest.approx(
            single.monitors["span"]["convergence"], rel=1e-6, abs=1e-12)
        np.testing.assert_allclose(curve.displacements["crown"][i],
                                   single.monitors["crown"]["displacement"],
                                   rtol=1e-6, atol=1e-12)
        # The crown's convergence: its displacement towards the opening (straight down).
        np.testing.assert_allclose(inward(scene, scene.excavations[0], "crown"), [0.0, -1.0],
                                   atol=1e-12)
        assert curve.monitors["crown"][i] == pytest.approx(
            -single.monitors["crown"]["displacement"][1], rel=1e-6, abs=1e-12)


def test_in_situ_normal_stress_on_a_square_opening():
    scene = parse_scene(roof_wedge())
    gamma, depth, k0 = 26.0, 20.0, 0.3
    assert in_situ_pressure(scene, scene.excavations[0]) == pytest.approx(
        gamma * depth * (1 + k0) / 2, rel=1e-12)


def test_grc_command_writes_the_curve_and_names_the_falling_wedge(tmp_path, capsys):
    path = tmp_path / "wedge.toml"
    path.write_text(to_toml(roof_wedge()))
    out = tmp_path / "out"
    code = main(["grc", str(path), "--levels", "4", "--out", str(out), "--monitor", "roof",
                 "--support-stiffness", "1e6", "--support-capacity", "300",
                 "--install-convergence", "0.00005"])
    assert code == 0
    data = json.loads((out / "grc.json").read_text())
    assert (out / "grc.png").stat().st_size > 0
    assert data["excavation"] == "opening" and data["levels"] == 4
    np.testing.assert_allclose(data["pressure"], [338.0, 338.0 * 2 / 3, 338.0 / 3, 0.0])
    assert set(data["monitors"]) == {"span", "roof"}
    assert all(len(v) == 4 for v in data["monitors"].values())
    assert data["monitor"] == "roof" and data["parameter"] == "supports.0.pressure"
    # Unsupported, the wedge drops: a mechanism at p = 0, and the block named is the
    # wedge (the triangle on the 2 m roof with its apex 2 m above it).
    assert data["status"][:3] == ["converged"] * 3 and data["status"][3] == "mechanism"
    assert data["monitors"]["roof"][3] is None          # no equilibrium: null
    m = data["mechanism"]
    assert m["pressure"] == 0.0 and m["level"] == 3 and len(m["moving_blocks"]) == 1
    solved = grc_scene(parse_scene(roof_wedge()), "opening")[0]    # with the support added
    result = jaxdem.solve(solved, set={data["parameter"]: 0.0})
    wedge = result.geometry["initial_vertices"][m["moving_blocks"][0]]
    assert signed_area(wedge) == pytest.approx(2.0, rel=1e-9)
    np.testing.assert_allclose(centroid(wedge), [0.0, 1.0 + 2.0 / 3.0], atol=1e-9)
    # The wedge's area, 2 m3/m (half its 2 m base times its 2 m height); not small: the
    # scene has no joint sets, so no default max_loose_volume.
    assert m["volume"] == pytest.approx(2.0, rel=1e-9) and m["small"] is False
    said = capsys.readouterr().out
    assert "mechanism first appears at 0 kPa" in said and "It is small" not in said
    # The support line meets the curve above the mechanism, between the levels at 225
    # and 113 kPa, on both lines.
    eq = data["equilibrium"]
    assert eq["status"] == "equilibrium" and 338.0 / 3 < eq["pressure"] < 338.0 * 2 / 3
    line = SupportLine(1e6, 300.0, 5e-5)
    assert eq["pressure"] == pytest.approx(float(line.pressure(eq["convergence"])), rel=1e-9)
    p, u = np.array(data["pressure"][1:3]), np.array(data["monitors"]["roof"][1:3])
    assert eq["pressure"] == pytest.approx(np.interp(eq["convergence"], u, p), rel=1e-9)
    assert eq["factor_of_safety"] == pytest.approx(300.0 / eq["pressure"], rel=1e-12)


@pytest.mark.parametrize("args, field", [
    (["--levels", "1"], "--levels"),
    (["--excavation", "tunnel"], "--excavation"),
    (["--from", "400"], "--from"),
    (["--p0", "-5"], "--p0"),
    (["--monitor", "nowhere"], "--monitor"),
    (["--support-stiffness", "1e5"], "--support-capacity"),
    (["--support-stiffness", "-1", "--support-capacity", "100"], "--support-stiffness"),
])
def test_bad_input_is_refused_naming_the_field(tmp_path, capsys, args, field):
    path = tmp_path / "wedge.toml"
    path.write_text(to_toml(roof_wedge()))
    out = tmp_path / "out"
    assert main(["grc", str(path), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {field}") and "Traceback" not in err
    assert not out.exists()                              # refused before any computation


def test_a_wedge_that_falls_free_within_max_loose_volume_is_removed_as_a_single_solve_does():
    """The roof wedge (2 m3/m) with ``solver.max_loose_volume`` 2.5: unsupported it falls
    free and is small, so the batch removes it as a loose block and the level converges
    (no mechanism), with the span's convergence of a single solve at p = 0 (which removes
    it too) to 1e-9; a first mechanism that is small is said to be (the message)."""
    data = roof_wedge()
    data["solver"]["max_loose_volume"] = 2.5
    curve = jaxdem.ground_reaction(parse_scene(data), "opening", levels=2, monitor="roof")
    assert curve.status == ["converged", "converged"] and curve.mechanism is None
    solved = grc_scene(parse_scene(data), "opening")[0]
    single = jaxdem.solve(solved, set={curve.parameter: 0.0})
    assert single.converged and len(single.loose_blocks) == 1
    assert single.loose_blocks[0]["volume"] == pytest.approx(2.0, rel=1e-9)
    assert curve.monitors["span"][1] == pytest.approx(
        single.monitors["span"]["convergence"], rel=1e-9)
    small = dataclasses.replace(curve, mechanism=dict(
        level=1, pressure=0.0, status="mechanism", moving_blocks=[7], message="",
        volume=0.04, small=True))
    assert "It is small (0.04 m3/m, no larger than solver.max_loose_volume)" in \
        grc_module._message(small)


def test_bad_input_is_refused_by_the_python_interface():
    scene = parse_scene(roof_wedge())
    for kwargs, field in [(dict(excavation="tunnel"), "excavation"),
                          (dict(levels=1), "levels"), (dict(start=339.0), "start"),
                          (dict(support=dict(stiffness=1e5)), "support.capacity")]:
        args = dict(excavation="opening", levels=3) | kwargs
        with pytest.raises(SceneError) as err:
            jaxdem.ground_reaction(scene, args.pop("excavation"), **args)
        assert err.value.path == field


def test_a_later_stage_is_left_out():
    """The staged tunnel: the heading's curve stops at the end of stage 1; the bench, the
    bolts and the 50 kPa support of stage 2 are not part of it, and a support is added."""
    scene = load_scene(ROOT / "examples" / "staged_tunnel.toml")
    solved, index, note, dropped = grc_scene(scene, "heading")
    assert dropped == ["bench"] and [s.name for s in solved.stages] == ["heading"]
    assert [e.name for e in solved.excavations] == ["heading"]
    assert solved.bolts == ()
    assert len(solved.supports) == 1 and index == 0 and "added" in note
    assert solved.supports[0].excavation == "heading" and solved.supports[0].stage == "heading"


def test_support_line_intersection_with_a_straight_curve():
    """A linear curve p = p0 - K u meets p_s = k (u - u0) at u = (p0 + k u0) / (K + k),
    exactly, wherever the levels fall; on the plateau at p_max; not before u0."""
    p = np.linspace(1000.0, 0.0, 7)
    u = (1000.0 - p) / 4e6
    eq = intersect(p, u, SupportLine(5e5, 400.0, 5e-5))
    u_eq = (1000.0 + 5e5 * 5e-5) / (4e6 + 5e5)
    assert eq["status"] == "equilibrium"
    assert eq["convergence"] == pytest.approx(u_eq, rel=1e-12)
    assert eq["pressure"] == pytest.approx(1000.0 - 4e6 * u_eq, rel=1e-12)
    capped = intersect(p, u, SupportLine(5e6, 300.0, 0.0))
    assert capped["status"] == "at_capacity" and capped["pressure"] == pytest.approx(300.0)
    assert capped["factor_of_safety"] == pytest.approx(1.0)
    late = intersect(p, u, SupportLine(5e5, 400.0, 1.0))
    assert late["status"] == "not_loaded" and late["factor_of_safety"] is None
    broken = u.copy()
    broken[4:] = np.nan                                  # mechanisms below 333 kPa
    none = intersect(p, broken, SupportLine(1e3, 400.0, 0.0))
    assert none["status"] == "no_intersection" and none["pressure"] is None
