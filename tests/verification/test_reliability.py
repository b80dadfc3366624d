"""FORM reliability index (jaxdem.reliability, ``jaxdem reliability``) against closed forms.

- Ultimate limit state, a cohesionless block on a plane inclined at a = 25 deg: the
  factor of safety is F = tan(phi) / tan(a) (Goodman, Introduction to Rock Mechanics,
  8.2), so with phi ~ normal(30, 3) deg failure is phi <= 25 deg, linear in phi:
  beta = (30 - 25) / 3 exactly, Pf = Phi(-5/3) = 0.0478, design point phi = 25 deg.
- Serviceability, a block on a horizontal joint: its settlement is u = W / (k L),
  k the equivalent normal stiffness of eq. 6 (the joint's kn in series with the two
  blocks' rock: 1/k = h1/kn_i + h2/kn_i + 1/kn). With kn lognormal (lambda, zeta) the
  limit u <= u_allow fails where kn <= kn*, 1/kn* = L u_allow / W - (h1 + h2) / kn_i
  (kn* = W / (L u_allow) for rigid rock), so beta = (lambda - ln kn*) / zeta exactly.
- Two variables, cohesion and friction of the incline's joint (a 2 x 0.5 m block):
  F = max(F1, F2) of the per-point Mohr-Coulomb law (tests/test_fos.py), and the design
  point by a direct minimisation of |u| on F(c(u), phi(u)) = 1 (SLSQP).
- Monte Carlo with the same variables agrees with Phi(-beta) where FORM is exact.
- Bad input is refused before any solve, naming the field, exit status 2.
"""

import json
import math

import numpy as np
import pytest
from scenes import block_on_incline
from scipy.optimize import minimize
from scipy.special import ndtr
from test_cli import SCENE

import jaxdem
from jaxdem.cli import main
from jaxdem.core.laws import equivalent_stiffness, intact_stiffness
from jaxdem.reliability import Limit, Reliability
from jaxdem.scene import SceneError, parse_scene

FRICTION = "joints.base.friction_deg"
COHESION = "joints.base.cohesion"


@pytest.fixture(scope="module")
def incline():
    scene = parse_scene(block_on_incline(25.0, 30.0))
    return jaxdem.reliability(scene, [f"{FRICTION}=normal:30:3"], "stable", check="mc:96",
                              seed=10)


def test_incline_friction_ultimate_beta_is_five_thirds(incline):
    r = incline
    assert isinstance(r, Reliability) and r.converged, r.warnings
    assert r.beta == pytest.approx(5.0 / 3.0, rel=0.01)
    assert r.probability == pytest.approx(ndtr(-5.0 / 3.0), rel=0.01)
    assert r.probability == pytest.approx(0.0478, abs=5e-4)
    assert r.design_point[FRICTION] == pytest.approx(25.0, abs=0.1)
    assert r.importance == pytest.approx({FRICTION: 1.0})
    assert r.alpha[FRICTION] < 0                  # friction is a resistance
    assert r.solves["with_sensitivities"] == 0 and r.solves["plain"] > 0


def test_incline_monte_carlo_fails_exactly_where_friction_is_below_the_slope(incline):
    """The check's samples are phi = 30 + 3 z (z standard normal, the seed's); a sample
    fails (a mechanism at F = 1) exactly where phi < 25 deg (5 of 96 with seed 10, whose
    nearest sample lies 0.49 deg from the limit)."""
    c = incline.check
    z = np.random.default_rng(10).standard_normal((96, 1))
    assert c["failures"] == int(np.sum(30.0 + 3.0 * z < 25.0)) and c["undecided"] == 0
    # The sliding block is the whole scene's free rock, and a scene without joint sets has
    # no default max_loose_volume: none of the failures is a small mechanism.
    assert c["small_mechanisms"] == 0
    assert c["ci95"][0] <= incline.probability <= c["ci95"][1]


def test_incline_factor_and_its_derivative_match_tan_phi_over_tan_alpha(incline):
    """The first point is the median (phi = 30 deg): g = F - 1 with F = tan 30 / tan 25,
    and dg/du = dF/dphi * sd = sd (pi / 180) / (cos^2(30) tan 25), by central differences
    of bracketed factors."""
    first = incline.history[0]
    a, phi, sd = math.radians(25.0), math.radians(30.0), math.radians(3.0)
    assert first["g"] == pytest.approx(math.tan(phi) / math.tan(a) - 1.0, abs=1e-4)
    assert first["gradient_norm"] == pytest.approx(sd / (math.cos(phi) ** 2 * math.tan(a)),
                                                   rel=1e-3)


SETTLE = dict(mean=1e6, sd=3e5, u_allow=4e-5)


