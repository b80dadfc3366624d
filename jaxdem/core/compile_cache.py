"""Compiled programs kept per shape: the registry, its bound, compile times, XLA options,
and the programs stored on disk.

Owns :func:`compiled_program` (a jitted function compiled once per argument shapes
and static settings, least recently used dropped beyond :data:`MAX_COMPILED`),
:data:`COMPILE_TIMES` and :data:`CPU_COMPILER_OPTIONS`. Keys are the jitted
function objects themselves, so a program is found again wherever its
function lives.

Programs stored on disk (:func:`on_disk`): JAX's persistent compilation cache
keys a program on its lowered text, so a warm run still traces and lowers
it (0.7-1.6 s of a 2-3 s run). A function named with :func:`on_disk` is also
kept as a serialised executable in ``programs/`` of the compilation cache
directory, under a key made of everything that decides the program without
tracing it: the source of the jaxdem package, the JAX and jaxlib versions, the
backend, device and processor, the x64 flag, the argument tree (with its
static fields: block count, solver, flags) and shapes, the static arguments and
the XLA options. A later process loads it without tracing. Programs with host
callbacks (the SciPy fallback of the sparse solve, the sensitivities' host solve) cannot
be stored, and are not; nor is a program
that JAX itself loaded from its cache rather than compiled (such an executable
serialises without its kernels, and the copy fails when called: "Function ...
not found"). So that JAX's cache does not serve a stored program under its
lowered text (the same text after a change of the jaxdem source elsewhere), each
is compiled with an option that changes no code and names its key (:func:`_salt`).

The small programs of a solve's host steps (the monitors' readings, the forces of the
blocks removed, the bolts' anchors, a mechanism's groups) are run by :func:`run_stored`,
stored on disk the same way: a warm run traces and lowers no program at all (JAX traced,
lowered and looked each up in its cache in every run, 10-30 ms each and 60 ms for a
process's first lowering: 0.08-0.18 s of a 1.8-2.3 s warm run of seed example 4 wet or the demo).

A warm start (:func:`warm_start`, the command line's): the stored programs that the last
run of the same scene file used (``programs/recent.json``) are loaded on background
threads from the moment JAX is imported, before the solver's modules are imported and
the scene is built, which is when their keys are known; :func:`_lower` takes a load by
its key's file name, so a load of another run's program is wasted work, never wrong.

Compilation beside other work: XLA compiles without Python's interpreter lock.
:func:`prefetch` traces a program on the caller's thread and compiles it on a
background one (the solver's increment, while the monitors' programs and the
in-situ preload are compiled); :func:`compiled_program` collects it. :func:`while_compiling`
runs host work (the command line's matplotlib warm-up) once a compilation starts.

Several threads: :func:`compiled_program` compiles a program once however many
threads ask for it at the same time (the workers of :func:`jaxdem.batch.solve_batch`):
the first compiles (or loads) it, the others wait for it.

Data flow: knows nothing of the solver; the host driver (:mod:`jaxdem.solver`)
and :mod:`jaxdem.batch` compile through it.
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import hashlib
import json
import os
import pickle
import random
import tempfile
import threading
import time
import zlib
from pathlib import Path

import jax

_COMPILED: collections.OrderedDict = collections.OrderedDict()
_PENDING: dict = {}  # key -> Future of a program compiling in the background (prefetch)
_COMPILING: dict = {}  # key -> Future of a program a caller's thread compiles or loads now
_BACKGROUND: list = []  # the one worker thread's executor, made on first use
_HOST_TASKS: list = []  # host work waiting for the next compilation (while_compiling)
_WAITING_TASKS: list = []  # work for a thread that would wait for a prefetch (while_waiting)
_RESULTS: dict = {}  # key -> the result shapes of a program lowered here (result_shapes)
_LOCK = threading.Lock()  # guards these and COMPILE_TIMES: the background threads use them

MAX_COMPILED = 16
"""Compiled increments kept in memory (least recently used dropped first)."""

_SMALL: collections.OrderedDict = collections.OrderedDict()  # run_stored's programs
MAX_SMALL = 64
"""Small programs of the host steps kept in memory (:func:`run_stored`; least recently used
dropped first, without clearing JAX's caches: each is a few hundred kilobytes)."""


COMPILE_TIMES = {"lower_s": 0.0, "compile_s": 0.0}
"""Time spent in :func:`compiled_program` by this process: tracing and lowering, and XLA
compilation (or loading from the persistent cache), s."""


CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
"""XLA options of jaxdem's large programs on a CPU. Without the new fusion emitters
XLA compiled the increment in 0.6 to 0.7 of the time (10.3 -> 6.1 s dense, 10.7 ->
7.7 s cg, 20 x 20 grid; 14 -> 9 s, incline) and the solve was no slower, with
bitwise the same answers (BENCHMARKS.md, "Time to answer"). LLVM's optimisation level
1 (XLA's default is 3): the wet seed example 4's whole cold run 6.01 -> 5.58 s
(medians of 5 alternating runs), seed example 2's 10.3 -> 9.9 s, for a solve 0-5%
slower (3% on the 70 x 70 grid), the same iterations and the monitors within 3e-11
(BENCHMARKS.md, "Fifteenth session"). A jaxlib that does not know an option compiles
without them."""


QUICK_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}
"""XLA options added on a CPU for a program that runs briefly (``quick``), over
:data:`CPU_COMPILER_OPTIONS`: LLVM's optimisation level 0. It compiles the increment
in 0.4-0.6 of the time and runs it 2-3 times slower (BENCHMARKS.md, "Time to
answer"), which wins wherever the solve takes less than the compilation saves: a
single solve of a small scene, or a small batch."""

