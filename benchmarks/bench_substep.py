"""Where one geometry sub-step's time goes: detection, packing, Newton, the pieces of an
iteration, on a real scene.

Solves the scene once (its increments' arguments recorded), then times each piece of
the sub-step at the start of one increment, each jitted alone, on that increment's
model, state and loads: the broad phase, the narrow phase, the whole detection
(``prepare_substep``), the packing of the touching slots (their rows Bn, Bs formed
there), the Newton iteration, one iteration's assembly (springs summed into the blocks
of the touching pairs, the triplets CHOLMOD gets), its linear solve (the secant matrix
with values met before, whose factor sparsax reuses, and with new ones; the slip
tangent with new ones), the final evaluation, the corner bound, Newton with everything
after it (``newton_and_commit``), the commit alone (the blocks moved, the springs'
history laid out over every slot, the global balance over the touching ones), and the
whole sub-step.
Medians of ``--repeats`` calls, ms. The accuracy of what is timed is the solver's own
(the whole sub-step is the solver's); the table also gives the sizes that set the
costs (pairs, touching pairs and slots, places).

    PYTHONPATH=. python benchmarks/bench_substep.py examples/seed_example2_tunnel.toml
    PYTHONPATH=. python benchmarks/bench_substep.py jaxdem/data/demo.toml --increment 0
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--increment", type=int, default=3,
                        help="which increment's start (default 3)")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp

    import jaxdem
    from jaxdem import solver
    from jaxdem.core import _contact, _linsolve, _substep
    from jaxdem.core._springs import evaluate, slip_coupling, stiffness_terms

    jaxdem.config.configure()
    recorded = []
    run_increment = solver.run_increment

    def spy(model, state, loads, tangents=None, quick=False):
        recorded.append((model, state, loads))
        return run_increment(model, state, loads, tangents, quick)

    solver.run_increment = spy
    try:
        jaxdem.solve(jaxdem.load_scene(args.scene))
    finally:
        solver.run_increment = run_increment
    model, state, loads = recorded[min(args.increment, len(recorded) - 1)]
    mdl = dataclasses.replace(model, free=model.free & state.alive)

    def timed(f, *a, each=None):
        """Median ms of ``f(*a)`` jitted; with ``each``, the i-th call's arguments are
        ``each(i)`` (a) for the compiling call)."""
        f = jax.jit(f)
        jax.block_until_ready(f(*a))
        times = []
        for i in range(args.repeats):
            call = a if each is None else jax.block_until_ready(each(i))
            t = time.perf_counter()
            jax.block_until_ready(f(*call))
            times.append(time.perf_counter() - t)
        return 1e3 * statistics.median(times)

    rows = []
    broad = lambda m, s: _contact.broad_phase(m, s.verts, s.capacity, s.alive)  # noqa: E731
    rows.append(("broad phase", timed(broad, mdl, state)))
    pairs, count, _ = jax.jit(broad)(mdl, state)
    rows.append(("narrow phase", timed(lambda m, s, p: _contact.narrow_phase(
        m, s.verts, s.centroid, p), mdl, state, pairs)))
    # As a sub-step does: the rows Bn, Bs formed for the touching slots alone, at packing.
    detect = lambda m, s, ld: _substep.prepare_substep(m, s, ld, rows=False)  # noqa: E731
    rows.append(("detection (prepare_substep)", timed(detect, model, state, loads)))
    mdl2, sub, st0, pairs, found = jax.jit(detect)(model, state, loads)
    rows.append(("packing", timed(_substep.pack_slots, mdl2, sub, st0, state.centroid)))
    packed, st0p, sid, _, touching = jax.jit(_substep.pack_slots)(mdl2, sub, st0,
                                                                 state.centroid)
    newton = jax.jit(_substep._newton)(mdl2, packed, st0p)
    rows.append((f"Newton ({int(newton.it)} iterations)",
                 timed(_substep._newton, mdl2, packed, st0p)))
    band = _substep.force_scales(mdl2, packed)[1]
    held = lambda m, sb, du, st: evaluate(m, sb, du, jnp.zeros(st.shape, bool), st, st,  # noqa: E731
                                          _substep.force_scales(m, sb)[1])
    rows.append(("evaluation, packed slots", timed(held, mdl2, packed, newton.du, st0p)))
    ev = jax.jit(lambda m, sb, du, st: evaluate(m, sb, du, jnp.zeros(st.shape, bool), st, st,
                                                band))(mdl2, packed, newton.du, st0p)

    def assembly(m, sb, ev):
        a, b, B, k = stiffness_terms(m, sb, ev, False, None)
        diag = _linsolve.pseudo_mass_diagonal(m, sb)
        return _linsolve.coo_of_blocks(m, *_linsolve.stiffness_blocks(m, sb, a, b, B, B, k,
                                                                      diag), upper=True)

    rows.append(("assembly and triplets", timed(assembly, mdl2, packed, ev)))
    triplets = jax.jit(assembly)(mdl2, packed, ev)[0].shape[0]

    # One iteration's linear solve, assembly included, with the springs' stiffness scaled
    # by a factor that changes from call to call (as the states do between iterations:
    # sparsax refactorises only for new values) and with the same values each call (as
    # with the states held: its factor is reused). The slip tangent: the exact tangent of
    # slipping slots (on the sparse path GMRES on CHOLMOD's factor, KLU where GMRES fails).
    def solve(scale, m, sb, ev, tangent):
        t = jnp.asarray(tangent)
        a, b, B, k = stiffness_terms(m, sb, ev, t, None)
        return _linsolve.linear_solve(m, sb, (a, b, B, k * scale), ev.R, symmetric=~t,
                                      coupling=slip_coupling(sb, ev, t) if tangent else None)

    def timed_new(tangent):
        return timed(lambda s, m, sb, e: solve(s, m, sb, e, tangent),
                     jnp.asarray(1.0), mdl2, packed, ev,
                     each=lambda i: (jnp.asarray(1.0 + 1e-9 * (i + 1)), mdl2, packed, ev))

    rows.append(("secant solve, same values", timed(
        lambda m, sb, e: solve(1.0, m, sb, e, False), mdl2, packed, ev)))
    rows.append(("secant solve, new values", timed_new(False)))
    rows.append(("slip tangent solve, new values", timed_new(True)))
    rows.append(("corner bound", timed(
        lambda m, sb, s, c, du: _substep.corner_bound(m, sb, s.centroid, c, du,
                                                      packed.geo.a.shape[0]),
        mdl2, sub, state, found.corners, newton.du)))
    rows.append(("Newton and commit", timed(_substep.newton_and_commit, mdl2, state, sub, st0,
                                            pairs, found)))
    # The evaluation laid out over every slot, as the commit gets it (none to lay out
    # where every slot has a place: pack_slots gives no indices).
    laid = ev if sid is None else jax.jit(_substep._unpacked)(mdl2, sub, ev, sid)

    def commit(m, s, sb, p, du, e, pk, pe):
        # The balance over the touching slots (their rows), as newton_and_commit sums it.
        return _substep.commit_substep(m, s, sb, p, du.astype(sb.load.dtype), e, None,
                                       (pk, pe))

    rows.append(("commit (move, springs, balance)",
                 timed(commit, mdl2, state, sub, pairs, newton.du, laid, packed, ev)))
    rows.append(("whole sub-step", timed(_substep.substep, model, state, loads)))

    S = st0.shape[0]
    print(f"# {args.scene}, increment {args.increment}; {platform.machine()}, "
          f"jax {jax.__version__}; medians of {args.repeats}, ms")
    print(f"# blocks {model.n_blocks} (size class), V {model.n_vertices}, narrow phase with "
          f"{model.narrow_vertices} ({model.wide_capacity} wide places); pairs "
          f"{int(count)} in {state.capacity} places, touching {int(touching)} in "
          f"{min(model.touch_capacity, state.capacity)}; slots touching "
          f"{int(jnp.sum(sub.geo.active))} of {S}, packed places "
          f"{packed.geo.a.shape[0]}; watched {int(jnp.sum(found.corners.watch))}; "
          f"CHOLMOD triplets {triplets}")
    print(f"{'piece':>32s} {'ms':>9s}")
    for name, ms in rows:
        print(f"{name:>32s} {ms:9.2f}")


if __name__ == "__main__":
    main()
