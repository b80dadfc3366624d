"""Batched solves (jaxdem.batch): the same answers as single solves, one compilation per
shape, capacities in buckets, sharding over devices, the persistent compilation cache."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scenes import block_on_incline, jointed_tunnel

import jaxdem
from jaxdem import batch
from jaxdem.batch import solve_batch
from jaxdem.core import compile_cache
from jaxdem.core.model import bucket
from jaxdem.differentiable import Problem
from jaxdem.scene import SceneError, parse_scene

ROOT = Path(__file__).resolve().parents[1]
TUNNEL_PARAMS = ["joints.set1.kn", "joints.set2.friction_deg", "in_situ.k0",
                 "bolts.0.stiffness", "supports.0.pressure"]


@pytest.fixture(scope="module")
def tunnel():
    return parse_scene(jointed_tunnel(spacing=3.5, top="roller"))


def test_batch_matches_single_solves(tunnel):
    """Each sample of a batch is the single solve with those parameters (jointed tunnel
    with slip, a bolt, a support and water), to the solver's round-off."""
    theta = np.array([[2.0e6, 30.0, 0.8, 5.0e4, 100.0],
                      [1.0e6, 22.0, 1.2, 1.0e5, 50.0],
                      [4.0e6, 38.0, 0.6, 2.0e4, 150.0]])
    batch = solve_batch(tunnel, TUNNEL_PARAMS, theta)
    assert batch.converged.all()
    for i, row in enumerate(theta):
        single = jaxdem.solve(tunnel, set=dict(zip(TUNNEL_PARAMS, row, strict=True)))
        assert single.status == batch.status[i]
        span = single.monitors["span"]["convergence"]
        assert batch.monitors["span"][i] == pytest.approx(span, rel=1e-8, abs=1e-12)
        crown = np.array(single.monitors["crown"]["displacement"])
        np.testing.assert_allclose(batch.monitors["crown"][i], crown, rtol=1e-8, atol=1e-12)
        assert batch.iterations[i] == sum(sum(s["iterations"]) for s in single.stages)


def test_samples_compile_once(tunnel):
    """A second batch of the same size with other values compiles nothing new."""
    rng = np.random.default_rng(3)
    theta = np.column_stack([rng.uniform(1e6, 4e6, 4), rng.uniform(25, 40, 4)])
    solve_batch(tunnel, TUNNEL_PARAMS[:2], theta, chunk=4)
    compiled = len(compile_cache._COMPILED)
    again = solve_batch(tunnel, TUNNEL_PARAMS[:2], theta[::-1] * [1.1, 0.95], chunk=4)
    assert len(compile_cache._COMPILED) == compiled
    assert again.timing["compile_s"] == 0.0


def test_back_analysis_iterations_compile_once(tunnel):
    """The first solve with sensitivities and the first plain solve compile their
    programs; the iterations after them, at other values, compile nothing."""
    problem = Problem(tunnel, ["joints.set1.kn", "joints.set1.ks"])
    problem.evaluate(problem.theta0 * 1.1, jacobian=True)
    problem.evaluate(problem.theta0 * 1.2)
    compiled = len(compile_cache._COMPILED)
    problem.evaluate(problem.theta0 * 0.8, jacobian=True)
    problem.evaluate(problem.theta0 * 1.3)
    assert len(compile_cache._COMPILED) == compiled


def test_failed_samples_are_held_and_reported():
    """Block on a 25 degree incline: a sample slides (a mechanism) exactly when its joint
    friction is below the slope (limit equilibrium, tan(phi) = tan(alpha)); the others
    rest, and a chunk that is padded (5 samples, chunk 4) gives the same answers."""
    scene = parse_scene(block_on_incline(25.0, 30.0))
    phi = np.array([15.0, 24.0, 26.0, 30.0, 40.0])
    batch = solve_batch(scene, ["joints.base.friction_deg"], phi[:, None], chunk=4)
    np.testing.assert_array_equal(batch.stable, phi > 25.0)
    assert batch.status == ["mechanism", "mechanism", "converged", "converged", "converged"]
    assert np.isnan(batch.monitors["block"][:2]).all()
    assert np.isfinite(batch.monitors["block"][2:]).all()
    whole = solve_batch(scene, ["joints.base.friction_deg"], phi[:, None], chunk=8)
    np.testing.assert_allclose(whole.monitors["block"][2:], batch.monitors["block"][2:],
                               rtol=1e-12)


