"""Rock bolts against statics: key blocks hung on bolts, a bolted block on an incline,
large displacement and the elasto-plastic path.

Closed forms:
- A key block hanging on vertical bolts of equal stiffness k (Hoek & Brown,
  Underground Excavations in Rock, ch. 9: the bolts carry the loosened wedge's
  weight W): force and moment balance of the rigid block with the bolts' elastic
  compatibility, T_i = k (d + phi (x_i - x_mean)), sum T_i = W, sum T_i (x_i - x_c)
  = 0; one bolt through the centroid: T = W, drop W / k.
- A block on a plane inclined at a, friction phi, held at limit equilibrium by a
  bolt at angle b to the plane (up-slope, into the base) (Hoek & Bray, Rock Slope
  Engineering, ch. 6): T = W (sin a - cos a tan phi) / (cos b + sin b tan phi).
- A bolt's force is k x (its length - its rest length) at any displacement, capped
  at its yield force, with the plastic elongation kept (elastic unloading).
"""

import math

import numpy as np
import pytest
from scenes import ROCK, incline_frame, rect_on_slope, slope_base

import jaxdem
from jaxdem import solver
from jaxdem.core import model as model_mod
from jaxdem.core.loads import make_loads
from jaxdem.core.status import Status
from jaxdem.scene import parse_scene

GAMMA = 39.0  # kN/m3: the symmetric wedge below weighs 58.5 kN/m
K_BOLT = 1e5  # kN/m


def key_block(bolts, apex=(0.0, 1.5), *, in_situ=False, yield_force=200.0, stages=None):
    """A triangular roof wedge (-1, 0), (1, 0), apex, between fixed rock; cohesionless joints,
    self-weight only. ``bolts``: [(lower anchor in the wedge, upper anchor in the rock)]."""
    ax, ay = apex
    d = {
        "scene": {"name": "key block"},
        "solver": {"load_steps": 1},
        "materials": {"rock": {"E": 1e7, "nu": 0.25, "unit_weight": GAMMA}},
        "joints": {"j": {"kn": 1e6, "ks": 5e5, "friction_deg": 30.0, "cohesion": 0.0}},
        "blocks": [
            {"vertices": [[-1, 0], [1, 0], [ax, ay]], "material": "rock"},
            {"vertices": [[-3, 0], [-1, 0], [ax, ay], [ax, 2], [-3, 2]], "material": "rock",
             "fixed": True},
            {"vertices": [[1, 0], [3, 0], [3, 2], [ax, 2], [ax, ay]], "material": "rock",
             "fixed": True},
            {"vertices": [[-3, 2], [3, 2], [3, 3], [-3, 3]], "material": "rock", "fixed": True},
        ],
        "bolts": [{"from": list(f), "to": list(t), "stiffness": K_BOLT,
                   "yield_force": yield_force, "anchor_capacity": 1.5 * yield_force}
                  for f, t in bolts],
        "monitors": [{"name": "wedge", "point": [ax / 3.0, ay / 3.0]}],
    }
    if in_situ:
        d["in_situ"] = {"mode": "uniform", "sigma_xx": 0.0, "sigma_yy": 0.0}
    if stages:
        d["stages"] = stages
    return d


def _weight(apex):
    return GAMMA * 0.5 * 2.0 * apex[1]


def _vertical_bolt_forces(xs, apex):
    """T_i of vertical bolts of equal stiffness at abscissae xs under a rigid wedge."""
    xs = np.asarray(xs, float)
    xc = (-1.0 + 1.0 + apex[0]) / 3.0
    W = _weight(apex)
    if len(xs) == 1:
        return np.array([W])
    # Unknowns (d, phi): T_i = k (d + phi (x_i - mean)).
    m = xs.mean()
    A = np.array([[len(xs), np.sum(xs - m)], [np.sum(xs - xc), np.sum((xs - m) * (xs - xc))]])
    d, phi = np.linalg.solve(K_BOLT * A, [W, 0.0])
    return K_BOLT * (d + phi * (xs - m))