QUICK_WORK = 2_560
"""Largest work (blocks of the size class x increments, x samples for a batch) of a
solve compiled ``quick``: the demo (512 x 5 increments) and the dry seed example 4
(256 x 8) are within, the wet one (256 x 12) and seed example 2 (1,280 x 5) above. At
LLVM's level 0 the demo's cold run took 4.8-5.0 s against 6.8 (compile 3.1-3.3 s against
5.3-5.4) and its warm run 1.95 against 1.46 (a solve of 0.6-0.75 s against 0.30); the
wet seed example 4 would have taken 5.3 cold but 2.5 warm (solve 1.5 s against 0.46:
it iterates more an increment), so it stays at level 1 (BENCHMARKS.md,
"Thirteenth session"). A solve with sensitivities, one of many in a back-analysis, is
never quick."""


def _options(quick: bool = False) -> dict:
    """The XLA options of this backend's programs."""
    if jax.default_backend() != "cpu":
        return {}
    return {**CPU_COMPILER_OPTIONS, **(QUICK_COMPILER_OPTIONS if quick else {})}


def _xla_compile(lowered, quick: bool = False, salt: int | None = None):
    """``lowered.compile()``, with :data:`CPU_COMPILER_OPTIONS` (and the quick ones) on a CPU;
    ``salt`` (a stored program's, :func:`_salt`) among the options."""
    options = _options(quick)
    if salt is not None:
        options = {**options, _SALT_OPTION: salt}
    if options:
        try:
            return lowered.compile(compiler_options=options)
        except jax.errors.JaxRuntimeError:  # an option this XLA does not have
            pass
    return lowered.compile()


_ON_DISK: dict = {}


def on_disk(name: str):
    """Store the compiled programs of a jitted module-level function on disk (as ``name``).

    Only for functions whose program is decided by the jaxdem source, the
    arguments' tree and shapes and the static arguments (no closure over
    values): the key knows nothing else.
    """

    def register(fn):
        _ON_DISK[fn] = name
        return fn

    return register


STORED_BYTES = 256 * 2**20
"""Most bytes of stored programs kept on disk (least recently written dropped first):
every change of the jaxdem source makes new keys."""

