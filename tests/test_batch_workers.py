"""Chunks of a batch solved by several threads at once (jaxdem.batch, ``workers``): the
answers of one chunk after another, row by row and bit for bit; each thread takes the
next chunk when it is free; every program compiled once; no hang."""

import collections
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from scenes import block_on_incline, jointed_tunnel

from jaxdem import batch
from jaxdem.batch import solve_batch
from jaxdem.core import compile_cache
from jaxdem.scene import SceneError, parse_scene

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ["joints.set2.friction_deg", "supports.0.pressure"]
# Newton iterations 12, 43, 12, 28, 8, 23: chunks of unequal cost, finished out of order.
THETA = np.array([[30.0, 100.0], [12.0, 0.0], [25.0, 50.0], [8.0, 0.0], [35.0, 150.0],
                  [20.0, 20.0]])


def sparse_tunnel_scene():
    """The small jointed tunnel on the sparse path, which solves one sample per chunk."""
    d = jointed_tunnel(spacing=3.5, top="roller")
    d["solver"]["linear_solver"] = "sparse"
    return parse_scene(d)


@pytest.fixture(scope="module")
def tunnel():
    return sparse_tunnel_scene()


def test_workers_give_the_sequential_answers_row_by_row(tunnel):
    """Two threads at once and one chunk after another: the same status, Newton
    iterations and monitors in every row, bit for bit (each sample is the same program
    on the same inputs, whichever thread runs it)."""
    one = solve_batch(tunnel, PARAMS, THETA, workers=1)
    two = solve_batch(tunnel, PARAMS, THETA, workers=2)
    assert one.timing["chunk"] == two.timing["chunk"] == 1
    assert (one.timing["workers"], two.timing["workers"]) == (1, 2)
    assert two.status == one.status and one.converged.all()
    np.testing.assert_array_equal(two.iterations, one.iterations)
    assert len(set(one.iterations.tolist())) > 3  # chunks of unequal cost
    for name, values in one.monitors.items():
        np.testing.assert_array_equal(two.monitors[name], values)
    np.testing.assert_array_equal(two.theta, THETA)


def test_mechanisms_land_in_their_rows():
    """Block on a 25 degree incline, one sample per chunk, three threads: a sample slides
    exactly where its friction is below the slope (tan(phi) = tan(alpha)), with the
    moving block and NaN monitors in its own row, as one chunk after another gives."""
    scene = parse_scene(block_on_incline(25.0, 30.0))
    phi = np.array([15.0, 40.0, 24.0, 30.0, 26.0, 10.0])
    one = solve_batch(scene, ["joints.base.friction_deg"], phi[:, None], chunk=1, workers=1)
    three = solve_batch(scene, ["joints.base.friction_deg"], phi[:, None], chunk=1,
                        workers=3)
    assert three.timing["workers"] == 3
    np.testing.assert_array_equal(three.stable, phi > 25.0)
    assert three.status == one.status
    assert three.moving_blocks == one.moving_blocks
    assert all(three.moving_blocks[i] for i in np.nonzero(phi < 25.0)[0])
    np.testing.assert_array_equal(three.monitors["block"], one.monitors["block"])
    assert np.isnan(three.monitors["block"][phi < 25.0]).all()


def test_progress_counts_every_sample_once(tunnel):
    calls = []
    solve_batch(tunnel, PARAMS, THETA, workers=2, progress=lambda d, n: calls.append((d, n)))
    assert calls == [(k, len(THETA)) for k in range(1, len(THETA) + 1)]


def test_a_free_thread_takes_the_next_chunk():
    """A slow first chunk (0.6 s) and five quick ones (0.1 s) on two threads: the second
    thread solves the quick ones meanwhile (0.6 s in all, not the 0.8 s of three chunks
    each); every chunk is solved once and handed back as it finishes."""
    durations = [0.6, 0.1, 0.1, 0.1, 0.1, 0.1]
    chunks = [np.array([i]) for i in range(len(durations))]
    threads = {}

    def solve(rows, ready=None):
        if ready is not None:
            ready.set()
        time.sleep(durations[rows[0]])
        threads[int(rows[0])] = threading.get_ident()
        return int(rows[0])

    t = time.perf_counter()
    order = list(batch._solved(solve, chunks, 2))
    elapsed = time.perf_counter() - t
    assert sorted(order) == list(range(len(durations)))
    assert order[-1] == 0  # the slow one, handed back last
    assert len(set(threads.values())) == 2
    assert elapsed < 0.75


def test_an_error_in_a_chunk_reaches_the_caller_and_stops_the_rest():
    started = []

    def solve(rows, ready=None):
        if ready is not None:
            ready.set()
        started.append(int(rows[0]))
        if rows[0] == 1:
            raise RuntimeError("chunk 1 failed")
        time.sleep(0.05)
        return int(rows[0])

    with pytest.raises(RuntimeError, match="chunk 1 failed"):
        list(batch._solved(solve, [np.array([i]) for i in range(40)], 2))
    assert len(started) < 40


