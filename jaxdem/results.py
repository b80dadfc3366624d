"""Host-side results of a solve: the :class:`Result` object and its JSON form.

``Result.to_dict()`` is the content of ``result.json`` (SPEC section 3). The
arrays kept for plotting (initial and final block outlines, contact points and
states, increment histories) live in ``Result.geometry`` and ``Result.history``
and are not written to JSON.

Sign conventions: displacements in m (x right, y up), rotations in rad
(counter-clockwise positive), stresses in kPa with compression positive.
"""

from __future__ import annotations

import collections
import dataclasses
import json
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem import geometry
from jaxdem.core.compile_cache import on_disk, run_stored
from jaxdem.core.kinematics import (
    MOVING,
    bolt_geometry,
    group_limits,
    rotate_vectors,
    strain_times,
)
from jaxdem.core.model import TRAVEL_FLOOR
from jaxdem.core.state import OPEN, SLIP
from jaxdem.core.status import IMBALANCE_FACTOR, LARGE_SLIP, OVERLAP_TOL, STRENGTH_TOL, Status
from jaxdem.rockmass import small_block_area


@dataclasses.dataclass
class Result:
    """What a solve returns: the answer, its status, and the data behind the figures.

    Attributes:
      scene: scene name.
      converged: every increment reached equilibrium within the tolerance.
      stable: no mechanism was found (no block travelled ``max_displacement``, or where
        the scene leaves it out its own size, in an increment).
      status: a :class:`Status`, a ``str`` enumeration equal to its label:
        ``"converged"``, ``"mechanism"``, ``"iteration_limit"``, ``"capacity_overflow"``,
        ``"non_finite"``, ``"overlap"``, ``"law_violation"`` or ``"imbalance"`` (the
        last three: balance found, but not admissible; see ``admissibility``).
      message: one human sentence about the outcome.
      monitors: monitor name -> ``{"displacement": [ux, uy]}`` (m) for a point, or
        ``{"convergence": c, "along": [a_from, a_to]}`` (m) for a section.
      blocks: one dict per block: ``id``, ``centroid`` [x, y] (m, initial),
        ``u`` [ux, uy, rot] (m, m, rad), ``stress`` [sxx, syy, sxy] (kPa,
        compression positive: a deformable cell's own stress, else the
        average (1/A) sum r (x) F of its contact forces), ``fixed``; deformable
        cells (``mesh_size``) also ``strain`` [exx, eyy, gxy] (extension
        positive, from the same reference as ``u``).
      contacts: counts of contact springs in contact: ``total``, ``open``, ``slipping``.
      bolts: one dict per scene bolt: ``id``, ``force`` (kN), ``force_per_m`` (kN/m),
        ``state`` (``elastic``, ``yielded``, ``pulled out``, ``slack``, ``yielded in
        compression``, or ``not installed``: its stage never ran, force 0),
        ``compression_capacity`` (kN).
      stages: per stage ``name``, ``converged``, ``stable``, ``iterations`` (Newton
        iterations per increment), ``substeps`` (geometry updates per increment),
        ``residual`` (final relative residual per increment), ``imbalance``
        (relative global force imbalance per increment), ``max_slip`` and
        ``max_opening`` (m, the largest joint slip and opening in each
        increment), ``monitors``
        (monitor name -> value after each increment); in a scene where an excavation's
        load is released over several stages (``release``), also ``released``
        (excavation name -> the fraction of its load released after each increment, for
        the excavations whose load the stage releases).
      moving_blocks: ids of the blocks that kept moving when a mechanism was found.
      unbalanced_blocks: where the analysis stopped at the iteration limit, the free
        blocks furthest out of balance at its last iteration (at most five, those beyond
        the tolerance, the largest first): per block ``id``, ``centroid`` [x, y]
        (initial, m), ``force`` (kN/m, the largest of |Fx|, |Fy| and |M| / radius left
        unbalanced) and ``relative`` (that over the block's force scale, its load or the
        largest force on it); else empty.
      loose_blocks: the small blocks that fell free into an opening and were removed
        (``solver.loose_blocks = "remove"``): per block ``id``, ``stage`` (the stage they
        fell in, which was then solved again without them), ``volume`` (m3 per m of
        tunnel: the block's area) and ``centroid`` [x, y] (m, initial).
      equilibrium: global balance of the final state: ``applied`` [Fx, Fy, M]
        (kN/m, kN m/m), ``reaction`` (forces from fixed blocks and walls on the
        free blocks) and ``imbalance``: |applied + reaction| over the larger of the
        summed load and reaction magnitudes.
      timing: ``build_s``, ``compile_s``, ``solve_s`` (s).
      admissibility: of the final state: ``overlap`` (m, the deepest
        interpenetration of two blocks, over every pair whose boxes meet:
        :func:`block_overlap`), ``overlap_rel`` (that over the smaller
        block's size), ``strength_excess`` (largest excess of a contact's forces
        over its strength, relative to its blocks' force scale), ``imbalance``
        (global), each with its tolerance (``tolerances``), and ``admissible``.
        ``converged`` requires all three within their tolerances; otherwise
        ``status`` names the one that failed (``overlap``, ``law_violation``,
        ``imbalance``).
      warnings: sentences for the engineer to review: the scene's plausibility
        warnings (a value most likely in the wrong unit, ``Scene.warnings``), then e.g.
        a joint slip in one increment larger than ``LARGE_SLIP`` (5%) of the block's size.
      geometry: plotting data, not written to JSON: ``initial_vertices`` and
        ``final_vertices`` (lists of (n_i, 2) arrays, m), ``fixed`` (bool per
        block), ``walls`` (list of (2, 2) segments), ``contacts`` with ``points``
        (m, 2), ``normals`` (m, 2), ``state`` (m,) in {OPEN, STICK, SLIP},
        ``fn``, ``fs`` (kN/m), ``monitors`` (name -> initial point or section ends),
        ``stress`` (n, 3) block stresses sxx, syy, sxy (kPa, compression
        positive), ``centroids`` (n, 2) current centroids (m), ``excavated``
        (n,) bool, ``loose`` (n,) bool (removed as loose blocks), ``bolts`` (list of
        (2, 2) current anchor positions, m, in the order of ``bolts``); from
        :func:`jaxdem.solve`, also ``stages``: the state at the end of each stage, in the
        order of ``stages`` (the last one where the analysis stopped), each a
        :func:`stage_frame`.
      history: per increment: ``stage``, ``step``, ``load_factor`` and
        ``monitors`` (name -> scalar: |u| for a point, convergence for a section).
    """

    scene: str
    converged: bool
    stable: bool
    status: Status
    message: str
    monitors: dict[str, dict[str, Any]]
    blocks: list[dict[str, Any]]
    contacts: dict[str, int]
    bolts: list[dict[str, Any]]
    stages: list[dict[str, Any]]
    moving_blocks: list[int]
    equilibrium: dict[str, Any]
    timing: dict[str, float]
    geometry: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)
    history: list[dict[str, Any]] = dataclasses.field(default_factory=list, repr=False)
    admissibility: dict[str, Any] = dataclasses.field(default_factory=dict)
    warnings: list[str] = dataclasses.field(default_factory=list)
    loose_blocks: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    unbalanced_blocks: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    def __post_init__(self):
        self.status = Status(self.status)  # a label given as a plain string, too

    def to_dict(self) -> dict[str, Any]:
        """The content of ``result.json``: plain JSON types only."""
        out = {
            "scene": self.scene,
            "converged": self.converged,
            "stable": self.stable,
            "status": self.status.value,
            "message": self.message,
            "monitors": self.monitors,
            "blocks": self.blocks,
            "contacts": self.contacts,
            "bolts": self.bolts,
            "stages": self.stages,
            "moving_blocks": self.moving_blocks,
            "equilibrium": self.equilibrium,
            "timing": self.timing,
            "admissibility": self.admissibility,
            "warnings": self.warnings,
            "loose_blocks": self.loose_blocks,
            "unbalanced_blocks": self.unbalanced_blocks,
        }
        return jsonable(out)

    def write_json(self, path: str | Path) -> Path:
        """Write ``to_dict()`` to ``path`` (indented JSON); returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2))
        return path


def write_json(data: dict[str, Any], path: str | Path) -> Path:
    """Write plain-JSON ``data`` (see :func:`jsonable`) to ``path``, indented, refusing
    NaN (not standard JSON); makes the folder. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    return path


