"""Settings: float64 around the solver, and the process-wide settings made on request.

Importing jaxdem changes nothing in the caller's process: no JAX flag, no environment
variable, no cache. What the solver needs it sets around its own work:

- **float64**: the public entry points (``jaxdem.solve``, ``solve_batch``, ``sweep``,
  ``factor_of_safety``, the solves behind ``differentiable``, ``inverse.back_analyse``)
  run under :func:`float64`, JAX's ``enable_x64`` context, and restore the caller's
  setting on return. A scene may ask for float32 (``solver.dtype``): its arrays are
  float32 inside that context too.

What only a whole process can decide is made by :func:`configure`, which the command
line calls where it starts (``jaxdem ...``) and a program may call once, first thing:

- float64 for the whole process (``jax_enable_x64``), so that arrays made outside the
  entry points (``jaxdem.core`` used directly, a benchmark) are float64 too.
- One OpenBLAS thread, unless ``OPENBLAS_NUM_THREADS`` is set: XLA runs its own thread
  pool, and a multithreaded OpenBLAS beside it (jaxlib's LAPACK and SciPy's sparse solve
  use it) oversubscribes the cores; on a busy 2-core CPU a 1,500-unknown Cholesky
  factorisation took 121 ms with OpenBLAS's threads against 28 ms with one. It takes
  effect only before SciPy's OpenBLAS is loaded, hence first thing.
- JAX's persistent compilation cache, so that a second run of the same scene (or the
  same sweep) loads its compiled programs instead of compiling them again. It lives in
  ``$JAXDEM_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxdem/xla``, else
  ``~/.cache/jaxdem/xla``. ``JAXDEM_COMPILATION_CACHE=0`` (or ``off``) leaves it off;
  :func:`compilation_cache` turns it on or off at run time. A cache directory the user
  already gave JAX (``jax_compilation_cache_dir``) is kept.

Example::

    import jaxdem
    jaxdem.config.configure()      # optional: float64, one OpenBLAS thread, the cache
    result = jaxdem.solve(jaxdem.load_scene("tunnel.toml"))
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

F = TypeVar("F", bound=Callable)

_OFF = ("0", "off", "false", "no")


def default_cache_dir() -> Path:
    if os.environ.get("JAXDEM_CACHE_DIR"):
        return Path(os.environ["JAXDEM_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxdem" / "xla"


def compilation_cache(path: str | os.PathLike | None | bool = True) -> Path | None:
    """Turn JAX's persistent compilation cache on (a directory, or True for the default)
    or off (None or False). Returns the directory in use, or None."""
    import jax

    if path is None or path is False:
        jax.config.update("jax_compilation_cache_dir", None)
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    directory = default_cache_dir() if path is True else Path(path)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    # Every program, however quick to compile: the increment takes seconds,
    # the small host-step programs add up to about as much again.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return directory


def float64(fn: F) -> F:
    """``fn`` run with JAX's 64-bit types on (``jax.enable_x64``); the caller's setting is
    restored on return. Arrays that ``fn`` returns keep their dtype."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        import jax

        if jax.config.jax_enable_x64:
            return fn(*args, **kwargs)
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def configure() -> None:
    """The process-wide settings of the module docstring: float64, one OpenBLAS thread,
    the persistent compilation cache. Call it first thing (the command line does)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import jax

    jax.config.update("jax_enable_x64", True)
    if os.environ.get("JAXDEM_COMPILATION_CACHE", "1").strip().lower() in _OFF:
        return
    if jax.config.jax_compilation_cache_dir is None:
        compilation_cache(True)
