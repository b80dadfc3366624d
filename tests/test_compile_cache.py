"""The compiled-program registry's overlap of work with XLA compilation (jaxdem.core.compile_cache).

XLA compiles without Python's global interpreter lock. ``prefetch`` traces a
program on the caller's thread and compiles it on another; ``_compiled`` then
collects it instead of compiling it again. ``while_compiling`` runs host work
(the command line's matplotlib warm-up) while a program compiles.
"""

import dataclasses
import json
import random
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import block_on_incline, jointed_tunnel

import jaxdem
from jaxdem import solver
from jaxdem.core import _substep as substep
from jaxdem.core import compile_cache
from jaxdem.core.increment import increment, substeps_to_equilibrium
from jaxdem.scene import parse_scene


@pytest.fixture
def xla_compiles(monkeypatch):
    """Every XLA compilation made through the registry, as a list of thread names."""
    calls = []
    compile_ = compile_cache._xla_compile

    def counted(lowered, quick=False, salt=None):
        calls.append(threading.current_thread().name)
        return compile_(lowered, quick, salt)

    monkeypatch.setattr(compile_cache, "_xla_compile", counted)
    return calls


def test_a_prefetched_program_is_collected_not_compiled_again(xla_compiles):
    f = jax.jit(lambda x: 2.0 * x + 1.0)
    x = jnp.arange(7.0)  # a shape no other test compiles f for
    compile_cache._PENDING.clear()
    compile_cache.prefetch(f, x)
    compiled, _ = compile_cache.compiled_program(f, x)
    np.testing.assert_array_equal(np.asarray(compiled(x)), 2.0 * np.arange(7.0) + 1.0)
    again, waited = compile_cache.compiled_program(f, x)
    assert again is compiled and waited == 0.0
    assert len(xla_compiles) == 1 and xla_compiles[0].startswith("jaxdem-compile")
    assert not compile_cache._PENDING


def test_a_stored_program_is_loaded_beside_the_caller(xla_compiles, monkeypatch, tmp_path):
    """A prefetched program stored on disk is loaded on the background thread (XLA parses
    and links it without Python's lock: 0.5 s for the demo's increment, beside the
    in-situ preload), and collected without an XLA compilation."""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: tmp_path / "programs")
    f = compile_cache.on_disk("test-affine")(jax.jit(lambda x: 3.0 * x - 2.0))
    x = jnp.arange(9.0)
    compile_cache.compiled_program(f, x)
    assert len(xla_compiles) >= 1 and list((tmp_path / "programs").glob("*.pkl"))
    compile_cache._COMPILED.pop(compile_cache._key(f, (x,), {}, False)[0])
    xla_compiles.clear()
    loads = []
    load = compile_cache._load_program

    def counted(path):
        loads.append(threading.current_thread().name)
        return load(path)

    monkeypatch.setattr(compile_cache, "_load_program", counted)
    compile_cache.prefetch(f, x)
    compiled, _ = compile_cache.compiled_program(f, x)
    assert len(loads) == 1 and loads[0].startswith("jaxdem-compile") and not xla_compiles
    np.testing.assert_array_equal(np.asarray(compiled(x)), 3.0 * np.arange(9.0) - 2.0)