def jsonable(x: Any, finite: bool = False) -> Any:
    """NumPy scalars and arrays to Python numbers and lists, recursively; with ``finite``,
    NaN and infinities to None (null), so that the JSON is standard."""
    if isinstance(x, dict):
        return {str(k): jsonable(v, finite) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v, finite) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist(), finite)
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return None if finite and not np.isfinite(x) else x
    return x


# ---------------------------------------------------------------------------
# Building a Result from the solver's final state (host, NumPy)


@on_disk("material_points")
@jax.jit
def _material_points(centroid, rot, strain, blocks, offsets, weights):
    """Weighted mean over holders of c + (I + E) R(rot) offset: (n, H) blocks -> (n, 2) points."""
    r = rotate_vectors(offsets, rot[blocks])
    p = centroid[blocks] + r + strain_times(strain[blocks], r)
    return jnp.sum(weights[..., None] * p, axis=-2)


@on_disk("material_moves")
@jax.jit
def _material_moves(u, rot, strain, blocks, offsets, weights):
    """The displacements of the same points since the start, u + (I + E) R(rot) r - r.

    From the accumulated displacements, not as the difference of two positions: in
    float32 a position near y = 2.5 m is resolved to 2.4e-7 m, which is 1.5e-3 of a
    0.16 mm settlement.
    """
    r = rotate_vectors(offsets, rot[blocks])
    d = u[blocks] + r + strain_times(strain[blocks], r) - offsets
    return jnp.sum(weights[..., None] * d, axis=-2)


def monitor_positions(m, centroid, rot, strain):
    """Current positions of a monitor's material points, c + (I + E) R(rot) offset
    (the mean over the blocks that hold a point on their common face).

    jax.numpy, so that :mod:`jaxdem.differentiable` differentiates the same readings.
    """
    return _material_points(centroid, rot, strain, jnp.asarray(m["blocks"]),
                            jnp.asarray(m["offsets"]), jnp.asarray(m["weights"], centroid.dtype))


def _stacked(ms, key: str, dtype) -> jax.Array:
    """The field ``key`` of every monitor of ``ms``, concatenated, on the device
    (``jax.device_put``: ``jnp.asarray`` of a host array compiles a program for each new
    shape)."""
    return jax.device_put(np.concatenate([np.asarray(m[key], dtype) for m in ms]))


