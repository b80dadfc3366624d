"""What a cold run's compilation is made of: the increment program and its parts, traced,
lowered and compiled on their own, and where its operations come from (issue 30's cold
targets).

For a scene's first increment (its model, state and loads as the solver builds them),
these programs:

- ``detection``: :func:`jaxdem.core._substep.prepare_substep` (broad and narrow phase,
  the slots' fields);
- ``sub-step``: :func:`jaxdem.core._substep.substep` (detection, the Newton iteration,
  the commit);
- ``bare loop``: the sub-step in a ``lax.while_loop`` of five that carries the state alone
  (the floor for a loop of sub-steps: what the loop itself costs the compiler);
- ``exit loop``: the same, ending where the sub-step converged, its step was not finite,
  a block travelled beyond ``max_displacement``, or after five (a trip count known only as
  it runs, as the increment's);
- ``fixed loop``: the same sub-steps and exit in a ``lax.fori_loop`` of 50 whose body is a
  ``lax.cond`` on "not yet ended" (a trip count XLA knows);
- ``increment``: :func:`jaxdem.core.increment.increment` (the loop of sub-steps with what
  it reports, what the solver compiles).

The loops also run (the median of 3 runs of the compiled program at the last level, s;
their answers compared: the blocks' centroids the same to the last bit or not). Each is
traced and lowered once (s), then compiled ``--repeats`` times at each LLVM
level asked for, alternating programs, under a distinct value of an XLA option that
changes no code (so that JAX's caches never answer; the median is printed, s). Level 0 is
what a brief single solve compiles with (``QUICK_COMPILER_OPTIONS``), level 1 the rest
(``CPU_COMPILER_OPTIONS``). Then the increment's StableHLO operations counted by the
``jaxdem`` module whose source line made them (the innermost frame in the package; the
count is of operations before XLA's passes, the measure of program size that tracing,
lowering and compiling all grow with). Timings are noisy: compare runs made side by side.
The accuracy of what is timed is not at stake (nothing is solved).

    PYTHONPATH=. python benchmarks/bench_compile.py jaxdem/data/demo.toml
    PYTHONPATH=. python benchmarks/bench_compile.py examples/seed_example2_tunnel.toml --levels 1
"""

from __future__ import annotations

import argparse
import collections
import os
import platform
import re
import statistics
import time

from bench_time_to_answer import cpu_model  # this folder is on the path: run as a script


