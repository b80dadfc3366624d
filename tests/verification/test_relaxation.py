"""Staged relaxation (RS2's load split): an excavation's load released over several stages.

Closed forms:
- Kirsch (1898; Jaeger, Cook & Zimmerman, Fundamentals of Rock Mechanics, 8.4): a
  circular opening of radius a in intact elastic rock under hydrostatic in-situ stress
  p0 moves its wall in by u = (1 + nu) a p0 / E in plane strain once its load is
  released. The convergence-confinement method (Panet 1995; Carranza-Torres &
  Fairhurst 2000, "Application of the convergence-confinement method of tunnel design
  to rock masses", Tunnelling and Underground Space Technology 15(2)) writes a partial
  release as a fictitious pressure (1 - lambda) p0 left on the wall: the elastic wall
  has then moved lambda u. Released 40% then 60% (over two load steps): 0.4 u, 0.7 u, u.
- A bolt is installed unstressed at its length of the moment: one installed after the
  first stage carries k times the change of its anchors' distance over the second
  stage only. Its anchors are the centroids of the cells that hold them, points that
  each cell's own strain does not move (the solver's bolt anchors follow a cell's
  rigid motion but not yet its strain).

The rock is a quarter of the Kirsch benchmark's (benchmarks/bench_kirsch.py) by symmetry:
rollers on the axes x = 0 and y = 0 and at 16 a, the quarter opening an inscribed
polygon of 12 segments, deformable cells of 0.5 a at the opening. The far rollers make
the answer a little smaller than u (about 1% at 16 a, tests/verification/
test_deformable_cells.py), the mesh a little either way.
"""

import functools
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scenes import jointed_tunnel

import jaxdem
from jaxdem import batch, geometry, solver
from jaxdem.cli import main
from jaxdem.core import model as model_mod
from jaxdem.differentiable import Problem
from jaxdem.results import bolt_anchors, scene_bolts
from jaxdem.scene import SceneError, parse_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_kirsch import NU, A, E, P  # noqa: E402  (the benchmark's rock and opening)
from bench_kirsch import scene as kirsch_scene  # noqa: E402

U = (1 + NU) * A * P / E  # m: the wall's displacement once all is released
K_BOLT = 1e6  # kN/m: a stiff bolt (it takes about 33 kN over the second stage)
NEAR_WALL = (1.07 * A * math.cos(math.radians(43.0)), 1.07 * A * math.sin(math.radians(43.0)))


def relaxed_opening(h: float = 0.5, release=(0.4, 0.6), bolt: bool = False) -> dict:
    """A quarter of the Kirsch scene, its opening released by ``release`` over the stages
    "relax" (1 load step) and "rest" (2 load steps); ``bolt``: a bolt from near the wall
    outwards, installed in "rest", between the centroids of two cells."""
    R = 16.0 * A  # noqa: N806
    d = kirsch_scene(h, half_width=R)
    d["domain"]["outline"] = [[0.0, 0.0], [R, 0.0], [R, R], [0.0, R]]
    arc = [[A * math.cos(t), A * math.sin(t)] for t in np.linspace(0.0, 0.5 * math.pi, 13)]
    d["excavations"] = [{"name": "hole", "shape": "polygon", "vertices": [[0.0, 0.0], *arc],
                         **({"release": list(release)} if release is not None else {})}]
    d["stages"] = [{"name": "relax"}, {"name": "rest", "load_steps": 2}]
    d["monitors"] = [{"name": "x", "point": [A, 0.0]}, {"name": "y", "point": [0.0, A]}]
    if bolt:
        head, end = _cell_centroids(h, (NEAR_WALL, tuple(3.0 * x for x in NEAR_WALL)))
        d["bolts"] = [{"from": head, "to": end, "stiffness": K_BOLT, "yield_force": 1e6,
                       "anchor_capacity": 1e6, "stage": "rest"}]
    return d


@functools.lru_cache
def _cell_centroids(h: float, points: tuple) -> list:
    """The centroids [x, y] (m) of the cells of ``relaxed_opening(h)`` holding ``points``."""
    layout = model_mod.build(parse_scene(relaxed_opening(h)))[2]
    return [next(geometry.centroid(v).tolist() for v in layout.polygons
                 if geometry.point_in_polygon(np.asarray(q), v)) for q in points]


# --------------------------------------------------------------------------- the closed forms