def _all_positions(layout, state) -> list[np.ndarray]:
    """Every monitor's material points in ``state``, in the order of ``layout.monitors``.

    One compiled call for all monitors: the solver records them after every load
    step, and reading each monitor with eager JAX operations cost a small scene
    more than its increments (about 20 ms a solve on the benchmark tunnel).
    """
    ms = list(layout.monitors.values())
    pts = np.asarray(run_stored(_material_points, state.centroid, state.rot, state.strain,
                                _stacked(ms, "blocks", np.int32), _stacked(ms, "offsets", float),
                                _stacked(ms, "weights", state.centroid.dtype)))
    return np.split(pts, np.cumsum([len(m["points"]) for m in ms])[:-1])


def _all_moves(layout, state) -> list[np.ndarray]:
    """Every monitor's material-point displacements since the start (:func:`_material_moves`)."""
    ms = list(layout.monitors.values())
    moves = np.asarray(run_stored(_material_moves, state.u, state.rot, state.strain,
                                  _stacked(ms, "blocks", np.int32),
                                  _stacked(ms, "offsets", state.u.dtype),
                                  _stacked(ms, "weights", state.u.dtype)))
    return np.split(moves, np.cumsum([len(m["points"]) for m in ms])[:-1])


def monitor_values(layout, state, ref=None) -> dict[str, dict[str, Any]]:
    """Monitor readings of a state: point displacement or section convergence (m).

    A point monitor follows the material point of the rock block that held it
    at the start (the mean of those of the blocks whose common face it lies on). A section's
    convergence is the shortening of the distance
    between its two material points (positive when they approach); ``along``
    is each end's displacement projected on the section direction from -> to.
    Displacements are measured from ``ref`` (a state), else from the start.
    """
    if not layout.monitors:
        return {}
    out = {}
    now_all = _all_positions(layout, state)
    ref_all = None if ref is None else _all_positions(layout, ref)
    moves = _all_moves(layout, state)
    ref_moves = None if ref is None else _all_moves(layout, ref)
    for i, (name, m) in enumerate(layout.monitors.items()):
        now = now_all[i]
        start = m["points"] if ref is None else ref_all[i]
        disp = moves[i] if ref is None else moves[i] - ref_moves[i]
        if m["kind"] == "point":
            out[name] = {"displacement": disp[0].tolist()}
        else:
            e = start[1] - start[0]
            length0 = np.linalg.norm(e)
            e = e / length0
            conv = length0 - np.linalg.norm(now[1] - now[0])
            along = [float(disp[0] @ e), float(disp[1] @ e)]
            out[name] = {"convergence": float(conv), "along": along}
    return out


def _scalar(reading: dict) -> float:
    if "convergence" in reading:
        return reading["convergence"]
    return float(np.linalg.norm(reading["displacement"]))


def block_stress(n_blocks, area, centroid, snap) -> np.ndarray:
    """Block stresses sigma = -(1/A) sum sym(r (x) F) over contact forces (kPa, compression +).

    r is the contact point relative to the block centroid and F the contact
    force on the block; the minus sign makes compression positive.
    Returns (n_blocks, 3): sxx, syy, sxy.
    """
    act = snap.active
    p, n = snap.point[act], snap.normal[act]
    # The kernels' face tangent t and outward normal n satisfy n = (t_y, -t_x).
    t = np.stack([-n[:, 1], n[:, 0]], axis=1)
    F = snap.fn[act, None] * n - snap.fs[act, None] * t
    out = np.zeros((len(area), 2, 2))
    for blk, sign in ((snap.a[act], 1.0), (snap.b[act], -1.0)):
        r = p - centroid[blk]
        outer = sign * r[:, :, None] * F[:, None, :]
        np.add.at(out, blk, outer)
    sig = -0.5 * (out + np.transpose(out, (0, 2, 1))) / np.asarray(area)[:, None, None]
    return np.stack([sig[:n_blocks, 0, 0], sig[:n_blocks, 1, 1], sig[:n_blocks, 0, 1]], axis=1)


_BOLT_STATES = {0: "elastic", 1: "yielded", 2: "pulled out", 3: "slack",
                4: "yielded in compression"}

NOT_INSTALLED = "not installed"
"""The state of a bolt whose stage never ran (the analysis stopped before it): it
carries nothing, and is reported with force 0."""

BOLT_STATE_CODES = {**{name: code for code, name in _BOLT_STATES.items()}, NOT_INSTALLED: -1}
"""Integer code of each bolt state (the solver's, and -1 for ``not installed``), as the VTK
files write it."""


# A scene bolt split into sub-bolts (an anchor on a shared face) reports the state of
# its most advanced part, in this order.
_BOLT_STATE_RANK = (0, 3, 4, 1, 2)


def _by_scene_bolt(layout, n: int) -> list[np.ndarray]:
    """The solver bolts (sub-bolts) of each of the scene's n bolts."""
    of = np.asarray(layout.bolt_of)
    if of.size == 0 and n:
        of = np.arange(n)
    return [np.nonzero(of == i)[0] for i in range(int(of.max(initial=-1)) + 1)]