_JAX_CACHE_HITS: collections.Counter = collections.Counter()
"""Hits on JAX's persistent cache, by thread: a compilation and the hit it may score run
on one thread, while another thread compiles (and hits) other programs meanwhile."""


def _count_jax_cache_hits(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _JAX_CACHE_HITS[threading.get_ident()] += 1


jax.monitoring.register_event_listener(_count_jax_cache_hits)


@functools.lru_cache(maxsize=1)
def _processor() -> str:
    """The processor's model and features (a program compiled for one may not run on another)."""
    try:
        info = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        import platform

        return platform.processor() or platform.machine()
    keep = [line for line in info if line.startswith(("model name", "flags", "Features"))]
    return hashlib.sha256("\n".join(sorted(set(keep))).encode()).hexdigest()


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """sha256 of the jaxdem package's Python source, every subpackage (computed once a process)."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]  # jaxdem/, above jaxdem/core/
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _program_dir() -> Path | None:
    """``programs/`` in the persistent compilation cache directory, when that is on."""
    directory = jax.config.jax_compilation_cache_dir
    if not (jax.config.jax_enable_compilation_cache and directory):
        return None
    return Path(directory) / "programs"


def _disk_key(name, tree, leaves, static, options) -> str:
    import jaxlib

    device = jax.devices()[0]
    parts = (name, _source_digest(), jax.__version__, jaxlib.__version__, device.platform,
             device.device_kind, _processor(), bool(jax.config.jax_enable_x64), str(tree),
             tuple((tuple(x.shape), str(x.dtype)) for x in leaves),
             tuple(sorted(static.items())), tuple(sorted(options.items())))
    return hashlib.sha256(repr(parts).encode()).hexdigest()


_SALT_OPTION = "xla_debug_buffer_assignment_show_max"
"""An XLA option that changes no code (how many buffers a debugging printout of the
buffer assignment lists) but enters JAX's cache key: see :func:`_salt`."""


def _salt(path: Path) -> int:
    """The value of :data:`_SALT_OPTION` with which the program stored at ``path`` is compiled.

    Made of the program's key, so that JAX's persistent cache never holds it under the key
    of another program that lowers to the same text: a program that JAX loads from its
    cache serialises without its kernels (module docstring), so a JAX hit could not be
    stored. Without the salt the text of a program stays the same when the jaxdem source
    changes where the program does not, and every run after such a change found its
    program in JAX's cache, not in ``programs/``, and traced and lowered it again
    (1.6-2.2 s of a 3-6 s warm run).
    """
    return 16 + int(path.stem[:12], 16) % 2**40


def _load_program(path: Path):
    """The compiled program stored at ``path``, or None (absent, unreadable, stale)."""
    if not path.is_file():
        return None
    try:
        blob, trees, lapack = _read_program(path)
        return _program_of(_executable_of(blob, lapack), trees)
    except Exception:  # noqa: BLE001 - any failure: compile instead
        return None


def _read_program(path: Path):
    """A stored program's parts: the serialised executable, the pickled argument and result
    trees apart (unpickling them imports the jaxdem modules of their types, which
    :func:`warm_start`'s threads must not do beside the main thread's imports), and
    whether it calls LAPACK."""
    blob, trees, lapack = pickle.loads(zlib.decompress(path.read_bytes()))
    return blob, trees, lapack


def _executable_of(blob: bytes, lapack: bool):
    """XLA's load of a serialised executable (it parses and links the program: 0.4-0.7 s for
    the demo's increment, most of a warm run's wait), as JAX's
    ``serialize_executable.deserialize_and_load`` does before it unpickles the trees:
    (loaded executable, flat argument infos, no_kwargs). Imports no jaxdem module."""
    import io

    from jax._src.lax.linalg import initialize_lapack
    from jax.experimental import serialize_executable

    # A loaded program that calls LAPACK (the dense LU; the bolts' eigen-pairs under "cg") does so
    # without a lowering that would have set up its kernels first: without this it
    # crashes (the set-up imports SciPy's BLAS and LAPACK: 0.13 s, which a program
    # without LAPACK, the sparse path's, does not pay). The sparse solve's FFI targets,
    # registered when sparsax is imported, must be there before XLA loads a program
    # that calls them ("No FFI handler registered").
    if lapack:
        initialize_lapack()
    try:
        import sparsax  # noqa: F401
    except ImportError:
        pass
    backend = jax.devices()[0].client
    unloaded, args_info, no_kwargs = serialize_executable._JaxPjrtUnpickler(
        io.BytesIO(blob), backend).load()
    return unloaded.load(), args_info, no_kwargs


def _program_of(executable, trees: bytes):
    """The callable program of :func:`_executable_of`'s parts and the pickled trees."""
    loaded, args_info, no_kwargs = executable
    in_tree, out_tree = pickle.loads(trees)
    return jax.stages.Compiled(loaded, [], in_tree.unflatten(args_info), out_tree,
                               no_kwargs=no_kwargs)


def _store_program(path: Path, compiled) -> None:
    """Write ``compiled`` to ``path`` (atomically), unless it holds host callbacks."""
    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if unloaded is None or getattr(unloaded, "host_callbacks", None):
        return
    try:
        from jax.experimental import serialize_executable

        lapack = "lapack_" in compiled.as_text()
        blob, in_tree, out_tree = serialize_executable.serialize(compiled)
        data = zlib.compress(pickle.dumps((blob, pickle.dumps((in_tree, out_tree)), lapack)), 1)
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, delete=False) as f:
            f.write(data)
        os.replace(f.name, path)
        _prune(path.parent, STORED_BYTES)
    except Exception:  # noqa: BLE001 - a program that cannot be stored is compiled next time
        return