@pytest.fixture(scope="module")
def settlement():
    scene = parse_scene(block_on_incline(0.0, 30.0))   # a 1 x 1 m block on a horizontal joint
    limit = f"block.uy >= {-SETTLE['u_allow']}"
    return jaxdem.reliability(scene, [f"joints.base.kn=lognormal:{SETTLE['mean']}:"
                                      f"{SETTLE['sd']}"], limit, check="mc:400", seed=0)


def test_settlement_lognormal_stiffness_beta_is_exact(settlement):
    r = settlement
    W, L = 25.0 * 1.0 * 1.0, 1.0                   # unit weight 25 kN/m3, 1 m base
    kn_i, _ = intact_stiffness(1e7, 0.25)
    h1, h2 = 0.5, 1.0                             # centroids of the block and the 2 m base
    kn_star = 1.0 / (L * SETTLE["u_allow"] / W - (h1 + h2) / kn_i)
    zeta = math.sqrt(math.log1p((SETTLE["sd"] / SETTLE["mean"]) ** 2))
    lam = math.log(SETTLE["mean"]) - 0.5 * zeta ** 2
    assert r.converged, r.warnings
    assert r.beta == pytest.approx((lam - math.log(kn_star)) / zeta, rel=0.01)
    assert r.design_point["joints.base.kn"] == pytest.approx(kn_star, rel=0.01)
    # The settlement of the model itself is eq. 6's (the rock adds 14% to 1/kn here).
    k = equivalent_stiffness(h1, h2, 1 / kn_i, 1 / kn_i, 1 / SETTLE["mean"])
    assert W / (k * L) == pytest.approx(W * (1 / SETTLE["mean"] + 1.5 / kn_i), rel=1e-12)
    # Exact gradients: a handful of solves, each with sensitivities.
    assert r.solves["with_sensitivities"] <= 8 and r.solves["plain"] == 0
    assert r.importance == pytest.approx({"joints.base.kn": 1.0})


def test_monte_carlo_agrees_with_form_where_form_is_exact(settlement):
    c = settlement.check
    assert c["samples"] == c["solves"] == 400 and c["undecided"] == 0
    assert c["ci95"][0] <= settlement.probability <= c["ci95"][1]
    assert c["form_within_ci95"]
    assert c["failures"] == round(c["probability"] * c["decided"])


def _two_variable_factor(c, phi_deg, w=2.0, h=0.5, alpha=25.0, unit_weight=25.0):
    """F of a w x h block on the incline with cohesion c (kPa) and friction phi: the
    uphill contact point fails first (F1) unless the downhill one alone holds (F2)."""
    a, tp = math.radians(alpha), math.tan(math.radians(phi_deg))
    W, L = unit_weight * w * h, w
    T = W * math.sin(a)
    F1 = (c * L + W * math.cos(a) * tp) / T - h / L * tp
    F2 = (c * L / 2 + W * math.cos(a) * tp) / T
    return max(F1, F2)


def test_two_variables_cohesion_and_friction_match_the_direct_minimisation():
    c_mean, c_sd, phi_mean, phi_sd = 4.0, 1.0, 20.0, 3.0
    found = minimize(lambda u: u @ u, np.zeros(2), method="SLSQP", options=dict(ftol=1e-14),
                     constraints=[dict(type="eq", fun=lambda u: _two_variable_factor(
                         c_mean + c_sd * u[0], phi_mean + phi_sd * u[1]) - 1.0)])
    beta = math.sqrt(found.fun)
    assert found.success and 1.5 < beta < 2.5
    scene = parse_scene(block_on_incline(25.0, phi_mean, cohesion=c_mean, width=2.0,
                                         height=0.5))
    r = jaxdem.reliability(scene, [f"{COHESION}=normal:{c_mean}:{c_sd}",
                                   f"{FRICTION}=normal:{phi_mean}:{phi_sd}"], "stable")
    assert r.converged, r.warnings
    assert r.beta == pytest.approx(beta, rel=0.01)
    u = [r.design_point_u[COHESION], r.design_point_u[FRICTION]]
    np.testing.assert_allclose(u, found.x, atol=0.02)
    assert sum(r.importance.values()) == pytest.approx(1.0)
    assert r.alpha[COHESION] < 0 and r.alpha[FRICTION] < 0


# ---------------------------------------------------------------------------
# Bad input: refused before any solve, naming the field, exit status 2


@pytest.fixture
def block_file(tmp_path):
    path = tmp_path / "block_on_base.toml"
    path.write_text(SCENE.format(E="1e7"))
    return path