def test_a_warm_start_loads_the_last_runs_programs_before_they_are_asked_for(
        xla_compiles, monkeypatch, tmp_path):
    """``warm_start`` loads, on threads of its own, the stored programs that the last run
    with the same fingerprint used (``remember_run`` records them), before the scene is
    built; a program is taken by its key's file name alone: one of another run, or whose
    file is gone, is never taken for it."""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: tmp_path / "programs")
    for name, empty in (("_EARLY", {}), ("_USED", []), ("_SEEN", set()), ("_RUN", [])):
        monkeypatch.setattr(compile_cache, name, empty)
    f = compile_cache.on_disk("test-warm-f")(jax.jit(lambda x: 5.0 * x + 1.0))
    g = compile_cache.on_disk("test-warm-g")(jax.jit(lambda x: x * x))
    x = jnp.arange(11.0)
    compile_cache.warm_start("run-a")  # nothing recorded yet: nothing to load
    assert not compile_cache._EARLY
    compile_cache.compiled_program(f, x)
    compile_cache.remember_run()
    (f_file,) = (tmp_path / "programs").glob("*.pkl")
    compile_cache.warm_start("run-b")
    compile_cache.compiled_program(g, x)
    compile_cache.remember_run()
    g_file = next(p for p in (tmp_path / "programs").glob("*.pkl") if p != f_file)

    loads = []
    read = compile_cache._read_program

    def counted(path):
        loads.append((path.name, threading.current_thread().name))
        return read(path)

    monkeypatch.setattr(compile_cache, "_read_program", counted)
    for fn in (f, g):  # a new process: nothing compiled in memory
        compile_cache._COMPILED.pop(compile_cache._key(fn, (x,), {}, False)[0])
    compile_cache._SEEN.clear()
    xla_compiles.clear()
    compile_cache.warm_start("run-a")
    compile_cache._EARLY[f_file.name].result(timeout=60)
    assert loads == [(f_file.name, "jaxdem-warm-start")]
    compiled, _ = compile_cache.compiled_program(f, x)
    np.testing.assert_array_equal(np.asarray(compiled(x)), 5.0 * np.arange(11.0) + 1.0)
    assert not compile_cache._EARLY and not xla_compiles and len(loads) == 1

    # A program this process has asked for is in memory: not loaded early again.
    compile_cache.warm_start("run-a")
    assert not compile_cache._EARLY and len(loads) == 1

    # run-b's program, loaded early, is not f's: f's own file is loaded for f.
    compile_cache._COMPILED.pop(compile_cache._key(f, (x,), {}, False)[0])
    compile_cache._SEEN.clear()
    compile_cache.warm_start("run-b")
    compile_cache._EARLY[g_file.name].result(timeout=60)
    compiled, _ = compile_cache.compiled_program(f, x)
    np.testing.assert_array_equal(np.asarray(compiled(x)), 5.0 * np.arange(11.0) + 1.0)
    assert [name for name, _ in loads[1:]] == [g_file.name, f_file.name]
    assert list(compile_cache._EARLY) == [g_file.name] and not xla_compiles
    compile_cache.remember_run()  # the run's end lets go of it, and records f's alone
    assert not compile_cache._EARLY
    recent = json.loads((tmp_path / "programs" / "recent.json").read_text())
    assert list(recent.values()) == [[f_file.name], [f_file.name]]

    # Another version of jaxdem's source (a benchmark's baseline on the same cache) has
    # runs of its own.
    compile_cache._SEEN.clear()
    digest = compile_cache._source_digest
    monkeypatch.setattr(compile_cache, "_source_digest", lambda: "another version")
    compile_cache.warm_start("run-a")
    assert not compile_cache._EARLY
    monkeypatch.setattr(compile_cache, "_source_digest", digest)

    # A recorded program whose file is gone is not loaded; an unknown run loads nothing.
    compile_cache._SEEN.clear()
    f_file.unlink()
    compile_cache.warm_start("run-b")
    compile_cache.warm_start("run-c")
    assert not compile_cache._EARLY and len(loads) == 3


def test_a_prefetched_program_never_collected_is_let_go():
    """One program is prefetched at a time (the solver's prefetch is wasted when the preload
    grows the pair capacity): an older one is dropped, not held for the process's life."""
    f = jax.jit(lambda x: x - 1.0)
    compile_cache.prefetch(f, jnp.zeros(5))
    compile_cache.prefetch(f, jnp.zeros(6))
    assert len(compile_cache._PENDING) == 1
    compiled, _ = compile_cache.compiled_program(f, jnp.zeros(6))
    assert not compile_cache._PENDING
    np.testing.assert_array_equal(np.asarray(compiled(jnp.ones(6))), np.zeros(6))