def _prune(directory: Path, limit: int) -> None:
    """Delete the oldest stored programs until those left take at most ``limit`` bytes."""
    files = sorted(directory.glob("*.pkl"), key=lambda f: f.stat().st_mtime, reverse=True)
    total = 0
    for f in files:
        total += f.stat().st_size
        if total > limit:
            f.unlink(missing_ok=True)


RECENT_RUNS = 64
"""Runs whose stored programs :func:`warm_start` remembers (the least recent forgotten)."""

_RECENT_FILE = "recent.json"
_EARLY: dict = {}  # a stored program's file name -> Future of its load started by warm_start
_USED: list = []  # the file names of the stored programs this run asked for, in order
_SEEN: set = set()  # those this process asked for: in memory already, not loaded early
_RUN: list = []  # the fingerprint warm_start was given (remember_run records under it)


def warm_start(fingerprint: str) -> None:
    """Start loading, on two background threads, the stored programs that the last run with
    ``fingerprint`` used (:func:`remember_run` records them), largest first.

    A stored program is otherwise loaded once its key is known: once the scene is read,
    its blocks generated and its model built (0.1-0.4 s of a warm run), after which the
    main thread waits for the load (XLA parses and links the demo's increment in
    0.5-0.7 s). ``fingerprint`` names what decides a run's programs without building
    anything (the command line's: the scene file's bytes and the ``--set`` values). A
    program is still taken only by its key (:func:`_lower` matches the file's name, made
    of the key): an early load that no key asks for (the scene's capacities grew, the
    source changed) is work wasted on a background thread, never a wrong program.
    """
    directory = _program_dir()
    if directory is None:
        return
    # The jaxdem source and JAX's version too: a run of another version (a benchmark's
    # baseline on the same cache directory) used programs this one never asks for.
    _RUN[:] = [hashlib.sha256(repr((fingerprint, _source_digest(), jax.__version__))
                              .encode()).hexdigest()]
    with _LOCK:
        _USED.clear()
    try:
        names = json.loads((directory / _RECENT_FILE).read_text()).get(_RUN[0], [])
        sizes = {name: (directory / name).stat().st_size for name in names
                 if name not in _SEEN and (directory / name).is_file()}
    except (OSError, ValueError, AttributeError, TypeError):
        return
    queue = collections.deque(sorted(sizes, key=sizes.get, reverse=True))
    if not queue:
        return
    # The backend, JAX's deserialiser and the sparse solve's FFI targets here, on the
    # caller's thread: the threads then import nothing that the caller may be importing
    # at the same time (but SciPy's BLAS, for a program that calls LAPACK).
    jax.devices()
    from jax.experimental import serialize_executable  # noqa: F401
    try:
        import sparsax  # noqa: F401
    except ImportError:
        pass
    with _LOCK:
        for name in queue:
            _EARLY.setdefault(name, concurrent.futures.Future())

    def work():
        while True:
            try:
                name = queue.popleft()
            except IndexError:
                return
            future = _EARLY.get(name)
            if future is None or not future.set_running_or_notify_cancel():
                continue
            try:
                blob, trees, lapack = _read_program(directory / name)
                future.set_result((_executable_of(blob, lapack), trees))
            except BaseException:  # noqa: BLE001 - _lower loads it again
                future.set_result(None)

    for _ in range(min(2, len(queue))):
        threading.Thread(target=work, daemon=True, name="jaxdem-warm-start").start()