def test_opening_released_40_then_60_percent_moves_its_wall_0_4_then_1_u():
    r = jaxdem.solve(parse_scene(relaxed_opening()))
    assert r.converged and r.stable
    stages = r.to_dict()["stages"]
    assert [s["name"] for s in stages] == ["initial", "relax", "rest"]
    assert "released" not in stages[0]
    assert stages[1]["released"] == {"hole": [pytest.approx(0.4)]}
    assert stages[2]["released"] == {"hole": [pytest.approx(0.7), pytest.approx(1.0)]}
    # The wall points on the axes move radially (along the axis, by symmetry): the point
    # monitors' |u| per increment is the wall's radial displacement.
    for m in ("x", "y"):
        walls = stages[1]["monitors"][m] + stages[2]["monitors"][m]
        for got, fraction in zip(walls, (0.4, 0.7, 1.0), strict=True):
            assert got == pytest.approx(fraction * U, rel=0.05), (m, fraction)
        # Elastic: each increment moves the wall in proportion to what it released.
        assert walls[0] / walls[2] == pytest.approx(0.4, rel=1e-4)
    ux, uy = r.monitors["x"]["displacement"]
    assert -ux == pytest.approx(U, rel=0.05) and abs(uy) < 1e-3 * U


def _run_with_stage_ends(d: dict):
    """Solve through the host driver; returns (scene, layout, driver, {stage: bolt anchors
    (2, 2) m at its end})."""
    scene = parse_scene(d)
    model, state, layout = model_mod.build(scene)
    ends = {}

    def stage_end(drv, name):
        if model.n_bolts:
            ends[name] = bolt_anchors(drv.model, drv.state, layout)[0]

    drv = solver.run(scene, model, state, layout, solver.scene_data(scene, layout),
                     stage_end=stage_end)
    return scene, layout, drv, ends


def test_bolt_installed_after_the_first_stage_carries_only_the_second_stage():
    scene, layout, drv, ends = _run_with_stage_ends(relaxed_opening(bolt=True))
    assert drv.status == solver.Status.CONVERGED
    bolt = scene_bolts(scene, layout, drv.state)[0]
    assert bolt["state"] == "elastic"
    length = {name: float(np.linalg.norm(p[1] - p[0])) for name, p in ends.items()}
    installed = float(np.linalg.norm(np.subtract(scene.bolts[0].end, scene.bolts[0].start)))
    stretch = length["rest"] - length["relax"]
    assert bolt["force"] == pytest.approx(K_BOLT * stretch, rel=1e-6)
    # Its anchors moved apart in the first stage too (0.4 of the release), before it was
    # there: a force from its installed length would be far larger.
    first = length["relax"] - installed
    assert first > 0.3 * stretch and bolt["force"] > 0.0
    assert K_BOLT * (length["rest"] - installed) > 1.2 * bolt["force"]


def test_excavations_of_one_stage_released_on_their_own_schedules():
    # The opening in two halves, one excavation each, released on the same schedule (one
    # group of blocks) or on two schedules that differ by 1e-10 (each half's release
    # taken apart, without what each half pushed on the other): the same answer.
    def halves(second):
        d = relaxed_opening(h=1.0)
        v = d["excavations"][0]["vertices"]
        d["excavations"] = [
            {"name": "a", "shape": "polygon", "vertices": v[:8], "release": [0.4, 0.6]},
            {"name": "b", "shape": "polygon", "vertices": [v[0], *v[7:]], "release": second}]
        return jaxdem.solve(parse_scene(d))

    one, two = halves([0.4, 0.6]), halves([0.4 + 1e-10, 0.6 - 1e-10])
    assert one.converged and two.converged
    assert two.to_dict()["stages"][1]["released"] == {"a": [0.4], "b": [pytest.approx(0.4)]}
    for m in ("x", "y"):
        a, b = (np.asarray(r.monitors[m]["displacement"]) for r in (one, two))
        np.testing.assert_allclose(b, a, rtol=1e-7, atol=1e-7 * np.abs(a).max())
    assert one.monitors["x"]["displacement"][0] == pytest.approx(-U, rel=0.1)


# --------------------------------------------------------------------------- a jointed tunnel


def relaxed_tunnel(release=(0.4, 0.6)) -> dict:
    """The small jointed tunnel of tests/scenes.py (rigid blocks, two joint sets, gravity
    in-situ stress, water), released by ``release`` over "relax" and "rest"; its support
    pressure and roof bolt go in at "rest"."""
    d = jointed_tunnel(top="roller")
    d["stages"] = [{"name": "relax"}, {"name": "rest"}]
    if release is not None:
        d["excavations"][0]["release"] = list(release)
    d["supports"][0]["stage"] = d["bolts"][0]["stage"] = "rest"
    return d


def test_release_in_one_stage_is_the_default_and_records_nothing_new():
    a, b = (jaxdem.solve(parse_scene(relaxed_tunnel(release))).to_dict()
            for release in (None, [1.0]))
    for out in (a, b):
        out.pop("timing")
    assert a == b
    assert all("released" not in s for s in a["stages"])


