"""Ground reaction curve of an excavation, all levels in one batch (``jaxdem grc``).

The convergence-confinement method sizes support from two curves (Panet 1995,
"Le calcul des tunnels par la methode convergence-confinement"; Carranza-Torres
& Fairhurst 2000, "Application of the convergence-confinement method of tunnel
design to rock masses that satisfy the Hoek-Brown failure criterion", Tunnelling
and Underground Space Technology 15(2)): the ground reaction curve, the support
pressure p on the opening's wall against the wall's convergence u as p falls
from the in-situ stress p0 to 0, and the support characteristic, the pressure
a support develops as the wall converges after it is installed. Where they
cross the rock and the support are in equilibrium.

A level p is the scene with a support pressure p (``[[supports]]``: a uniform
normal pressure on the excavation's faces) installed in the excavation's own
stage and ramped over its load steps, so the wall is unloaded by p0 - p
under hydrostatic stress. The K levels, from ``start`` (default p0) down to 0
evenly spaced, are one :func:`jaxdem.batch.solve_batch` over the parameter
``supports.I.pressure``; each level is the single solve with that pressure.

The scene solved (:func:`grc_scene`) is the scene as given, through the
excavation's stage (later stages, and what they excavate, install or apply,
are left out: the curve is that excavation's). Its support on the excavation:
the first ``[[supports]]`` entry on it in that stage carries the level's
pressure (its own value is replaced), further entries on it in that stage are
set to 0; without one, a support of pressure 0 is added. Bolts, other
excavations in the stage and supports of other excavations stay as given.

p0, the in-situ normal stress at the face (:func:`in_situ_pressure`), is the
mean over the excavation's outline of the normal stress sigma_n = n . sigma . n
that the ``[in_situ]`` stress puts on it (compression positive; exactly p0
under a hydrostatic stress p0), or a value given.

A level whose solve finds no equilibrium is reported with its status; at the
highest pressure at which a mechanism appears the moving blocks are named from the
batch's own solve of that level (:attr:`jaxdem.batch.BatchResult.moving_blocks`,
the blocks a single run names). A level at the very edge of a mechanism may end
differently in a batch beside other levels than alone (docs/ground-reaction.md).

The support characteristic (:class:`SupportLine`) is p_s(u) = min(k (u - u0),
p_max) for u >= u0 and 0 before: stiffness k (kPa per m of convergence),
capacity p_max (kPa), installed when the convergence is u0 (m). Its
intersection with the ground reaction curve (straight between levels) gives
the equilibrium pressure p_eq and convergence u_eq, and the support's factor of
safety p_max / p_eq. The convergence is that of one monitor (``monitor``):
a section's convergence (m, positive when closing; across a diameter twice the
wall's radial displacement), or a point monitor's displacement towards the
centroid of the excavation's outline (m, positive inwards: on a circular
opening's wall the radial displacement u_r; :func:`inward`); default the
first section monitor, else the first point monitor. A point's |u| is not
used: it does not change sign, so where a support pressure above the local
in-situ stress pushes the wall out, the curve would fold back on itself.

Example::

    scene = jaxdem.load_scene("tunnel.toml")
    curve = jaxdem.ground_reaction(scene, "tunnel", levels=16,
                                   support=dict(stiffness=2e5, capacity=300.0,
                                                installed_at=0.002))
    curve.pressure, curve.monitors["span"], curve.equilibrium
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from jaxdem.config import float64
from jaxdem.core.status import Status
from jaxdem.geometry import centroid, point_in_polygon
from jaxdem.results import jsonable, write_json
from jaxdem.scene import SceneError, parse_scene

MAX_LEVELS = 1024
"""Most levels of a curve (each level is a solve)."""

#: Outcome labels of a level (from :class:`jaxdem.core.status.Status`).
STABLE, MECHANISM = "converged", "mechanism"


@dataclasses.dataclass(frozen=True)
class SupportLine:
    """A support characteristic: p_s(u) = min(stiffness (u - installed_at), capacity) once
    the convergence u passes ``installed_at``, 0 before.

    Attributes:
      stiffness: k, kPa of support pressure per m of convergence (> 0).
      capacity: p_max, the largest pressure it carries, kPa (> 0).
      installed_at: u0, the convergence when it is installed, m (>= 0).
    """

    stiffness: float
    capacity: float
    installed_at: float = 0.0

    @classmethod
    def of(cls, value: SupportLine | Mapping | tuple) -> SupportLine:
        """A SupportLine from itself, a mapping of its fields, or a (k, p_max, u0) tuple;
        checked (SceneError naming the field)."""
        if isinstance(value, SupportLine):
            line = value
        elif isinstance(value, Mapping):
            unknown = set(value) - {"stiffness", "capacity", "installed_at"}
            if unknown:
                raise SceneError(f"support.{sorted(unknown)[0]}", "unknown field; the fields "
                                 "are stiffness, capacity, installed_at")
            missing = {"stiffness", "capacity"} - set(value)
            if missing:
                raise SceneError(f"support.{sorted(missing)[0]}", "required")
            line = cls(**value)
        else:
            try:
                line = cls(*value)
            except TypeError:
                raise SceneError("support", "expected (stiffness, capacity[, installed_at]) "
                                 f"(got {value!r})") from None
        for name, lo, closed in (("stiffness", 0.0, False), ("capacity", 0.0, False),
                                 ("installed_at", 0.0, True)):
            x = getattr(line, name)
            ok = isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
            if not ok or not math.isfinite(x) or not (x >= lo if closed else x > lo):
                raise SceneError(f"support.{name}", f"must be a number {'>=' if closed else '>'} "
                                 f"{lo:g} (got {x!r})")
        return cls(float(line.stiffness), float(line.capacity), float(line.installed_at))

    def pressure(self, u) -> np.ndarray:
        """p_s(u), kPa, at convergences u (m)."""
        u = np.asarray(u, float)
        return np.clip(self.stiffness * (u - self.installed_at), 0.0, self.capacity)


@dataclasses.dataclass
class GroundReaction:
    """A ground reaction curve and, with a support line, its equilibrium.

    Attributes:
      scene: the scene's name.
      excavation: the excavation's name; ``stage`` the stage that excavates it.
      p0: the in-situ normal stress at the face (kPa); ``p0_from`` "in_situ" (the mean
        normal stress on the outline) or "given".
      pressure: (K,) support pressure of each level, kPa, from ``start`` down to 0.
      monitors: monitor name -> (K,) values (m): a section's convergence, a point's
        displacement towards the excavation's centroid (:func:`inward`); NaN where the
        level found no equilibrium.
      displacements: point monitor name -> (K, 2) [ux, uy] (m).
      status: (K,) status label of each level ("converged", "mechanism", ...).
      monitor: the monitor whose value is the convergence of the support line.
      parameter: the support pressure's parameter path in the scene solved.
      supports_note: what was done to the scene's supports (module docstring).
      dropped_stages: the stages after the excavation's, left out.
      mechanism: the highest pressure whose level is a mechanism, or None: ``level``
        (index), ``pressure`` (kPa), ``moving_blocks`` (ids, from the batch's solve of that
        level), ``volume`` (their area together, m3/m), ``small`` (no larger than
        ``solver.max_loose_volume``: pieces working loose, not a collapse;
        :attr:`jaxdem.batch.BatchResult.small_mechanism`), ``status`` and ``message``.
      undecided: levels that neither converged nor found a mechanism.
      support: the :class:`SupportLine`, or None.
      equilibrium: with a support: ``pressure`` p_eq (kPa), ``convergence`` u_eq (m),
        ``factor_of_safety`` capacity / p_eq (None when p_eq = 0), ``status``
        ("equilibrium", "at_capacity", "not_loaded" or "no_intersection") and
        ``message``; None without.
      message: one paragraph for a rock engineer.
      timing: ``build_s``, ``compile_s``, ``solve_s`` of the batch, ``mechanism_s`` of
        naming the mechanism's blocks, ``total_s`` (s); ``chunk``, ``devices``, ``workers``.
    """

    scene: str
    excavation: str
    stage: str | None
    p0: float
    p0_from: str
    pressure: np.ndarray
    monitors: dict
    displacements: dict
    status: list
    monitor: str
    parameter: str
    supports_note: str
    dropped_stages: list
    mechanism: dict | None
    undecided: list
    support: SupportLine | None
    equilibrium: dict | None
    message: str
    timing: dict

    @property
    def levels(self) -> int:
        return len(self.pressure)

    def to_dict(self) -> dict[str, Any]:
        """The content of ``grc.json``: plain JSON types, NaN as null."""
        return jsonable(finite=True, x=dict(
            scene=self.scene, excavation=self.excavation, stage=self.stage, p0=self.p0,
            p0_from=self.p0_from, levels=self.levels, pressure=self.pressure,
            monitors=self.monitors, displacements=self.displacements, status=self.status,
            monitor=self.monitor, parameter=self.parameter, supports_note=self.supports_note,
            dropped_stages=self.dropped_stages, mechanism=self.mechanism,
            undecided=self.undecided,
            support=None if self.support is None else dataclasses.asdict(self.support),
            equilibrium=self.equilibrium, message=self.message, timing=self.timing))


@float64
def ground_reaction(scene, excavation: str, levels: int = 16, *, p0: float | None = None,
                    start: float | None = None,
                    support: SupportLine | Mapping | tuple | None = None,
                    monitor: str | None = None, name_blocks: bool = True,
                    chunk: int | None = None, devices=None, workers: int | None = None,
                    progress: Callable[[int, int], None] | None = None) -> GroundReaction:
    """The ground reaction curve of ``excavation``: K support pressures in one batch.

    Args:
      scene: a validated scene (:func:`jaxdem.load_scene`).
      excavation: the name of one of its ``[[excavations]]``.
      levels: K >= 2 support pressures, evenly spaced from ``start`` down to 0.
      p0: the in-situ normal stress at the face (kPa, > 0); default
        :func:`in_situ_pressure` (needs ``[in_situ]``).
      start: the highest support pressure (kPa), 0 < start <= p0; default p0.
      support: a :class:`SupportLine` (or its fields as a mapping, or a
        (stiffness, capacity, installed_at) tuple) to intersect with the curve.
      monitor: the monitor that measures convergence for the support line;
        default the first section monitor, else the first point monitor.
      name_blocks: name the first mechanism's moving blocks (from the batch).
      chunk, devices, workers, progress: see :func:`jaxdem.batch.solve_batch`.
    Returns:
      a :class:`GroundReaction`.

    Raises:
      SceneError: bad input, naming the argument (``excavation``, ``levels``, ``p0``,
        ``start``, ``monitor``, ``support.FIELD``), before any solve.

    Example::

        curve = jaxdem.ground_reaction(scene, "hole", levels=5)
        curve.pressure          # [1000., 750., 500., 250., 0.]
        curve.monitors["h"]     # convergence of section "h" at each level (m)
    """
    from jaxdem.batch import solve_batch

    t0 = time.perf_counter()
    c = check_inputs(scene, excavation, levels, p0=p0, start=start, support=support,
                     monitor=monitor)
    exc, levels, name, line = c["excavation"], c["levels"], c["monitor"], c["support"]
    p0, p0_from, start, towards = c["p0"], c["p0_from"], c["start"], c["inward"]
    solved, index, note, dropped = grc_scene(scene, excavation)
    path = f"supports.{index}.pressure"
    pressure = np.linspace(start, 0.0, levels)
    batch = solve_batch(solved, [path], pressure[:, None], chunk=chunk, devices=devices,
                        workers=workers, progress=progress)
    monitors, displacements = {}, {}
    for m, v in batch.monitors.items():
        if v.ndim == 2:
            displacements[m] = v
            monitors[m] = v @ towards[m]
        else:
            monitors[m] = v
    status = list(batch.status)
    timing = {k: float(batch.timing[k]) for k in ("build_s", "compile_s", "solve_s")}
    timing.update(chunk=batch.timing["chunk"], devices=batch.timing["devices"],
                  workers=batch.timing["workers"])
    t1 = time.perf_counter()
    mechanism = _mechanism(pressure, batch, name_blocks)
    timing["mechanism_s"] = time.perf_counter() - t1
    undecided = [i for i, s in enumerate(status) if s not in (STABLE, MECHANISM)]
    equilibrium = None if line is None else intersect(pressure, monitors[name], line)
    timing["total_s"] = time.perf_counter() - t0
    curve = GroundReaction(
        scene=scene.name, excavation=excavation, stage=_stage_of(scene, exc), p0=p0,
        p0_from=p0_from, pressure=pressure, monitors=monitors, displacements=displacements,
        status=status, monitor=name, parameter=path, supports_note=note, dropped_stages=dropped,
        mechanism=mechanism, undecided=undecided, support=line, equilibrium=equilibrium,
        message="", timing=timing)
    curve.message = _message(curve)
    return curve


def check_inputs(scene, excavation: str, levels: int, *, p0=None, start=None, support=None,
                 monitor=None) -> dict[str, Any]:
    """:func:`ground_reaction`'s arguments checked and completed, before any solve.

    Returns:
      ``excavation`` (the Excavation), ``levels``, ``monitor`` (its name), ``support``
      (a SupportLine or None), ``p0`` (kPa), ``p0_from`` ("in_situ" or "given"),
      ``start`` (kPa) and ``inward`` (point monitor name -> :func:`inward`).
    Raises:
      SceneError: naming the argument (see :func:`ground_reaction`).
    """
    exc = _excavation(scene, excavation)
    levels = _check_levels(levels)
    name = _monitor(scene, monitor)
    line = None if support is None else SupportLine.of(support)
    p0, p0_from = _p0(scene, exc, p0)
    start = p0 if start is None else _positive(start, "start")
    if start > p0 * (1 + 1e-12):
        raise SceneError("start", f"{start:g} kPa is above p0 = {p0:g} kPa: the curve runs "
                         "from at most the in-situ normal stress at the face down to 0")
    towards = {m.name: inward(scene, exc, m.name) for m in scene.monitors if m.kind == "point"}
    return dict(excavation=exc, levels=levels, monitor=name, support=line, p0=p0,
                p0_from=p0_from, start=start, inward=towards)


def in_situ_pressure(scene, excavation) -> float | None:
    """The in-situ normal stress at the face of ``excavation`` (an Excavation), kPa.

    The mean over the outline, weighted by edge length, of sigma_n = n . sigma . n,
    the normal stress the ``[in_situ]`` stress tensor puts on each edge (compression
    positive). sigma_n is linear along an edge (gravity mode: sigma_yy = gamma
    (surface_y - y), sigma_xx = K0 sigma_yy, with the unit weight of the material of
    :func:`jaxdem.solver.gravity_material`), so its value at the edge's
    midpoint is its mean there. Hydrostatic p0: exactly p0. None without ``[in_situ]``.
    """
    s = scene.in_situ
    if s is None:
        return None
    a = np.asarray(excavation.vertices, float)
    b = np.roll(a, -1, axis=0)
    mid, edge = 0.5 * (a + b), b - a
    length = np.hypot(edge[:, 0], edge[:, 1])
    n = np.column_stack([edge[:, 1], -edge[:, 0]]) / length[:, None]
    if s.mode == "gravity":
        gamma = scene.materials[_gravity_material(scene)].unit_weight
        syy = gamma * (s.surface_y - mid[:, 1])
        sxx, sxy = s.k0 * syy, 0.0
    else:
        sxx, syy, sxy = s.sigma_xx, s.sigma_yy, s.sigma_xy
    sn = sxx * n[:, 0] ** 2 + syy * n[:, 1] ** 2 + 2.0 * sxy * n[:, 0] * n[:, 1]
    return float(np.sum(length * sn) / np.sum(length))


def inward(scene, excavation, monitor: str) -> np.ndarray:
    """The unit vector from point monitor ``monitor`` towards the centroid of
    ``excavation``'s outline: a point's displacement along it is its convergence
    (for a point on a circular opening's wall, the radial displacement u_r of the
    closed forms, positive inwards)."""
    point = next(m.point for m in scene.monitors if m.name == monitor)
    d = centroid(np.asarray(excavation.vertices, float)) - np.asarray(point, float)
    length = float(np.hypot(*d))
    if length == 0.0:
        raise SceneError(f"monitors.{monitor}", f"lies at the centroid of {excavation.name!r}: "
                         "it has no direction to converge in")
    return d / length


def grc_scene(scene, excavation: str) -> tuple[Any, int, str, list[str]]:
    """The scene a ground reaction curve of ``excavation`` solves (module docstring).

    Returns:
      (the scene, the index I of the support whose ``supports.I.pressure`` is the
      level's pressure, what was done to the scene's supports, the stages left out).
    """
    exc = _excavation(scene, excavation)
    stage = _stage_of(scene, exc)
    names = [st.name for st in scene.stages]
    data = copy.deepcopy(scene.data)
    dropped: list[str] = []
    keep = {section: [True] * len(getattr(scene, section))
            for section in ("excavations", "bolts", "supports", "boundaries")}
    if names and names.index(stage) < len(names) - 1:
        k = names.index(stage)
        dropped = names[k + 1:]
        data["stages"] = data["stages"][:k + 1]
        for section, flags in keep.items():
            for i, item in enumerate(getattr(scene, section)):
                flags[i] = item.stage not in dropped
        gone = {e.name for e, kept in zip(scene.excavations, keep["excavations"], strict=True)
                if not kept}
        for i, sp in enumerate(scene.supports):
            keep["supports"][i] = keep["supports"][i] and sp.excavation not in gone
        for section, flags in keep.items():
            if section in data:
                data[section] = [t for t, kept in zip(data[section], flags, strict=True) if kept]
    supports = [sp for sp, kept in zip(scene.supports, keep["supports"], strict=True) if kept]
    ours = [i for i, sp in enumerate(supports)
            if sp.excavation == excavation and _stage_of(scene, sp) == stage]
    if ours:
        index = ours[0]
        for i in ours[1:]:
            data["supports"][i]["pressure"] = 0.0
        note = (f"the scene's support supports.{index} on {excavation!r} carries each level's "
                f"pressure (its {supports[index].pressure:g} kPa is replaced)")
        if len(ours) > 1:
            note += f"; {len(ours) - 1} more support(s) on it in that stage set to 0"
    else:
        entry: dict[str, Any] = {"excavation": excavation, "pressure": 0.0}
        if names:
            entry["stage"] = stage
        data.setdefault("supports", []).append(entry)
        index = len(data["supports"]) - 1
        note = f"a support on {excavation!r} in its stage was added (supports.{index})"
    return parse_scene(data, source=scene.source), index, note, dropped


def intersect(pressure, convergence, line: SupportLine) -> dict[str, Any]:
    """Where the support line meets the ground reaction curve.

    The curve is straight between levels (``pressure`` falling, ``convergence`` the
    monitor's value at each level, m); the first point, from the highest pressure
    down, where p(u) = p_s(u). The support line is straight between its kinks (u0 and
    u0 + capacity / stiffness), so the crossing is exact on the straight curve.

    Returns:
      ``pressure`` p_eq (kPa), ``convergence`` u_eq (m), ``factor_of_safety`` capacity /
      p_eq, ``status``: "equilibrium"; "at_capacity" (crossing on the support's
      plateau: its factor of safety is 1, it yields); "not_loaded" (the rock stops at
      0 support pressure before the convergence reaches u0: the support carries
      nothing); "no_intersection" (the curve ends, at a level with no equilibrium,
      before it meets the support line); and ``message``.
    """
    p = np.asarray(pressure, float)
    u = np.asarray(convergence, float)
    ok = np.isfinite(u)
    last = len(u) if ok.all() else int(np.argmin(ok))   # the curve ends before level last
    if last == 0:
        return _no_intersection("no level found equilibrium: there is no curve to meet")
    if p[0] <= line.pressure(u[0]):
        return _no_intersection(f"the support line is already at or above the curve at its "
                                f"first level ({p[0]:g} kPa): they meet above it; start the "
                                "curve higher")
    for i in range(last - 1):
        found = _crossing(p[i], u[i], p[i + 1], u[i + 1], line)
        if found is not None:
            return _equilibrium(*found, line)
    return _no_intersection(f"the curve ends at {p[last]:g} kPa (no equilibrium there) "
                            "before it meets the support line: the support is too soft, too "
                            "weak or installed too late")


def write_outputs(curve: GroundReaction, out_dir: str | Path) -> list[Path]:
    """Write ``grc.json`` and draw ``grc.png`` (:func:`jaxdem.plots.plot_ground_reaction`);
    returns the paths."""
    from jaxdem.plots import plot_ground_reaction

    out = Path(out_dir)
    data = curve.to_dict()
    return [write_json(data, out / "grc.json"), plot_ground_reaction(data, out / "grc.png")]


# ---------------------------------------------------------------------------
# Host helpers


def _excavation(scene, name):
    names = [e.name for e in scene.excavations]
    if not isinstance(name, str) or name not in names:
        listed = ", ".join(repr(n) for n in names) if names else "none"
        raise SceneError("excavation", f"no excavation {name!r} in the scene (its "
                         f"excavations: {listed})")
    return scene.excavations[names.index(name)]


def _stage_of(scene, item) -> str | None:
    """The stage that excavates or installs ``item`` (None: the scene has no [[stages]])."""
    return item.stage or (scene.stages[0].name if scene.stages else None)


def _gravity_material(scene) -> str:
    """The material of the gravity in-situ stress, as :func:`jaxdem.solver.gravity_material`
    picks it from the built model: the domain's, else that of the first explicit block
    whose centroid lies in no excavation."""
    if scene.domain is not None:
        return scene.domain.material
    for b in scene.blocks:
        c = centroid(np.asarray(b.vertices, float))
        if not any(point_in_polygon(c, np.asarray(e.vertices, float))
                   for e in scene.excavations):
            return b.material
    return scene.blocks[0].material


def _check_levels(levels) -> int:
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) \
            or not 2 <= levels <= MAX_LEVELS:
        raise SceneError("levels", f"must be a whole number from 2 to {MAX_LEVELS} "
                         f"(got {levels!r})")
    return int(levels)


def _positive(x, name: str) -> float:
    ok = isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
    if not ok or not math.isfinite(x) or x <= 0:
        raise SceneError(name, f"must be a number > 0 in kPa (got {x!r})")
    return float(x)


def _p0(scene, exc, given) -> tuple[float, str]:
    if given is not None:
        return _positive(given, "p0"), "given"
    value = in_situ_pressure(scene, exc)
    if value is None:
        raise SceneError("p0", "the scene has no [in_situ] stress to take the in-situ normal "
                         "stress at the face from: give p0 (kPa)")
    if not value > 0:
        raise SceneError("p0", f"the in-situ normal stress at the face of {exc.name!r} is "
                         f"{value:g} kPa (not compressive): give p0 (kPa)")
    return value, "in_situ"


def _monitor(scene, name) -> str:
    names = [m.name for m in scene.monitors]
    if name is not None:
        if name not in names:
            listed = ", ".join(repr(n) for n in names) if names else "none"
            raise SceneError("monitor", f"no monitor {name!r} in the scene (its monitors: "
                             f"{listed})")
        return name
    sections = [m.name for m in scene.monitors if m.kind == "section"]
    if sections:
        return sections[0]
    if names:
        return names[0]
    raise SceneError("monitors", "the scene has no monitors: a ground reaction curve needs a "
                     "section across the opening or a point on its wall ([[monitors]])")


def _mechanism(pressure, batch, name_blocks) -> dict | None:
    hits = [i for i, s in enumerate(batch.status) if s == MECHANISM]
    if not hits:
        return None
    i = hits[0]
    out: dict[str, Any] = dict(level=i, pressure=float(pressure[i]), status=MECHANISM,
                               moving_blocks=None, message="",
                               volume=float(batch.moving_volume[i]),
                               small=bool(batch.small_mechanism[i]))
    if name_blocks:
        moving = list(batch.moving_blocks[i])
        out.update(moving_blocks=moving, message=(
            f"{Status.MECHANISM.message} Moving blocks: {', '.join(map(str, moving))}."))
    return out


def _crossing(p1, u1, p2, u2, line: SupportLine):
    """(p, u) where the segment (u1, p1)-(u2, p2), above the support line at its start,
    first meets it, or None. The line is straight between its kinks: the difference
    p - p_s is linear on each piece of the segment between them."""
    kinks = [line.installed_at, line.installed_at + line.capacity / line.stiffness]
    ts = sorted({0.0, 1.0, *[(k - u1) / (u2 - u1) for k in kinks
                             if u2 != u1 and 0.0 < (k - u1) / (u2 - u1) < 1.0]})
    for a, b in zip(ts[:-1], ts[1:], strict=True):
        ga = p1 + a * (p2 - p1) - line.pressure(u1 + a * (u2 - u1))
        gb = p1 + b * (p2 - p1) - line.pressure(u1 + b * (u2 - u1))
        if ga > 0.0 >= gb:
            t = a + (b - a) * ga / (ga - gb)
            return p1 + t * (p2 - p1), u1 + t * (u2 - u1)
    return None


def _no_intersection(why: str) -> dict[str, Any]:
    return dict(pressure=None, convergence=None, factor_of_safety=None,
                status="no_intersection", message=why)


def _equilibrium(p, u, line: SupportLine) -> dict[str, Any]:
    p, u = float(p), float(u)
    if p <= 0.0:
        return dict(pressure=0.0, convergence=u, factor_of_safety=None, status="not_loaded",
                    message=f"the rock comes to rest at a convergence of {u:.4g} m without "
                            f"support pressure, before the support is installed (u0 = "
                            f"{line.installed_at:.4g} m): it carries nothing")
    fos = line.capacity / p
    at_capacity = p >= line.capacity * (1 - 1e-9)
    text = (f"equilibrium at {p:.4g} kPa and a convergence of {u:.4g} m; the support's factor "
            f"of safety is {fos:.3g} (capacity {line.capacity:g} kPa)")
    if at_capacity:
        text += ": the support works at its capacity (it yields)"
    return dict(pressure=p, convergence=u, factor_of_safety=fos,
                status="at_capacity" if at_capacity else "equilibrium", message=text)


def _message(c: GroundReaction) -> str:
    how = ("the mean in-situ normal stress on its outline" if c.p0_from == "in_situ"
           else "given")
    text = (f"Ground reaction curve of {c.excavation!r}: {c.levels} support pressures from "
            f"{c.pressure[0]:.4g} to 0 kPa (p0 = {c.p0:.4g} kPa, {how}), solved in one batch")
    u = c.monitors.get(c.monitor)
    if u is not None and np.isfinite(u).any():
        j = int(np.flatnonzero(np.isfinite(u))[-1])
        text += (f"; {c.monitor} converges by {u[j]:.4g} m at {c.pressure[j]:.4g} kPa")
    text += "."
    m = c.mechanism
    if m is not None:
        text += f" A mechanism first appears at {m['pressure']:.4g} kPa"
        if m["moving_blocks"]:
            blocks = ", ".join(str(b) for b in m["moving_blocks"][:20])
            more = len(m["moving_blocks"]) - 20
            text += f" (moving blocks {blocks}" + (f" and {more} more" if more > 0 else "") + ")"
        text += "."
        if m.get("small"):
            text += (f" It is small ({m['volume']:.3g} m3/m, no larger than "
                     f"solver.max_loose_volume): pieces working loose at the opening, not a "
                     f"collapse of the rock mass.")
    else:
        text += " Every level is stable." if not c.undecided else ""
    if c.undecided:
        listed = ", ".join(f"{c.pressure[i]:.4g} kPa ({c.status[i]})" for i in c.undecided[:6])
        text += (f" WARNING: {len(c.undecided)} level(s) neither converged nor found a "
                 f"mechanism: {listed}.")
    if c.dropped_stages:
        text += f" Later stages left out: {', '.join(c.dropped_stages)}."
    if c.equilibrium is not None:
        text += f" Support line: {c.equilibrium['message']}."
    return text


__all__ = ["GroundReaction", "MAX_LEVELS", "SupportLine", "check_inputs", "grc_scene",
           "ground_reaction", "in_situ_pressure", "intersect", "inward", "write_outputs"]