def _early_program(path: Path):
    """The program at ``path`` that :func:`warm_start` loaded (waiting for its load), or None."""
    with _LOCK:
        future = _EARLY.pop(path.name, None)
    if future is None or future.cancel():
        return None
    loaded = future.result()
    if loaded is None:
        return None
    try:
        return _program_of(*loaded)
    except Exception:  # noqa: BLE001 - loaded again by the caller
        return None


def _note_used(path: Path) -> None:
    with _LOCK:
        if path.name not in _USED:
            _USED.append(path.name)
        _SEEN.add(path.name)


def remember_run() -> None:
    """Record the stored programs this run used under :func:`warm_start`'s fingerprint,
    for the next run with it (at most :data:`RECENT_RUNS` runs are kept), and let go of
    the early loads that no key asked for."""
    directory = _program_dir()
    if directory is None or not _RUN:
        return
    with _LOCK:
        names = list(_USED)
        for future in _EARLY.values():
            future.cancel()
        _EARLY.clear()
    try:
        path = directory / _RECENT_FILE
        try:
            recent = json.loads(path.read_text())
            if not isinstance(recent, dict):
                recent = {}
        except (OSError, ValueError):
            recent = {}
        recent.pop(_RUN[0], None)
        recent[_RUN[0]] = names
        recent = dict(list(recent.items())[-RECENT_RUNS:])
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=directory, delete=False, suffix=".tmp") as f:
            json.dump(recent, f)
        os.replace(f.name, path)
    except OSError:
        return


def _key(fn, args, static, quick):
    leaves, tree = jax.tree.flatten(args)
    key = (fn, tree, tuple((x.shape, str(x.dtype)) for x in leaves), tuple(sorted(static.items())),
           quick)
    return key, leaves, tree


def _lower(fn, args, static, quick, leaves, tree):
    """A function that gives ``fn``'s program for these shapes, and holds no Python lock
    (it may run on another thread): the load of a stored program (XLA parses and links
    it: 0.5 s for the demo's increment, which :func:`prefetch` thus runs beside the
    in-situ preload and the monitors' programs), or the XLA compilation (and store), the
    tracing and lowering (in Python) being done here. A stored program that does not
    load is traced and compiled by that function instead.
    """
    name, directory = _ON_DISK.get(fn), _program_dir()
    path = None
    if name is not None and directory is not None:
        path = directory / f"{_disk_key(name, tree, leaves, static, _options(quick))}.pkl"
    if path is not None:
        _note_used(path)
    if path is not None and path.is_file():
        def load():
            t = time.perf_counter()
            compiled = _early_program(path) or _load_program(path)
            if compiled is not None:
                _count(0.0, time.perf_counter() - t)
                return compiled
            return _compiler(fn, args, static, quick, path)()

        return load
    return _compiler(fn, args, static, quick, path)


