"""Sweeps (jaxdem.sweep, ``jaxdem sweep``): sampling, the probability of instability
against a closed form, the tornado, the CSV, reproducibility and refusals."""

import csv
import importlib
import math
from pathlib import Path

import numpy as np
import pytest
from scenes import block_on_incline
from scipy.special import ndtr

import jaxdem
from jaxdem.batch import solve_batch
from jaxdem.cli import main
from jaxdem.scene import SceneError, parse_scene
from jaxdem.sweep import (
    Variable,
    distinct_rows,
    draw,
    probability_of_instability,
    sweep,
    tornado_solves,
)

ALPHA = 30.0
EXAMPLE = str(Path(__file__).resolve().parents[1] / "examples" / "block_on_incline.toml")


@pytest.fixture(scope="module")
def incline():
    return parse_scene(block_on_incline(ALPHA, 35.0))


@pytest.fixture(scope="module")
def friction_sweep(incline):
    return sweep(incline, ["joints.base.friction_deg=normal:33:3"], 120, method="lhs", seed=4)


def test_stability_of_each_sample_is_limit_equilibrium(friction_sweep):
    """A block on a 30 degree incline slides exactly when tan(phi) < tan(30 deg)."""
    phi = friction_sweep.batch.theta[:, 0]
    far = np.abs(phi - ALPHA) > 0.1
    np.testing.assert_array_equal(friction_sweep.batch.stable[far], phi[far] > ALPHA)
    assert friction_sweep.mode == "batched"


def test_probability_of_instability_contains_closed_form(friction_sweep):
    """phi ~ N(33, 3): P(slide) = P(phi < 30) = Phi(-1) = 0.1587, inside the 95% interval."""
    pr = friction_sweep.probability
    assert pr["decided"] == 120 and pr["undecided"] == 0
    lo, hi = pr["ci95"]
    assert lo < ndtr(-1.0) < hi
    assert pr["p_unstable"] == pytest.approx(pr["unstable"] / 120)


def test_tornado_is_one_at_a_time(incline):
    """The tornado's ends are single solves with one parameter at its low or high point:
    a stiffer joint (kn) settles less, and the swing is their difference."""
    res = sweep(incline, {"joints.base.kn": "5e5:2e6:log", "joints.base.ks": "2e5:8e5"}, 2)
    bars = {b["path"]: b for b in res.tornado["block"]}
    kn = bars["joints.base.kn"]
    assert (kn["low"], kn["high"]) == pytest.approx((5e5, 2e6))
    assert kn["base"] == pytest.approx(math.sqrt(5e5 * 2e6))
    single = jaxdem.solve(incline, set={"joints.base.kn": 2e6, "joints.base.ks": 5e5})
    assert kn["at_high"] == pytest.approx(np.linalg.norm(single.monitors["block"]["displacement"]),
                                          rel=1e-9)
    assert kn["at_low"] > kn["at_high"]
    assert kn["swing"] == pytest.approx(kn["at_high"] - kn["at_low"])
    assert kn["quantity"] == "|u|"  # a point monitor: the tornado's axis says so
    assert res.method == "grid" and res.batch.theta.shape == (4, 2)


def test_distinct_rows_keep_their_first_order_and_map_every_row():
    theta = np.array([[2.0, 1.0], [1.0, 1.0], [2.0, 1.0], [3.0, 0.5], [1.0, 1.0]])
    rows, where = distinct_rows(theta)
    np.testing.assert_array_equal(rows, [[2.0, 1.0], [1.0, 1.0], [3.0, 0.5]])
    np.testing.assert_array_equal(where, [0, 1, 0, 2, 1])
    np.testing.assert_array_equal(rows[where], theta)