def scene_bolts(scene, layout, state, active=None) -> list[dict[str, Any]]:
    """result.json's ``bolts``: per scene bolt, its force (kN, per bolt; ``force_per_m``
    per metre of tunnel: divided by the spacing), its state, and its compression
    capacity (kN; 0: it carries tension only, like a cable).

    ``active``: the driver's (B,) mask of the solver bolts installed so far
    (``_Driver.bolt_active``, the ``Loads.bolt_active`` of the increments); a bolt none
    of whose parts is installed (its stage never ran) is :data:`NOT_INSTALLED`, force 0.
    None: every bolt installed."""
    force = np.asarray(state.bolt_force)
    st = np.asarray(state.bolt_state)
    installed = np.ones(len(force), bool) if active is None else np.asarray(active, bool)
    out = []
    for i, subs in enumerate(_by_scene_bolt(layout, len(force))):
        comp = scene.bolts[i].compression if i < len(scene.bolts) else 0.0
        if not installed[subs].any():
            out.append({"id": i, "force": 0.0, "force_per_m": 0.0, "state": NOT_INSTALLED,
                        "compression_capacity": comp})
            continue
        per_m = float(np.sum(force[subs]))
        worst = max((int(x) for x in st[subs]), key=_BOLT_STATE_RANK.index, default=0)
        spacing = float(layout.bolt_spacing[subs[0]])
        out.append({"id": i, "force": per_m * spacing, "force_per_m": per_m,
                    "state": _BOLT_STATES[worst], "compression_capacity": comp})
    return out


bolt_geometry_program = on_disk("bolt_geometry")(jax.jit(bolt_geometry))
"""One program (a few hundredths of a second to compile), where run op by op the
function compiled some thirty primitives (0.5 s of the demo's result)."""


def bolt_anchors(model, state, layout=None) -> list[np.ndarray]:
    """Current anchor positions of each bolt: a list of (2, 2) arrays (m), for plotting.

    The same anchors the solver uses (:func:`jaxdem.core.kinematics.bolt_geometry`), one
    per scene bolt (the mean of its sub-bolts' when an anchor lies on a shared
    face); empty when the model has no bolts.
    """
    if not model.n_bolts:
        return []
    g = run_stored(bolt_geometry_program, model, state)
    ends = np.stack([np.asarray(g.point_b), np.asarray(g.point_a)], axis=1)
    if layout is None:
        return list(ends)
    share = np.asarray(layout.bolt_share)
    return [np.sum(share[s, None, None] * ends[s], axis=0) / np.sum(share[s])
            for s in _by_scene_bolt(layout, len(ends))]


def final_water_table(scene: Any) -> np.ndarray | None:
    """The water table (n, 2) m at the end of the analysis: the last stage's
    ``water_table``, else ``[water] table``; None without water."""
    tables = [st.water_table for st in getattr(scene, "stages", ()) or ()
              if st.water_table is not None]
    if tables:
        return np.asarray(tables[-1], float)
    water = getattr(scene, "water", None)
    return None if water is None else np.asarray(water.table, float)


def support_geometry(scene: Any) -> dict[str, Any]:
    """For the figures: ``excavations`` (name -> initial outline (n, 2) m) and
    ``supports`` (per ``[[supports]]``: ``excavation``, ``pressure`` kPa, ``stage``)."""
    excavations = {e.name: np.asarray(e.vertices, float)
                   for e in getattr(scene, "excavations", ()) or ()}
    supports = [{"excavation": sp.excavation, "pressure": float(sp.pressure), "stage": sp.stage}
                for sp in getattr(scene, "supports", ()) or ()]
    return {"excavations": excavations, "supports": supports}


def initial_contacts(snap: dict, act: np.ndarray, ref: Any) -> dict[str, np.ndarray]:
    """Per active contact slot of ``snap``, what the same slot (block, other block, vertex)
    was at the reference state ``ref`` (the state before the first stage):
    ``initial_state`` (OPEN, STICK or SLIP; -1 where it was not within the detection
    margin then, or there is no reference) and ``initial_fn`` (kN/m, compression
    positive; NaN likewise). The figures draw an open contact only where it carried a
    force at the reference, so that the open contacts shown are those the analysis
    opened, not corners of the far field that never carried anything."""
    n = int(act.sum())
    if ref is None:
        return {"initial_state": np.full(n, -1, np.int32), "initial_fn": np.full(n, np.nan)}
    cstate = np.asarray(ref.cstate)
    fn = np.asarray(ref.fn)
    V = cstate.shape[2]
    pairs = np.asarray(ref.pairs)
    present = np.asarray(ref.present)
    known = {}
    for p, side, v in zip(*np.nonzero(present), strict=True):
        A, B = (pairs[p, 0], pairs[p, 1]) if side == 0 else (pairs[p, 1], pairs[p, 0])
        known[(int(A), int(B), int(v))] = (int(cstate[p, side, v]), float(fn[p, side, v]))
    a, b = np.asarray(snap.a).reshape(-1), np.asarray(snap.b).reshape(-1)
    vertex = np.arange(a.size) % V
    idx = np.nonzero(act.reshape(-1))[0]
    found = [known.get((int(a[k]), int(b[k]), int(vertex[k])), (-1, np.nan)) for k in idx]
    return {"initial_state": np.array([f[0] for f in found], np.int32).reshape(n),
            "initial_fn": np.array([f[1] for f in found], float).reshape(n)}


def _percent(x: float) -> str:
    """0.0081 -> ``0.81%``, 0.41 -> ``41%``, 3.09 -> ``309%``."""
    return f"{100 * x:.2g}%" if 100 * x < 10 else f"{100 * x:.0f}%"