def _without_locations(lowered):
    """``lowered`` with its source locations dropped (MLIR's ``strip-debuginfo``, in place).

    XLA keeps each operation's location (the Python stack that made it) in the program
    it compiles and in the executable a later process loads: a fifth of seed example
    4's stored increment (2.93 -> 2.30 MB), which XLA parses again at every load. Without
    them the load and the compilation take a few per cent less (BENCHMARKS.md). Where
    this JAX's lowering does not allow it, ``lowered`` as it is.
    """
    try:
        from jax._src.lib.mlir import passmanager

        module = lowered.compiler_ir("stablehlo")
        with module.context:
            passmanager.PassManager.parse("builtin.module(strip-debuginfo)").run(
                module.operation)
    except Exception:  # noqa: BLE001 - locations only make the program larger
        pass
    return lowered


def _compiler(fn, args, static, quick, path):
    """Trace and lower ``fn`` now; returns the XLA compilation (and store at ``path``)."""
    t0 = time.perf_counter()
    lowered = _without_locations(fn.lower(*args, **static))
    t1 = time.perf_counter()
    _count(t1 - t0, 0.0)
    with _LOCK:
        _RESULTS[_key(fn, args, static, quick)[0]] = lowered.out_info
        if len(_RESULTS) > MAX_SMALL:  # the oldest go: their programs were made long ago
            del _RESULTS[next(iter(_RESULTS))]

    def finish():
        _start_host_tasks()
        t2 = time.perf_counter()
        me = threading.get_ident()
        hits = _JAX_CACHE_HITS[me]
        compiled = _xla_compile(lowered, quick, None if path is None else _salt(path))
        if path is not None and _JAX_CACHE_HITS[me] > hits:
            # JAX's cache had it (stored here once and since dropped from ``programs/``,
            # or never stored: see the module's docstring). Such an executable cannot be
            # stored: compile it afresh, once, under a salt JAX has never seen.
            hits = _JAX_CACHE_HITS[me]
            compiled = _xla_compile(lowered, quick, 1 + _salt(path) + random.getrandbits(40))
        if path is not None and _JAX_CACHE_HITS[me] == hits:
            _store_program(path, compiled)
        _count(0.0, time.perf_counter() - t2)
        return compiled

    return finish


def while_compiling(task) -> None:
    """Run ``task()`` on a background thread once the next program starts compiling.

    XLA compiles without Python's global interpreter lock, so host work that
    will be needed later costs no waiting then on a machine with a second core:
    the command line imports matplotlib and loads its fonts for the figures
    (0.3 s of a 3 s cold run of a small scene). Started earlier, the task
    would only share the lock with the tracing; a load of a stored program does not
    start it (the figures' warm-up beside a load made a warm run of the incline
    slower: 1.78 -> 2.01 s). A task is run at most once; one
    that never starts (every program was loaded) is dropped, and its work is
    done where it is needed. Its errors are ignored for the same reason.
    """
    with _LOCK:
        _HOST_TASKS.append(task)


def while_waiting(task) -> None:
    """Run ``task()`` on the thread that next has to wait for a program that
    :func:`prefetch` is still compiling, before it waits.

    That thread would otherwise idle while the other core compiles (in a cold run of
    the demo, 2.7 s between the in-situ preload's compilation and the increment's end):
    the small programs of the solve's host steps that would be compiled after it, on
    the way to the answer (:func:`precompile`), are compiled there instead. A task
    that never runs (no wait: the program was loaded, or came in time) is dropped at
    the next :func:`prefetch`, and its work is done where it is needed; its errors are
    ignored for the same reason.
    """
    with _LOCK:
        _WAITING_TASKS.append(task)


