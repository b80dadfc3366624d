"""jaxdem.differentiable: derivatives of the monitors against finite differences and closed forms.

The derivatives are implicit (one linear solve per converged sub-step, contact
states held), so they must agree with central differences of the full solve
wherever no contact changes state within the difference step.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import jointed_tunnel, stack

import jaxdem
from jaxdem.core.laws import equivalent_stiffness, intact_stiffness
from jaxdem.core.state import SNAPSHOT_FLOATS
from jaxdem.differentiable import Problem
from jaxdem.scene import SceneError, parse_scene


def _slipping_tunnel():
    """The small jointed tunnel with a weak second set: slipping and open contacts at the end.

    The top is a roller wall, so that the in-situ state stays in equilibrium when
    the in-situ parameters change (with a traction on top, a change of the
    stress field would move the model in the initial step and close or open the
    corner contacts that the in-situ state leaves at exactly zero force: a
    state threshold).
    """
    d = jointed_tunnel(top="roller")
    d["joints"]["set1"].update(friction_deg=30.0, cohesion=0.0)
    d["joints"]["set2"].update(friction_deg=15.0, cohesion=2.0)
    d["water"]["table"] = [[-9.0, 2.0], [9.0, 3.0]]
    # Its cohesive joints slip as they reach their strength (below: cohesion acts only
    # through those that fail in the last sub-step); event by event (the default), the
    # test after the cohesion's.
    d.setdefault("solver", {})["bond_failure"] = "substep"
    return d


TUNNEL_PARAMS = ["joints.set1.kn", "joints.set1.ks", "joints.set2.friction_deg",
                 "materials.rock.E", "materials.rock.nu", "in_situ.k0", "in_situ.surface_y",
                 "bolts.0.stiffness", "supports.0.pressure", "water.table.0.1",
                 "water.table.1.1"]


@pytest.fixture(scope="module")
def tunnel():
    scene = parse_scene(_slipping_tunnel())
    problem = Problem(scene, TUNNEL_PARAMS + ["joints.set2.cohesion"])
    y, J = problem.evaluate(problem.theta0, jacobian=True)
    return scene, problem, y, J


def test_tunnel_has_slipping_and_open_contacts_and_exact_sub_steps(tunnel):
    scene, problem, y, _ = tunnel
    r = jaxdem.solve(scene)
    assert r.converged
    assert r.contacts["slipping"] >= 3 and r.contacts["open"] >= 10
    assert not problem.last["approximate"]
    # f's values are the solve's monitors.
    assert y[2] == pytest.approx(r.monitors["span"]["convergence"], rel=1e-9)


@pytest.mark.parametrize("linear_solver", ["sparse", "cg"])
def test_sensitivities_on_each_linear_solver_equal_the_dense_ones(tunnel, linear_solver):
    """The sensitivity solve of the sparse path (KLU inside the program, refined on K)
    and of the cg path give the dense path's Jacobian (the same exact tangent, one
    factorisation each): to 1e-8 of the largest entry of each parameter's column. On
    the cg path the cohesion's column is left out: cohesion acts only through the
    contacts that fail in the last sub-step (the test below), which a forward path
    that differs within the tolerance changes (measured 1e-5 of that column)."""
    _, _, y, J = tunnel
    d = _slipping_tunnel()
    d.setdefault("solver", {})["linear_solver"] = linear_solver
    other = Problem(parse_scene(d), TUNNEL_PARAMS + ["joints.set2.cohesion"])
    y2, J2 = other.evaluate(other.theta0, jacobian=True)
    assert np.max(np.abs(y2 - y)) <= 1e-8 * np.max(np.abs(y))
    columns = len(TUNNEL_PARAMS) + (linear_solver == "sparse")
    J, J2 = J[:, :columns], J2[:, :columns]
    scale = np.max(np.abs(J), axis=0)
    assert np.all(np.max(np.abs(J2 - J), axis=0) <= 1e-8 * scale), (J2 - J) / scale


def _central_difference(problem, i, rel):
    theta = problem.theta0
    e = np.zeros_like(theta)
    e[i] = rel * abs(theta[i])
    return (problem.evaluate(theta + e)[0] - problem.evaluate(theta - e)[0]) / (2 * e[i])


@pytest.mark.parametrize("i", range(len(TUNNEL_PARAMS)), ids=TUNNEL_PARAMS)
def test_tunnel_derivatives_match_central_differences(tunnel, i):
    _, problem, _, J = tunnel
    fd = _central_difference(problem, i, 1e-4)
    scale = np.max(np.abs(fd))
    assert scale > 0, "the monitors must depend on the parameter"
    assert np.max(np.abs(J[:, i] - fd)) <= 1e-5 * scale


def test_tunnel_cohesion_derivative_is_small_and_matches_central_differences(tunnel):
    """Cohesion is lost when a contact first slips, so it acts only through contacts that
    fail in the last sub-step: here the monitors move 1e-10 m per kPa against 1 mm of
    convergence. Central differences of so small an effect carry the solver's round-off
    (1e-14 m): they settle to 1e-4 with a step of 1% and no better, so that is the test."""
    _, problem, _, J = tunnel
    i = len(TUNNEL_PARAMS)
    fd = _central_difference(problem, i, 1e-2)
    scale = np.max(np.abs(fd))
    assert 1e-11 < scale < 1e-9
    assert np.max(np.abs(J[:, i] - fd)) <= 2e-3 * scale



@pytest.mark.parametrize("name, within", [("joints.set1.kn", 1e-5),
                                          ("joints.set2.friction_deg", 1e-5),
                                          ("joints.set2.cohesion", 1e-3)])
def test_derivatives_where_springs_fail_event_by_event_match_central_differences(name, within):
    """With ``solver.bond_failure = "events"`` Newton balances the blocks with the springs
    that have strength to lose held elastic, and the law's forces are committed (one
    loaded beyond its strength carries it). The derivative differentiates each in its
    own states (jaxdem.core.sensitivities.substep_tangent). Differentiated both in the
    committed states, the joint stiffness's derivative was 8.6e-4 off, the friction's
    2.7e-3 and the cohesion's 76% (measured); now 5e-7, 3e-8 and 1e-5, central
    differences of 0.1% (at 0.01% and 0.001% the same to their round-off)."""
    d = _slipping_tunnel()
    d["solver"]["bond_failure"] = "events"
    problem = Problem(parse_scene(d), [name])
    _, J = problem.evaluate(problem.theta0, jacobian=True)
    fd = _central_difference(problem, 0, 1e-3)
    scale = np.max(np.abs(fd))
    assert scale > 0, "the monitors must depend on the parameter"
    assert np.max(np.abs(J[:, 0] - fd)) <= within * scale


def test_active_slots_alone_give_the_whole_detections_derivatives(monkeypatch):
    """The sensitivities differentiate only the active slots, gathered into S / 4 places
    (jaxdem.core.sensitivities._sub_tangents); a sub-step with more active slots differentiates
    the whole detection. Both give the same derivatives of a sub-step's new state and
    contact snapshot: an inactive slot carries no force whatever its geometry. Checked on
    the last increment of the slipping tunnel (water, bolts, slip, open contacts)."""
    import jaxdem.solver as solver_mod
    from jaxdem.core.sensitivities import ACTIVE_SHARE, substep_tangent

    calls = []
    run_increment = solver_mod.run_increment

    def record(model, state, loads, tangents=None, quick=False):
        out = run_increment(model, state, loads, tangents, quick)
        if tangents is not None:
            calls.append((out[0], state, loads, tangents))
        return out

    monkeypatch.setattr(solver_mod, "run_increment", record)
    problem = Problem(parse_scene(_slipping_tunnel()), ["joints.set1.kn", "in_situ.k0"])
    problem.evaluate(problem.theta0, jacobian=True)
    model, state, loads, tangents = calls[-1]
    args = (model, state, loads, tangents["model"], tangents["state"], tangents["loads"])
    S = state.fs.size

    def tangents_and_active(share):
        forward, derivatives = substep_tangent(*args, active_share=share)
        return derivatives, forward[5].active  # the sub-step's contact snapshot

    (dstate, dsnap), active = jax.jit(lambda: tangents_and_active(ACTIVE_SHARE))()
    assert 0 < int(jnp.sum(active)) <= S // ACTIVE_SHARE  # the gathered path is the one taken
    (dstate_w, dsnap_w), _ = jax.jit(lambda: tangents_and_active(S + 1))()  # whole

    def close(x, y):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(y))))

    for k in dstate:
        close(dstate[k], dstate_w[k])
    assert float(jnp.max(jnp.abs(dstate["centroid"]))) > 0
    # The snapshot's forces everywhere; its points and normals where a slot is active
    # (elsewhere they carry no force, and the release masks them out).
    for k in SNAPSHOT_FLOATS:
        where = slice(None) if k in ("fn", "fs", "pw") else active
        close(getattr(dsnap, k)[:, where], getattr(dsnap_w, k)[:, where])


def test_uniform_in_situ_stress_derivatives_match_central_differences():
    d = jointed_tunnel(water=False, bolts=False, top="roller")
    d["in_situ"] = {"mode": "uniform", "sigma_xx": 600.0, "sigma_yy": 800.0, "sigma_xy": 50.0}
    d["materials"]["rock"]["unit_weight"] = 0.0
    problem = Problem(parse_scene(d), ["in_situ.sigma_xx", "in_situ.sigma_yy",
                                       "in_situ.sigma_xy"])
    _, J = problem.evaluate(problem.theta0, jacobian=True)
    assert problem.last["status"] == jaxdem.Status.CONVERGED
    for i in range(3):
        fd = _central_difference(problem, i, 1e-4)
        assert np.max(np.abs(J[:, i] - fd)) <= 1e-5 * np.max(np.abs(fd))


def roof_prism(alpha_deg=20.0, height=2.0, kn=1e6, ks=4e5, sigma_xx=500.0):
    """A symmetric roof prism (apex up, semi-apical angle alpha) between two fixed blocks,
    clamped by a horizontal stress; its weight is applied in a stage."""
    half = height * math.tan(math.radians(alpha_deg))
    apex, left, right = [0.0, height], [-half, 0.0], [half, 0.0]
    top = height + 3.0
    return {
        "scene": {"name": "roof prism"}, "solver": {"load_steps": 1},
        # Rigid rock: the joints are the only compliance of the closed form.
        "materials": {"rock": {"E": 1e13, "nu": 0.2, "unit_weight": 25.0}},
        "joints": {"j": {"kn": kn, "ks": ks, "friction_deg": 60.0, "cohesion": 100.0}},
        "blocks": [
            {"vertices": [[-10.0, 0.0], left, apex, [0.0, top], [-10.0, top]],
             "material": "rock", "fixed": True},
            {"vertices": [right, [10.0, 0.0], [10.0, top], [0.0, top], apex],
             "material": "rock", "fixed": True},
            {"vertices": [left, right, apex], "material": "rock"},
        ],
        "in_situ": {"mode": "uniform", "sigma_xx": sigma_xx, "sigma_yy": 0.0, "sigma_xy": 0.0},
        "stages": [{"name": "gravity"}],
        "monitors": [{"name": "prism", "point": [0.0, height / 3]}],
    }


@pytest.mark.parametrize("alpha_deg", [15.0, 30.0])
def test_roof_prism_sag_derivatives_match_bray(alpha_deg):
    """Brady & Brown, Rock Mechanics for Underground Mining, section 9.3 (after Bray):
    the elastic sag of a clamped roof prism is W / (2 (Ks cos^2 a + Kn sin^2 a)), with
    Kn = kn L, Ks = ks L the stiffnesses of a face of length L."""
    kn, ks, height = 1e6, 4e5, 2.0
    f, theta0 = jaxdem.differentiable(parse_scene(roof_prism(alpha_deg, height, kn, ks)),
                                      ["joints.j.kn", "joints.j.ks"])
    a = math.radians(alpha_deg)
    L = height / math.cos(a)
    W = 25.0 * height**2 * math.tan(a)
    den = 2 * L * (ks * math.cos(a) ** 2 + kn * math.sin(a) ** 2)
    sag = lambda th: -f(th)["prism"][1]  # noqa: E731
    assert float(sag(theta0)) == pytest.approx(W / den, rel=1e-4)
    grad = jax.grad(sag)(theta0)
    assert float(grad[0]) == pytest.approx(-W * 2 * L * math.sin(a) ** 2 / den**2, rel=1e-4)
    assert float(grad[1]) == pytest.approx(-W * 2 * L * math.cos(a) ** 2 / den**2, rel=1e-4)


def test_stack_settlement_derivative_matches_closed_form():
    """Settlement of a column of n blocks: sum_k W (n - k) / (k_eq,k width), with
    1 / k_eq = h1 / kn_i + h2 / kn_i + 1 / kn (paper eqs. 6-7), so
    d settlement / d kn = -sum_k W (n - k) / (width kn^2) over the joints."""
    n, kn = 3, 1e6
    f, theta0 = jaxdem.differentiable(parse_scene(stack(n, kn=kn)), ["joints.j.kn"])
    settle = lambda th: -f(th)["top"][1]  # noqa: E731
    kn_i, _ = intact_stiffness(1e7, 0.25)
    W = 25.0
    closed = sum(W * (n - k) / equivalent_stiffness(0.5, 0.5, 1 / kn_i, 1 / kn_i, 1 / kn)
                 for k in range(n))
    assert float(settle(theta0)) == pytest.approx(closed, rel=1e-4)
    d_closed = -sum(W * (n - k) / kn**2 for k in range(n))
    assert float(jax.grad(settle)(theta0)[0]) == pytest.approx(d_closed, rel=1e-4)


def test_jit_grad_and_vmap_compose():
    f, theta0 = jaxdem.differentiable(parse_scene(stack(2)), ["joints.j.kn", "materials.rock.E"])

    def loss(th):
        return (f(th)["top"][1] + 1e-4) ** 2

    scales = jnp.linspace(0.5, 2.0, 8)
    thetas = theta0[None, :] * jnp.stack([scales, scales[::-1]], axis=1)
    batched = jax.jit(jax.vmap(jax.grad(loss)))(thetas)
    single = jnp.stack([jax.grad(loss)(th) for th in thetas])
    np.testing.assert_allclose(batched, single, rtol=1e-12)
    # Forward and reverse mode agree.
    np.testing.assert_allclose(jax.jacfwd(loss)(theta0), jax.jacrev(loss)(theta0), rtol=1e-12)
    assert float(jax.jit(loss)(theta0)) == pytest.approx(float(loss(theta0)))


def test_no_equilibrium_gives_nan():
    from scenes import block_on_incline

    f, theta0 = jaxdem.differentiable(parse_scene(block_on_incline(30.0, 20.0)),
                                      ["joints.base.kn"])
    assert np.all(np.isnan(np.asarray(f(theta0)["block"])))


@pytest.mark.parametrize("path, problem", [
    ("joints.set9.kn", "no such parameter"),
    ("joints.j.spacing", "depends on smoothly"),
    ("solver.tolerance", "depends on smoothly"),
    ("blocks.1.vertices.0.0", "depends on smoothly"),
])
def test_parameters_that_are_not_smooth_are_refused(path, problem):
    with pytest.raises(SceneError, match=problem):
        jaxdem.differentiable(parse_scene(stack(2)), [path])


def test_deformable_cells_derivatives_follow_linear_elasticity():
    """Kirsch opening in deformable cells (bench_kirsch's scene, coarse). With no joints
    everything stiff scales with E (the cells, and the intact bonds' penalty springs), so
    the convergence is u = C / E and du/dE = -u / E; it is linear in the in-situ stress,
    u = sigma_xx du/dsigma_xx + sigma_yy du/dsigma_yy. Both hold up to the geometric
    nonlinearity of the large-displacement update, O(strain) = 1e-4 here. Against
    central differences of the solve (which include it) the derivatives agree to 1e-5."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_kirsch import scene as kirsch_scene

    problem = Problem(parse_scene(kirsch_scene(1.0, half_width=8.0)),
                      ["materials.rock.E", "materials.rock.nu", "in_situ.sigma_xx",
                       "in_situ.sigma_yy"])
    theta = problem.theta0
    y, J = problem.evaluate(theta, jacobian=True)
    assert problem.last["status"] == jaxdem.Status.CONVERGED and not problem.last["approximate"]
    np.testing.assert_allclose(J[:, 0], -y / theta[0], rtol=1e-3)
    np.testing.assert_allclose(J[:, 2] * theta[2] + J[:, 3] * theta[3], y, rtol=1e-3)
    for i in range(4):
        fd = _central_difference(problem, i, 1e-4)
        assert np.max(np.abs(J[:, i] - fd)) <= 1e-5 * np.max(np.abs(fd))