def unbalanced_blocks(info, tol: float, centroids) -> list[dict[str, Any]]:
    """The blocks furthest out of balance at an increment's last iteration (``info``, the
    increment's report :class:`jaxdem.core.increment.Progress`), those beyond the tolerance
    ``tol`` relative to their force scale, the largest first: ``id``, ``centroid`` [x, y]
    (initial, m: ``centroids``, one per rock block), ``force`` (kN/m) and ``relative``
    (``Result.unbalanced_blocks``)."""
    ids, force, rel = (np.asarray(x) for x in info.unbalanced)
    return [dict(id=int(i), centroid=[float(x) for x in centroids[i]], force=float(f),
                 relative=float(r))
            for i, f, r in zip(ids, force, rel, strict=True) if r > tol and i < len(centroids)]


def moving_blocks(travel, max_displacement: float) -> list[int]:
    """The blocks of a mechanism: those that travelled more than
    :data:`jaxdem.core.kinematics.MOVING` (a tenth) of ``solver.max_displacement`` in the
    increment that found it (``travel``: (n,) m, the rock blocks' path lengths)."""
    return [int(i) for i in np.nonzero(np.asarray(travel) > MOVING * max_displacement)[0]]


_group_limits = on_disk("group_limits")(jax.jit(group_limits))


#: A mechanism whose moving blocks have each moved, net, less than this share of
#: their travel limit went back and forth: their path passed the limit, their
#: places did not (:func:`back_and_forth`).
BACK_AND_FORTH = 0.25


def back_and_forth(moving, u, rot, radius, limit) -> str | None:
    """The warning for a mechanism that is a path, not a collapse, else None.

    A mechanism is found where a block's path in one increment passes its travel limit
    (``limit``: m, a scalar or (n,): ``solver.max_displacement``, or by default each
    block's size, or its group's where blocks moved together,
    :func:`jaxdem.core.kinematics.group_limits`; ``moving``: their ids, :func:`moving_blocks`). A
    block that falls or slides is as far from where it was, less the turns of its
    course; one whose contacts chatter in the iteration goes back and forth, and its path
    can pass the limit where it has moved centimetres. Net movement is measured as the path is
    (:func:`jaxdem.core.kinematics.block_travel`: a block that tumbles travels by its
    rotation too): |u| + |rotation| x radius (``u`` (n, 2) m and ``rot`` (n,) rad from
    where displacements are measured, ``radius`` (n,) each block's largest
    centroid-to-vertex distance, m).
    """
    if not moving:
        return None
    ids = np.asarray(moving)
    net = np.hypot(u[ids, 0], u[ids, 1]) + np.abs(rot[ids]) * radius[ids]
    lim = np.broadcast_to(np.asarray(limit, float), np.shape(radius))[ids]
    if np.any(net >= BACK_AND_FORTH * lim):
        return None
    k = int(np.argmax(net / lim))
    return (f"unstable by path alone: the moving blocks went back and forth, the furthest "
            f"(block {int(ids[k])}) {1e3 * net[k]:.3g} mm from where it was for a path over "
            f"{lim[k]:.3g} m; a chatter of the iteration, not a collapse that "
            f"shows: review (README, \"Known limits\")")


def loose_limit(scene) -> float:
    """The largest group of blocks falling free that a stage removes and goes on (m3 per m
    of tunnel, the group's area): ``solver.max_loose_volume``, else a small block of the
    rock mass, :func:`jaxdem.rockmass.small_block_area` (0.1 x the smallest joint-set
    spacing squared, the default of ``domain.min_block_area``; 0 without joint sets, where
    a falling block is the answer, a key block, unless the scene says otherwise)."""
    if scene.solver.max_loose_volume is not None:
        return float(scene.solver.max_loose_volume)
    return small_block_area(scene)


#: How the warning of :func:`small_mechanism` begins.
SMALL_MECHANISM = "unstable, but the mechanism is small"


def mechanism_volume(moving, area) -> float:
    """The moving blocks' area together (m2, m3 per m of tunnel; 0.0 where none moves):
    ``moving`` their ids, ``area`` (n,) each rock block's area (m2)."""
    return float(np.sum(np.asarray(area)[np.asarray(moving, int)])) if len(moving) else 0.0


def is_small(moving, area, limit: float) -> bool:
    """Whether a mechanism (``moving``: its blocks' ids, ``area`` (n,) m2) is small: its
    blocks together no larger than ``limit`` (m3/m: ``solver.max_loose_volume`` or its
    default, :func:`loose_limit`; 0: none is). See :func:`small_mechanism`."""
    return bool(len(moving)) and limit > 0.0 and mechanism_volume(moving, area) <= limit