def test_a_batch_relaxes_as_single_solves_do():
    scene = parse_scene(relaxed_tunnel())
    k0 = [0.8, 0.6]
    res = batch.solve_batch(scene, ["in_situ.k0"], np.array([[k] for k in k0]))
    assert res.converged.all()
    for i, k in enumerate(k0):
        single = jaxdem.solve(scene, set={"in_situ.k0": k})
        np.testing.assert_allclose(res.monitors["crown"][i],
                                   single.monitors["crown"]["displacement"], rtol=1e-6)
        assert res.monitors["span"][i] == pytest.approx(single.monitors["span"]["convergence"],
                                                        rel=1e-6)
    # The support and the bolt go in after 40%, and take part of the other 60%: the span
    # closes less than when all is released before them (in one stage).
    at_once = jaxdem.solve(parse_scene(relaxed_tunnel(None)))
    assert res.monitors["span"][0] < 0.98 * at_once.monitors["span"]["convergence"]


def test_derivatives_through_a_relaxed_stage_match_central_differences():
    # k0 and surface_y change the released forces themselves, and so their derivatives,
    # which the stages carry along; kn changes the rock's response to them.
    scene = parse_scene(relaxed_tunnel())
    params = ["in_situ.k0", "in_situ.surface_y", "joints.set1.kn"]
    problem = Problem(scene, params, stages=["relax", "rest"])
    theta = problem.theta0
    _, J = problem.evaluate(theta, jacobian=True)
    assert not problem.last["approximate"]
    for i in range(len(params)):
        e = np.zeros_like(theta)
        e[i] = 1e-4 * abs(theta[i])
        fd = (problem.evaluate(theta + e)[0] - problem.evaluate(theta - e)[0]) / (2 * e[i])
        assert np.max(np.abs(J[:, i] - fd)) <= 1e-5 * np.max(np.abs(fd)), params[i]


# --------------------------------------------------------------------------- bad input

BAD_RELEASES = [
    # (id, edit of the scene dict, path, start of the problem)
    ("not summing to 1", lambda d: d["excavations"][0].update(release=[0.4, 0.5]),
     "excavations.0.release", "the fractions must sum to 1"),
    ("a zero fraction", lambda d: d["excavations"][0].update(release=[0.0, 1.0]),
     "excavations.0.release.0", "must be in (0, 1]"),
    ("a negative fraction", lambda d: d["excavations"][0].update(release=[1.2, -0.2]),
     "excavations.0.release.0", "must be in (0, 1]"),
    ("more fractions than stages", lambda d: d["excavations"][0].update(
        release=[0.4, 0.3, 0.3]), "excavations.0.release", "3 fractions need 3 stages"),
    ("from the last stage", lambda d: d["excavations"][0].update(stage="rest"),
     "excavations.0.release", "2 fractions need 2 stages from its stage 2 'rest' on"),
    ("without stages", lambda d: d.pop("stages"), "excavations.0.release",
     "2 fractions need 2 stages, but the scene has no [[stages]]"),
    ("a number", lambda d: d["excavations"][0].update(release=0.4), "excavations.0.release",
     "must be a list"),
    ("empty", lambda d: d["excavations"][0].update(release=[]), "excavations.0.release",
     "must be a list"),
    ("a string in it", lambda d: d["excavations"][0].update(release=["0.4", 0.6]),
     "excavations.0.release.0", "must be a number"),
]


@pytest.mark.parametrize(("edit", "path", "problem"),
                         [pytest.param(e, p, m, id=i) for i, e, p, m in BAD_RELEASES])
def test_bad_release_is_refused_naming_the_field(edit, path, problem):
    d = relaxed_opening()
    edit(d)
    with pytest.raises(SceneError) as info:
        parse_scene(d)
    assert info.value.path == path and info.value.problem.startswith(problem), str(info.value)


CLI_SCENE = """
[scene]
name = "relaxed opening"

[materials.rock]
E = 1e7
nu = 0.25
unit_weight = 0.0

[domain]
outline = [[-8.0, -8.0], [8.0, -8.0], [8.0, 8.0], [-8.0, 8.0]]
material = "rock"
mesh_size = 2.0

[[excavations]]
name = "hole"
shape = "circle"
center = [0.0, 0.0]
radius = 1.0
release = {release}

[in_situ]
mode = "uniform"
sigma_xx = 1000.0
sigma_yy = 1000.0

[[stages]]
name = "relax"

[[stages]]
name = "rest"
"""


@pytest.mark.parametrize(("release", "message"), [
    ("[0.4, 0.5]", "excavations.0.release: the fractions must sum to 1"),
    ("[0.0, 1.0]", "excavations.0.release.0: must be in (0, 1]"),
    ("[0.2, 0.2, 0.6]", "excavations.0.release: 3 fractions need 3 stages"),
])
def test_cli_refuses_a_bad_release_with_exit_2(tmp_path, capsys, release, message):
    path = tmp_path / "bad.toml"
    path.write_text(CLI_SCENE.format(release=release))
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: " + message) and len(err.splitlines()) == 1, err
    assert not out.exists()