def test_each_failed_sample_says_where_it_stopped():
    """The block on a 25 degree incline, its weight applied in 4 load steps: a joint with
    phi < 25 degrees cannot hold any share of the weight (limit equilibrium does not
    depend on it), so those samples slide in the first increment, at load factor 1/4, as
    the single solve reports; the samples that hold have no stop."""
    scene = parse_scene(block_on_incline(25.0, 30.0, load_steps=4))
    phi = np.array([15.0, 40.0, 20.0])
    batch = solve_batch(scene, ["joints.base.friction_deg"], phi[:, None], chunk=2)
    assert batch.status == ["mechanism", "converged", "mechanism"]
    assert batch.stopped == [{"stage": "loading", "load_factor": 0.25}, None,
                             {"stage": "loading", "load_factor": 0.25}]
    single = jaxdem.solve(scene, set={"joints.base.friction_deg": 15.0})
    last = single.stages[-1]
    assert (last["name"], last["load_factor"][-1]) == ("loading", 0.25)


def test_bad_batch_input_is_refused(tunnel):
    with pytest.raises(SceneError, match="theta"):
        solve_batch(tunnel, ["joints.set1.kn"], np.array([[1e6], [np.nan]]))
    with pytest.raises(SceneError, match="theta"):
        solve_batch(tunnel, ["joints.set1.kn"], np.ones((3, 2)))
    with pytest.raises(SceneError, match="no samples"):
        solve_batch(tunnel, ["joints.set1.kn"], np.ones((0, 1)))
    with pytest.raises(SceneError, match="joints.nope.kn"):
        solve_batch(tunnel, ["joints.nope.kn"], np.ones((3, 1)))
    with pytest.raises(SceneError, match="smoothly"):
        solve_batch(tunnel, ["joints.set1.spacing"], np.ones((3, 1)))


@given(st.integers(1, 10**7))
def test_capacity_buckets(n):
    """Buckets hold n with at most 50% head-room, and are few: 2^k or 3 x 2^(k-1)."""
    b = bucket(n)
    assert n <= b <= max(2, 1.5 * n)
    k = b.bit_length() - 1
    assert b == 1 << k or b == 3 << (k - 1)
    assert bucket(b) == b


def _python(code: str, env: dict) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, **env}, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_sweep_samples_shard_over_devices():
    """With four (forced host) devices each chunk is split over all four, and the answers
    are those of one device."""
    code = """
import json, jax, numpy as np, jaxdem
from jaxdem.batch import solve_batch
from jaxdem.scene import parse_scene
import sys; sys.path.insert(0, "tests")
from scenes import block_on_incline
scene = parse_scene(block_on_incline(25.0, 30.0))
theta = np.linspace(20.0, 35.0, 8)[:, None]
four = solve_batch(scene, ["joints.base.friction_deg"], theta)
one = solve_batch(scene, ["joints.base.friction_deg"], theta, devices=jax.devices()[:1])
print(json.dumps(dict(n=len(jax.devices()), four=four.timing["devices"], chunk=four.timing["chunk"],
                      one=one.timing["devices"], stable=[bool(s) for s in four.stable],
                      same=bool(np.array_equal(four.stable, one.stable)),
                      diff=float(np.nanmax(np.abs(four.monitors["block"]
                                                  - one.monitors["block"]))))))
"""
    res = json.loads(_python(code, {"XLA_FLAGS": "--xla_force_host_platform_device_count=4",
                                    "JAXDEM_COMPILATION_CACHE": "0"}).splitlines()[-1])
    assert res["n"] == 4 and res["four"] == 4 and res["one"] == 1
    assert res["chunk"] == 4  # one sample per CPU device (batch._one_per_device)
    assert res["same"] and res["stable"] == [False] * 3 + [True] * 5
    assert res["diff"] <= 1e-12