def small_mechanism(moving, area, limit: float, centroids) -> str | None:
    """The warning for a mechanism of small pieces, else None.

    A mechanism is reported wherever a block keeps moving, however small it is. Where the
    moving blocks (``moving``: their ids) are together no larger than ``limit`` (m2, m3
    per m of tunnel: ``solver.max_loose_volume``, else its default, a small block of the
    rock mass; 0: no warning) they are pieces working loose, not a collapse: ravelling at
    an opening, or slivers of a mesh where its lines, a joint and an opening's outline
    cross close together (seed example 3 at k0 = 1/3: a cut cell of 0.035 m2 at tunnel
    a's wall turns over with D, one of 0.022 m2 without). They were not removed
    as loose blocks (``solver.loose_blocks`` removes only groups that fall free of the rock,
    and none where it is ``"stop"``).
    ``area`` (n,) each rock block's area (m2), ``centroids`` (n, 2) where they were (m).
    """
    if not is_small(moving, area, limit):
        return None
    ids = np.asarray(moving)
    total = mechanism_volume(moving, area)
    k = int(ids[np.argmax(area[ids])])
    names = ", ".join(str(int(i)) for i in ids[:10]) + (", ..." if len(ids) > 10 else "")
    x, y = centroids[k]
    return (f"{SMALL_MECHANISM}: blocks {names}, {total:.3g} m3/m in all "
            f"(solver.max_loose_volume: {limit:.3g}), the largest at ({x:.3g}, {y:.3g}): "
            f"pieces that work loose (at an opening: ravelling, or slivers cut where mesh "
            f"lines, joints and its outline cross close together), not a collapse of the "
            f"rock mass; not removed as loose blocks (solver.loose_blocks removes groups "
            f"that fall free of the rock); review "
            f"(README, \"Loose blocks\")")


def stage_frame(scene, model, layout, state, ref, info, bolt_active, name: str, index: int,
                increments: int) -> dict[str, Any]:
    """Host copies of the state at the end of a stage (or where the analysis stopped in it),
    for files that step through the stages (:func:`jaxdem.vtk.write_vtk`'s ``.pvd``).

    Returns ``name`` (the stage's record name in ``Result.stages``), ``index`` (0 the
    initial state, k the k-th stage), ``increments`` (increments run so far), and as
    ``Result.blocks`` and ``Result.geometry`` read them: ``final_vertices``, ``u`` (n, 3)
    m, m, rad from ``ref``, ``stress`` (n, 3) kPa compression positive, ``fixed``,
    ``excavated``, ``contacts`` (``points``, ``normals``, ``state``, ``fn``, ``fs`` of the
    contact springs in contact), ``bolts`` (anchors, :func:`bolt_anchors`) and
    ``bolt_records`` (:func:`scene_bolts`).
    """
    nr = layout.n_rock
    snap = jax.tree.map(np.asarray, info.snapshot)
    u, rot = np.asarray(state.u)[:nr], np.asarray(state.rot)[:nr]
    if ref is not None:
        u, rot = u - np.asarray(ref.u)[:nr], rot - np.asarray(ref.rot)[:nr]
    if model.ndof == 6:
        stress = -np.asarray(state.stress)[:nr]
    else:
        stress = block_stress(nr, np.asarray(model.area), np.asarray(state.centroid), snap)
    verts, nv = np.asarray(state.verts), np.asarray(model.nv)
    act = snap.active
    return {
        "name": name, "index": index, "increments": increments,
        "final_vertices": [verts[i, : nv[i]] for i in range(nr)],
        "u": np.column_stack([u[:, :2], rot]), "stress": stress,
        "fixed": ~np.asarray(model.free)[:nr], "excavated": ~np.asarray(state.alive)[:nr],
        "contacts": {k: getattr(snap, key)[act]
                     for k, key in (("points", "point"), ("normals", "normal"), ("state", "state"),
                                    ("fn", "fn"), ("fs", "fs"))},
        "bolts": bolt_anchors(model, state, layout),
        "bolt_records": scene_bolts(scene, layout, state, bolt_active),
    }


def block_overlap(model, state, n_real: int) -> tuple[float, float]:
    """The deepest interpenetration of two blocks now (m), and that over the smaller one's size.

    Measured on the blocks' polygons (walls included, excavated blocks not) over every
    pair whose boxes meet and of which one block can move, as the separating-axis depth
    (:func:`jaxdem.geometry.overlap_depths`), not at the contacts of the last sub-step
    alone: a block that went into another where no contact point saw it counts too.
    The size is a block's largest centroid-to-vertex distance, the smaller of the
    pair's free blocks (as the solver's own check, :data:`jaxdem.core.status.OVERLAP_TOL`).
    """
    verts = np.asarray(state.verts)[:n_real]
    nv = np.asarray(model.nv)[:n_real]
    alive = np.asarray(state.alive)[:n_real]
    free = np.asarray(model.free)[:n_real] & alive
    radius = np.asarray(model.radius)[:n_real]
    polys = [verts[k, :nv[k]] for k in range(n_real)]
    i, j = geometry.near_box_pairs(geometry.bboxes(polys), 0.0)
    keep = alive[i] & alive[j] & (free[i] | free[j])
    i, j = i[keep], j[keep]
    if len(i) == 0:
        return 0.0, 0.0
    depth = geometry.overlap_depths(polys, i, j)
    size = np.minimum(np.where(free[i], radius[i], np.inf), np.where(free[j], radius[j], np.inf))
    return float(depth.max()), float((depth / size).max())


def _in_situ_limit_message(scene) -> str:
    """The iteration limit in the in-situ initial state: its stresses are in place at
    once, so more load steps do not help; where the scene's warning says that the rock
    cannot carry them (:attr:`jaxdem.scene.Scene.warnings`, "in_situ: ..."), say so."""
    message = ("The iteration limit was reached before equilibrium in the initial state: "
               "the in-situ stresses are in place at once (solver.load_steps does not "
               "divide them).")
    weak = [w for w in getattr(scene, "warnings", ()) if w.startswith("in_situ:")]
    if weak:
        return (f"{message} The intact rock cannot carry them (the in_situ warning); change "
                "in_situ.k0 or the rock's strength, or raise solver.max_iterations.")
    return f"{message} Try increasing solver.max_iterations."


