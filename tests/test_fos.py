"""Factor of safety by strength reduction (jaxdem.fos, ``jaxdem fos``).

Closed forms: a block on an incline (limit friction, and cohesion with the
per-point Mohr-Coulomb law of the SPEC) and Bray's symmetric roof prism
(Brady & Brown, Rock Mechanics for Underground Mining, section 9.3). The
bracketing logic is tested apart, on a stand-in for the batched solve.
"""

import json
import math
import types

import numpy as np
import pytest
from scenes import block_on_incline
from test_differentiable import roof_prism

import jaxdem
import jaxdem.batch
from jaxdem import fos as fos_mod
from jaxdem.cli import main
from jaxdem.scene import SceneError, parse_scene


def _assert_bracketed(r, closed, rel=0.01):
    lo, hi = r.bracket
    assert r.status == "converged" and r.decided
    assert r.factor_of_safety == pytest.approx(closed, rel=rel)
    assert lo <= closed <= hi, (r.bracket, closed)
    assert (hi - lo) / lo <= r.options["rtol"]


# ---------------------------------------------------------------------------
# Verification against closed forms


def test_block_on_incline_friction_gives_tan_phi_over_tan_alpha():
    """Limit friction on a plane (Goodman, Introduction to Rock Mechanics, 8.2):
    F = tan(phi) / tan(alpha); 35 deg on 25 deg: 1.5016. From the bracket (0.25, 8)
    with 8 trials, rtol 0.5% costs 4 batched solves."""
    r = jaxdem.factor_of_safety(parse_scene(block_on_incline(25.0, 35.0)), trials=8,
                                rtol=0.005, bracket=(0.25, 8.0))
    closed = math.tan(math.radians(35.0)) / math.tan(math.radians(25.0))
    _assert_bracketed(r, closed)
    assert len(r.rounds) <= 4 and r.solves == 8 * len(r.rounds)
    assert r.at_factor_1 == "converged"             # the scene as given is stable
    assert r.rounds[0]["factors"].count(1.0) == 1
    assert r.reduced == {"joints.base.friction_deg": 35.0}


def test_block_on_incline_with_cohesion_fails_progressively_per_contact_point():
    """Cohesion c on the base (length L) of a w x h block, weight W, slope alpha.

    The rigid-block limit, (c L + W cos(a) tan(phi)) / (W sin(a)) = Fg, assumes one
    uniform contact. The SPEC's law is per contact point (two points, each with half
    of c L) and a point that slips loses its cohesion. The shear is shared equally,
    but the moment of the down-slope weight about the base shifts the normal force
    downhill: the uphill point carries Fn_up = (W / 2)(cos a - sin a h / L). So the
    uphill point fails first, at F1 = (c L + 2 Fn_up tan(phi)) / (W sin a)
    = Fg - (h / L) tan(phi), and then the block slides unless the downhill point
    alone (c L / 2 left) holds: F2 = (c L / 2 + W cos(a) tan(phi)) / (W sin a).
    F = max(F1, F2). 2 m x 0.5 m block, alpha 25, phi 20, c 3.8 kPa: F1 = 1.4089
    (F2 = 1.140), while Fg = 1.4999 is 6% higher."""
    w, h, c, alpha, phi = 2.0, 0.5, 3.8, 25.0, 20.0
    r = jaxdem.factor_of_safety(parse_scene(block_on_incline(alpha, phi, cohesion=c, width=w,
                                                             height=h)))
    a, tp = math.radians(alpha), math.tan(math.radians(phi))
    W, L = 25.0 * w * h, w                          # unit weight 25 kN/m3, per metre
    T = W * math.sin(a)
    Fg = (c * L + W * math.cos(a) * tp) / T
    F1 = Fg - h / L * tp
    F2 = (c * L / 2 + W * math.cos(a) * tp) / T
    _assert_bracketed(r, max(F1, F2))
    assert r.bracket[1] < Fg / 1.05                 # not the uniform-contact answer
    assert set(r.reduced) == {"joints.base.friction_deg", "joints.base.cohesion"}