def ops_by_module(text: str) -> collections.Counter:
    """StableHLO operations of ``text`` (``Lowered.as_text(debug_info=True)``) counted by the
    jaxdem module (``core/_substep.py``, ...) of the innermost frame that made them; "other"
    where no frame of the package is recorded (JAX's own expansions)."""
    alias = dict(re.findall(r"^(#loc\d+) = loc\((.*)\)$", text, re.M))

    def module(ref: str, depth: int = 0) -> str | None:
        s = alias.get(ref, ref)
        m = re.search(r'"[^"]*/jaxdem/([^"]+\.py)":\d+', s)
        if m:
            return m.group(1)
        if depth < 32:
            for inner in re.findall(r"#loc\d+", s):
                found = module(inner, depth + 1)
                if found:
                    return found
        return None

    counts = collections.Counter()
    for line in text.splitlines():
        if "stablehlo." in line and " = " in line:
            m = re.search(r"loc\((#loc\d+)\)\s*$", line)
            counts[(module(m.group(1)) if m else None) or "other"] += 1
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--levels", type=int, nargs="+", default=[0, 1])
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp

    import jaxdem
    from jaxdem import solver
    from jaxdem.core import _substep, compile_cache
    from jaxdem.core.increment import increment
    from jaxdem.core.kinematics import block_travel

    jaxdem.config.configure()
    scene = jaxdem.load_scene(args.scene)
    model, state, loads = solver.increment_arguments(scene)

    def bare_loop(m, s, lo):
        def body(c):
            return c[0] + 1, _substep.substep(m, c[1], lo, jnp.array(False))[0]

        return jax.lax.while_loop(lambda c: c[0] < 5, body, (jnp.zeros((), jnp.int32), s))[1]

    def outcome_step(m, lo):
        # One sub-step and whether the loop ends after it: (count, state, travel, ended).
        def step(c):
            k, s, travel, _ = c
            new, du, newton, _, _, _ = _substep.substep(m, s, lo, jnp.array(False))
            travel = travel + block_travel(m, du)
            ended = ((k >= 4) | newton.converged | ~newton.finite
                     | (jnp.max(travel) > m.max_displacement))
            return k + 1, new, travel, ended

        return step

    def start(m, s):
        return jnp.zeros((), jnp.int32), s, jnp.zeros(m.n_blocks, s.verts.dtype), jnp.array(False)

    def exit_loop(m, s, lo):
        return jax.lax.while_loop(lambda c: ~c[3], outcome_step(m, lo), start(m, s))[1]

    def fixed_loop(m, s, lo):
        step = outcome_step(m, lo)
        body = lambda _, c: jax.lax.cond(c[3], lambda c: c, step, c)  # noqa: E731
        return jax.lax.fori_loop(0, 50, body, start(m, s))[1]

    programs = {
        "detection": lambda m, s, lo: _substep.prepare_substep(m, s, lo),
        "sub-step": lambda m, s, lo: _substep.substep(m, s, lo, jnp.array(False)),
        "bare loop": bare_loop,
        "exit loop": exit_loop,
        "fixed loop": fixed_loop,
        "increment": lambda m, s, lo: increment(m, s, lo),
    }
    lowered, lower_s = {}, {}
    for name, fn in programs.items():
        t = time.perf_counter()
        lowered[name] = jax.jit(fn).lower(model, state, loads)
        lower_s[name] = time.perf_counter() - t
    times = {(name, level): [] for name in programs for level in args.levels}
    salt = time.time_ns() % 2**30  # never a value an earlier run compiled under
    for _ in range(args.repeats):
        for level in args.levels:
            for name, low in lowered.items():
                salt += 1
                options = {**compile_cache.CPU_COMPILER_OPTIONS,
                           "xla_backend_optimization_level": level,
                           "xla_debug_buffer_assignment_show_max": salt}
                t = time.perf_counter()
                low.compile(compiler_options=options)
                times[name, level].append(time.perf_counter() - t)

    # The loops run as compiled at the last level asked for.
    last = {**compile_cache.CPU_COMPILER_OPTIONS, "xla_backend_optimization_level": args.levels[-1]}
    runs, ends = {}, {}
    for name in ("bare loop", "exit loop", "fixed loop"):
        salt += 1
        run = lowered[name].compile(compiler_options={**last,
                                                      "xla_debug_buffer_assignment_show_max": salt})
        jax.block_until_ready(run(model, state, loads))
        spent = []
        for _ in range(3):
            t = time.perf_counter()
            ends[name] = jax.block_until_ready(run(model, state, loads))
            spent.append(time.perf_counter() - t)
        runs[name] = statistics.median(spent)
    same = bool(jnp.all(ends["exit loop"].centroid == ends["fixed loop"].centroid))

    print(f"# {args.scene}: {model.n_blocks} blocks (size class), solver {model.linear_solver}; "
          f"{platform.machine()}, {cpu_model()}, {os.cpu_count()} cores, jax {jax.__version__}; "
          f"compile: medians of {args.repeats}, s")
    head = "".join(f" {'level ' + str(level):>9}" for level in args.levels)
    print(f"{'program':>10} {'ops':>6} {'chars':>8} {'lower':>7}{head} {'run':>7}")
    # The operations of each program by module (its text with locations, printed once).
    by_module = {name: ops_by_module(low.as_text(debug_info=True))
                 for name, low in lowered.items()}
    for name, low in lowered.items():
        ops = sum(by_module[name].values())
        cells = "".join(f" {statistics.median(times[name, level]):9.2f}" for level in args.levels)
        run = f" {runs[name]:7.3f}" if name in runs else f" {'-':>7}"
        print(f"{name:>10} {ops:6d} {len(low.as_text()):8d} {lower_s[name]:7.2f}{cells}{run}")
    print(f"# the exit loop and the fixed loop end with the same centroids, bit for bit: {same}")
    print("# the increment's operations by the module that made them")
    for module, n in by_module["increment"].most_common():
        print(f"{module:>24} {n:6d}")


if __name__ == "__main__":
    main()