def test_tornado_points_that_are_samples_are_solved_once(incline, monkeypatch):
    """A grid of 3 levels holds a range's ends and middle, the tornado's three points: the
    sweep solves 3 points, not 6, and the tornado reads the samples' own solves (its high
    end is a single solve at the high point, as in the test above)."""
    solved = []

    def spy(scene, params, theta, **kwargs):
        solved.append(np.array(theta))
        return solve_batch(scene, params, theta, **kwargs)

    sweep_module = importlib.import_module("jaxdem.sweep")  # jaxdem.sweep is also the function
    monkeypatch.setattr(sweep_module, "solve_batch", spy)
    variables = [Variable.parse("joints.base.kn=5e5:2e6")]
    assert tornado_solves(variables, draw(variables, 3, "grid")) == 0
    assert tornado_solves(variables, draw(variables, 4, "grid")) == 1  # the middle is new
    res = sweep(incline, ["joints.base.kn=5e5:2e6"], 3)
    assert len(solved) == 1
    np.testing.assert_array_equal(solved[0][:, 0], [5e5, 1.25e6, 2e6])
    u = np.linalg.norm(res.batch.monitors["block"], axis=1)
    bar = res.tornado["block"][0]
    assert (bar["at_low"], bar["at_base"], bar["at_high"]) == (u[0], u[1], u[2])
    single = jaxdem.solve(incline, set={"joints.base.kn": 2e6})
    assert bar["at_high"] == pytest.approx(
        np.linalg.norm(single.monitors["block"]["displacement"]), rel=1e-9)
    assert bar["at_low"] > bar["at_high"]  # a stiffer joint settles less
    assert res.batch.theta.shape == (3, 1) and len(res.batch.status) == 3


def test_reproducible_from_seed_and_same_table_as_cli(incline, tmp_path, friction_sweep):
    again = sweep(incline, ["joints.base.friction_deg=normal:33:3"], 120, method="lhs", seed=4)
    np.testing.assert_array_equal(again.batch.theta, friction_sweep.batch.theta)
    other = draw([Variable.parse("joints.base.friction_deg=normal:33:3")], 120, "lhs", seed=5)
    assert not np.array_equal(other, friction_sweep.batch.theta)
    out = tmp_path / "out"
    status = main(["sweep", EXAMPLE, "--vary",
                   "joints.base.friction_deg=normal:33:3", "--samples", "16", "--seed", "2",
                   "--out", str(out)])
    assert status == 0
    with (out / "sweep.csv").open() as f:
        rows = list(csv.DictReader(f))
    py = sweep(jaxdem.load_scene(EXAMPLE),
               ["joints.base.friction_deg=normal:33:3"], 16, seed=2)
    assert len(rows) == 16 and list(rows[0]) == py.columns()
    for row, ref in zip(rows, py.rows(), strict=True):
        assert float(row["joints.base.friction_deg"]) == ref["joints.base.friction_deg"]
        assert row["status"] == ref["status"]
        if ref["converged"]:
            assert float(row["block.uy"]) == pytest.approx(ref["block.uy"], rel=1e-12)
    assert (out / "tornado.png").stat().st_size > 0
    assert (out / "sweep.json").exists()


def test_geometry_parameters_fall_back_to_single_solves(incline):
    """A parameter that changes the model's shape (load steps here) cannot share a batch:
    the sweep solves its samples one by one and gives the same table."""
    res = sweep(incline, ["solver.load_steps=1:2"], 2, tornado=False)
    assert res.mode == "loop"
    assert res.batch.converged.all() and list(res.batch.theta[:, 0]) == [1.0, 2.0]


def test_the_table_says_where_each_sample_without_an_answer_stopped():
    """Friction 25 degrees on the 30 degree incline slides at any share of the weight: in
    single solves (load steps vary, mode "loop") the sample with one load step stops at
    load factor 1, the one with two at 1/2, both in the loading stage, as in the batched
    sweeps (tests/test_batch.py); the CSV has it in its columns stopped_stage and
    stopped_load_factor, then the mechanism's volume (the 1 m x 1 m block: 1.0 m3/m) and
    whether it is small (no: a scene without joint sets has no default
    max_loose_volume)."""
    scene = parse_scene(block_on_incline(ALPHA, 25.0))
    res = sweep(scene, ["solver.load_steps=1:2"], 2, tornado=False)
    assert res.mode == "loop" and res.batch.status == ["mechanism", "mechanism"]
    rows = res.rows()
    assert [(r["stopped_stage"], r["stopped_load_factor"]) for r in rows] == [
        ("loading", 1.0), ("loading", 0.5)]
    assert res.columns()[-5:] == ["stopped_stage", "stopped_load_factor", "moving_volume",
                                  "small_mechanism", "loose_blocks"]
    assert res.batch.moving_volume == pytest.approx([1.0, 1.0], rel=1e-12)
    assert res.to_csv().splitlines()[2].endswith(",mechanism,loading,0.5,1.0,False,0")