def test_a_prefetch_that_fails_leaves_the_error_to_the_call_that_needs_it():
    @jax.jit
    def bad(x):
        raise ValueError("no program for this")

    x = jnp.zeros(3)
    compile_cache.prefetch(bad, x)  # nothing raised here
    with pytest.raises(ValueError, match="no program for this"):
        compile_cache.compiled_program(bad, x)


def test_host_work_runs_once_while_a_program_compiles(xla_compiles):
    ran = []
    done = threading.Event()

    def task():
        ran.append(threading.current_thread().name)
        done.set()

    compile_cache.while_compiling(task)
    f = jax.jit(lambda x: jnp.sin(x) * 3.0)
    compile_cache.compiled_program(f, jnp.zeros(11))
    assert done.wait(10.0)
    compile_cache.compiled_program(f, jnp.zeros(12))  # a second compilation: the task is spent
    assert ran == ["jaxdem-host-task"] and len(xla_compiles) == 2


def _hold_background_compiles(monkeypatch, seconds, events=None):
    """Every XLA compilation on the background thread takes ``seconds`` longer (a caller
    that needs its program has to wait for it); with ``events``, each compilation appends
    ("compile", its thread's name)."""
    import time

    compile_ = compile_cache._xla_compile

    def slow(lowered, quick=False, salt=None):
        name = threading.current_thread().name
        if name.startswith("jaxdem-compile"):
            time.sleep(seconds)
        if events is not None:
            events.append(("compile", name))
        return compile_(lowered, quick, salt)

    monkeypatch.setattr(compile_cache, "_xla_compile", slow)


def test_work_while_waiting_compiles_small_programs_that_run_stored_then_calls(monkeypatch):
    """``while_waiting``'s task runs on the thread that would wait for a prefetched program
    still compiling, before it waits; ``result_shapes`` gives the prefetched program's
    result shapes; a program ``precompile``d for shapes alone is the one ``run_stored``
    calls with arrays of those shapes (nothing compiled again)."""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: None)
    events = []
    _hold_background_compiles(monkeypatch, 0.5, events)  # the other core, still compiling
    big = jax.jit(lambda x: (jnp.cos(x), {"sum": jnp.sum(x)}))
    small = jax.jit(lambda y, s: s["sum"] + jnp.sum(y))
    x = jnp.arange(13.0)
    compile_cache._PENDING.clear()
    compile_cache.prefetch(big, x)
    out = compile_cache.result_shapes(big, x)
    assert out[0].shape == (13,) and out[1]["sum"].shape == ()
    assert compile_cache.result_shapes(big, jnp.arange(14.0)) is None  # never traced

    def task():
        events.append(("task", threading.current_thread().name))
        compile_cache.precompile(small, out[0], out[1])

    compile_cache.while_waiting(task)
    compiled, waited = compile_cache.compiled_program(big, x)
    assert waited > 0.0
    main = threading.current_thread().name
    assert events[:2] == [("task", main), ("compile", main)]  # before the big one came in
    assert events[2][1].startswith("jaxdem-compile")
    c, d = compiled(x)
    np.testing.assert_allclose(compile_cache.run_stored(small, c, d),
                               np.sum(np.cos(np.arange(13.0))) + np.sum(np.arange(13.0)))
    assert len(events) == 3  # run_stored compiled nothing
    compile_cache.compiled_program(big, jnp.arange(15.0))  # no prefetch, no wait: task spent
    assert [e[0] for e in events].count("task") == 1
    stale = []
    compile_cache.while_waiting(lambda: stale.append(1))
    compile_cache.prefetch(big, jnp.arange(16.0))  # a new prefetch drops the work before it
    compile_cache.compiled_program(big, jnp.arange(16.0))
    assert not stale