@pytest.mark.parametrize("apex, xs", [
    ((0.0, 1.5), [0.0]),             # symmetric wedge, one bolt through the centroid
    ((0.4, 1.5), [0.4 / 3.0]),       # asymmetric wedge, one bolt through the centroid
    ((0.4, 1.5), [-0.5, 0.5]),       # asymmetric wedge, two bolts
    ((0.0, 1.5), [-0.6, 0.1, 0.55]),  # three bolts, unevenly spaced
])
@pytest.mark.parametrize("in_situ", [False, True])
def test_key_block_hangs_on_its_bolts(apex, xs, in_situ):
    bolts = [((x, 0.15), (x, 2.6)) for x in xs]
    r = jaxdem.solve(parse_scene(key_block(bolts, apex, in_situ=in_situ)))
    assert r.converged and r.stable and r.admissibility["admissible"]
    forces = np.array([b["force"] for b in r.bolts])
    expected = _vertical_bolt_forces(xs, apex)
    np.testing.assert_allclose(forces, expected, rtol=0.01)
    assert all(b["state"] == "elastic" for b in r.bolts)
    ux, uy = r.monitors["wedge"]["displacement"]
    if len(xs) == 1:
        # Through the centroid: a pure drop of W / k, no sideways travel.
        assert math.isclose(-uy, _weight(apex) / K_BOLT, rel_tol=0.01)
        assert abs(ux) < 0.01 * abs(uy)
    # The wedge has dropped out of its seat: no contact is closed and none overlaps.
    assert r.admissibility["overlap"] < 1e-6


def test_bolts_weaker_than_the_wedge_give_a_mechanism():
    # Two bolts of 20 kN each cannot hold a 58.5 kN wedge.
    bolts = [((-0.4, 0.15), (-0.4, 2.6)), ((0.4, 0.15), (0.4, 2.6))]
    r = jaxdem.solve(parse_scene(key_block(bolts, yield_force=20.0)))
    assert not r.stable and r.status == "mechanism" and r.moving_blocks == [0]
    assert all(b["state"] in ("yielded", "pulled out") for b in r.bolts)


def test_unbolted_key_block_falls_and_bolted_from_first_load_step_holds():
    # Without stages or in-situ stress a bolt acts from the first load step.
    free = jaxdem.solve(parse_scene(key_block([], (0.0, 1.5))))
    assert not free.stable
    held = jaxdem.solve(parse_scene(key_block([((0.0, 0.5), (0.0, 2.5))])))
    assert held.stable and held.converged
    assert math.isclose(held.bolts[0]["force"], _weight((0.0, 1.5)), rel_tol=0.01)


def test_bolt_named_in_a_later_stage_acts_only_from_it():
    stages = [{"name": "unbolted"}, {"name": "bolted"}]
    d = key_block([((0.0, 0.5), (0.0, 2.5))], in_situ=True, stages=stages)
    d["bolts"][0]["stage"] = "bolted"
    r = jaxdem.solve(parse_scene(d))
    # The wedge's weight is a load of the first stage (uniform in-situ stress), where it
    # has no bolt yet: it falls.
    assert not r.stable and r.bolts[0]["force"] == 0.0


def incline_with_bolt(alpha, phi, beta, *, k=5e4, yield_force=500.0, length=3.0):
    """A 1 m block on a plane at alpha (friction phi), bolted from its centroid into the base
    at beta to the plane (up-slope, into the base)."""
    t, n = incline_frame(alpha)
    blk = rect_on_slope(alpha, 4.0, 1.0, 1.0)
    c = np.mean(np.array(blk), axis=0)
    b = math.radians(beta)
    end = c + length * (math.cos(b) * t - math.sin(b) * n)
    return {
        "scene": {"name": "bolted block on incline"},
        "solver": {"load_steps": 2, "max_displacement": 2.0},
        "materials": {"rock": dict(ROCK)},
        "joints": {"base": {"kn": 1e6, "ks": 5e5, "friction_deg": phi}},
        "blocks": [{"vertices": slope_base(alpha), "material": "rock", "fixed": True},
                   {"vertices": blk, "material": "rock"}],
        "bolts": [{"from": c.tolist(), "to": end.tolist(), "stiffness": k,
                   "yield_force": yield_force, "anchor_capacity": 2 * yield_force}],
        "monitors": [{"name": "block", "point": c.tolist()}],
    }


def _incline_tension(alpha, phi, beta, W=25.0):
    a, p, b = (math.radians(x) for x in (alpha, phi, beta))
    return W * (math.sin(a) - math.cos(a) * math.tan(p)) / (math.cos(b) + math.sin(b) * math.tan(p))


def _final_bolt_angle(r, alpha):
    """Angle of the bolt (block anchor -> base anchor) to the up-slope direction, at the end."""
    t, n = incline_frame(alpha)
    p1, p2 = np.asarray(r.geometry["bolts"][0])
    e = (p2 - p1) / np.linalg.norm(p2 - p1)
    return math.degrees(math.atan2(-np.dot(e, n), np.dot(e, t)))