def test_several_cpu_devices_take_one_sample_each():
    """On several CPU devices each takes one sample at a time, and a larger chunk is
    refused before any work: jaxlib's batched LAPACK kernels on several CPU devices at
    once can deadlock (batch._one_per_device). One device keeps its cache-sized chunk."""
    scene = parse_scene(block_on_incline(25.0, 30.0))
    model, state = batch._prepared(scene, ("joints.base.friction_deg",))[:2]  # as a batch builds it
    assert model.linear_solver == "dense"
    cpu = jax.devices("cpu")[0]
    assert batch._chunk_size(model, state, 64, [cpu, cpu]) == 1
    assert batch._chunk_size(model, state, 64, [cpu]) > 1
    with pytest.raises(SceneError, match="chunk: at most one sample per device"):
        solve_batch(scene, ["joints.base.friction_deg"], np.full((8, 1), 30.0), chunk=4,
                    devices=[cpu, cpu])


def test_persistent_compilation_cache(tmp_path):
    """A second ``jaxdem run`` of a scene loads its compiled increment from the cache
    instead of tracing and compiling it, and gives the same answer bitwise;
    JAXDEM_COMPILATION_CACHE=0 writes no cache. The increment is stored as a
    serialised program (``programs/`` in the cache), so neither its XLA
    compilation nor its tracing and lowering run again: both are read from the
    phases the command line records ($JAXDEM_PHASES)."""
    scene = ROOT / "examples" / "block_on_incline.toml"

    def run(out, env):
        phases = out.parent / f"{out.name}-phases.json"
        subprocess.run([sys.executable, "-m", "jaxdem", "run", str(scene), "--out", str(out),
                        "--no-figures"], check=True, capture_output=True,
                       env={**os.environ, **env, "JAXDEM_PHASES": str(phases)}, cwd=ROOT,
                       timeout=600)
        result = json.loads((out / "result.json").read_text())
        result.pop("timing")
        return json.loads(phases.read_text())["increment"], result

    off = tmp_path / "off"
    run(tmp_path / "r0", {"JAXDEM_CACHE_DIR": str(off), "JAXDEM_COMPILATION_CACHE": "0"})
    assert not off.exists() or not any(off.iterdir())
    cache = tmp_path / "cache"
    first, answer = run(tmp_path / "r1", {"JAXDEM_CACHE_DIR": str(cache)})
    assert any((cache / "programs").iterdir())
    second, again = run(tmp_path / "r2", {"JAXDEM_CACHE_DIR": str(cache)})
    # What the store replaces (tracing and compiling) against what it costs (a load).
    total = lambda t: t["lower_s"] + t["compile_s"]  # noqa: E731
    assert total(second) < 0.3 * total(first), (first, second)
    assert second["lower_s"] == 0.0 < first["lower_s"], (first, second)
    assert again == answer
    # A program that JAX loads from its own cache cannot be stored (its copy would
    # lack its kernels and fail when called): with its stored copy gone, the next run
    # traces it and compiles it afresh (JAX's copy is not used), stores it, and
    # answers the same; the run after loads it again.
    shutil.rmtree(cache / "programs")
    third, answer3 = run(tmp_path / "r3", {"JAXDEM_CACHE_DIR": str(cache)})
    assert third["lower_s"] > 0.0 and any((cache / "programs").iterdir())
    fourth, answer4 = run(tmp_path / "r4", {"JAXDEM_CACHE_DIR": str(cache)})
    assert fourth["lower_s"] == 0.0, fourth
    assert answer3 == answer4 == answer