def test_a_cold_tunnel_solve_compiles_its_host_steps_while_the_increment_compiles(monkeypatch):
    """A cold single solve of an excavation with bolts compiles the programs of the removed
    blocks' forces and of the bolts' anchors on the main thread while the increment is
    still compiling on the other, not after it on the way to the answer. (This small
    scene's increment may compile before the preload does, on a busy machine: the
    background compilation is held up here, so that the main thread has to wait.)"""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: None)
    _hold_background_compiles(monkeypatch, 2.0)
    compile_cache._COMPILED.clear()
    compile_cache._SMALL.clear()
    compile_cache._PENDING.clear()
    compiler_ = compile_cache._compiler
    finished = []

    def recorded(fn, args, static, quick, path):
        finish = compiler_(fn, args, static, quick, path)

        def timed():
            compiled = finish()
            finished.append(getattr(fn, "__name__", ""))
            return compiled

        return timed

    monkeypatch.setattr(compile_cache, "_compiler", recorded)
    jax.clear_caches()
    result = jaxdem.solve(parse_scene(jointed_tunnel(water=False, bolts=True)))
    assert result.converged
    assert "release_forces" in finished and "bolt_geometry" in finished
    assert finished.index("release_forces") < finished.index("increment")
    assert finished.index("bolt_geometry") < finished.index("increment")


def _calls_in_trace(monkeypatch, name):
    """How often ``jaxdem.core._substep.<name>`` is called while the increment of a block on
    an incline is traced and lowered afresh."""
    calls = []
    fn = getattr(substep, name)

    def counted(*args, **kwargs):
        calls.append(1)
        return fn(*args, **kwargs)

    monkeypatch.setattr(substep, name, counted)
    jax.clear_caches()
    increment.lower(*_incline_increment())
    return len(calls)


def _incline_increment():
    """(model, state, loads) of the block on an incline's first increment, as the solver
    makes them."""
    return solver.increment_arguments(parse_scene(block_on_incline(30.0, 35.0)))


def test_increment_arguments_are_those_of_the_solvers_increment():
    """``solver.increment_arguments`` gives the program the arguments ``solve`` gives it: with
    one load step that increment is the whole solve, and run on them it moves the block on
    the incline as ``solve`` does (to round-off: the solver compiles the program with its own
    XLA options, this test with JAX's defaults)."""
    scene = parse_scene(block_on_incline(30.0, 35.0))
    model, state, loads = solver.increment_arguments(scene)
    new, info = increment(model, state, loads)
    assert solver.Status.of(info.status) == solver.Status.CONVERGED
    result = jaxdem.solve(scene)
    moved = np.asarray(new.centroid - state.centroid)
    for i, block in enumerate(result.blocks):
        np.testing.assert_allclose(moved[i], block["u"][:2], rtol=1e-9, atol=0.0)


def test_the_increment_traces_its_sub_step_once(monkeypatch):
    """The loop's carry shapes and its body share one trace of the sub-step (a second trace
    cost 0.1-0.2 s of every cold run)."""
    assert _calls_in_trace(monkeypatch, "prepare_substep") == 1


def test_the_newton_iteration_traces_its_body_once(monkeypatch):
    """The springs are evaluated in four places of the increment's program: the Newton
    iteration, its line search and the sub-step's final evaluation, in the iteration's
    law (which springs fail, event by event: the default ``solver.bond_failure``) and in
    the law's own (what is committed). JAX traced the iteration's body a second time
    when a weakly typed counter of its carry came back int32 (0.3 s of every cold run),
    and the line search had two evaluations."""
    assert _calls_in_trace(monkeypatch, "evaluate") == 4