@pytest.mark.parametrize("alpha, phi, beta", [(35, 25, 30), (40, 30, 60), (35, 20, 20)])
def test_bolted_block_on_incline_at_limit_equilibrium(alpha, phi, beta):
    r = jaxdem.solve(parse_scene(incline_with_bolt(alpha, phi, beta)))
    assert r.converged and r.stable and r.admissibility["admissible"]
    # The block slid (alpha > phi) until the bolt took the rest: the joint is at its
    # Mohr-Coulomb limit, the bolt gives the difference. The bolt has turned a little
    # as the block slid; the closed form is taken at its final angle.
    T = r.bolts[0]["force"]
    assert math.isclose(T, _incline_tension(alpha, phi, _final_bolt_angle(r, alpha)), rel_tol=0.01)
    assert math.isclose(T, _incline_tension(alpha, phi, beta), rel_tol=0.03)


def test_bolt_force_is_k_times_stretch_after_a_large_slide():
    # A soft bolt: the block slides about 0.25 m before it holds.
    k, alpha, phi, beta = 25.0, 35.0, 25.0, 25.0
    d = incline_with_bolt(alpha, phi, beta, k=k)
    # Loaded gradually, the block slides with the joint at its limit all the way (in one
    # step it overshoots and comes back, and the joint ends stuck, below its limit: also
    # an equilibrium, of another load path).
    d["solver"]["load_steps"] = 8
    r = jaxdem.solve(parse_scene(d))
    assert r.converged and r.stable
    u = np.linalg.norm(r.monitors["block"]["displacement"])
    assert u > 0.1
    d0 = incline_with_bolt(alpha, phi, beta, k=k)["bolts"][0]
    length0 = np.linalg.norm(np.subtract(d0["to"], d0["from"]))
    p1, p2 = np.asarray(r.geometry["bolts"][0])
    stretch = np.linalg.norm(p2 - p1) - length0
    T = r.bolts[0]["force"]
    assert math.isclose(T, k * stretch, rel_tol=1e-6)
    assert math.isclose(T, _incline_tension(alpha, phi, _final_bolt_angle(r, alpha)), rel_tol=0.01)


# ---------------------------------------------------------------------------
# The elasto-plastic path, driven by loads on a block held only by its bolt and a stop


def _pull_scene(gap=0.05, yield_force=100.0, compression=0.0):
    """A weightless free block between a fixed anchor block (3 m to the left, no contact)
    and a fixed stop ``gap`` to its right; a horizontal bolt from the block to the anchor."""
    return {
        "scene": {"name": "bolt path"},
        "solver": {"load_steps": 1, "max_displacement": 1.0},
        "materials": {"rock": {"E": 1e7, "nu": 0.25, "unit_weight": 0.0}},
        "joints": {"j": {"kn": 1e6, "ks": 5e5, "friction_deg": 0.0}},
        "blocks": [
            {"vertices": [[0, 0], [1, 0], [1, 1], [0, 1]], "material": "rock"},
            {"vertices": [[-4, 0], [-3, 0], [-3, 1], [-4, 1]], "material": "rock", "fixed": True},
            {"vertices": [[1 + gap, -0.5], [2 + gap, -0.5], [2 + gap, 1.5], [1 + gap, 1.5]],
             "material": "rock", "fixed": True},
        ],
        "bolts": [{"from": [0.5, 0.5], "to": [-3.5, 0.5], "stiffness": 1e4,
                   "yield_force": yield_force, "anchor_capacity": 2 * yield_force,
                   "compression": compression}],
    }


def _drive(scene, loads_x):
    """Apply horizontal loads (kN/m) on block 0 one increment after another; returns
    (status, ux, bolt force, bolt state) after each."""
    model, state, layout = model_mod.build(scene)
    out = []
    for fx in loads_x:
        force = np.zeros((model.n_blocks, model.ndof))
        force[0, 0] = fx
        loads = make_loads(model, force, bolt_active=np.ones(1, bool))
        model, state, info, _ = solver.run_increment(model, state, loads)
        out.append((Status.of(info.status), float(state.u[0, 0]),
                    float(state.bolt_force[0]), int(state.bolt_state[0])))
    return out