def build_result(scene, model, layout, state, ref, info, records, history, timing,
                 bolt_active=None, loose=(), cuts=()) -> Result:
    """Assemble the host Result from the final state and the increment records.

    ``ref`` is the state displacements are measured from (None: the start);
    ``bolt_active`` the driver's mask of installed bolts (:func:`scene_bolts`); ``loose``
    the blocks removed as loose (``Result.loose_blocks``); ``cuts`` the stage of each load
    step cut (:func:`jaxdem.solver.ramp`).
    """
    nr = layout.n_rock
    snap = jax.tree.map(np.asarray, info.snapshot)
    status = Status.of(info.status)
    travel = np.asarray(info.travel)[:nr]
    max_disp = float(model.max_displacement)
    limit = np.asarray(model.travel_limit, float)
    if status == Status.MECHANISM:
        # Blocks that moved together had their group's limit (group_limits).
        limit, group = (np.asarray(x)
                        for x in run_stored(_group_limits, model, info.snapshot, info.travel))
    last = records[-1]
    overlap, overlap_rel = block_overlap(model, state, nr + len(layout.walls))
    if status == Status.CONVERGED and overlap_rel > OVERLAP_TOL:
        # The solver checks the overlap at its contacts; blocks gone into each other
        # where no contact saw it are not an admissible equilibrium either.
        status = Status.OVERLAP
    moving = moving_blocks(travel, max_disp) if status == Status.MECHANISM else []
    stable = status != Status.MECHANISM
    converged = status == Status.CONVERGED
    where = f"load step {last['step']} of stage {last['stage']}"
    cuts_in = collections.Counter(cuts)  # stage -> load steps cut in it
    cut = cuts_in[last["stage"]]
    held = ""
    if cut and not converged:
        # Where the shortest step failed: how far the stage's loads held.
        k, n = last["step"], last["n_steps"]
        where = f"load step {k} of {n} of stage {last['stage']}"
        held = (f" Its load step was cut {cut} time{'s' if cut > 1 else ''}: the last "
                f"equilibrium at load factor {(k - 1) / n:.4g}, none found at {k / n:.4g}.")
    if status == Status.MECHANISM:
        # Which block passed its limit: the scene's max_displacement, its own size or
        # its group's.
        first = int(np.argmax(travel / limit[:nr]))
        together = np.flatnonzero(group[:nr] == group[first])
        if limit[first] >= max_disp:
            past = f"travel over {max_disp:.3g} m"
        elif len(together) > 1:
            names = ", ".join(str(int(i)) for i in together[:10])
            past = (f"blocks {names}{', ...' if len(together) > 10 else ''} moved together "
                    f"and block {first} travelled over their limit, {limit[first]:.3g} m (the "
                    f"size of their {float(np.sum(np.asarray(model.area)[together])):.3g} "
                    f"m2 together, at least {TRAVEL_FLOOR:g} x the median block's),")
        else:
            past = (f"block {first} travelled over its own limit, {limit[first]:.3g} m (its "
                    f"size, at least {TRAVEL_FLOOR:g} x the median block's),")
        message = (f"{status.message} Moving blocks: {', '.join(map(str, moving))} "
                   f"({past} in {where}).{held}")
    elif converged:
        shortened = "".join(f"; the load step of stage {name} cut {m} time{'s' if m > 1 else ''}"
                            for name, m in cuts_in.items())
        message = f"{status.message} {len(records)} increments{shortened}, stable."
    elif status == Status.ITERATION_LIMIT and last["stage"] == "initial" and scene.in_situ:
        message = _in_situ_limit_message(scene)
    else:
        message = f"{status.message} Stopped in {where}.{held}"
    unbalanced = (unbalanced_blocks(info, float(model.tol), layout.centroids[:nr])
                  if status == Status.ITERATION_LIMIT else [])
    if unbalanced:
        message += " Out of balance: " + ", ".join(
            f"block {b['id']} at ({b['centroid'][0]:.3g}, {b['centroid'][1]:.3g}) by "
            f"{b['force']:.3g} kN/m ({_percent(b['relative'])} of the largest force on it)"
            for b in unbalanced) + "."
    if loose:
        message += " " + _loose_sentence(loose)

    cen = np.asarray(state.centroid)
    alive = np.asarray(state.alive)[:nr]
    u = np.asarray(state.u)
    rot = np.asarray(state.rot)
    if ref is not None:
        u = u - np.asarray(ref.u)
        rot = rot - np.asarray(ref.rot)
    strain = None
    if model.ndof == 6:
        # Deformable cells carry their own stress (tension positive in the solver).
        stress = -np.asarray(state.stress)[:nr]
        strain = np.asarray(state.strain)[:nr]
        if ref is not None:
            strain = strain - np.asarray(ref.strain)[:nr]
    else:
        stress = block_stress(nr, np.asarray(model.area), cen, snap)
    fixed = ~np.asarray(model.free)[:nr]
    blocks = [
        {"id": i, "centroid": layout.centroids[i].tolist(), "u": [u[i, 0], u[i, 1], rot[i]],
         "stress": stress[i].tolist(), "fixed": bool(fixed[i]),
         **({"strain": strain[i].tolist()} if strain is not None else {}),
         **({"excavated": True} if not alive[i] else {})}
        for i in range(nr)
    ]
    act = snap.active
    st = snap.state[act]
    contacts = {"total": int(act.sum()), "open": int((st == OPEN).sum()),
                "slipping": int((st == SLIP).sum())}
    bal = jax.tree.map(np.asarray, info.balance)
    equilibrium = {"applied": bal.applied.tolist(), "reaction": bal.reaction.tolist(),
                   "imbalance": last["imbalance"]}
    monitors = monitor_values(layout, state, ref)
    stages = []
    for name in dict.fromkeys(r["stage"] for r in records):
        recs = [r for r in records if r["stage"] == name]
        hist = [h for h in history if h["stage"] == name]
        stages.append({
            "name": name,
            "converged": all(r["status"] == Status.CONVERGED for r in recs),
            "stable": all(r["status"] != Status.MECHANISM for r in recs),
            "load_factor": [r["load_factor"] for r in recs],
            "step_cuts": cuts_in[name],
            "iterations": [r["iterations"] for r in recs],
            "substeps": [r["substeps"] for r in recs],
            "residual": [r["residual"] for r in recs],
            "imbalance": [r["imbalance"] for r in recs],
            "max_slip": [r.get("slip", 0.0) for r in recs],
            "max_opening": [r.get("opening", 0.0) for r in recs],
            "monitors": {m: [_scalar(h["monitors"][m]) for h in hist] for m in monitors},
            **({"released": {e: [r["released"][e] for r in recs] for e in recs[0]["released"]}}
               if "released" in recs[0] else {}),
        })
    bolts = scene_bolts(scene, layout, state, bolt_active)
    imbalance_tol = IMBALANCE_FACTOR * float(model.tol)

    admissibility = {
        "overlap": overlap, "overlap_rel": overlap_rel,
        "strength_excess": last.get("strength_excess", 0.0), "imbalance": last["imbalance"],
        "tolerances": {"overlap_rel": OVERLAP_TOL, "strength_excess": STRENGTH_TOL,
                       "imbalance": imbalance_tol},
    }
    admissibility["admissible"] = bool(
        admissibility["overlap_rel"] <= OVERLAP_TOL
        and admissibility["strength_excess"] <= STRENGTH_TOL
        and admissibility["imbalance"] <= imbalance_tol)
    warnings = list(getattr(scene, "warnings", ()))  # plausibility: a value in the wrong unit?
    big = [r for r in records if r.get("slip_rel", 0.0) > LARGE_SLIP]
    if big:
        r = max(big, key=lambda r: r["slip"])
        pair = " and ".join(_block_name(i, nr) for i in r["slip_blocks"])
        lead = ("stable, but" if converged else "unstable, but" if not stable
                else "no admissible equilibrium, and")
        warnings.append(
            f"{lead} joint slip of {1e3 * r['slip']:.0f} mm "
            f"in one increment (load step {r['step']} of stage {r['stage']}) at blocks {pair}: "
            f"more than {LARGE_SLIP:.0%} of the block's size; review")
    chatter = back_and_forth(moving, u, rot, np.asarray(model.radius), limit)
    if chatter:
        warnings.append(chatter)
    small = small_mechanism(moving, np.asarray(model.area)[:nr], loose_limit(scene),
                            np.asarray(layout.centroids)[:nr])
    if small:
        warnings.append(small)
    verts = np.asarray(state.verts)
    nv = np.asarray(model.nv)
    geometry = {
        "initial_vertices": layout.polygons,
        "final_vertices": [verts[i, : nv[i]] for i in range(nr)],
        "fixed": fixed,
        "excavated": ~alive,
        "loose": np.isin(np.arange(nr), [b["id"] for b in loose]),
        "walls": layout.walls,
        "contacts": {"points": snap.point[act], "normals": snap.normal[act], "state": st,
                     "fn": snap.fn[act], "fs": snap.fs[act],
                     **initial_contacts(snap, act, ref)},
        "monitors": {name: m["points"] for name, m in layout.monitors.items()},
        "stress": stress,
        "centroids": cen[:nr],
        "bolts": bolt_anchors(model, state, layout),
        "water_table": final_water_table(scene),
        **support_geometry(scene),
    }
    hist = [{"stage": h["stage"], "step": h["step"], "load_factor": h["load_factor"],
             "monitors": {k: _scalar(v) for k, v in h["monitors"].items()}} for h in history]
    return Result(
        scene=scene.name, converged=converged, stable=stable, status=status,
        message=message, monitors=monitors, blocks=blocks, contacts=contacts, bolts=bolts,
        stages=stages, moving_blocks=moving, equilibrium=equilibrium, timing=timing,
        geometry=geometry, history=hist, admissibility=admissibility, warnings=warnings,
        loose_blocks=[dict(b) for b in loose], unbalanced_blocks=unbalanced,
    )


def _loose_sentence(loose) -> str:
    """``Loose blocks removed: 474 (0.0426 m3/m, stage heading).``"""
    return "Loose blocks removed: " + ", ".join(
        f"{b['id']} ({b['volume']:.3g} m3/m, stage {b['stage']})" for b in loose) + "."


def _block_name(i: int, n_rock: int) -> str:
    """A block id as the user knows it: rock blocks by id, the rest are boundaries."""
    return str(i) if i < n_rock else "boundary"