def test_a_program_jax_has_cached_under_its_text_is_stored_for_a_new_source(tmp_path):
    """A change of the jaxdem source gives every stored program a new key, while a program
    the change does not touch lowers to the same text. JAX's persistent cache, keyed on
    that text, must not serve it: its executable could not be stored, and every later run
    would trace and lower it again (1.6-2.2 s of a warm run before this was found). Each
    stored program is compiled under a salt of its own key, so after the change the
    program is compiled afresh and stored once more, and the run after loads it; all
    three answer the same. (The source digest is replaced in each process.)"""
    scene = ROOT / "examples" / "block_on_incline.toml"
    code = (
        "import json, sys\n"
        "import jaxdem\n"
        "jaxdem.config.configure()\n"
        "from jaxdem.core import compile_cache\n"
        "compile_cache._source_digest = lambda: sys.argv[1]\n"
        "r = jaxdem.solve(jaxdem.load_scene(sys.argv[2]))\n"
        "print(json.dumps([compile_cache.COMPILE_TIMES['lower_s'], r.monitors]))\n")

    def run(digest):
        out = subprocess.run([sys.executable, "-c", code, digest, str(scene)], check=True,
                             capture_output=True, text=True, cwd=ROOT, timeout=600,
                             env={**os.environ, "JAXDEM_CACHE_DIR": str(tmp_path)})
        lower_s, monitors = json.loads(out.stdout.strip().splitlines()[-1])
        return lower_s, monitors, len(list((tmp_path / "programs").glob("*.pkl")))

    lower1, answer1, stored1 = run("source one")
    lower2, answer2, stored2 = run("source two")
    lower3, answer3, stored3 = run("source two")
    assert lower1 > 0.0 and lower2 > 0.0 and lower3 == 0.0, (lower1, lower2, lower3)
    assert stored2 > stored1 == stored3 - (stored2 - stored1) and stored3 == stored2
    assert answer1 == answer2 == answer3


def test_a_sample_that_finds_a_mechanism_names_its_moving_blocks_as_a_single_run():
    """A block on a 30 degree incline slides where its joint's friction is below 30
    degrees (tan(phi) < tan(30): no equilibrium) and rests above: the sliding sample names
    the block, as a single run of the same scene does, and the resting one names none."""
    scene = parse_scene(block_on_incline(30.0, 35.0))
    out = solve_batch(scene, ["joints.base.friction_deg"], [[35.0], [20.0]])
    single = jaxdem.solve(scene, set={"joints.base.friction_deg": 20.0})
    assert out.status == ["converged", "mechanism"] and single.status == "mechanism"
    assert out.moving_blocks == [[], list(single.moving_blocks)] == [[], [1]]


def test_a_stored_program_is_found_only_for_its_own_key():
    """The stored programs' key holds what decides a program without tracing it: the
    argument tree with its static fields (here the linear solver), the shapes, the
    static arguments and the XLA options. A change of any gives another file."""
    from jaxdem.core import compile_cache

    x = {"a": jnp.zeros(3)}
    leaves, tree = jax.tree.flatten(x)
    keys = {compile_cache._disk_key("f", tree, leaves, {}, {}),
            compile_cache._disk_key("g", tree, leaves, {}, {}),
            compile_cache._disk_key("f", jax.tree.flatten({"b": jnp.zeros(3)})[1], leaves, {}, {}),
            compile_cache._disk_key("f", tree, [jnp.zeros(4)], {}, {}),
            compile_cache._disk_key("f", tree, [jnp.zeros(3, jnp.int32)], {}, {}),
            compile_cache._disk_key("f", tree, leaves, {"mode": "gravity"}, {}),
            compile_cache._disk_key("f", tree, leaves, {}, {"xla_backend_optimization_level": 0})}
    assert len(keys) == 7
    assert compile_cache._disk_key("f", tree, leaves, {}, {}) in keys  # and it is stable


def test_float32_batch_matches_float64(tunnel):
    """A float32 batch (solver.dtype) gives the float64 convergences to 1e-3: the span
    closes by about 0.7 mm, and float32 carries about 1e-7 of the coordinates (9 m),
    amplified by the iteration's conditioning."""
    d = jointed_tunnel(spacing=3.5, top="roller")
    d["solver"]["dtype"] = "float32"
    theta = np.array([[2e6, 30.0], [1e6, 25.0], [3e6, 38.0]])
    single = solve_batch(parse_scene(d), TUNNEL_PARAMS[:2], theta)
    double = solve_batch(tunnel, TUNNEL_PARAMS[:2], theta)
    assert single.converged.all() and double.converged.all()
    np.testing.assert_allclose(single.monitors["span"], double.monitors["span"], rtol=1e-3)