def test_programs_are_compiled_without_source_locations():
    """XLA keeps the location of each operation in what it compiles and stores; they are
    dropped first (the stored program is a fifth smaller, and loads and compiles a few
    per cent faster)."""
    lowered = jax.jit(lambda x: jnp.sin(x) * 3.0).lower(jnp.zeros(3))
    assert "test_compile_cache.py" in lowered.as_text(debug_info=True)
    stripped = compile_cache._without_locations(lowered)
    assert "test_compile_cache.py" not in stripped.as_text(debug_info=True)
    np.testing.assert_allclose(stripped.compile()(jnp.ones(3)), 3.0 * np.sin(np.ones(3)))


def test_an_in_situ_solve_compiles_its_increment_beside_the_preload(xla_compiles, monkeypatch):
    """With in-situ stress the increment is compiled on the background thread while the
    preload compiles and runs, once, and the answer is the one the solver gives without it."""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: None)  # compile, do not load
    compile_cache._COMPILED.clear()
    d = jointed_tunnel(water=False, bolts=False)
    scene = parse_scene(d)
    assert scene.in_situ is not None
    compile_cache._PENDING.clear()
    result = jaxdem.solve(scene)
    assert result.converged
    assert not compile_cache._PENDING
    assert sum(name.startswith("jaxdem-compile") for name in xla_compiles) == 1
    compiles = len(xla_compiles)

    compile_cache._COMPILED.clear()
    monkeypatch.setattr(solver, "prefetch", lambda *args, **kwargs: 0.0)
    plain = jaxdem.solve(scene)
    assert all(not name.startswith("jaxdem-compile") for name in xla_compiles[compiles:])
    for name, m in result.monitors.items():
        for k, v in m.items():
            assert plain.monitors[name][k] == v, (name, k)


def test_a_prefetched_program_counts_in_the_bound_of_kept_programs(monkeypatch, tmp_path):
    """A program that ``prefetch`` loads from the disk store is kept under the same bound
    (MAX_COMPILED) as one that ``_compiled`` compiles; the time the prefetch took is returned
    (the solver counts it as compilation) and is 0.0 when the program was there."""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: tmp_path)
    monkeypatch.setattr(compile_cache, "MAX_COMPILED", 1)
    monkeypatch.setattr(compile_cache, "_COMPILED", type(compile_cache._COMPILED)())
    f = jax.jit(lambda x: x * x)
    compile_cache.on_disk("test_square")(f)
    try:
        x, y = jnp.zeros(13), jnp.zeros(14)
        compile_cache.compiled_program(f, x)  # compiled and stored
        compile_cache._COMPILED.clear()
        assert compile_cache.prefetch(f, y) > 0.0  # traced, compiles in the background
        compile_cache.compiled_program(f, y)
        assert compile_cache.prefetch(f, x) > 0.0  # loaded from the store
        assert len(compile_cache._COMPILED) == 1
        assert compile_cache.prefetch(f, x) == 0.0  # there already
    finally:
        compile_cache._ON_DISK.pop(f, None)


def _outer_loop(fn, *args):
    """The first ``while`` of ``fn``'s jaxpr: the increment's loop of sub-steps."""
    jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
    return next(e for e in jaxpr.eqns if e.primitive.name == "while")


def test_a_single_solve_skips_its_sub_steps_and_a_batch_ends_its_loop():
    """The loop of sub-steps: in a single solve a loop to ``max_substeps`` whose body is a
    cond that skips the sub-step once the increment has ended (XLA compiles it a third
    faster than a loop that ends on the outcome: BENCHMARKS.md, "Twenty-fourth session");
    in a batch (``model.lanes``, under vmap) a loop that ends when every member has ended
    (its predicate one flag per member, the loop going on while any is true): a cond on a
    member's status would become a select there, and every member would run all
    ``max_substeps`` sub-steps."""
    model, state, loads = _incline_increment()
    # The model an argument, as in the solver's programs (closed over, its max_substeps
    # would be a constant, and the loop a scan).
    single = _outer_loop(substeps_to_equilibrium, model, state, loads)
    body = [e.primitive.name for e in single.params["body_jaxpr"].jaxpr.eqns]
    assert "cond" in body
    assert single.params["cond_jaxpr"].out_avals[0].shape == ()  # a count of sub-steps

    lanes = dataclasses.replace(model, lanes="lanes")
    stack = lambda t: jax.tree.map(lambda x: x[None], t)  # noqa: E731
    batched = _outer_loop(jax.vmap(substeps_to_equilibrium, in_axes=(None, 0, 0),
                                   axis_name="lanes"), lanes, stack(state), stack(loads))
    assert batched.params["cond_jaxpr"].out_avals[0].shape == (1,)  # each member's status