def test_default_workers():
    """One per core (at most one per chunk) on one CPU device with chunks of one sample;
    one with larger chunks (batched LAPACK, see _worker_count) and on several devices."""
    cpu = jax.devices("cpu")[0]
    cores = os.cpu_count() or 1
    assert batch._worker_count(None, 1, 100, [cpu]) == cores
    assert batch._worker_count(None, 1, 1, [cpu]) == 1
    assert batch._worker_count(None, 4, 100, [cpu]) == 1
    assert batch._worker_count(None, 2, 100, [cpu, cpu]) == 1
    assert batch._worker_count(8, 1, 3, [cpu]) == 3


def test_unsafe_or_bad_workers_are_refused(tunnel):
    cpu = jax.devices("cpu")[0]
    theta = np.full((4, 2), 30.0)
    with pytest.raises(SceneError, match="workers: must be a whole number"):
        solve_batch(tunnel, PARAMS, theta, workers=0)
    with pytest.raises(SceneError, match="workers: 2 workers on a CPU solve chunks of one"):
        solve_batch(tunnel, PARAMS, theta, chunk=2, workers=2)
    with pytest.raises(SceneError, match="workers: must be 1 on 2 devices"):
        solve_batch(tunnel, PARAMS, theta, workers=2, devices=[cpu, cpu])
    # Several workers without a chunk take chunks of one sample, even on the dense path.
    scene = parse_scene(block_on_incline(25.0, 30.0))
    b = solve_batch(scene, ["joints.base.friction_deg"], np.full((4, 1), 30.0), workers=2)
    assert (b.timing["chunk"], b.timing["workers"]) == (1, 2)


_COMPILES: collections.Counter = collections.Counter()
_COUNTING = threading.Event()


def _count_compiles(event: str, duration: float, **kw) -> None:
    if _COUNTING.is_set() and event == "/jax/core/compile/backend_compile_duration":
        _COMPILES[kw.get("fun_name")] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compiles)


def test_every_program_is_compiled_once(tunnel, monkeypatch):
    """From empty in-memory caches, two threads compile (or load) exactly the programs one
    thread does: the increment once (compile_cache.compiled_program makes a second
    thread wait for the first), and JAX's small programs once each."""
    lowered = collections.Counter()
    lower = compile_cache._lower

    def counted(fn, *args):
        lowered[getattr(fn, "__name__", repr(fn))] += 1
        return lower(fn, *args)

    monkeypatch.setattr(compile_cache, "_lower", counted)

    def compiled(workers):
        jax.clear_caches()
        compile_cache._COMPILED.clear()
        batch._PREPARED.clear()
        batch._increment_fn.cache_clear()
        _COMPILES.clear()
        lowered.clear()
        _COUNTING.set()
        try:
            solve_batch(tunnel, PARAMS, THETA, workers=workers)
        finally:
            _COUNTING.clear()
        return collections.Counter(_COMPILES), collections.Counter(lowered)

    compiled(1)  # stores the programs on disk, as the runs below find them
    one, two = compiled(1), compiled(2)
    assert two == one
    assert all(n == 1 for n in one[1].values())


def test_threads_asking_for_one_program_compile_it_once(monkeypatch):
    """compile_cache.compiled_program from four threads at once: one traces and compiles,
    the others wait for it and get the same program."""
    calls = []
    lower = compile_cache._lower

    def counted(*args):
        calls.append(threading.get_ident())
        time.sleep(0.2)  # the other threads arrive while this one compiles
        return lower(*args)

    monkeypatch.setattr(compile_cache, "_lower", counted)
    fn = jax.jit(lambda x: (x * 2.0).sum())
    x = np.arange(5.0)
    got = []
    barrier = threading.Barrier(4)

    def ask():
        barrier.wait()
        got.append(compile_cache.compiled_program(fn, x)[0])

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len(got) == 4 and all(g is got[0] for g in got)


_HANG_CHECK = """
import sys, numpy as np
sys.path.insert(0, "tests")
import jaxdem
jaxdem.config.configure()
from jaxdem.batch import solve_batch
from jaxdem.scene import parse_scene
from scenes import block_on_incline
from test_batch_workers import PARAMS, THETA, sparse_tunnel_scene
tunnel = sparse_tunnel_scene()
incline = parse_scene(block_on_incline(25.0, 30.0))
phi = np.linspace(15.0, 40.0, 8)[:, None]
for _ in range(REPEATS):
    assert solve_batch(tunnel, PARAMS, THETA, workers=2).converged.all()
    solve_batch(incline, ["joints.base.friction_deg"], phi, chunk=1, workers=2)
print("done")
"""


def test_workers_do_not_hang():
    """Sparse (SuiteSparse) and dense (LAPACK LU, one matrix a call) factorisations in two
    threads at once, batch after batch: every run ends (a deadlock would time out)."""
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", _HANG_CHECK.replace("REPEATS", "6")],
                             capture_output=True, text=True, cwd=ROOT, timeout=300,
                             env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert out.returncode == 0, out.stderr[-3000:]
        assert out.stdout.strip().endswith("done")


def test_the_commands_refuse_workers_below_one(tmp_path, capsys):
    from jaxdem.cli import main

    for command in (["grc", str(ROOT / "jaxdem" / "data" / "demo.toml")],
                    ["sweep", str(ROOT / "examples" / "block_on_incline.toml"), "--vary",
                     "joints.base.kn=1e6:2e6", "--samples", "2"]):
        code = main([*command, "--workers", "0", "--out", str(tmp_path / command[0])])
        assert code == 2
        assert "--workers must be >= 1 (got 0)" in capsys.readouterr().err