def _run_waiting_tasks() -> None:
    with _LOCK:
        tasks, _WAITING_TASKS[:] = list(_WAITING_TASKS), []
    for task in tasks:
        _quietly(task)


def result_shapes(fn, *args, quick: bool = False, **static):
    """The shapes of ``fn``'s results (a tree of ``jax.ShapeDtypeStruct``-like leaves)
    for these arguments, where this process has lowered its program (:func:`prefetch`,
    :func:`compiled_program`); else None (never traced here: loaded, or not asked for)."""
    key = _key(fn, args, static, quick)[0]
    with _LOCK:
        return _RESULTS.get(key)


def precompile(fn, *args, **static) -> None:
    """Compile (or load) now the program that ``run_stored(fn, *args, **static)`` will
    call, where the arguments need only have the later call's shapes
    (``jax.ShapeDtypeStruct``): :func:`while_waiting`'s work."""
    key, leaves, tree = _key(fn, args, static, False)
    with _LOCK:
        if key in _SMALL:
            return
    _keep_small(key, _lower(fn, args, static, False, leaves, tree)())


def _keep_small(key, compiled) -> None:
    """Keep a small program (:func:`run_stored`'s) under ``key``; at most :data:`MAX_SMALL`."""
    with _LOCK:
        _SMALL[key] = compiled
        if len(_SMALL) > MAX_SMALL:
            _SMALL.popitem(last=False)


def _start_host_tasks() -> None:
    with _LOCK:
        tasks, _HOST_TASKS[:] = list(_HOST_TASKS), []
    for task in tasks:
        threading.Thread(target=_quietly, args=(task,), daemon=True,
                         name="jaxdem-host-task").start()


def _quietly(task) -> None:
    try:
        task()
    except Exception:  # noqa: BLE001 - see while_compiling
        pass


def _count(lower_s: float, compile_s: float) -> None:
    with _LOCK:
        COMPILE_TIMES["lower_s"] += lower_s
        COMPILE_TIMES["compile_s"] += compile_s


def prefetch(fn, *args, quick: bool = False, **static) -> float:
    """Trace ``fn`` for these shapes now and compile it on a background thread.

    :func:`compiled_program` collects the program. XLA compiles without Python's
    global interpreter lock, so a program that will be needed next (the
    increment, while the in-situ preload is traced, compiled and run) costs no
    waiting on a machine with a second core. Tracing stays on the caller's
    thread: it needs the lock, and sharing it would only slow both. The
    arguments need only have the shapes of the later call. Nothing is started
    for a program already there. One program is prefetched at a time.

    Returns the seconds this call spent (tracing; a stored program is loaded in the
    background too); 0.0 when the program was there already.
    """
    key, leaves, tree = _key(fn, args, static, quick)
    with _LOCK:
        if key in _COMPILED or key in _PENDING or key in _COMPILING:
            return 0.0
    t0 = time.perf_counter()
    try:
        finish = _lower(fn, args, static, quick, leaves, tree)
    except Exception:  # noqa: BLE001 - the call that needs the program reports it
        return time.perf_counter() - t0
    with _LOCK:
        if not _BACKGROUND:
            _BACKGROUND.append(concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="jaxdem-compile"))
        # One at a time: a program never collected (the preload grew the pair
        # capacity, so the increment came with other shapes) is let go, and the
        # work that was to be done while waiting for it (while_waiting) with it.
        _PENDING.clear()
        _WAITING_TASKS.clear()
        _PENDING[key] = _BACKGROUND[0].submit(finish)
    return time.perf_counter() - t0


def _remember(key, compiled) -> None:
    """Keep ``compiled`` under ``key``; beyond :data:`MAX_COMPILED` drop the least recently used."""
    with _LOCK:
        _COMPILED[key] = compiled
        dropped = len(_COMPILED) > MAX_COMPILED
        if dropped:
            _COMPILED.popitem(last=False)
    if dropped:
        jax.clear_caches()