def _prism_factor(alpha_deg, height, kn, ks, sigma_xx, phi_deg, unit_weight=25.0):
    """Factor of safety of Bray's roof prism with elastic joints (see the test)."""
    a = math.radians(alpha_deg)
    L = height / math.cos(a)
    W = unit_weight * height**2 * math.tan(a)
    H0 = sigma_xx * height
    Kn, Ks = kn * L, ks * L
    K2 = Ks * math.cos(a) ** 2 + Kn * math.sin(a) ** 2
    t = ((W * Ks * math.cos(a) + 2 * H0 * K2 * math.sin(a))
         / (2 * H0 * K2 * math.cos(a) - W * Kn * math.sin(a)))
    return math.tan(math.radians(phi_deg)) / t, W, H0


@pytest.mark.parametrize("kn, ks", [(1e6, 1e6), (1e6, 4e5)], ids=["kn=ks", "kn=2.5ks"])
def test_roof_prism_factor_where_limit_load_equals_weight(kn, ks):
    """Brady & Brown section 9.3 (after Bray): a symmetric roof prism of semi-apical
    angle alpha, clamped by the horizontal force H on each face, carries at most
    P_lim = 2 H tan(phi - alpha) before it slips out. With tan(phi_F) = tan(phi) / F,
    F is where P_lim = W: F = tan(phi) / tan(alpha + atan(W / (2 H))).

    H: the in-situ sigma_xx puts H0 = sigma_xx h on each face (normal H0 cos a,
    shear H0 sin a). As the weight is applied the prism sags d elastically: the
    face opens by d sin a and shears by d cos a, so N = H0 cos a - Kn d sin a,
    S = H0 sin a + Ks d cos a and H = H0 + (Ks - Kn) d sin a cos a (Kn = kn L,
    Ks = ks L per face of length L). With Kn = Ks, H = H0 and F is Bray's formula
    with H0 exactly. Otherwise slip starts (S = N tan phi_F, both faces at once by
    symmetry; beyond it the load carried falls) at the sag whose vertical load
    2 d (Ks cos^2 a + Kn sin^2 a) (the sag formula of the same section) is W:
    tan phi_F = (W Ks cos a + 2 H0 K2 sin a) / (2 H0 K2 cos a - W Kn sin a),
    K2 = Ks cos^2 a + Kn sin^2 a: Bray's formula with H at slip. alpha 15 deg,
    h 2 m, phi 40 deg, sigma_xx 50 kPa: F = 2.0128 (kn = ks) and 1.9776 (kn =
    2.5 ks, where H0 in Bray's formula would give 2.0128, 1.8% too high)."""
    alpha, height, sigma_xx, phi = 15.0, 2.0, 50.0, 40.0
    d = roof_prism(alpha, height, kn, ks, sigma_xx)
    d["joints"]["j"].update(friction_deg=phi, cohesion=0.0)
    r = jaxdem.factor_of_safety(parse_scene(d))
    closed, W, H0 = _prism_factor(alpha, height, kn, ks, sigma_xx, phi)
    if kn == ks:
        bray = math.tan(math.radians(phi)) / math.tan(math.radians(alpha) + math.atan(W / (2 * H0)))
        assert closed == pytest.approx(bray, rel=1e-12)
    assert 1.5 < closed < 3.0
    _assert_bracketed(r, closed)
    assert len(r.rounds) <= 4
    # With the weight applied the prism is stable as given, and the trials far
    # beyond failure (iteration limit) do not set the bracket.
    assert r.at_factor_1 == "converged"
    assert all(f > r.bracket[1] for f in r.undecided)


# ---------------------------------------------------------------------------
# Strength reduction


