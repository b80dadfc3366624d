"""Linear solver paths: the iterative path against the direct ones, the automatic choice."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import jointed_tunnel, stack

import jaxdem
from jaxdem.core import model as model_mod
from jaxdem.core._linsolve import compact_terms, solve_cg, solve_dense
from jaxdem.core._springs import evaluate, stiffness_terms
from jaxdem.core._substep import prepare_substep
from jaxdem.core.increment import increment
from jaxdem.core.loads import make_loads
from jaxdem.core.status import Status
from jaxdem.scene import parse_scene


def _with_solver(d, **kw):
    d = dict(d)
    d["solver"] = {**d.get("solver", {}), **kw}
    return d


@pytest.fixture(scope="module")
def tunnel_solutions():
    """The small jointed tunnel (two joint sets, in-situ stress, excavation, bolt, water,
    support pressure) solved with each linear solver."""
    out = {}
    for name in ("dense", "sparse", "cg"):
        r = jaxdem.solve(parse_scene(_with_solver(jointed_tunnel(), linear_solver=name)))
        assert r.converged, (name, r.status)
        out[name] = np.array([b["u"] for b in r.blocks])
    return out


@pytest.mark.parametrize("direct", ["dense", "sparse"])
def test_iterative_path_agrees_with_direct_solves(tunnel_solutions, direct):
    """CG with the inexact-Newton forcing term reaches the same equilibrium to 1e-7."""
    u_cg, u_ref = tunnel_solutions["cg"], tunnel_solutions[direct]
    scale = np.abs(u_ref[:, :2]).max()
    assert scale > 0
    np.testing.assert_allclose(u_cg[:, :2], u_ref[:, :2], rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose(u_cg[:, 2], u_ref[:, 2], rtol=0,
                               atol=1e-7 * np.abs(u_ref[:, 2]).max())


def test_iterative_path_vmaps():
    """The matrix-free path has no host callback: a batch of load factors under vmap."""
    model, state, _ = model_mod.build(parse_scene(_with_solver(stack(3), linear_solver="cg")))
    assert model.linear_solver == "cg"
    lams = jnp.array([0.5, 1.0])
    batch = jax.vmap(lambda lam: make_loads(model, lam * model.f_ext))(lams)
    states, info = jax.vmap(increment, in_axes=(None, None, 0))(model, state, batch)
    assert (np.asarray(info["status"]) == Status.CONVERGED.code).all()
    dense = dataclasses.replace(model, linear_solver="dense")
    for k, lam in enumerate(lams):
        s1, _ = increment(dense, state, make_loads(model, lam * model.f_ext))
        scale = np.abs(np.asarray(s1.u)).max()
        np.testing.assert_allclose(np.asarray(states.u[k]), np.asarray(s1.u), rtol=0,
                                   atol=1e-7 * scale)


def test_pcg_and_compaction_match_a_dense_solve():
    """The packed rank-one terms and PCG give (K + eps M)^-1 R of the assembled matrix."""
    model, state, _ = model_mod.build(parse_scene(stack(4)))
    loads = make_loads(model, model.f_ext)
    mdl, sub, st0, _, _ = prepare_substep(model, state, loads)
    ev = evaluate(mdl, sub, jnp.zeros_like(loads.force), jnp.zeros_like(st0, bool), st0,
                          st0, 0.0)
    terms = stiffness_terms(mdl, sub, ev, False)
    packed = compact_terms(mdl, terms)
    assert packed[3].shape[0] < terms[3].shape[0]
    assert np.isclose(np.sum(np.abs(packed[3])), np.sum(np.abs(terms[3])))
    x_cg = solve_cg(mdl, sub, terms, ev["R"], 1e-12)
    a, b, B, k = terms
    x_dense = solve_dense(mdl, sub, (a, b, B, B, k), ev["R"])
    np.testing.assert_allclose(np.asarray(x_cg), np.asarray(x_dense), rtol=0,
                               atol=1e-9 * np.abs(np.asarray(x_dense)).max())


@pytest.mark.parametrize("unknowns, platform, expected", [
    (300, "cpu", "dense"), (600, "cpu", "dense"), (603, "cpu", "sparse"),
    (1800, "cpu", "sparse"), (6000, "cpu", "sparse"), (6003, "cpu", "sparse"),
    (31_392, "cpu", "sparse"), (1800, "gpu", "dense"),
    (1803, "gpu", "cg"), (31_392, "tpu", "cg"),
])
def test_auto_rule(unknowns, platform, expected):
    """"auto": dense up to 600 unknowns on a CPU (1,800 on an accelerator); above, sparse
    direct on a CPU; matrix-free CG on an accelerator (README, Solver)."""
    assert model_mod.linear_solver_for("auto", unknowns, platform=platform) == expected


@pytest.mark.parametrize("unknowns, platform, expected", [
    (600, "cpu", "dense"), (603, "cpu", "sparse"), (31_392, "cpu", "sparse"),
    (1803, "gpu", "cg"),
])
def test_auto_rule_for_a_batch(unknowns, platform, expected):
    """A batch on a CPU takes sparse direct from 600 unknowns on (members factorised one
    after another, finished ones skipped)."""
    assert model_mod.linear_solver_for("auto", unknowns, platform=platform,
                                       batch=True) == expected


@pytest.mark.parametrize("choice", ["dense", "sparse", "cg"])
def test_explicit_choice_is_kept(choice):
    for unknowns, platform in [(30, "cpu"), (50_000, "gpu")]:
        assert model_mod.linear_solver_for(choice, unknowns, platform=platform) == choice


def test_scene_setting_reaches_the_model(monkeypatch):
    scene = stack(3)
    assert model_mod.build(parse_scene(scene))[0].linear_solver == "dense"
    for choice in ("sparse", "cg", "dense"):
        m = model_mod.build(parse_scene(_with_solver(scene, linear_solver=choice)))[0]
        assert m.linear_solver == choice
    # A "large" scene: lower the dense limit below this one's 9 unknowns.
    monkeypatch.setattr(model_mod, "_DENSE_UP_TO", 6)
    monkeypatch.setattr(model_mod, "_DENSE_UP_TO_ACCELERATOR", 6)
    large = parse_scene(scene)
    expected = "sparse" if jax.default_backend() == "cpu" else "cg"
    assert model_mod.build(large)[0].linear_solver == expected
