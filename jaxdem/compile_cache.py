"""Compiled programs kept per shape: the registry, its bound, compile times, XLA options.

Owns :func:`_compiled` (a jitted function compiled once per argument shapes
and static settings, least recently used dropped beyond :data:`MAX_COMPILED`),
:data:`COMPILE_TIMES` and :data:`CPU_COMPILER_OPTIONS`. Keys are the jitted
function objects themselves, so a program is found again wherever its
function lives.

Data flow: knows nothing of the solver; the host driver (:mod:`jaxdem.solver`)
and :mod:`jaxdem.batch` compile through it.
"""

from __future__ import annotations

import collections
import time

import jax

_COMPILED: collections.OrderedDict = collections.OrderedDict()
MAX_COMPILED = 16
"""Compiled increments kept in memory (least recently used dropped first)."""


COMPILE_TIMES = {"lower_s": 0.0, "compile_s": 0.0}
"""Time spent in :func:`_compiled` by this process: tracing and lowering, and XLA
compilation (or loading from the persistent cache), s."""


CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
"""XLA options of jaxdem's large programs on a CPU. Without the new fusion emitters
XLA compiled the increment in 0.6 to 0.7 of the time (10.3 -> 6.1 s dense, 10.7 ->
7.7 s cg, 20 x 20 grid; 14 -> 9 s, incline) and the solve was no slower, with
bitwise the same answers (BENCHMARKS.md, "Time to answer"). A jaxlib that does
not know an option compiles without them."""


def _xla_compile(lowered):
    """``lowered.compile()``, with :data:`CPU_COMPILER_OPTIONS` on a CPU."""
    if CPU_COMPILER_OPTIONS and jax.default_backend() == "cpu":
        try:
            return lowered.compile(compiler_options=dict(CPU_COMPILER_OPTIONS))
        except jax.errors.JaxRuntimeError:  # an option this XLA does not have
            pass
    return lowered.compile()


def _compiled(fn, *args, **static):
    """``fn`` (jitted) compiled for these argument shapes and static settings; compile time (s).

    ``static`` holds ``fn``'s static keyword arguments; the compiled program is
    called without them.

    One compilation per shape: the samples of a sweep and the iterations of a
    back-analysis reuse it. At most :data:`MAX_COMPILED` are kept: a compiled
    increment holds about 35 MB and hundreds of memory mappings, and a process
    that solved some hundreds of differently-shaped scenes ran out of mappings
    and crashed in XLA's compiler. When one is dropped, JAX's own caches (the
    small host-step programs) are cleared with it; the persistent compilation
    cache on disk still serves a shape that comes back.
    """
    leaves, tree = jax.tree.flatten(args)
    key = (fn, tree, tuple((x.shape, str(x.dtype)) for x in leaves), tuple(sorted(static.items())))
    if key in _COMPILED:
        _COMPILED.move_to_end(key)
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    lowered = fn.lower(*args, **static)
    t1 = time.perf_counter()
    compiled = _xla_compile(lowered)
    COMPILE_TIMES["lower_s"] += t1 - t0
    COMPILE_TIMES["compile_s"] += time.perf_counter() - t1
    _COMPILED[key] = compiled
    if len(_COMPILED) > MAX_COMPILED:
        _COMPILED.popitem(last=False)
        jax.clear_caches()
    return compiled, time.perf_counter() - t0