def test_sampling_methods():
    v = [Variable.parse("a.b=0:1"), Variable.parse("c.d=10:1000:log")]
    grid = draw(v, 3, "grid")
    assert grid.shape == (9, 2)
    assert sorted(set(grid[:, 1])) == pytest.approx([10.0, 100.0, 1000.0])
    lhs = draw(v, 50, "lhs", seed=1)
    # One sample in each of the 50 equal-probability strata of every variable.
    assert sorted(np.floor(lhs[:, 0] * 50).astype(int)) == list(range(50))
    u = (np.log(lhs[:, 1]) - np.log(10)) / (np.log(1000) - np.log(10))
    assert sorted(np.floor(u * 50).astype(int)) == list(range(50))
    mc = draw([Variable.parse("x.y=lognormal:2e6:5e5"), Variable.parse("x.z=normal:30:2"),
               Variable.parse("x.w=truncnormal:30:5:25:32")], 100_000, "mc", seed=0)
    assert mc[:, 0].mean() == pytest.approx(2e6, rel=0.01)
    assert mc[:, 0].std() == pytest.approx(5e5, rel=0.02)
    assert mc[:, 1].mean() == pytest.approx(30, abs=0.03)
    assert mc[:, 1].std() == pytest.approx(2, rel=0.02)
    assert mc[:, 2].min() >= 25 and mc[:, 2].max() <= 32


def test_wilson_interval():
    """Wilson score interval at 95%: 0 of 10 gives [0, 0.2775]; 5 of 10 gives
    [0.2366, 0.7634] (Newcombe 1998, table I)."""
    class B:
        def __init__(self, stable):
            self.stable = np.array(stable)
            self.converged = self.stable.copy()

    lo, hi = probability_of_instability(B([True] * 10))["ci95"]
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = probability_of_instability(B([True] * 5 + [False] * 5))["ci95"]
    assert (lo, hi) == pytest.approx((0.2366, 0.7634), abs=1e-4)


@pytest.mark.parametrize("spec, match", [
    ("joints.base.kn", "PATH=LOW:HIGH"),
    ("joints.base.kn=2e6:1e6", "LOW must be below HIGH"),
    ("joints.base.kn=-1:1e6:log", "LOW > 0"),
    ("joints.base.kn=normal:1e6", "normal takes 2 numbers"),
    ("joints.base.kn=normal:1e6:0", "standard deviation"),
    ("joints.base.kn=lognormal:-1:3", "mean > 0"),
    ("joints.base.kn=1e6:abc", "not a number"),
    ("joints.base.kn=nan:1e6", "NaN"),
])
def test_bad_vary_is_refused(spec, match):
    with pytest.raises(SceneError, match=match) as err:
        Variable.parse(spec)
    assert "--vary" in str(err.value)


def test_draws_the_scene_refuses_are_refused_before_solving(incline, capsys):
    """A normal kn wide enough to draw a negative stiffness is refused, naming the path."""
    with pytest.raises(SceneError, match="joints.base.kn.*refuses"):
        sweep(incline, ["joints.base.kn=normal:1e6:1e6"], 200, seed=0)
    status = main(["sweep", EXAMPLE, "--vary",
                   "joints.base.kn=normal:1e6:1e6", "--samples", "200"])
    assert status == 2
    assert "joints.base.kn" in capsys.readouterr().err
    assert main(["sweep", EXAMPLE, "--vary", "joints.nope.kn=1:2",
                 "--samples", "2"]) == 2