def test_a_chunk_on_the_sparse_path_solves_each_sample_with_its_own_contacts():
    """Four samples in one chunk on the sparse path (KLU inside the program), the
    loose-roof tunnel (tests/data/loose_roof_tunnel.toml, 183 blocks) at four cohesions of
    its two joint sets: their contacts, so the sparsity patterns of their matrices,
    differ once bonds fail. Each sample is its single solve: the same status, loose blocks
    removed and Newton iterations, the span's convergence to 1e-9. sparsax's own vmap rule
    solves a batch with the first member's pattern: three of these samples were
    mechanisms (two in the initial state) where their single solves converge. (Without
    sparsax, SciPy's solve on the host takes the samples one by one: the same check.)"""
    scene = jaxdem.load_scene(ROOT / "tests" / "data" / "loose_roof_tunnel.toml",
                              set={"domain.min_block_area": 0.0, "joints.smooth.cohesion": 500.0,
                                   "solver.linear_solver": "sparse"})
    params = ["joints.set1.cohesion", "joints.set2.cohesion"]
    theta = np.array([[0.0, 0.0], [0.0, 500.0], [500.0, 0.0], [500.0, 500.0]])
    b = solve_batch(scene, params, theta, chunk=4)
    assert b.timing["chunk"] == 4
    for i, row in enumerate(theta):
        single = jaxdem.solve(scene, set=dict(zip(params, row, strict=True)))
        assert (b.status[i], single.status) == ("converged", "converged")
        assert b.loose_blocks[i] == [x["id"] for x in single.loose_blocks]
        assert b.iterations[i] == sum(sum(s["iterations"]) for s in single.stages)
        assert b.monitors["span"][i] == pytest.approx(single.monitors["span"]["convergence"],
                                                      rel=1e-9)


def test_a_held_samples_report_is_padded_where_the_contacts_places_grew():
    """A sample that sits out a stage's rerun (loose blocks elsewhere in its chunk) keeps
    its last report; where the rerun grew the contacts' places, that report's per-slot
    arrays are padded with zeros (inactive slots) to the new size, the others' taken as
    they come (``jaxdem.batch._lanes_where``)."""
    held = {"active": jnp.ones((2, 3), bool), "fn": jnp.full((2, 3), 5.0), "k": jnp.ones(2)}
    new = {"active": jnp.zeros((2, 5), bool), "fn": jnp.full((2, 5), 7.0), "k": jnp.zeros(2)}
    out = batch._lanes_where(jnp.array([True, False]), held, new)
    np.testing.assert_array_equal(out["active"], [[1, 1, 1, 0, 0], [0, 0, 0, 0, 0]])
    np.testing.assert_array_equal(out["fn"], [[5, 5, 5, 0, 0], [7, 7, 7, 7, 7]])
    np.testing.assert_array_equal(out["k"], [1, 0])


def test_threads_that_free_sparse_factorisations_do_not_disturb_each_other():
    """Two threads solve samples one at a time on the sparse path (CHOLMOD, and KLU where
    the slip tangent is taken), and each frees sparsax's patterns and
    factors after every increment, while the other may be between two of its solves:
    every sample is still its single solve (to round-off), and nothing is left in
    sparsax's cache."""
    sparsax = pytest.importorskip("sparsax")
    d = jointed_tunnel(water=False, bolts=False)
    d["solver"] = {**d.get("solver", {}), "linear_solver": "sparse"}
    scene = parse_scene(d)
    params = ["joints.set1.kn", "joints.set2.friction_deg"]
    theta = np.array([[2.0e6, 30.0], [1.0e6, 22.0], [4.0e6, 38.0], [3.0e6, 26.0]])
    before = sparsax.factorization_count()
    batch = solve_batch(scene, params, theta, chunk=1, workers=2)
    assert sparsax.factorization_count() > before
    assert sparsax.cache_size() == 0
    assert batch.converged.all()
    for i, row in enumerate(theta):
        single = jaxdem.solve(scene, set=dict(zip(params, row, strict=True)))
        crown = np.array(single.monitors["crown"]["displacement"])
        np.testing.assert_allclose(batch.monitors["crown"][i], crown, rtol=1e-8, atol=1e-12)