def test_strength_overrides_divide_tan_phi_and_cohesion():
    d = block_on_incline(25.0, 35.0, cohesion=10.0)
    d["joints"]["base"]["tensile_strength"] = 4.0
    d["materials"]["rock"].update(friction_deg=50.0, cohesion=1000.0, tensile_strength=300.0)
    scene = parse_scene(d)
    s = fos_mod.strength_overrides(scene, 2.0)
    assert set(s) == {"joints.base.friction_deg", "joints.base.cohesion"}
    assert math.tan(math.radians(s["joints.base.friction_deg"])) == pytest.approx(
        math.tan(math.radians(35.0)) / 2.0, rel=1e-12)
    assert s["joints.base.cohesion"] == pytest.approx(5.0)
    s = fos_mod.strength_overrides(scene, 2.0, intact=True, tensile=True)
    assert s["materials.rock.cohesion"] == pytest.approx(500.0)
    assert s["materials.rock.tensile_strength"] == pytest.approx(150.0)
    assert s["joints.base.tensile_strength"] == pytest.approx(2.0)
    assert math.tan(math.radians(s["materials.rock.friction_deg"])) == pytest.approx(
        math.tan(math.radians(50.0)) / 2.0, rel=1e-12)
    assert fos_mod.strength_overrides(scene, 1.0)["joints.base.friction_deg"] == pytest.approx(35)


def test_nothing_to_reduce_and_bad_options_are_scene_errors():
    scene = parse_scene(block_on_incline(25.0, 0.0))
    with pytest.raises(SceneError, match="joints: no strength to reduce"):
        jaxdem.factor_of_safety(scene)
    scene = parse_scene(block_on_incline(25.0, 35.0))
    for kwargs, field in [(dict(trials=1), "trials"), (dict(rtol=0.0), "tolerance"),
                          (dict(bracket=(2.0, 1.0)), "bracket"),
                          (dict(bracket=(0.001, 8.0)), "bracket"),
                          (dict(max_rounds=0), "max_rounds")]:
        with pytest.raises(SceneError, match=f"^{field}: "):
            jaxdem.factor_of_safety(scene, **kwargs)


# ---------------------------------------------------------------------------
# Bracketing, on a stand-in for the batched solve: outcome(F) -> status label


@pytest.fixture
def fake_batch(monkeypatch):
    """Replace solve_batch by outcome(F) (F read back from the reduced friction angle);
    returns the list of batch sizes it was called with."""
    calls = []

    def install(outcome):
        def solve_batch(scene, params, theta, **_):
            assert params == ["joints.base.friction_deg"]
            phi = scene.joints["base"].friction_deg
            F = math.tan(math.radians(phi)) / np.tan(np.radians(theta[:, 0]))
            calls.append(len(F))
            return types.SimpleNamespace(status=[outcome(f) for f in F],
                                         timing=dict(build_s=0.0, compile_s=0.0, solve_s=0.0))

        monkeypatch.setattr(jaxdem.batch, "solve_batch", solve_batch)
        return calls

    return install


def _run(outcome, fake_batch, **kwargs):
    calls = fake_batch(outcome)
    r = jaxdem.factor_of_safety(parse_scene(block_on_incline(25.0, 35.0)), **kwargs)
    assert set(calls) == {r.options["trials"]}      # one batch shape: one compilation
    return r


def _threshold(F_star):
    return lambda f: "converged" if f <= F_star else "mechanism"


@pytest.mark.parametrize("F_star", [0.3, 0.93, 1.0, 2.7182818, 7.9])
def test_four_rounds_of_eight_reach_half_a_percent_from_a_ratio_32(F_star, fake_batch):
    r = _run(_threshold(F_star), fake_batch)
    lo, hi = r.bracket
    assert lo <= F_star < hi and (hi - lo) / lo <= 0.005
    assert len(r.rounds) <= 4 and r.status == "converged" and r.decided
    assert not r.undecided and not r.non_monotone