def test_a_small_host_program_is_run_by_one_compilation_and_stored(xla_compiles, monkeypatch,
                                                                   tmp_path):
    """``run_stored`` gives the jitted function's answer, compiles it once for a shape (the
    next call, and one with other values, run that program), stores it on disk under its
    ``on_disk`` name, and a registry that has forgotten it loads it from there untraced.

    The program holds a constant of this run's own: JAX's persistent cache (shared by the
    runs of the suite on a machine) has never seen it, so that the compilation is not a hit
    there, which :func:`compile_cache._compiler` would answer with a second one that can be
    stored."""
    monkeypatch.setattr(compile_cache, "_program_dir", lambda: tmp_path)
    monkeypatch.setattr(compile_cache, "_SMALL", compile_cache.collections.OrderedDict())
    nonce = 1.0 + random.random()

    @compile_cache.on_disk("test_small_program")
    @jax.jit
    def f(x, k):
        return jnp.cumsum(x) * k * nonce

    x, two, three = jnp.arange(5.0), jnp.asarray(2.0), jnp.asarray(3.0)
    np.testing.assert_array_equal(compile_cache.run_stored(f, x, two), f(x, two))
    np.testing.assert_array_equal(compile_cache.run_stored(f, x + 1.0, three), f(x + 1.0, three))
    assert len(xla_compiles) == 1
    assert len(list(tmp_path.glob("*.pkl"))) == 1
    compile_cache._SMALL.clear()
    lowered = []
    monkeypatch.setattr(compile_cache, "_compiler", lambda *a: lowered.append(a))
    np.testing.assert_array_equal(compile_cache.run_stored(f, x, two), f(x, two))
    assert lowered == [] and len(xla_compiles) == 1


def test_a_warm_run_traces_no_program(tmp_path):
    """A second ``jaxdem demo`` (an excavation, bolts, monitors: every host step of a
    staged solve) loads every program it runs: the increment and the in-situ preload, and
    the small ones of the monitors' readings, the forces of the excavated blocks and the
    bolts' anchors (``run_stored``); the model's arrays go to the device without a
    program (``jnp.asarray`` of a host array compiles one). JAX's log of what it traces
    is empty."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "JAXDEM_CACHE_DIR": str(tmp_path / "cache")}
    code = (
        "import logging, sys\n"
        "import jax\n"
        "jax.config.update('jax_log_compiles', True)\n"
        "traced = []\n"
        "class H(logging.Handler):\n"
        "    def emit(self, r):\n"
        "        m = r.getMessage()\n"
        "        if m.startswith('Finished tracing'):\n"
        "            traced.append(m.split(' in ')[0])\n"
        "logging.getLogger('jax').addHandler(H())\n"
        "from jaxdem.cli import main\n"
        "assert main(['demo', '--no-figures', '--out', sys.argv[1]]) == 0\n"
        "print('TRACED', traced)\n")
    runs = [subprocess.run([sys.executable, "-c", code, str(tmp_path / f"out{k}")], env=env,
                           capture_output=True, text=True, check=True, timeout=600)
            for k in range(2)]
    first, second = (r.stdout.splitlines()[-1] for r in runs)
    assert "increment" in first  # the cold run traced its programs
    assert second == "TRACED []", second
