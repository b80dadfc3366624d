"""Batched solves: one scene, many parameter sets, solved together with ``jax.vmap``.

A scene is built once; each sample changes only parameters that leave the
block geometry alone (joint and rock properties, in-situ stress, bolts,
supports, water: the parameters of :mod:`jaxdem.differentiable`). The samples
then share every array shape, so one compiled increment serves them all: the
host loop over stages and load steps is the single solve's
(:func:`jaxdem.solver.run`), and each increment advances every sample at once.

A sample that fails (a mechanism, the iteration limit) is held where it
stopped and skipped from then on; the others go on. Samples are solved in
chunks sized to fit memory, padded so that every chunk has the same shape
(one compilation), and, with several devices, each chunk is split over them
with ``jax.shard_map`` so that each device iterates its own part to
convergence without waiting for the others.

On one CPU device, chunks of one sample (the sparse path's) are solved by a
few threads at once (``workers``, one per core by default), each taking the
next chunk when it has finished one: XLA runs each program on a thread of its
own, without Python's lock, so the cores share the samples, and a slow sample
(hundreds of Newton iterations near a mechanism) holds up only its own thread.
The answers are those of one chunk after another, bit for bit.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import functools
import os
import threading
import time
import types

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from jaxdem.config import float64
from jaxdem.core import model as model_mod
from jaxdem.core.compile_cache import QUICK_WORK, compiled_program, on_disk
from jaxdem.core.increment import bounded_factorisations, substeps_to_equilibrium
from jaxdem.core.loads import in_situ_preload, release_forces
from jaxdem.core.state import Loads, grow_capacity
from jaxdem.core.status import Status
from jaxdem.differentiable import ParameterMap, monitor_readings
from jaxdem.results import is_small, loose_limit, mechanism_volume, moving_blocks
from jaxdem.scene import SceneError, apply_overrides
from jaxdem.solver import Data, falling_free, increment_count, run, scene_data

SAMPLE_AXIS = "samples"


@dataclasses.dataclass
class BatchResult:
    """Outcome of a batch of solves of one scene.

    Attributes:
      params: the parameter paths, in the column order of ``theta``.
      theta: (S, p) parameter values of each sample (file units).
      monitors: monitor name -> (S,) convergence of a section or (S, 2)
        displacement [ux, uy] of a point (m), at the end of the last stage;
        NaN where the sample found no equilibrium.
      status: (S,) :class:`jaxdem.core.status.Status` labels of each sample's last increment.
      stable: (S,) bool, no mechanism was found.
      converged: (S,) bool, every increment reached equilibrium.
      iterations: (S,) Newton iterations of each sample, summed over increments.
      moving_blocks: (S,) lists: where a sample found a mechanism, the blocks that kept
        moving (:func:`jaxdem.results.moving_blocks`, as ``Result.moving_blocks``); else [].
      moving_volume: (S,) the moving blocks' area together (m3 per m of tunnel;
        :func:`jaxdem.results.mechanism_volume`), 0.0 where a sample found no mechanism.
      small_mechanism: (S,) bool, a sample's mechanism is small: its moving blocks
        together no larger than ``solver.max_loose_volume`` or its default
        (:func:`jaxdem.results.is_small`): pieces working loose, not a collapse
        (docs/results.md, "A small mechanism").
      loose_blocks: (S,) lists: the blocks each sample removed as loose (README, "Loose
        blocks"), as ``Result.loose_blocks``' ids; [] where none fell.
      stopped: (S,) where a sample without an answer stopped: ``{"stage": name,
        "load_factor": f}``, the stage ("loading", "initial" or the file's stage name)
        and the fraction of its load at the increment that failed (as ``Result.stages``'
        ``load_factor``); None for a sample that converged.
      timing: ``build_s``, ``compile_s``, ``solve_s`` (s: wall time; ``solve_s`` is
        the time from the first chunk's start to the last one's end, less
        ``compile_s``, the longest any worker waited for programs); ``chunk``
        (samples per batch), ``devices`` (the devices the samples were spread over)
        and ``workers`` (chunks solved at the same time).
    """

    params: list
    theta: np.ndarray
    monitors: dict
    status: list
    stable: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    timing: dict
    moving_blocks: list = dataclasses.field(default_factory=list)
    stopped: list = dataclasses.field(default_factory=list)
    moving_volume: np.ndarray | None = None
    small_mechanism: np.ndarray | None = None
    loose_blocks: list | None = None

    def __post_init__(self):
        S = len(self.status)
        if self.moving_volume is None:
            self.moving_volume = np.zeros(S)
        if self.small_mechanism is None:
            self.small_mechanism = np.zeros(S, bool)
        if self.loose_blocks is None:
            self.loose_blocks = [[] for _ in range(S)]


@float64
def solve_batch(scene, params, theta, *, chunk: int | None = None, devices=None,
                workers: int | None = None, progress=None) -> BatchResult:
    """Solve ``scene`` at each row of ``theta`` (values of ``params``), batched.

    Args:
      scene: a validated scene.
      params: parameter paths that leave the geometry alone: those of
        :func:`jaxdem.differentiable` and the strengths (a path that changes
        the blocks or the array shapes raises a SceneError saying so).
      theta: (S, p) values, file units (friction in degrees).
      chunk: samples solved together, a multiple of the number of devices;
        default: on a CPU a few (what stays in cache, see :func:`_chunk_size`),
        one with the sparse path or several workers; on a GPU as many as fit in
        memory (at most 1,024 per device). On several CPU devices one per device,
        and no more is accepted (:func:`_one_per_device`).
      devices: devices to shard each chunk over (default: all local devices
        of the default backend).
      workers: chunks solved at the same time, each by its own thread, which takes
        the next chunk when it has finished one (:func:`_worker_count`). Default:
        on one CPU device with chunks of one sample, one per core
        (``os.cpu_count()``, at most one per chunk); else 1. On a CPU more than one
        needs chunks of one sample (a larger ``chunk`` is refused); on several
        devices it must be 1.
      progress: optional callable, called after each chunk with
        (samples done, samples in all).
    Returns:
      a :class:`BatchResult`.
    """
    params = [params] if isinstance(params, str) else list(params)
    theta = np.asarray(theta, float)
    if theta.ndim != 2 or theta.shape[1] != len(params):
        raise SceneError("theta", f"must be (samples, {len(params)}); got {theta.shape}")
    if not np.all(np.isfinite(theta)):
        raise SceneError("theta", "holds a NaN or infinite value")
    if theta.shape[0] == 0:
        raise SceneError("theta", "has no samples")
    for path in params:
        try:
            apply_overrides(scene.data, {path: 0.0})
        except SceneError as err:
            raise SceneError(path, err.problem) from None
    devices = list(devices) if devices is not None else jax.local_devices()
    n_dev = len(devices)
    if chunk is not None and _one_per_device(devices) and chunk > n_dev:
        raise SceneError("chunk", f"at most one sample per device on {n_dev} CPU devices "
                         f"(got {chunk}): batched LAPACK calls on several CPU devices at once "
                         f"can deadlock in jaxlib (see README, 'Several devices')")
    _check_workers(workers, chunk, devices)
    t0 = time.perf_counter()
    prepared = _prepared(scene, tuple(params))
    model, state, layout = prepared[:3]
    S = theta.shape[0]
    # A small batch runs briefly: its program compiled quick (jaxdem.core.compile_cache).
    quick = model.n_blocks * increment_count(scene, layout) * S <= QUICK_WORK
    if workers not in (None, 1) and devices[0].platform == "cpu":
        per_device = 1  # several workers on a CPU: unbatched factorisations (_worker_count)
    else:
        per_device = _chunk_size(model, state, -(-S // n_dev), devices)
    size = chunk if chunk is not None else per_device * n_dev
    size = max(n_dev, -(-min(size, max(S, 1)) // n_dev) * n_dev)
    chunks = [np.arange(start, min(start + size, S)) for start in range(0, S, size)]
    workers = _worker_count(workers, size, len(chunks), devices)
    build_s = time.perf_counter() - t0

    def solve(rows, ready=None):
        return _solve_chunk(scene, prepared, theta, rows, size, devices, quick, ready)

    out_mon: dict = {}
    status = np.zeros(S, int)
    iterations = np.zeros(S, int)
    moving: list = [[] for _ in range(S)]
    loose: list = [[] for _ in range(S)]
    stopped: list = [None] * S
    compile_by_thread: collections.Counter = collections.Counter()
    placed = done = 0
    t1 = time.perf_counter()
    for c in _solved(solve, chunks, workers):
        rows = c["rows"]
        status[rows] = c["status"]
        iterations[rows] = c["iterations"]
        for i, row in enumerate(rows):
            moving[row] = c["moving"][i]
            loose[row] = c["loose"][i]
            stopped[row] = c["stopped"][i]
        for name, v in c["monitors"].items():
            out_mon.setdefault(name, np.full((S,) + v.shape[1:], np.nan))[rows] = v
        compile_by_thread[c["thread"]] += c["compile_s"]
        placed = max(placed, c["devices"])
        done += len(rows)
        if progress is not None:
            progress(done, S)
    # Wall time: the workers compile (or wait for a program) at the same time.
    compile_s = max(compile_by_thread.values())
    solve_s = time.perf_counter() - t1 - compile_s
    ok = status == Status.CONVERGED.code
    for v in out_mon.values():
        v[~ok] = np.nan
    area = np.asarray(model.area)[:layout.n_rock]
    volume = np.array([mechanism_volume(m, area) for m in moving])
    small_limit = loose_limit(scene)
    small = np.array([is_small(m, area, small_limit) for m in moving], bool)
    return BatchResult(
        params=params, theta=theta, monitors=out_mon,
        status=[Status.of(s).label for s in status], stable=status != Status.MECHANISM.code,
        converged=ok, iterations=iterations,
        timing=dict(build_s=build_s, compile_s=compile_s, solve_s=solve_s, chunk=size,
                    devices=placed, workers=workers), moving_blocks=moving, stopped=stopped,
        moving_volume=volume, small_mechanism=small, loose_blocks=loose)


def _solve_chunk(scene, prepared, theta, rows, size: int, devices, quick: bool,
                 ready=None) -> dict:
    """Solve the samples ``rows`` of ``theta`` as one chunk of ``size`` (padded).

    Returns their ``status``, ``iterations``, ``moving`` blocks, where they ``stopped``
    and ``monitors`` (name -> values in the rows' order), and the chunk's ``compile_s``, the
    ``devices`` it was placed on and the ``thread`` that solved it. ``ready``, if
    given, is set once the chunk's programs are in hand (:class:`_BatchDriver`).
    """
    model, state, layout, data0, values, read = prepared
    try:
        # Pad the last chunk with copies of its last sample: one shape, one compilation.
        take = np.concatenate([rows, np.full(size - len(rows), rows[-1])])
        fields, arrays = values(jnp.asarray(theta[take], jnp.float64))
        data = _batch_data(data0, arrays, size)
        cast = {k: jnp.asarray(v, model.radius.dtype) for k, v in fields.items()}
        d = _BatchDriver(model, cast, state, layout, data, devices, quick, ready)
        run(scene, model, state, layout, data, driver=d)
    finally:
        if ready is not None:
            ready.set()
    n = len(rows)
    keys = ("centroid", "rot", "strain")
    now = {k: getattr(d.state, k) for k in keys}
    ref = None if d.ref is None else {k: getattr(d.ref, k) for k in keys}
    monitors = {}
    for name, v in read(now, ref).items():
        v = np.asarray(v, float)[:n]
        monitors[name] = v[:, 0] if layout.monitors[name]["kind"] == "section" else v
    return dict(rows=rows, status=d.status_of[:n], iterations=d.iterations[:n],
                moving=d.moving[:n], loose=d.loose[:n], stopped=d.stopped[:n], monitors=monitors,
                compile_s=d.compile_s, devices=len(d.state.verts.sharding.device_set),
                thread=threading.get_ident())


def _solved(solve, chunks: list, workers: int):
    """``solve(rows)`` of each chunk, yielded as each is done: in turn on this thread,
    or by ``workers`` threads at once, each taking the next chunk when it has finished
    one (a chunk near a mechanism takes ten times the Newton iterations of another, so
    a fixed share would leave threads waiting for the slowest).

    The first chunk starts alone, and the others once its increment's program is
    compiled (or loaded): that program, and JAX's small programs of the array
    operations every chunk runs before it, are compiled once, not by each thread.
    """
    if workers == 1:
        for rows in chunks:
            yield solve(rows)
        return
    pool = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="jaxdem-batch")
    try:
        ready = threading.Event()
        first = pool.submit(float64(solve), chunks[0], ready)
        while not ready.wait(0.05) and not first.done():
            pass
        pending = [first] + [pool.submit(float64(solve), rows) for rows in chunks[1:]]
        for future in concurrent.futures.as_completed(pending):
            yield future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _check_workers(workers, chunk, devices) -> None:
    """Refuse a ``workers`` that is not a whole number >= 1, or that would solve chunks
    at the same time where that is not safe (:func:`_worker_count`)."""
    if workers is None:
        return
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise SceneError("workers", f"must be a whole number >= 1 (got {workers!r})")
    if workers == 1:
        return
    if len(devices) > 1:
        raise SceneError("workers", f"must be 1 on {len(devices)} devices: each chunk is "
                         "split over them (see README, 'Several devices')")
    if devices[0].platform == "cpu" and chunk is not None and chunk > 1:
        raise SceneError("workers", f"{workers} workers on a CPU solve chunks of one sample "
                         f"(got chunk {chunk}): batched LAPACK calls from several threads at "
                         "once can deadlock in jaxlib (see README, 'Several devices')")


def _worker_count(workers, size: int, n_chunks: int, devices) -> int:
    """Threads that solve chunks at the same time (``workers``; None: the default).

    On one CPU device with chunks of one sample, one per core by default: XLA runs
    each program on its own thread of its CPU pool, without Python's lock, so the
    programs of several chunks run at the same time (sparsax runs SuiteSparse's
    numeric factorisations one at a time, under its own lock; the rest of an
    increment, contacts, assembly and line search, runs in parallel). The demo
    tunnel's 16-level curve (487 blocks) solved in 0.61-0.74 of the time of one
    chunk after another with two workers on a 2-core CPU (1.85 cores busy against
    1.45: XLA already runs independent parts of one program side by side). Chunks
    of one sample keep every factorisation unbatched: jaxlib 0.10.2's batched
    LAPACK kernels wait on XLA's CPU thread pool, which concurrent programs share
    (the deadlock of :func:`_one_per_device`). Elsewhere one: on a GPU a chunk
    already fills the device, and several devices share each chunk.
    """
    if workers is None:
        one_cpu = len(devices) == 1 and devices[0].platform == "cpu"
        workers = (os.cpu_count() or 1) if one_cpu and size == 1 else 1
    return int(max(1, min(workers, n_chunks)))


_PREPARED: collections.OrderedDict = collections.OrderedDict()


def _prepared(scene, params: tuple):
    """The built scene and its jitted parameter map and monitor readings, kept for the
    next batch of the same scene and parameters (the rounds of a factor-of-safety
    search, repeated sweeps): no rebuilding, no retracing."""
    key = (id(scene), params)
    hit = _PREPARED.get(key)
    if hit is not None and hit[0] is scene:
        _PREPARED.move_to_end(key)
        return hit[1:]
    model, state, layout = model_mod.build(scene)
    # A batch on a CPU takes the dense LU up to 600 unknowns, where a single solve takes
    # the sparse path (linear_solver_for).
    unknowns = layout.n_rock * model.ndof
    model = dataclasses.replace(model, linear_solver=model_mod.linear_solver_for(
        scene.solver.linear_solver, unknowns, batch=True))
    data0 = scene_data(scene, layout)
    pmap = ParameterMap(scene, model, layout, data0, list(params))
    values = jax.jit(jax.vmap(pmap._values))
    read = jax.jit(jax.vmap(functools.partial(monitor_readings, layout)))
    _PREPARED[key] = (scene, model, state, layout, data0, values, read)
    while len(_PREPARED) > 4:
        _PREPARED.popitem(last=False)
    return model, state, layout, data0, values, read


def _batch_data(data0: Data, arrays: dict, size: int) -> Data:
    """The driver's Data with every stack over the samples of a chunk."""
    np_ = lambda x: np.asarray(x, float)  # noqa: E731
    tile = lambda x: np.broadcast_to(np_(x[0]), (size,) + np_(x[0]).shape).copy()  # noqa: E731
    return dataclasses.replace(
        data0, weight=np_(arrays["weight"]), traction=tile(data0.traction),
        supports=[np_(arrays[f"support{i}"]) for i in range(len(data0.supports))],
        sigma=np_(arrays["sigma"]), k0=np_(arrays["k0"]), gamma=np_(arrays["gamma"]),
        surface=np_(arrays["surface"]), water_y=np_(arrays["water_y"]),
        stage_water={k: np_(arrays[f"water:{k}"]) for k in data0.stage_water}, dmodel=None)


def _chunk_size(model, state, S: int, devices) -> int:
    """Samples per chunk (per device).

    On a CPU, few: a chunk whose arrays stay in cache (about 8 MB: the state's
    arrays and the dense matrix of each sample) is solved fastest per sample.
    Measured on a 2-core CPU with the 59-block test tunnel (0.5 MB a sample):
    19 ms a sample in chunks of 4, 21 in 8, 39 in 16, 42 in 64; with the
    52-block benchmark tunnel at pair capacity 256 (0.4 MB a sample): 11.4 ms
    in chunks of 10, 10.1 in 16, 32 and 64 (BENCHMARKS.md, "Throughput").
    On a CPU with the sparse path, one: its factorisations run one member after
    another inside the native call anyway, and members in a chunk go in lockstep, so
    every one pays the Newton iterations and sub-steps of the slowest (the levels of
    a ground reaction curve near a mechanism take hundreds, the others tens). The
    demo tunnel's 16-level curve took 40.5 s in chunks of 1, 62 s in 5, 86 s in 2
    and 243 s in 8 (BENCHMARKS.md, "Ground reaction curve"). Chunks of one sample
    are solved several at a time, by ``workers`` threads (:func:`_worker_count`).
    On a GPU, many: as many as fit in a quarter
    of its free memory (the state and its copies inside an increment, and the
    dense matrix and its factor), at most 1,024.
    """
    if _one_per_device(devices):
        return 1
    n = model.n_blocks * model.ndof
    itemsize = state.verts.dtype.itemsize
    state_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(state))
    matrix_bytes = n * n * itemsize if model.linear_solver == "dense" else 0
    if devices[0].platform == "cpu":
        if model.linear_solver == "sparse":
            return 1
        return int(max(1, min(16, S, 8e6 // (state_bytes + matrix_bytes))))
    per = 16 * state_bytes + 4 * matrix_bytes
    return int(max(1, min(1024, S, 0.25 * _free_memory(devices[0]) // per)))


def _one_per_device(devices) -> bool:
    """Whether each device must take one sample at a time: several CPU devices.

    jaxlib 0.10.2's CPU LAPACK kernels (Cholesky, LU) hand each matrix of a
    batch of more than one to XLA's CPU thread pool and block until it is
    done. All CPU devices share that pool (as many threads as cores); with
    several devices running at once every pool thread can block so, and the
    work they wait for is never run: a deadlock, reproduced with JAX alone
    (a vmapped while-loop of two Cholesky factorisations on two forced host
    devices hangs in about half the runs). One sample per device keeps every
    factorisation unbatched. A single device, or a GPU, is not affected.
    """
    return len(devices) > 1 and devices[0].platform == "cpu"


def _free_memory(device) -> float:
    """Bytes the device can still give (GPU: its allocator's limit; CPU: available RAM)."""
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    if stats and "bytes_limit" in stats:
        return float(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 4e9


# ---------------------------------------------------------------------------
# Batched kernels (one sample per vmap lane; fields = the sample's model fields)

LANES = "lanes"
"""The vmap axis of the samples (``Model.lanes``): Newton's step is skipped once no lane
needs it."""


def _member_increment(model, fields, state, loads, skip):
    return substeps_to_equilibrium(dataclasses.replace(model, lanes=LANES, **fields), state, loads,
                                   skip=skip)


def _increment_lanes(model, fields, state, loads, skip):
    return jax.vmap(_member_increment, in_axes=(None, 0, 0, 0, 0), axis_name=LANES)(
        model, fields, state, loads, skip)


@functools.lru_cache(maxsize=8)
def _increment_fn(devices: tuple):
    """The jitted batched increment, sharded over ``devices`` when there are several.

    With shard_map each device runs its own while-loop over its own samples,
    so a slow sample holds back only the samples on its device.
    """
    if len(devices) == 1:
        return on_disk("batch_increment")(jax.jit(_increment_lanes))
    mesh = Mesh(np.array(devices), (SAMPLE_AXIS,))
    lanes = PartitionSpec(SAMPLE_AXIS)
    sharded = jax.shard_map(_increment_lanes, mesh=mesh,
                            in_specs=(PartitionSpec(), lanes, lanes, lanes, lanes),
                            out_specs=lanes, check_vma=False)
    return jax.jit(sharded)


@on_disk("batch_preload")
@functools.partial(jax.jit, static_argnames=("mode",))
def _preload_lanes(model, fields, state, loads, args, mode):
    def one(fl, st, ld, a):
        return in_situ_preload(dataclasses.replace(model, **fl), st, ld, *a, mode=mode)

    return jax.vmap(one)(fields, state, loads, args)


@functools.partial(jax.jit, static_argnames=("ndof",))
def _release_lanes(centroid, snap, removed, ndof):
    # ``removed``: (N,) the same blocks for every sample, or (C, N) each sample's own.
    removed = jnp.broadcast_to(removed, centroid.shape[:1] + removed.shape[-1:])
    return jax.vmap(lambda c, s, r: release_forces(c, s, r, ndof))(centroid, snap, removed)


@jax.jit
def _lanes_where(mask, a, b):
    """The pytree ``a`` on the lanes (samples) where ``mask`` (C,), ``b`` on the others.
    A leaf of ``a`` smaller than ``b``'s (a report's contacts, whose places grew in
    between) is padded with zeros: inactive contacts."""
    def pick(x, y):
        x = jnp.pad(x, [(0, m - s) for s, m in zip(x.shape, y.shape, strict=True)])
        return jnp.where(mask.reshape((-1,) + (1,) * (y.ndim - 1)), x, y)

    return jax.tree.map(pick, a, b)


def _grow(state, capacity: int):
    return jax.vmap(functools.partial(grow_capacity, capacity=capacity))(state)


class _BatchDriver:
    """The host loop's driver (see :func:`jaxdem.solver.run`) for a chunk of samples.

    It has the single-solve driver's interface; ``status`` is CONVERGED while
    any sample is still going, so the loop runs until every sample has finished
    or failed. Each sample's own outcome is in ``status_of``. ``ready`` (a
    threading.Event), if given, is set once the increment's program is in hand.

    Loose blocks (README, "Loose blocks") as a single solve removes them: where a
    sample's stage ends in a mechanism of small blocks falling free, that sample runs the
    stage again from its start without them (:meth:`again`); the others keep their end of
    the stage and sit the rerun out (``held``: skipped by the batched program, as a
    sample that failed is, but still going). ``loose`` holds each sample's removed
    blocks.
    """

    def __init__(self, model, fields, state, layout, data: Data, devices, quick=False,
                 ready=None):
        C = data.weight.shape[0]
        self.C, self.devices, self.quick, self.ready = C, tuple(devices), quick, ready
        self.model, self.fields, self.layout, self.data = model, fields, layout, data
        self.state = jax.tree.map(lambda x: jnp.broadcast_to(x, (C,) + x.shape), state)
        self.status_of = np.full(C, Status.CONVERGED.code)
        self.live = np.ones(C, bool)
        self.iterations = np.zeros(C, int)
        self.moving: list = [[] for _ in range(C)]  # each sample's mechanism, where it found one
        self.loose: list = [[] for _ in range(C)]  # each sample's blocks removed as loose
        self.found_in: list = [None] * C  # (travel, snapshot) of each sample's mechanism
        self.started = np.ones(C, bool)  # the samples that run the current stage
        self.held = np.zeros(C, bool)  # the samples that sit out a stage's rerun (again)
        # Their end of the stage, (mask, state, info), for step to put back: the state
        # once, at the rerun's first increment (then None), the report at each.
        self.kept = None
        self.stopped: list = [None] * C  # where each sample that failed stopped
        self.ref = self.dref = self.dstate = self.info = None
        self.records: list = []
        self.bolt_active = np.zeros(model.n_bolts, bool)
        self.water_y = data.water_y
        self.compile_s = self.solve_s = 0.0
        self.approximate = False
        if C % len(devices) == 0 and len(devices) > 1:
            sharding = jax.sharding.NamedSharding(Mesh(np.array(devices), (SAMPLE_AXIS,)),
                                                  PartitionSpec(SAMPLE_AXIS))
            self.fields = jax.device_put(fields, sharding)
            self.state = jax.device_put(self.state, sharding)

    @property
    def status(self) -> Status:
        if self.live.any():
            return Status.CONVERGED
        return Status.of(self.status_of.max())

    def loads(self, force, water_y=None, water_scale=1.0):
        wy = self.water_y if water_y is None else water_y
        C, dtype = self.C, self.model.radius.dtype
        xs = jnp.asarray(self.data.water_x, dtype)
        loads = Loads(force=jnp.asarray(force, dtype),
                      water_x=jnp.broadcast_to(xs, (C,) + xs.shape),
                      water_y=jnp.asarray(wy, dtype), water_scale=jnp.full(C, water_scale, dtype),
                      bolt_active=jnp.broadcast_to(jnp.asarray(self.bolt_active),
                                                   (C, self.model.n_bolts)))
        return loads, None

    def step(self, stage, k, n, loads, released=None):
        loads = loads[0]
        fn_jit = _increment_fn(self.devices)
        if self.kept is not None and self.kept[1] is not None:
            # The rerun's first increment: the samples that sit it out are back where their
            # stage ended (the stage's loads, released forces included, were worked out
            # from its start, as for every sample); skipped, they stay there.
            keep, end_state, end_info = self.kept
            self.state = _lanes_where(keep, end_state, self.state)
            self.kept = (keep, None, end_info)
        running = self.live & ~self.held
        while True:
            skip = jnp.asarray(~running)
            t1 = time.perf_counter()
            fn, dt = compiled_program(fn_jit, self.model, self.fields, self.state, loads, skip,
                                      quick=self.quick)
            if self.ready is not None:
                self.ready.set()
            with bounded_factorisations():  # sparsax's memory, up to the program's result
                new, info = fn(self.model, self.fields, self.state, loads, skip)
                status = np.asarray(info.status)
            self.compile_s += dt
            self.solve_s += time.perf_counter() - t1 - dt
            over = (status == Status.CAPACITY_OVERFLOW.code) & running
            if not over.any():
                break
            self.model = model_mod.grown(self.model,
                                         bool(np.asarray(info.cell_full)[over].any()),
                                         bool(np.asarray(info.slots_full)[over].any()),
                                         int(np.asarray(info.touch_needed)[over].max()))
            need = int(np.asarray(info.pairs_needed)[over].max())
            cap = self.state.capacity
            if need > cap:
                self.state = _grow(self.state, model_mod.bucket(max(2 * cap, need)))
        if self.kept is not None:
            # A skipped sample's report holds nothing: theirs is the stage's last.
            info = _lanes_where(self.kept[0], self.kept[2], info)
        self.state, self.info = new, info
        self.iterations += np.where(running, np.asarray(info.iterations), 0)
        found = np.nonzero(running & (status == Status.MECHANISM.code))[0]
        if found.size:
            travel = np.asarray(info.travel)
            limit = np.broadcast_to(np.asarray(self.fields.get(
                "max_displacement", self.model.max_displacement), float), (self.C,))
            for c in found:
                self.moving[c] = moving_blocks(travel[c, :self.layout.n_rock], float(limit[c]))
                # What free_falling reads once the stage is done (the sample's later
                # increments are skipped, and their reports hold nothing of it): its
                # contacts' blocks and states alone, in small types.
                snap = info.snapshot
                self.found_in[c] = (travel[c], types.SimpleNamespace(
                    a=np.asarray(snap.a[c], np.int32), b=np.asarray(snap.b[c], np.int32),
                    active=np.asarray(snap.active[c]), state=np.asarray(snap.state[c], np.int8)))
        for c in np.nonzero(running & (status != Status.CONVERGED.code))[0]:
            self.stopped[c] = dict(stage=stage, load_factor=k / n)
        self.status_of = np.where(running, status, self.status_of)
        self.live &= self.held | (status == Status.CONVERGED.code)
        self.records.append(dict(stage=stage, step=k, load_factor=k / n,
                                 live=int(self.live.sum()),
                                 **({} if released is None else dict(released=released))))
        return bool((self.live & ~self.held).any())

    def no_loose(self) -> np.ndarray:
        return np.zeros((self.C, self.model.n_blocks), bool)

    def checkpoint(self) -> dict:
        """The samples' state at the start of a stage, to run it again (:meth:`again`)."""
        self.started = self.live.copy()  # the samples that run this stage
        self.held[:], self.kept = False, None
        return dict(state=self.state, info=self.info, live=self.live.copy(),
                    status_of=self.status_of.copy(), iterations=self.iterations.copy(),
                    moving=list(self.moving), stopped=list(self.stopped),
                    bolt_active=self.bolt_active.copy(), records=len(self.records))

    def again(self, saved: dict, found) -> None:
        """Back to the stage's :meth:`checkpoint` ``saved`` for the samples whose loose blocks
        were ``found`` ((C, N) masks), which :func:`jaxdem.solver.run` then removes and runs
        the stage again for (the model keeps any capacity grown since). The other samples
        keep where the stage ended (their state, report, outcome and iterations) and sit the
        rerun out: ``held`` where still going (they go on with the next stage), skipped
        either way, so a rerun costs what the samples that run it cost."""
        keep = ~np.asarray(found).any(axis=1)

        def pick(end, start):  # per sample: its end of the stage where kept, else the start
            if isinstance(end, np.ndarray):
                return np.where(keep, end, start)
            return [e if k else s for e, s, k in zip(end, start, keep, strict=True)]

        self.held = keep & self.live
        self.kept = (jnp.asarray(keep), self.state, self.info)
        self.live = pick(self.live, saved["live"])
        self.status_of = pick(self.status_of, saved["status_of"])
        self.iterations = pick(self.iterations, saved["iterations"])
        self.moving = pick(self.moving, saved["moving"])
        self.stopped = pick(self.stopped, saved["stopped"])
        self.found_in = pick(self.found_in, [None] * self.C)
        self.state, self.info = saved["state"], saved["info"]
        if self.state.capacity < self.kept[1].capacity:  # grown in the stage
            self.state = _grow(self.state, self.kept[1].capacity)
        self.bolt_active = saved["bolt_active"].copy()
        del self.records[saved["records"]:]

    def record_loose(self, found, stage: str) -> None:
        for c, row in enumerate(np.asarray(found)):
            self.loose[c] += [int(i) for i in np.nonzero(row)[0]]

    def free_falling(self, limit: float):
        """The (C, N) masks of each sample's blocks falling free (as the single solve's
        :func:`jaxdem.solver.falling_free`) where its stage ended in a mechanism, else
        None."""
        out = self.no_loose()
        mechanism = self.started & (self.status_of == Status.MECHANISM.code)
        for c in np.nonzero(mechanism)[0]:
            if self.found_in[c] is None:
                continue
            travel, snap = self.found_in[c]
            mask = falling_free(self.model, self.layout, travel, snap,
                                np.asarray(self.state.alive[c]), limit)
            if mask is not None:
                out[c] = mask
        return out if out.any() else None

    def release(self, removed):
        N, D = self.model.n_blocks, self.model.ndof
        if not removed.any() or self.info is None:
            return np.zeros((self.C, N, D))
        return np.asarray(_release_lanes(self.state.centroid, self.info.snapshot,
                                         jnp.asarray(removed), D))

    def preload(self, scene, base):
        data, dtype = self.data, self.model.radius.dtype
        args = tuple(jnp.asarray(x, dtype) for x in (data.sigma, data.surface, data.gamma,
                                                     data.k0))
        loads, _ = self.loads(base)
        while True:
            # Run once a chunk: compiled quick, as the single solve's.
            fn, dt = compiled_program(_preload_lanes, self.model, self.fields, self.state,
                                      loads, args, mode=scene.in_situ.mode, quick=True)
            self.compile_s += dt
            st, overflow = fn(self.model, self.fields, self.state, loads, args)
            if not bool(np.asarray(overflow).any()):
                break
            # Pairs, or the detection's places (as the solver's preload): grow both.
            self.state = _grow(self.state, model_mod.bucket(2 * self.state.capacity))
            self.model = model_mod.grown(self.model, True, False)
        self.state = st


__all__ = ["BatchResult", "solve_batch"]