def test_bracket_grows_up_and_down_within_limits(fake_batch):
    r = _run(_threshold(40.0), fake_batch)
    assert r.status == "converged" and r.bracket[0] <= 40.0 < r.bracket[1]
    r = _run(_threshold(0.05), fake_batch)
    assert r.status == "converged" and r.bracket[0] <= 0.05 < r.bracket[1]
    assert r.at_factor_1 == "mechanism" and "(F = 1) is not stable" in r.message
    r = _run(_threshold(500.0), fake_batch)
    assert r.status == "above_limit" and r.bracket == [100.0, None]
    assert "F > 100" in r.message
    r = _run(_threshold(0.001), fake_batch)
    assert r.status == "below_limit" and r.factor_of_safety is None
    assert r.bracket == [None, pytest.approx(0.01)] and "F < 0.01" in r.message
    json.dumps(r.to_dict(), allow_nan=False)


def test_undecided_trials_count_as_unstable_and_are_reported(fake_batch):
    """Iteration limits between F = 1.5 and 1.6, mechanisms above: the bracket stops at
    the first iteration limit, F's upper bound is not a proven mechanism."""
    def outcome(f):
        return "converged" if f <= 1.5 else "iteration_limit" if f <= 1.6 else "mechanism"

    r = _run(outcome, fake_batch)
    assert r.bracket[0] <= 1.5 < r.bracket[1] <= 1.6
    assert not r.decided and r.to_dict()["decided"] is False
    assert "WARNING" in r.message and "not a proven mechanism" in r.message
    # Beyond failure the same outcome is harmless and said to be.
    r = _run(lambda f: "converged" if f <= 1.5 else "mechanism" if f <= 4 else "non_finite",
             fake_batch)
    assert r.decided and r.undecided and "do not change F" in r.message
    assert "WARNING" not in r.message


def test_non_monotone_outcomes_are_reported(fake_batch):
    r = _run(lambda f: "converged" if f <= 1.2 or 2.5 < f < 3.5 else "mechanism", fake_batch)
    assert r.bracket[0] <= 1.2 < r.bracket[1]
    assert r.non_monotone and all(2.5 < f < 3.5 for f in r.non_monotone)
    assert "not monotone" in r.message


def test_round_limit_reports_the_bracket_it_has(fake_batch):
    r = _run(_threshold(2.0), fake_batch, max_rounds=2)
    assert r.status == "round_limit" and len(r.rounds) == 2
    assert r.bracket[0] <= 2.0 < r.bracket[1] and "wider than rtol" in r.message


# ---------------------------------------------------------------------------
# Command line


def test_cli_fos_writes_json_mechanism_and_trials(tmp_path, capsys):
    scene = tmp_path / "incline.toml"
    scene.write_text(_INCLINE_TOML)
    out = tmp_path / "out"
    assert main(["fos", str(scene), "--out", str(out), "--tolerance", "0.01"]) == 0
    data = json.loads((out / "fos.json").read_text())
    closed = math.tan(math.radians(30.0)) / math.tan(math.radians(25.0))
    assert data["bracket"][0] <= closed <= data["bracket"][1]
    assert data["factor_of_safety"] == pytest.approx(closed, rel=0.01)
    assert {"factor_of_safety", "bracket", "status", "message", "rounds", "solves",
            "mechanism", "decided"} <= set(data)
    assert data["mechanism"]["status"] == "mechanism" and data["mechanism"]["moving_blocks"]
    assert (out / "mechanism.png").stat().st_size > 0 and (out / "fos.png").is_file()
    captured = capsys.readouterr()
    assert "round 1:" in captured.err and "Factor of safety F =" in captured.out


def test_cli_fos_exits_3_when_the_bracket_ends_at_an_iteration_limit(tmp_path, capsys,
                                                                      fake_batch):
    """Trials stop at the iteration limit between F = 1.1 and 1.3 (stand-in batch): the
    bracket's unstable end is not a proven mechanism, so the command says so and exits 3,
    with fos.json and the figures written."""
    fake_batch(lambda f: "converged" if f <= 1.1 else "iteration_limit" if f <= 1.3
               else "mechanism")
    scene = tmp_path / "incline.toml"
    scene.write_text(_INCLINE_TOML)
    out = tmp_path / "out"
    assert main(["fos", str(scene), "--out", str(out)]) == 3
    data = json.loads((out / "fos.json").read_text())
    assert data["decided"] is False and 1.1 < data["bracket"][1] <= 1.3
    assert "not a proven mechanism" in capsys.readouterr().out
    assert (out / "mechanism.png").is_file()