def test_load_yield_unload_follows_the_elasto_plastic_path():
    k, Y, gap = 1e4, 100.0, 0.05
    path = _drive(parse_scene(_pull_scene(gap, Y)), [50.0, 150.0, 0.0, 50.0])
    (s1, u1, f1, st1), (s2, u2, f2, st2), (s3, u3, f3, st3), (s4, u4, f4, st4) = path
    assert all(s == Status.CONVERGED for s, *_ in path)
    # Elastic: 50 kN stretches the bolt 5 mm.
    assert math.isclose(f1, 50.0, rel_tol=1e-6) and math.isclose(u1, 50.0 / k, rel_tol=1e-6)
    assert st1 == 0
    # 150 kN: the bolt yields at 100 kN and the block rests on the stop 50 mm away (the
    # stop's spring then settles a little, and the bolt unloads elastically by 2e-5 Y).
    assert math.isclose(f2, Y, rel_tol=1e-4) and st2 in (0, 1)
    assert u2 == pytest.approx(gap, abs=2e-4)
    # Unloaded: elastic from the yielded length, the plastic elongation gap - Y / k stays.
    assert abs(f3) < 1e-6 * Y
    assert u3 == pytest.approx(u2 - f2 / k, abs=1e-6)
    assert u3 > 0.8 * (gap - Y / k)
    # Reloaded to 50 kN: elastic again, 5 mm further, well below yield.
    assert math.isclose(f4, 50.0, rel_tol=1e-6) and st4 == 0
    assert u4 == pytest.approx(u3 + 50.0 / k, abs=1e-6)


def test_a_bolt_carries_compression_only_when_given_a_capacity():
    # Pushed towards its anchor: a cable (compression 0) goes slack and the block moves on;
    # a bar with a compression capacity holds it elastically.
    scene = parse_scene(_pull_scene(compression=0.0))
    (s,) = [p[0] for p in _drive(scene, [-20.0])]
    assert s == Status.MECHANISM
    scene = parse_scene(_pull_scene(compression=80.0))
    ((s, u, f, st),) = _drive(scene, [-20.0])
    assert s == Status.CONVERGED
    assert math.isclose(f, -20.0, rel_tol=1e-6) and math.isclose(u, -20.0 / 1e4, rel_tol=1e-6)


# ---------------------------------------------------------------------------
# Derivatives through the bolts, and the slip report


def test_key_block_drop_derivatives_match_statics():
    """A wedge on one bolt through its centroid drops W / k: d drop / dk = -W / k^2.
    On two bolts (asymmetric wedge) the derivatives match central differences: the
    implicit derivative uses the bolts' full tangent (axial, string and lever-arm terms)."""
    import jax

    f, theta0 = jaxdem.differentiable(parse_scene(key_block([((0.0, 0.5), (0.0, 2.5))])),
                                      ["bolts.0.stiffness"])
    drop = lambda th: -f(th)["wedge"][1]  # noqa: E731
    W = _weight((0.0, 1.5))
    assert float(drop(theta0)) == pytest.approx(W / K_BOLT, rel=1e-6)
    assert float(jax.grad(drop)(theta0)[0]) == pytest.approx(-W / K_BOLT**2, rel=1e-6)

    d = key_block([((-0.5, 0.15), (-0.5, 2.6)), ((0.5, 0.15), (0.5, 2.6))], (0.4, 1.5))
    f, theta0 = jaxdem.differentiable(parse_scene(d), ["bolts.0.stiffness", "bolts.1.stiffness"])
    jac = np.asarray(jax.jacfwd(lambda th: f(th)["wedge"])(theta0))
    for i in range(2):
        h = 1e-4 * float(theta0[i])
        up, dn = np.array(theta0), np.array(theta0)
        up[i] += h
        dn[i] -= h
        fd = (np.asarray(f(up)["wedge"]) - np.asarray(f(dn)["wedge"])) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-5, atol=1e-12 * float(np.abs(fd).max()))


def test_large_joint_slip_is_reported_and_small_is_not():
    from scenes import slide_and_stop

    from jaxdem.cli._summaries import result_summary
    from jaxdem.core.status import LARGE_SLIP

    # Seed example 1: the block slides 1 m down the slope and comes to rest on a stop.
    r = jaxdem.solve(parse_scene(slide_and_stop(gap=1.0)))
    assert r.converged and r.stable
    slip = max(max(s["max_slip"]) for s in r.stages)
    assert slip == pytest.approx(1.0, rel=0.05)
    assert len(r.warnings) == 1 and "joint slip of" in r.warnings[0] and "review" in r.warnings[0]
    assert "blocks 1 and 0" in r.warnings[0] or "blocks 0 and 1" in r.warnings[0]
    assert "warning: stable, but joint slip of" in result_summary(r)
    # A block resting on a plane flatter than its friction angle barely moves.
    r = jaxdem.solve(parse_scene(tb_incline_at_rest()))
    assert r.converged and r.stable and not r.warnings
    assert max(max(s["max_slip"]) for s in r.stages) < LARGE_SLIP * 0.5


def tb_incline_at_rest():
    from scenes import block_on_incline

    return block_on_incline(20.0, 30.0)
