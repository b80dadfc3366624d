"""Host driver: load steps, in-situ stress and stages, each to static equilibrium; solve.

Owns :func:`solve` (scene -> :class:`jaxdem.results.Result`, the only place a
Result is built), :func:`run` and :class:`_Driver` (the host loop over stages
and load steps), :func:`stage_plan`, the driver's inputs :class:`Data` and
:func:`scene_data`, and :func:`run_increment` (one increment, growing the
contact capacity on overflow).

Data flow: the top of the solver. Scene -> :func:`jaxdem.core.model.build` -> device
Model and State -> increments (:mod:`jaxdem.core.increment`, compiled through
:mod:`jaxdem.core.compile_cache`) with loads from :mod:`jaxdem.core.loads` -> Result
(:mod:`jaxdem.results`). The pieces below, from the bottom up:
:mod:`jaxdem.core.status`, :mod:`jaxdem.core.kinematics`, :mod:`jaxdem.core._springs`,
:mod:`jaxdem.core._linsolve`, :mod:`jaxdem.core.loads`, :mod:`jaxdem.core._substep`,
:mod:`jaxdem.core.sensitivities`, :mod:`jaxdem.core.increment`. ``Status`` and
``COMPILE_TIMES`` are re-exported here for callers of ``jaxdem.solver``.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.config import float64
from jaxdem.core import model as model_mod
from jaxdem.core.compile_cache import (
    COMPILE_TIMES,
    QUICK_WORK,
    compiled_program,
    on_disk,
    precompile,
    prefetch,
    result_shapes,
    run_stored,
    while_waiting,
)
from jaxdem.core.increment import bounded_factorisations, increment, increment_tangent
from jaxdem.core.kinematics import MOVING, connected_groups
from jaxdem.core.loads import in_situ_preload, make_loads, release_forces_jit
from jaxdem.core.sensitivities import STATE_FLOATS, preload_tangent, release_with_tangent
from jaxdem.core.state import OPEN, Loads, Model, State, grow_capacity
from jaxdem.core.status import Status, global_imbalance
from jaxdem.results import (
    bolt_geometry_program,
    build_result,
    loose_limit,
    monitor_values,
    stage_frame,
)

__all__ = ["COMPILE_TIMES", "Data", "Status", "gravity_material", "increment_arguments",
           "increment_count", "loose_limit", "run", "run_increment", "scene_data", "solve"]


@float64
def solve(scene, set: dict | None = None, progress=None):
    """Solve a scene: load steps, in-situ stress and stages, each to static equilibrium.

    Without ``[in_situ]`` the scene starts unloaded and self-weight and
    tractions are applied over ``solver.load_steps`` increments. With it, the
    contacts start with the in-situ stress (zero displacement). Then each
    stage (``[[stages]]``, or one stage when the scene has excavations,
    supports or bolts but no stages) removes its excavations, whose forces on
    the remaining rock are released over the stage's load steps, installs its
    bolts, ramps its support pressures and moves the water table.
    Displacements are reported from the state before the first stage.

    Args:
      scene: a validated :class:`jaxdem.scene.Scene` (from :func:`jaxdem.load_scene`).
      set: parameter overrides by dotted path, e.g. ``{"joints.set1.kn": 2e6}``.
      progress: optional callable, called after each increment with a dict
        (``stage``, ``step``, ``n_steps``, ``status``, ``cut``: the increment ended at the
        iteration limit and is tried again with half the load step, ``iterations``,
        ``substeps``, ``residual``, ``stage_index``: 0 for the initial state (the
        "loading" or in-situ "initial" record), k for the k-th stage (the file's
        ``stage = k``), ``n_stages``: how many stages follow the initial state).
    Returns:
      a :class:`jaxdem.results.Result`.

    Example::

        scene = jaxdem.load_scene("examples/block_on_incline.toml")
        result = jaxdem.solve(scene, set={"joints.base.friction_deg": 25.0})
        print(result.stable, result.monitors)
    """
    if set:
        scene = scene.with_overrides(set)
    t0 = time.perf_counter()
    model, state, layout = model_mod.build(scene)
    jax.block_until_ready(state.verts)
    build_s = time.perf_counter() - t0
    frames = []

    def frame(d, name=None):
        # Host copies of the state at the end of each stage (Result.geometry["stages"]).
        frames.append(stage_frame(scene, d.model, layout, d.state, d.ref, d.info,
                                  d.bolt_active.copy(), d.records[-1]["stage"], d.stage_index,
                                  len(d.records)))

    d = run(scene, model, state, layout, scene_data(scene, layout), progress, stage_end=frame)
    if not frames or frames[-1]["increments"] != len(d.records):  # stopped inside a stage
        frame(d)
    timing = dict(build_s=build_s, compile_s=d.compile_s, solve_s=d.solve_s)
    result = build_result(scene, d.model, layout, d.state, d.ref, d.info, d.records, d.history,
                          timing, bolt_active=d.bolt_active, loose=d.loose, cuts=d.cuts)
    result.geometry["stages"] = frames
    return result


@float64
def increment_arguments(scene):
    """(model, state, loads): the arguments of a scene's increment program
    (:func:`jaxdem.core.increment.increment`) as :func:`solve` makes them for a load step of
    self-weight and tractions from the unloaded start, to compile, time or profile that
    program alone (``benchmarks/bench_compile.py``). Every increment of the scene (in-situ,
    stages) has these shapes until a contact capacity grows, so this is the program they
    all run (the solver compiles it with its own XLA options:
    :func:`jaxdem.core.compile_cache.compiled_program`).

    Example (float64 for the whole process first, as the command line has it)::

        from jaxdem.core.increment import increment

        jaxdem.config.configure()
        model, state, loads = jaxdem.solver.increment_arguments(scene)
        compiled = increment.lower(model, state, loads).compile()
        new_state, report = compiled(model, state, loads)
    """
    model, state, layout = model_mod.build(scene)
    data = scene_data(scene, layout)
    loads, _ = _Driver(model, state, layout, data, None).loads(data.weight + data.traction)
    return model, state, loads


def run(scene, model: Model, state: State, layout, data: Data, progress=None,
        stage_end=None, driver=None, quick: bool | None = None) -> _Driver:
    """Run a built scene through its loading and stages; returns the finished driver.

    ``data`` gives the loads (and, with p > 0, their derivatives, which the
    driver then carries: :class:`Data`). ``stage_end``, if given, is called
    with the driver and the stage name at the end of each stage ("initial"
    for the state before the first stage). ``driver``, if given, replaces the
    single-solve :class:`_Driver` (``jaxdem.batch`` passes one that solves a
    batch of samples, with ``data`` stacked over the samples). ``quick``: compile
    the programs for a brief run (:data:`jaxdem.core.compile_cache.QUICK_COMPILER_OPTIONS`);
    None decides by the size of the solve: a single small solve (blocks x
    increments up to :data:`jaxdem.core.compile_cache.QUICK_WORK`, no sensitivities).
    A caller that solves the same scene many times passes False.
    """
    plan = stage_plan(scene)
    if driver is None:
        if quick is None:
            quick = data.p == 0 and model.n_blocks * increment_count(scene, layout) <= QUICK_WORK
        driver = _Driver(model, state, layout, data, progress, quick)
        if data.p == 0:
            driver.start_compiling(data.weight + data.traction, bool(scene.excavations))
    d = driver
    # Where the progress events are: 0 the initial state (loading or in-situ), k the
    # k-th stage of the plan (the file's ``stage = k``), of ``n_stages``.
    d.stage_index, d.n_stages = 0, len(plan)
    in_situ = scene.in_situ
    N, D = model.n_blocks, model.ndof
    zero = np.zeros((1 + data.p, N, D))
    pending = zero  # applied over the first stage (uniform in-situ mode)
    if in_situ is None and not plan:
        # Without in-situ stress and with nothing after the loading (no stage, no
        # excavation, no support), a bolt is part of the scene the loading builds: it
        # acts from the first load step. Otherwise it is installed in its stage (the
        # first, when it names none).
        d.bolt_active[:] = True
    if isinstance(d, _Driver):
        d.max_cuts = scene.solver.max_step_cuts
    if in_situ is None:
        base = data.weight + data.traction
        # Pore pressure grows with the weight: a saturated slope is loaded
        # as a whole, not by full water pressure on a weightless mass.
        ramp(d, "loading", layout.load_steps,
             lambda lam: (d.loads(lam * base, water_scale=lam), None))
    else:
        if in_situ.mode == "gravity":
            base = data.weight + data.traction
        else:
            base, pending = data.traction, data.weight
        d.preload(scene, base)
        d.step("initial", 1, 1, d.loads(base))
    # Displacements count from the state before the first stage, once there
    # is one and the loading before it found equilibrium.
    started = (plan or in_situ is not None) and d.status == Status.CONVERGED
    d.ref, d.dref = (d.state, d.dstate) if started else (None, None)
    if stage_end is not None:
        stage_end(d, "initial")
    # The excavations whose load is being released (RS2's load split): the forces their
    # blocks carried on the rock (``load``, (1 + p, N, D)), the fraction of it still held at
    # the start of the stage (``before``), and after it and each stage to come (``held``,
    # from ``Excavation.held``).
    releasing: list[dict] = []
    relaxed = any(len(e.release) > 1 for e in scene.excavations)
    # Loose blocks (README, "Loose blocks"): a stage that ends in a mechanism of small
    # blocks falling free is run again from its start with them excavated in it (in a
    # batch, for the samples where they fell: jaxdem.batch).
    limit = loose_limit(scene) if scene.solver.loose_blocks == "remove" else None
    if limit is not None and limit <= 0.0:
        limit = None
    for index, stage in enumerate(plan, 1):
        if d.status != Status.CONVERGED:
            break
        d.stage_index = index
        start = d.checkpoint() if limit is not None else None
        loose = d.no_loose()  # (N,); in a batch (C, N), each sample's own
        for attempt in range(MAX_LOOSE_ROUNDS + 1):
            now = _run_stage(d, stage, layout, data, base, pending, releasing, loose, relaxed)
            found = (d.free_falling(limit) if limit is not None and attempt < MAX_LOOSE_ROUNDS
                     else None)
            if found is None or not (found & ~loose).any():
                break
            found &= ~loose
            d.again(start, found)
            d.record_loose(found, stage["name"])
            loose |= found
        base, pending = base + pending + now["support"], zero
        releasing = [dict(r, before=r["held"][0], held=r["held"][1:]) for r in now["releasing"]
                     if len(r["held"]) > 1]
        d.water_y = now["water_y"]
        if stage_end is not None and d.status == Status.CONVERGED:
            stage_end(d, stage["name"])
    return d


def _run_stage(d, stage, layout, data, base, pending, releasing, loose, relaxed) -> dict:
    """The increments of one stage: it removes its excavations (and the ``loose`` (N,)
    blocks, all released in this stage), installs its bolts, ramps its supports and moves
    the water table. Returns the stage's ``support`` load, the ``releasing`` list of this
    stage (those before it and its own) and its water table ``water_y``."""
    N, D = d.model.n_blocks, d.model.ndof
    zero = np.zeros((1 + data.p, N, D))
    releasing = list(releasing)
    removed = np.zeros(N, bool)
    removed[:layout.n_rock] = [e is not None and e in stage["excavations"]
                               for e in layout.excavation]
    groups = _release_groups(stage["excavations"], layout, N)
    if loose.any():
        groups.append(([], loose, (0.0,)))
    removed = removed | loose  # (N,), or (C, N) in a batch: each sample's own
    for names, mask, held in groups:
        load = d.release(mask)
        if not np.array_equal(mask, removed):
            # Several schedules in one stage: what these blocks pushed on the blocks
            # removed with them is on no block left.
            load = np.where((removed & ~mask)[..., None], 0.0, load)
        releasing.append(dict(names=names, load=load, before=1.0, held=held))
    if removed.any():
        alive = np.asarray(d.state.alive) & ~removed
        d.state = dataclasses.replace(d.state, alive=jax.device_put(alive))
    for b, bs in enumerate(layout.bolt_stages):
        if bs == stage["name"] or (bs is None and stage["first"]):
            d.bolt_active[b] = True
    support = sum((f for sp, f in zip(layout.supports, data.supports, strict=True)
                   if sp["stage"] == stage["name"] or (sp["stage"] is None and stage["first"])),
                  zero)
    y_old = d.water_y
    y_new = data.stage_water.get(stage["name"], y_old)

    def at(lam):
        # What is still held of each release, from ``before`` down to ``held[0]``
        # (1 - lam of it for a release in one stage).
        still = [r["before"] - lam * (r["before"] - r["held"][0]) for r in releasing]
        parts = [h * r["load"] for h, r in zip(still, releasing, strict=True)]
        release = sum(parts[1:], parts[0]) if parts else zero
        force = base + release + lam * (pending + support)
        # (rounded to 12 digits for the record: 0.08, not 0.08000000000000007)
        released = ({name: round(1.0 - h, 12) for h, r in zip(still, releasing, strict=True)
                     for name in r["names"]} if relaxed else None)
        return d.loads(force, (1 - lam) * y_old + lam * y_new), released

    ramp(d, stage["name"], stage["load_steps"] or layout.load_steps, at)
    return dict(support=support, releasing=releasing, water_y=y_new)


def ramp(d, stage: str, n: int, at) -> None:
    """The increments of one stage (or of the loading): its load factor from 0 to 1 in
    ``n`` steps, ``at(lam)`` giving the loads of the increment that ends at lam (and the
    released fractions to record, or None), until one does not converge.

    A load step that ends at the iteration limit is cut in two and tried again from the
    equilibrium before it (the driver's :meth:`_Driver.checkpoint`), at most
    ``d.max_cuts`` times in the stage; the rest of the stage keeps the shorter step
    (README, "Load steps cut"). That is how an implicit code controls its step: a step
    too long for Newton to follow the contacts' changes is not a failure of the rock
    (seed example 3 without D at k0 = 1/3: 4 load steps stop at half the release, 8
    reach it). Where the shortest step fails too, the analysis stops there, with the
    last equilibrium the one before it. The load factors are k / (n 2^cuts), exactly
    those of a stage of that many steps. A batch (``jaxdem.batch``, whose driver has no
    ``max_cuts``) never cuts: its samples share their load steps.
    """
    cuts = getattr(d, "max_cuts", 0)
    k, made = 0, 0
    while k < n:
        saved = d.checkpoint() if made < cuts else None
        loads, released = at((k + 1) / n)
        if d.step(stage, k + 1, n, loads, released, **({} if saved is None else {"retry": True})):
            k += 1
            continue
        if saved is None or d.status != Status.ITERATION_LIMIT:
            return
        d.restore(saved)
        k, n, made = 2 * k, 2 * n, made + 1
        d.cuts.append(stage)


MAX_LOOSE_ROUNDS = 5
"""Most times a stage is solved again without the loose blocks found (each time a whole
stage): a rock mass that keeps ravelling after that is reported as a mechanism."""


def _release_groups(excavations: dict, layout, N: int) -> list:
    """The blocks a stage removes, grouped by how their load is released: a list of
    (excavation names, (N,) bool mask, fractions held after each stage of the release)."""
    groups: dict[tuple, tuple] = {}
    for i, name in enumerate(layout.excavation[:layout.n_rock]):
        if name is not None and name in excavations:
            names, mask = groups.setdefault(excavations[name], ([], np.zeros(N, bool)))
            mask[i] = True
            if name not in names:
                names.append(name)
    return [(names, mask, held) for held, (names, mask) in groups.items()]


def increment_count(scene, layout) -> int:
    """How many increments a solve of ``scene`` takes (if each finds equilibrium)."""
    first = 1 if scene.in_situ is not None else layout.load_steps
    return first + sum(stage["load_steps"] or layout.load_steps for stage in stage_plan(scene))


def stage_plan(scene) -> list[dict]:
    """The stages after the initial state, in order, with what each one does.

    ``excavations``: {name: the fractions of its load held after each stage of its
    release (:attr:`jaxdem.scene.Excavation.held`)} of those the stage removes."""
    excavations = scene.excavations
    stages = list(scene.stages)
    bolts_later = scene.bolts and scene.in_situ is not None
    if not stages and (excavations or scene.supports or bolts_later):
        return [dict(name="excavation", first=True, load_steps=None, water_table=None,
                     excavations={e.name: e.held for e in excavations})]
    if not stages and scene.in_situ is not None and scene.in_situ.mode == "uniform":
        # A uniform in-situ stress leaves self-weight to the first stage; with
        # no stage, it is applied over the load steps of a "loading" stage.
        return [dict(name="loading", first=True, load_steps=None, water_table=None,
                     excavations={})]
    first = stages[0].name if stages else None
    return [dict(name=st.name, first=st.name == first, load_steps=st.load_steps,
                 water_table=st.water_table,
                 excavations={e.name: e.held for e in excavations
                              if e.stage == st.name or (e.stage is None and st.name == first)})
            for st in stages]


@dataclasses.dataclass
class Data:
    """What the host driver applies, with derivatives: every array has a leading axis 1 + p.

    Entry 0 is the value, entries 1..p its derivatives with respect to p scene
    parameters (p = 0 for a plain solve). The driver only adds and scales these
    arrays, so derivatives follow the values through stages and load steps.
    For a batch (``jaxdem.batch``) the leading axis holds the samples instead.

    Attributes:
      weight, traction: (1 + p, N, D) self-weight and boundary tractions (kN/m).
      supports: one (1 + p, N, D) load per entry of ``Layout.supports``.
      sigma: (1 + p, 3) uniform in-situ stress (kPa, compression positive);
        k0, gamma, surface: (1 + p,) gravity in-situ K0, unit weight (kN/m3)
        and ground surface (m).
      water_x: (X,) abscissae of the water tables (m); water_y: (1 + p, X) the
        scene's table; stage_water: {stage name: (1 + p, X)}.
      dmodel: {field: (p, ...)} derivatives of the model's
        :data:`jaxdem.core.sensitivities.SMOOTH_MODEL` fields (None when p = 0).
    """

    weight: np.ndarray
    traction: np.ndarray
    supports: list
    sigma: np.ndarray
    k0: np.ndarray
    gamma: np.ndarray
    surface: np.ndarray
    water_x: np.ndarray
    water_y: np.ndarray
    stage_water: dict
    dmodel: dict | None = None

    @property
    def p(self) -> int:
        return self.weight.shape[0] - 1


def gravity_material(scene, layout) -> str:
    """The material whose unit weight makes the gravity in-situ stress: the domain's,
    else that of the first rock block that is not excavated."""
    if scene.domain is not None:
        return scene.domain.material
    return next(layout.materials[i] for i in range(layout.n_rock) if layout.excavation[i] is None)


def scene_data(scene, layout) -> Data:
    """The driver's inputs of a scene as built, without derivatives (p = 0)."""
    one = lambda x: np.asarray(x, float)[None]  # noqa: E731
    in_situ = scene.in_situ
    gamma = surface = k0 = 0.0
    sigma = np.zeros(3)
    if in_situ is not None:
        k0 = in_situ.k0
        sigma = np.array([in_situ.sigma_xx, in_situ.sigma_yy, in_situ.sigma_xy])
        if in_situ.mode == "gravity":
            name = gravity_material(scene, layout)
            gamma, surface = scene.materials[name].unit_weight, in_situ.surface_y
    water = scene.water
    tables = ([water.table] if water is not None else []) + [
        st.water_table for st in scene.stages if st.water_table is not None]
    xs = (np.unique(np.concatenate([np.asarray(t, float)[:, 0] for t in tables]))
          if tables else np.array([0.0, 1.0]))
    # A size class for the abscissae too (the last repeated): one program for similar tables.
    xs = np.concatenate([xs, np.full(model_mod.bucket(len(xs)) - len(xs), xs[-1])])
    sample = lambda table: np.interp(xs, *np.asarray(table, float).T)  # noqa: E731
    return Data(
        weight=one(layout.weight), traction=one(layout.traction),
        supports=[one(sp["force"]) for sp in layout.supports], sigma=one(sigma), k0=one(k0),
        gamma=one(gamma), surface=one(surface), water_x=xs,
        water_y=one(sample(water.table) if water is not None else np.full(xs.shape, -1e30)),
        stage_water={st.name: one(sample(st.water_table)) for st in scene.stages
                     if st.water_table is not None})


_connected_groups = on_disk("connected_groups")(jax.jit(connected_groups))
"""Groups of blocks in closed contact, for :func:`falling_free` (one program)."""


def falling_free(model: Model, layout, travel, snap, alive, limit: float):
    """The (N,) mask of the blocks of a mechanism if they all fall free and are small,
    else None: ``travel`` (N,) each block's path in the increment that found it (m),
    ``snap`` its contacts at the end, ``alive`` (N,) the blocks still there.

    Moving: travelled more than :data:`jaxdem.core.kinematics.MOVING` (a tenth) of
    ``max_displacement`` in the increment (as ``Result.moving_blocks``). Free: no closed
    contact (stuck or slipping) joins a moving block to one that is not moving, or to a
    boundary. Small: each group of moving blocks in closed contact with each other has an
    area of at most ``limit`` (m2, m3 per m of tunnel).
    """
    nr, N = layout.n_rock, model.n_blocks
    moving = np.zeros(N, bool)
    moving[:nr] = np.asarray(travel)[:nr] > MOVING * float(model.max_displacement)
    moving &= np.asarray(alive)
    if not moving.any():
        return None
    closed = (np.asarray(snap.active) & (np.asarray(snap.state) != OPEN)).reshape(-1)
    a, b = np.asarray(snap.a).reshape(-1), np.asarray(snap.b).reshape(-1)
    if np.any(moving[a[closed]] != moving[b[closed]]):
        return None  # a contact in the way: the blocks slide or rotate on the rock
    # Groups of moving blocks in closed contact (the slots' fixed shapes: one program).
    put = jax.device_put
    group = np.asarray(run_stored(_connected_groups, put(moving), put(a), put(b), put(closed)))
    area = np.bincount(group[moving], weights=np.asarray(model.area)[moving], minlength=N)
    return moving if area.max() <= limit else None


class _Driver:
    """Host loop over stages and load steps; collects the records of a Result.

    With derivatives (``data.p > 0``) it carries ``dstate``, the derivatives
    of the state's :data:`jaxdem.core.sensitivities.STATE_FLOATS` with respect to the p parameters.
    """

    def __init__(self, model, state, layout, data: Data, progress, quick: bool = False):
        self.model, self.state, self.layout = model, state, layout
        self.data, self.progress = data, progress
        self.compile_s = self.solve_s = 0.0
        self.records, self.history = [], []
        self.info = None
        self.ref = None  # the state displacements are measured from (None: the start)
        self.dref = None
        self.status = Status.CONVERGED
        self.bolt_active = np.zeros(model.n_bolts, bool)
        self.stage_index = self.n_stages = 0  # set by run(): see its progress events
        self.water_y = data.water_y
        self.approximate = False
        self.quick = quick  # programs compiled quick (compile_cache.QUICK_COMPILER_OPTIONS)
        self.loose: list[dict] = []  # blocks removed as loose: id, stage, volume, centroid
        # Load steps cut (:func:`ramp`): at most max_cuts a stage; the stage of each cut.
        self.max_cuts = 0
        self.cuts: list[str] = []
        p = data.p
        self.dstate = None if p == 0 else {
            k: jnp.zeros((p,) + getattr(state, k).shape, getattr(state, k).dtype)
            for k in STATE_FLOATS}

    def start_compiling(self, force, excavating=False):
        """Compile the increment on a background thread from now (a single solve).

        Meanwhile this thread compiles the monitors' programs, and then the
        in-situ preload (:meth:`preload`): on two cores neither waits for the
        other. ``force`` (1 + p, N, D) gives the loads' shapes. Where it would then
        wait, it compiles the small programs that come after the first increment: the
        bolts' anchors (each stage's result) and, where the scene excavates
        (``excavating``), the forces of the blocks removed (:meth:`release`): in a cold
        run of the demo 0.35 s that were spent after the increment's compilation, on the
        way to the answer.
        """
        # The tracing is this thread's time, and counts as compilation; the XLA
        # compilation (or a stored program's load) runs beside what comes next.
        model, state, loads = self.model, self.state, self.loads(force)[0]
        self.compile_s += prefetch(increment, model, state, loads, quick=self.quick)
        if self.layout.monitors:
            monitor_values(self.layout, self.state)

        def host_steps():
            if model.n_bolts:
                precompile(bolt_geometry_program, model, state)
            out = result_shapes(increment, model, state, loads, quick=self.quick)
            if excavating and out is not None:
                N = model.n_blocks
                precompile(release_forces_jit, state.centroid, out[1].snapshot,
                           jax.ShapeDtypeStruct((N,), jnp.bool_), ndof=model.ndof)

        while_waiting(host_steps)

    def loads(self, force, water_y=None, water_scale=1.0):
        """Loads of an increment from (1 + p, ...) stacks, and their derivatives (or None)."""
        wy = self.water_y if water_y is None else water_y
        loads = make_loads(self.model, force[0], self.data.water_x, wy[0], self.bolt_active,
                           water_scale)
        if self.dstate is None:
            return loads, None
        dtype = loads.force.dtype
        return loads, dict(force=jnp.asarray(force[1:], dtype), water_y=jnp.asarray(wy[1:], dtype))

    def step(self, stage, k, n, loads, released=None, retry=False):
        """One increment (load step k of n of ``stage``); ``released``: {excavation: fraction
        of its load released so far}, recorded in scenes that release loads over stages;
        ``retry``: an iteration limit will be tried again with half the step (:func:`ramp`),
        which the progress event says (``cut``)."""
        loads, dloads = loads
        tangents = None if dloads is None else dict(model=self.data.dmodel, state=self.dstate,
                                                    loads=dloads)
        t1 = time.perf_counter()
        self.model, self.state, info, dt = run_increment(self.model, self.state, loads, tangents,
                                                         self.quick)
        jax.block_until_ready(self.state.verts)
        self.compile_s += dt
        self.solve_s += time.perf_counter() - t1 - dt
        self.info = info
        if tangents is not None:
            self.dstate = info.dstate
            self.approximate |= bool(info.approximate)
        self.status = Status.of(info.status)
        bal, jm = info.balance, info.joints
        rec = dict(stage=stage, step=k, n_steps=n, load_factor=k / n, status=self.status,
                   iterations=int(info.iterations), substeps=int(info.substeps),
                   residual=float(info.residual), imbalance=global_imbalance(bal),
                   overlap=float(bal.overlap), overlap_rel=float(bal.overlap_rel),
                   strength_excess=float(bal.excess),
                   slip=float(jm.slip), slip_rel=float(jm.slip_rel),
                   slip_blocks=[int(x) for x in np.asarray(jm.slip_blocks)],
                   opening=float(jm.opening),
                   opening_blocks=[int(x) for x in np.asarray(jm.opening_blocks)])
        if released is not None:
            rec["released"] = released
        self.records.append(rec)
        self.history.append(dict(stage=stage, step=k, load_factor=k / n,
                                 monitors=monitor_values(self.layout, self.state, self.ref)))
        if self.progress is not None:
            self.progress(dict(stage=stage, step=k, n_steps=n, status=self.status.label,
                               cut=retry and self.status == Status.ITERATION_LIMIT,
                               iterations=rec["iterations"], substeps=rec["substeps"],
                               residual=rec["residual"], stage_index=self.stage_index,
                               n_stages=self.n_stages))
        return self.status == Status.CONVERGED

    def checkpoint(self) -> dict:
        """What a stage changes in the driver, to run it again (:meth:`restore`)."""
        return dict(state=self.state, dstate=self.dstate, info=self.info, status=self.status,
                    records=len(self.records), history=len(self.history),
                    bolt_active=self.bolt_active.copy(), approximate=self.approximate,
                    cuts=len(self.cuts))

    def again(self, saved: dict, found) -> None:
        """Back to the stage's :meth:`checkpoint` ``saved``, to run it again without the
        loose blocks ``found`` (N,) (:func:`run`)."""
        self.restore(saved)

    def restore(self, saved: dict) -> None:
        """Back to a :meth:`checkpoint` (the model keeps any capacity grown since)."""
        self.state, self.dstate, self.info = saved["state"], saved["dstate"], saved["info"]
        self.status, self.approximate = saved["status"], saved["approximate"]
        del self.records[saved["records"]:], self.history[saved["history"]:]
        del self.cuts[saved["cuts"]:]
        self.bolt_active = saved["bolt_active"].copy()

    def no_loose(self) -> np.ndarray:
        """The (N,) mask of no loose block, which :func:`run` fills stage by stage."""
        return np.zeros(self.model.n_blocks, bool)

    def record_loose(self, found, stage: str) -> None:
        """The blocks ``found`` (N,) falling free in ``stage``, for ``Result.loose_blocks``."""
        self.loose += [dict(id=int(i), stage=stage, volume=float(np.asarray(self.model.area)[i]),
                            centroid=self.layout.centroids[i].tolist())
                       for i in np.nonzero(found)[0]]

    def free_falling(self, limit: float):
        """After a mechanism: the (N,) mask of the moving blocks if they all fall free and
        are small, else None (:func:`falling_free`)."""
        if self.status != Status.MECHANISM:
            return None
        return falling_free(self.model, self.layout, self.info.travel, self.info.snapshot,
                            self.state.alive, limit)

    def release(self, removed):
        """Forces (1 + p, N, D) of the blocks being removed on the rest, from the last contacts."""
        N, D = self.model.n_blocks, self.model.ndof
        out = np.zeros((1 + self.data.p, N, D))
        if not removed.any() or self.info is None:
            return out
        snap, rm = self.info.snapshot, jax.device_put(np.asarray(removed))
        if self.dstate is None:
            out[0] = np.asarray(run_stored(release_forces_jit, self.state.centroid, snap, rm,
                                           ndof=D))
            return out
        value, tangent = release_with_tangent(self.state.centroid, snap, rm,
                                              self.dstate["centroid"], self.info.dsnapshot, D)
        out[0], out[1:] = np.asarray(value), np.asarray(tangent)
        return out

    def preload(self, scene, base):
        """The in-situ state (contact forces of the in-situ stress at zero displacement)."""
        data, mode = self.data, scene.in_situ.mode
        stacks = (data.sigma, data.surface, data.gamma, data.k0)
        args = tuple(jax.device_put(np.asarray(x[0], self.layout.dtype)) for x in stacks)
        loads, dloads = self.loads(base)
        while True:
            if self.dstate is None:
                # Run once a solve: compiled quick, whatever the increment.
                pre, dt = compiled_program(in_situ_preload, self.model, self.state, loads, *args,
                                           mode=mode, quick=True)
                self.compile_s += dt
                st, overflow = pre(self.model, self.state, loads, *args)
            else:
                dargs = tuple(jnp.asarray(x[1:], self.layout.dtype) for x in stacks)
                st, overflow, self.dstate = preload_tangent(
                    self.model, self.state, loads, args, data.dmodel, dloads, dargs, mode=mode)
            if not bool(overflow):
                break
            # More candidate pairs than places, or more neighbours in the grid's cells or
            # wide pairs than the detection's places (the preload says only that one
            # overflowed): grow both, and redo.
            self.state = grow_capacity(self.state, model_mod.bucket(2 * self.state.capacity))
            self.model = model_mod.grown(self.model, True, False)
        self.state = st


def run_increment(model: Model, state: State, loads: Loads, tangents: dict | None = None,
                  quick: bool = False):
    """One increment with capacity growth: on overflow, grow and redo from ``state``.

    Returns (model, state, info, compile_s), info the increment's
    report (:class:`jaxdem.core.increment.Progress`): the model changes only when a
    grid cell capacity grew. Growing recompiles; nothing is ever truncated.
    With ``tangents`` (see :func:`jaxdem.core.increment.increment_tangent`) the state's derivatives
    are carried along (``info.dstate``). ``quick``: compile for a brief run
    (:func:`jaxdem.core.compile_cache.compiled_program`).
    """
    compile_s = 0.0
    while True:
        if tangents is None:
            fn, dt = compiled_program(increment, model, state, loads, quick=quick)
            args = (model, state, loads)
        else:
            fn, dt = compiled_program(increment_tangent, model, state, loads, tangents)
            args = (model, state, loads, tangents)
        with bounded_factorisations():  # sparsax's memory, up to the program's result
            new, info = fn(*args)
            status = Status.of(info.status)
        compile_s += dt
        if status != Status.CAPACITY_OVERFLOW:
            return model, new, info, compile_s
        model = model_mod.grown(model, bool(info.cell_full), bool(info.slots_full),
                                int(info.touch_needed))
        need = int(info.pairs_needed)
        if need > state.capacity:
            capacity = model_mod.bucket(max(2 * state.capacity, int(1.3 * need) + 16))
            state = grow_capacity(state, capacity)
            if tangents is not None:
                tangents = dict(tangents, state=_grow_tangent(tangents["state"], capacity))


def _grow_tangent(dstate: dict, capacity: int) -> dict:
    """Slot derivatives (p, P, 2, V) padded with zeros to a larger pair capacity."""
    out = dict(dstate)
    for k in ("fs", "fn", "fn0"):
        x = dstate[k]
        out[k] = jnp.zeros((x.shape[0], capacity) + x.shape[2:], x.dtype).at[:, :x.shape[1]].set(x)
    return out