def test_fos_json_says_when_the_single_solve_is_no_mechanism(tmp_path, fake_batch, monkeypatch):
    """The batch found a mechanism above F = 1.1 (stand-in), but the single solve drawn at
    the bracket's unstable end stops at the iteration limit (one Newton iteration a
    geometry update): fos.json says so, and does not call it an equilibrium."""
    fake_batch(lambda f: "converged" if f <= 1.1 else "mechanism")
    monkeypatch.setattr(fos_mod, "solve_at", lambda scene, factor, **_: jaxdem.solve(
        scene, set={"solver.max_iterations": 1}))
    scene = tmp_path / "incline.toml"
    scene.write_text(_INCLINE_TOML)
    out = tmp_path / "out"
    main(["fos", str(scene), "--out", str(out)])
    mechanism = json.loads((out / "fos.json").read_text())["mechanism"]
    assert mechanism["status"] == "iteration_limit"
    assert "ended as iteration_limit, not a mechanism" in mechanism["note"]
    assert "equilibrium" not in mechanism["note"]


def test_fos_json_says_when_the_mechanism_at_the_unstable_end_is_small(tmp_path, fake_batch):
    """The single solve drawn above F = tan 30 / tan 25 = 1.238 slides the 1 m2 block: a
    mechanism. With solver.max_loose_volume 2 m3/m it is small, and fos.json's mechanism
    says so (jaxdem.results.small_mechanism); with the default (0: explicit blocks, no
    joint sets) it says nothing."""
    fake_batch(lambda f: "converged" if f <= 1.25 else "mechanism")
    for extra, small in (("max_loose_volume = 2.0\n", True), ("", False)):
        scene = tmp_path / "incline.toml"
        scene.write_text(_INCLINE_TOML.replace("load_steps = 1\n", "load_steps = 1\n" + extra))
        out = tmp_path / f"out{int(small)}"
        main(["fos", str(scene), "--out", str(out)])
        mechanism = json.loads((out / "fos.json").read_text())["mechanism"]
        assert mechanism["status"] == "mechanism" and mechanism["moving_blocks"] == [1]
        if small:
            assert mechanism["note"].startswith("unstable, but the mechanism is small: "
                                                "blocks 1, 1 m3/m in all")
        else:
            assert "note" not in mechanism


@pytest.mark.parametrize("argv, field", [
    (["--trials", "1"], "--trials"),
    (["--tolerance", "0"], "--tolerance"),
    (["--set", "joints.base.nope=3"], "--set joints.base.nope"),
])
def test_cli_fos_bad_option_exits_2(tmp_path, capsys, argv, field):
    scene = tmp_path / "incline.toml"
    scene.write_text(_INCLINE_TOML)
    assert main(["fos", str(scene), "--out", str(tmp_path / "out")] + argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {field}") and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_cli_fos_bad_scene_exits_2(tmp_path, capsys):
    scene = tmp_path / "bad.toml"
    scene.write_text(_INCLINE_TOML.replace("friction_deg = 30.0", "friction_deg = -5.0"))
    assert main(["fos", str(scene), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "joints.base.friction_deg" in err
    assert "Traceback" not in err


_INCLINE_TOML = """
[scene]
name = "incline 25/30"

[solver]
load_steps = 1

[materials.rock]
E = 1.0e7
nu = 0.25
unit_weight = 25.0

[joints.base]
kn = 1.0e6
ks = 5.0e5
friction_deg = 30.0

[[blocks]]
vertices = [[-1.0, -2.466307658], [12.0, -2.466307658], [12.0, 5.595691898],
            [-1.0, -0.466307658]]
material = "rock"
fixed = true

[[blocks]]
vertices = [[3.625231148, 1.690473047], [4.531538935, 2.113091309],
            [4.108920673, 3.019399096], [3.202612886, 2.596780834]]
material = "rock"
"""