def compiled_program(fn, *args, quick: bool = False, **static):
    """``fn`` (jitted) compiled for these argument shapes and static settings; compile time (s).

    ``static`` holds ``fn``'s static keyword arguments; the compiled program is
    called without them. ``quick`` adds :data:`QUICK_COMPILER_OPTIONS` on a CPU
    (a program that will run briefly). The time returned is the time this
    call waited: a program that :func:`prefetch` compiled in the background
    while the caller worked costs only what was left of its compilation.

    One compilation per shape: the samples of a sweep and the iterations of a
    back-analysis reuse it. At most :data:`MAX_COMPILED` are kept: a compiled
    increment holds about 35 MB and hundreds of memory mappings, and a process
    that solved some hundreds of differently-shaped scenes ran out of mappings
    and crashed in XLA's compiler. When one is dropped, JAX's own caches (the
    small host-step programs) are cleared with it; the persistent compilation
    cache on disk still serves a shape that comes back.

    Thread-safe: a thread that asks for a program another thread is compiling (or
    loading) waits for that one, and the time returned is its wait.
    """
    key, leaves, tree = _key(fn, args, static, quick)
    t0 = time.perf_counter()
    with _LOCK:
        if key in _COMPILED:
            _COMPILED.move_to_end(key)
            return _COMPILED[key], 0.0
        other = _COMPILING.get(key)
        if other is None:
            pending = _PENDING.pop(key, None)
            mine = _COMPILING[key] = concurrent.futures.Future()
    if other is not None:
        try:
            return other.result(), time.perf_counter() - t0
        except Exception:  # noqa: BLE001 - compile here, where an error reaches the caller
            compiled, _ = compiled_program(fn, *args, quick=quick, **static)
            return compiled, time.perf_counter() - t0
    try:
        compiled = _collected(pending, fn, args, static, quick, leaves, tree)
        _remember(key, compiled)
    except BaseException as err:
        _done_compiling(key, mine, error=err)
        raise
    _done_compiling(key, mine, compiled)
    return compiled, time.perf_counter() - t0


def _collected(pending, fn, args, static, quick, leaves, tree):
    """The program that :func:`prefetch` compiled (``pending``, its future, or None), else
    one compiled (or loaded) now: where the prefetch failed, here, where an error reaches
    the caller."""
    if pending is not None:
        if not pending.done():
            _run_waiting_tasks()
        try:
            return pending.result()
        except Exception:  # noqa: BLE001 - compile below, where an error reaches the caller
            pass
    return _lower(fn, args, static, quick, leaves, tree)()


def run_stored(fn, *args, **static):
    """``fn(*args)`` (``static``: its static keyword arguments) run by its compiled program,
    for the small programs of a solve's host steps (the monitors' readings, the forces of
    the blocks removed, the bolts' anchors). Where ``fn`` is named by :func:`on_disk` a
    later process loads the program without tracing or lowering it: called as jitted
    functions, JAX traced, lowered and looked each up in its cache in every warm run
    (10-30 ms each, and the first lowering of a process 60 ms more). One taken from
    :func:`prefetch` is collected. Only with arrays, not inside a trace.
    """
    key, leaves, tree = _key(fn, args, static, False)
    with _LOCK:
        compiled = _SMALL.get(key)
        if compiled is not None:
            _SMALL.move_to_end(key)
        pending = _PENDING.pop(key, None) if compiled is None else None
    if compiled is None:
        compiled = _collected(pending, fn, args, static, False, leaves, tree)
        _keep_small(key, compiled)
    return compiled(*args)


def _done_compiling(key, future, compiled=None, error=None) -> None:
    """Hand the program (or the error) to the threads waiting for it in
    :func:`compiled_program`; a later caller finds it in the registry."""
    with _LOCK:
        _COMPILING.pop(key, None)
    if error is None:
        future.set_result(compiled)
    else:
        future.set_exception(error)
