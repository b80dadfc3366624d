"""Plausibility warnings: values that are valid but most likely in the wrong unit (E in
GPa or MPa where the file wants kPa, a friction angle in radians, a joint stiffness in
MPa/m or Pa/m) are warned about, not refused: on stderr by the command line, in
``Scene.warnings`` and in result.json's ``warnings``, each naming the field. The bundled
examples give none."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from test_cli import SCENE

import jaxdem
from jaxdem.cli import main
from jaxdem.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = sorted(ROOT.glob("examples/*.toml")) + [ROOT / "jaxdem" / "data" / "demo.toml"]


def _scene(**replace: str):
    text = SCENE.format(E=replace.pop("E", "1e7"))
    for line, new in replace.items():
        assert line in text
        text = text.replace(line, new)
    return load_scene(text)


def test_a_plausible_scene_has_no_warning():
    assert _scene().warnings == ()


@pytest.mark.parametrize("E, words", [
    ("20", "below 10000 kPa (10 MPa), softer than any rock; E is in kPa: was it written in "
           "GPa or MPa?"),
    ("2e4", None),       # 20 MPa: a soft rock, plausible
    ("2e10", "above 1e+09 kPa (1,000 GPa), stiffer than any rock; E is in kPa: was it "
             "written in Pa?"),
])
def test_young_modulus_in_the_wrong_unit(E, words):
    warnings = _scene(E=E).warnings
    if words is None:
        assert warnings == ()
    else:
        assert warnings == (f"materials.rock.E: {float(E):g} kPa is {words} "
                            "(20 GPa is E = 2e7)",)


@pytest.mark.parametrize("phi, warned", [(0.52, True), (4.9, True), (0.0, False), (5.0, False)])
def test_friction_in_radians(phi, warned):
    warnings = _scene(**{"friction_deg = 30.0": f"friction_deg = {phi}"}).warnings
    if not warned:  # exactly 0: a deliberate frictionless joint; 5 deg and up: plausible
        assert warnings == ()
        return
    (w,) = warnings
    assert w.startswith(f"joints.j.friction_deg: {phi:g} deg is below 5 deg; ")
    assert "was it written in radians?" in w
    if phi == 0.52:
        assert "0.52 rad = 30 deg" in w


@pytest.mark.parametrize("key, value, words", [
    ("kn", "10.0", "below 1000 kPa/m (1 MPa/m), softer than any rock joint; stiffness is in "
                   "kPa/m: was it written in MPa/m or GPa/m?"),
    ("ks", "5e12", "above 1e+09 kPa/m (1,000 GPa/m), stiffer than any rock joint; stiffness "
                   "is in kPa/m: was it written in Pa/m?"),
    ("kn", "1e3", None),  # the ends of the range are plausible
    ("ks", "1e9", None),
])
def test_joint_stiffness_outside_the_range_of_rock_joints(key, value, words):
    warnings = _scene(**{f"{key} = 1e7": f"{key} = {value}"}).warnings
    if words is None:
        assert warnings == ()
    else:
        assert warnings == (f"joints.j.{key}: {float(value):g} kPa/m is {words} "
                            "(10 GPa/m is 1e7)",)


def test_overrides_are_checked_too():
    scene = _scene()
    assert scene.with_overrides({"joints.j.friction_deg": 0.6}).warnings[0].startswith(
        "joints.j.friction_deg: 0.6 deg")


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.name)
def test_the_bundled_examples_give_no_warning(path):
    warnings = load_scene(path).warnings
    if path.name.startswith("seed_example3"):
        # The paper's K0 = 0 under 48 m of rock: test_in_situ_beyond_the_rock_strength.
        assert len(warnings) == 1 and warnings[0].startswith("in_situ: at k0 = 0")
    else:
        assert warnings == ()


def test_in_situ_beyond_the_rock_strength():
    """Seed example 3 (Hataf & Baharloo, table 2): gravity only, K0 = 0, intact rock c =
    200 kPa, phi = 35 deg, 26 kN/m3 in cells, the surface at y = 20 m and the model's base
    at y = -28 m. Uniaxial (sigma_h = 0), the rock fails where sigma_v = 26 z passes its
    uniaxial strength 2 c tan(45 + phi / 2) = 768 kPa: below z = 29.55 m, y = -9.55 m, and
    the base is at 48 m (1,248 kPa). Its initial state ran into the iteration limit there
    (1,200 Newton iterations, 316 s); the warning says why. With k0 >= 1 / tan^2(62.5 deg)
    = 0.271 (Mohr-Coulomb: sigma_1 - N sigma_3 = sigma_v (1 - N k0) <= 0) it cannot fail."""
    path = ROOT / "examples" / "seed_example3_without_D.toml"
    scene = load_scene(path)
    (w,) = scene.warnings
    n = 3.6902   # tan^2(62.5 deg)
    depth = 2 * 200 * n**0.5 / 26.0
    assert depth == pytest.approx(29.55, abs=0.01)
    assert f"below y = {20.0 - depth:.1f} m, {depth:.1f} m deep" in w
    assert "uniaxial strength 768 kPa" in w and "materials.rock" in w
    assert scene.with_overrides({"in_situ.k0": 0.28}).warnings == ()
    # k0 = 0.26: 1 - N k0 = 0.0405, z* = 29.55 / 0.0405 = 730 m, far below the model.
    assert scene.with_overrides({"in_situ.k0": 0.26}).warnings == ()
    # k0 = 0.2: z* = 29.55 / 0.262 = 113 m: still below the base (48 m).
    assert scene.with_overrides({"in_situ.k0": 0.2}).warnings == ()
    # k0 = 0.1: z* = 29.55 / 0.631 = 46.8 m, just above the base.
    assert len(scene.with_overrides({"in_situ.k0": 0.1}).warnings) == 1
    # A stronger rock carries it all.
    assert scene.with_overrides({"materials.rock.cohesion": 420.0}).warnings == ()


WEAK_AT_DEPTH = """
[scene]
name = "weak rock under its own weight"
[solver]
max_iterations = 2
[materials.rock]
E = 4.0e7
nu = 0.25
cohesion = 2.0
friction_deg = 35.0
unit_weight = 26.0
tensile_strength = 2.85
[domain]
outline = [[0.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]]
material = "rock"
mesh_size = 2.0
[in_situ]
mode = "gravity"
k0 = 0.0
surface_y = 8.0
[[boundaries]]
side = "bottom"
condition = "fixed"
[[boundaries]]
side = "left"
condition = "roller"
[[boundaries]]
side = "right"
condition = "roller"
"""


def test_an_initial_state_at_the_iteration_limit_says_why_not_load_steps():
    """Rock of c = 2 kPa, phi = 35 deg, 26 kN/m3, 8 m of it at K0 = 0: uniaxial strength
    2 c tan(62.5 deg) = 7.7 kPa, passed 0.3 m below the surface (the base carries 208 kPa),
    so its in-situ state must fail into a plastic equilibrium, which 2 Newton iterations
    a geometry update do not find. The in-situ stresses are in place at once: the message
    does not send the engineer to solver.load_steps (no load step divides them) but to the
    warning, k0 and the strength; without that warning, to solver.max_iterations."""
    scene = load_scene(WEAK_AT_DEPTH)
    assert len(scene.warnings) == 1 and "uniaxial strength 8 kPa" in scene.warnings[0]
    r = jaxdem.solve(scene)
    assert r.status == "iteration_limit" and r.unbalanced_blocks
    assert r.message.startswith("The iteration limit was reached before equilibrium in the "
                                "initial state: the in-situ stresses are in place at once")
    assert "(the in_situ warning); change in_situ.k0 or the rock's strength" in r.message
    assert "Try increasing" not in r.message
    quiet = jaxdem.solve(dataclasses.replace(scene, warnings=()))
    assert quiet.status == "iteration_limit"
    assert "Try increasing solver.max_iterations." in quiet.message
    assert "in_situ warning" not in quiet.message and "load_steps." not in quiet.message


def test_the_command_line_prints_them_on_stderr_and_writes_them_to_result_json(tmp_path, capsys):
    scene = tmp_path / "block.toml"
    scene.write_text(SCENE.format(E="5e9").replace("friction_deg = 30.0", "friction_deg = 0.5"))
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "--no-figures"]) == 0
    err = capsys.readouterr().err
    warned = [line for line in err.splitlines() if line.startswith("warning: ")]
    assert [w.split(":")[1].strip() for w in warned] == ["materials.rock.E",
                                                         "joints.j.friction_deg"]
    data = json.loads((out / "result.json").read_text())
    assert data["warnings"][:2] == [w.removeprefix("warning: ") for w in warned]
    # jaxdem check says so too, before drawing.
    assert main(["check", str(scene), "--out", str(tmp_path / "check")]) == 0
    assert capsys.readouterr().err.count("warning: ") == 2