@pytest.mark.parametrize("argv, field", [
    (["--vary", "joints.j.kn=lognormal:1e7:2e6", "--limit", "crown.|u| <= 0.01"], "--limit"),
    (["--vary", "joints.j.kn=lognormal:1e7:2e6", "--limit", "top.uz <= 0.01"], "--limit"),
    (["--vary", "blocks.1.vertices.0.0=normal:1.5:0.01", "--limit", "top.uy >= -1e-5"],
     "--vary blocks.1.vertices.0.0"),
    (["--vary", "joints.j.kn=normal:1e7:0", "--limit", "top.uy >= -1e-5"],
     "--vary joints.j.kn"),
    (["--vary", "joints.j.kn=normal:1e7:-5", "--limit", "stable"], "--vary joints.j.kn"),
    (["--vary", "joints.j.kn=1e6:1e7", "--limit", "stable"], "--vary joints.j.kn"),
    (["--vary", "joints.nope.kn=normal:1e7:1e6", "--limit", "stable"], "--vary joints.nope.kn"),
    (["--vary", "joints.j.kn=normal:1e7:1e6", "--limit", "top.uy >= -1e-5",
      "--check", "mc:0"], "--check"),
    (["--vary", "joints.j.kn=normal:1e7:1e6", "joints.j.ks=normal:1e7:1e6",
      "--limit", "top.uy >= -1e-5", "--correlation", "joints.j.kn,joints.j.ks=1.5"],
     "--correlation"),
])
def test_bad_input_exits_2_naming_the_field(block_file, tmp_path, capsys, argv, field):
    code = main(["reliability", str(block_file), "--out", str(tmp_path / "out"), *argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith(f"error: {field}"), err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_python_interface_refuses_the_same(block_file):
    scene = jaxdem.load_scene(block_file)
    with pytest.raises(SceneError, match=r"^--limit: no monitor named 'crown'"):
        jaxdem.reliability(scene, ["joints.j.kn=lognormal:1e7:2e6"], "crown.|u| <= 0.01")
    with pytest.raises(SceneError, match=r"^--vary joints.j.kn: the standard deviation"):
        jaxdem.reliability(scene, ["joints.j.kn=lognormal:1e7:0"], "top.uy >= -1e-5")
    with pytest.raises(SceneError, match=r"^--limit: 'top' is a point"):
        Limit.parse("top <= 0.01", scene)


def test_cli_writes_reliability_json_and_figure(block_file, tmp_path, capsys):
    """A 1 x 1 m block on a 1 m thick base, joint kn lognormal: the settlement
    W / (k L) with 1/k = 0.5/kn_i + 0.5/kn_i + 1/kn exceeds 7 um where kn <= kn*."""
    out = tmp_path / "rel"
    code = main(["reliability", str(block_file), "--vary", "joints.j.kn=lognormal:1e7:3e6",
                 "--limit", "top.uy >= -7e-6", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    data = json.loads((out / "reliability.json").read_text())
    assert (out / "reliability.png").stat().st_size > 10_000
    for key in ("beta", "probability", "design_point", "importance", "solves", "history",
                "warnings", "converged", "status"):
        assert key in data
    kn_i, _ = intact_stiffness(1e7, 0.25)
    kn_star = 1.0 / (7e-6 / 25.0 - 1.0 / kn_i)
    zeta = math.sqrt(math.log1p(0.3 ** 2))
    beta = (math.log(1e7) - 0.5 * zeta ** 2 - math.log(kn_star)) / zeta
    assert data["converged"] and data["warnings"] == []
    assert data["beta"] == pytest.approx(beta, rel=0.01)
    assert data["probability"] == pytest.approx(ndtr(-data["beta"]), rel=1e-9)
    assert sum(data["importance"].values()) == pytest.approx(1.0)
    assert data["solves"]["with_sensitivities"] >= 2
    assert "beta = " in captured.out and "design point" in captured.out


def test_cli_exits_3_when_the_medians_have_no_equilibrium(tmp_path, capsys):
    """A block on a 35 deg plane with 30 deg friction slides at the medians: a
    serviceability limit has no value there, FORM cannot start (exit 3, said in the JSON)."""
    scene = tmp_path / "sliding.toml"
    d = block_on_incline(35.0, 30.0)
    lines = ['[scene]\nname = "sliding"\n[solver]\nload_steps = 1\nmax_displacement = 0.05\n',
             "[materials.rock]\nE = 1e7\nnu = 0.25\nunit_weight = 25.0\n",
             "[joints.base]\nkn = 1e6\nks = 5e5\nfriction_deg = 30.0\n"]
    for b in d["blocks"]:
        lines.append(f"[[blocks]]\nvertices = {[[float(x), float(y)] for x, y in b['vertices']]}"
                     f"\nmaterial = \"rock\"\nfixed = {str(b.get('fixed', False)).lower()}\n")
    lines.append(f"[[monitors]]\nname = \"block\"\npoint = {d['monitors'][0]['point']}\n")
    scene.write_text("\n".join(lines))
    out = tmp_path / "rel"
    code = main(["reliability", str(scene), "--vary", "joints.base.kn=lognormal:1e6:2e5",
                 "--limit", "block.|u| <= 0.01", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 3, captured.err
    data = json.loads((out / "reliability.json").read_text())
    assert data["status"] == "no_answer_at_start" and not data["converged"]
    assert data["beta"] is None and any("cannot start" in w for w in data["warnings"])
