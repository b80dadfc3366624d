"""Scene files: TOML -> validated host-side ``Scene`` (SPEC section 2); ``SceneError``.

Everything here is plain Python and NumPy. A scene is validated completely before
any computation: the first problem found is raised as one ``SceneError`` whose
message starts with the field's dotted path, for example::

    materials.rock.E: must be > 0 (got -1)
    blocks.3.vertices: vertices are clockwise; list them counter-clockwise

Units as in the files (SPEC section 1): m, kN, kPa, kN/m3, angles in degrees (the
solver converts to radians). Every numeric entry is a parameter addressable by its
dotted path (``joints.set1.kn``, ``boundaries.1.traction.0``), which is what
``--set PATH=VALUE`` and ``Scene.with_overrides`` change.

Example::

    >>> scene = load_scene("examples/two_blocks.toml", set={"joints.j.kn": 2e6})
    >>> scene.joints["j"].kn
    2000000.0

This version models explicit-block scenes only; ``domain``, ``excavations``,
``in_situ``, ``bolts``, ``supports``, ``water`` and ``stages`` are refused.

Documented extensions and choices:

- ``[solver] regularization`` (default 1e-6, in (0, 1)) and ``step_length``
  (m, optional, > 0) are jaxdem extensions.
- ``[[discontinuities]] joint`` may be left out: the line then takes the scene's
  default joint.
- ``set``/overrides may also set an optional numeric field that the file leaves out
  (``joints.j.cohesion``), when its table exists; anything else unknown is refused.
- ``load_scene`` also accepts TOML text (a string containing a newline).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxdem import geometry

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

__all__ = [
    "Block",
    "Boundary",
    "Discontinuity",
    "Joint",
    "Material",
    "Monitor",
    "Scene",
    "SceneError",
    "SolverSettings",
    "apply_overrides",
    "load_scene",
    "parse_scene",
    "parse_set_arguments",
]

MAX_MAGNITUDE = 1e15
"""Largest absolute value accepted for any number in a scene (typos such as 3e70)."""


class SceneError(ValueError):
    """An invalid scene: the message starts with the field path, then what is wrong.

    ``path`` is the dotted field path (``"blocks.3.vertices"``), the file name for
    file-level problems, or ``"--set"`` for malformed command-line overrides.
    """

    def __init__(self, path: str, problem: str, *, prefix: str = "") -> None:
        self.path = path
        self.problem = problem
        super().__init__(f"{prefix}{path}: {problem}")


# --------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True)
class Material:
    """Intact rock: E (kPa), nu (-), unit_weight (kN/m3), cohesion (kPa), friction_deg (deg),
    tensile_strength (kPa)."""

    name: str
    E: float
    nu: float
    unit_weight: float
    cohesion: float = 0.0
    friction_deg: float = 45.0
    tensile_strength: float = 0.0


@dataclass(frozen=True)
class Joint:
    """Joint: kn, ks (kPa/m), friction_deg (deg), cohesion, tensile_strength (kPa).

    Optional set geometry (parsed and validated, not yet generated): dip_deg (trace angle,
    deg counter-clockwise from +x), spacing (m), origin (x, y) (m), persistence (0-1], gap (m).
    """

    name: str
    kn: float
    ks: float
    friction_deg: float
    cohesion: float = 0.0
    tensile_strength: float = 0.0
    dip_deg: float | None = None
    spacing: float | None = None
    origin: tuple[float, float] | None = None
    persistence: float | None = None
    gap: float | None = None


@dataclass(frozen=True, eq=False)
class Block:
    """Explicit block: vertices (n, 2) in m, counter-clockwise and convex (read-only array)."""

    vertices: np.ndarray
    material: str
    fixed: bool = False


@dataclass(frozen=True, eq=False)
class Discontinuity:
    """A joint trace from ``start`` to ``end`` (m, shape (2,)) carrying joint ``joint``."""

    start: np.ndarray
    end: np.ndarray
    joint: str


@dataclass(frozen=True, eq=False)
class Boundary:
    """A boundary condition on segment start-end (m); traction (tx, ty) in kPa, zeros unless
    condition == "traction". ``side`` is "left"|"right"|"bottom"|"top" or None for from/to."""

    condition: str
    start: np.ndarray
    end: np.ndarray
    side: str | None
    traction: np.ndarray


@dataclass(frozen=True, eq=False)
class Monitor:
    """A point monitor (displacement of a rock point) or a section (convergence start-end), m."""

    name: str
    kind: str
    point: np.ndarray | None = None
    start: np.ndarray | None = None
    end: np.ndarray | None = None


@dataclass(frozen=True)
class SolverSettings:
    """Solver controls; max_displacement and step_length in m (None: the solver chooses)."""

    load_steps: int = 5
    tolerance: float = 1e-9
    max_iterations: int = 60
    max_displacement: float | None = None
    dtype: str = "float64"
    regularization: float = 1e-6
    step_length: float | None = None


@dataclass(frozen=True, eq=False)
class Scene:
    """A validated scene. ``data`` is the raw parsed TOML (for overrides); ``source`` its origin."""

    name: str
    description: str
    default_joint: str
    solver: SolverSettings
    materials: dict[str, Material]
    joints: dict[str, Joint]
    blocks: tuple[Block, ...]
    discontinuities: tuple[Discontinuity, ...]
    boundaries: tuple[Boundary, ...]
    monitors: tuple[Monitor, ...]
    data: dict
    source: str

    def with_overrides(self, overrides: Mapping[str, float]) -> Scene:
        """A new Scene re-validated from ``data`` with numeric entries set by dotted path."""
        return parse_scene(apply_overrides(self.data, overrides), source=self.source)


# --------------------------------------------------------------------------- schema

SUPPORTED_SECTIONS = (
    "scene",
    "solver",
    "materials",
    "joints",
    "blocks",
    "discontinuities",
    "boundaries",
    "monitors",
)
UNSUPPORTED_SECTIONS = ("domain", "excavations", "in_situ", "bolts", "supports", "water", "stages")

SCENE_FIELDS = ("name", "description", "default_joint")
SOLVER_FIELDS = (
    "load_steps",
    "tolerance",
    "max_iterations",
    "max_displacement",
    "dtype",
    "regularization",
    "step_length",
)
MATERIAL_FIELDS = ("E", "nu", "unit_weight", "cohesion", "friction_deg", "tensile_strength")
JOINT_FIELDS = (
    "kn",
    "ks",
    "cohesion",
    "friction_deg",
    "tensile_strength",
    "dip_deg",
    "spacing",
    "origin",
    "persistence",
    "gap",
)
BLOCK_FIELDS = ("vertices", "material", "fixed")
DISCONTINUITY_FIELDS = ("from", "to", "joint")
BOUNDARY_FIELDS = ("side", "from", "to", "condition", "traction")
MONITOR_FIELDS = ("name", "point", "from", "to")

SIDES = ("left", "right", "bottom", "top")
CONDITIONS = ("fixed", "roller", "traction")
DTYPES = ("float64", "float32")

# Scalar numeric fields that an override may add when the file leaves them out.
_OPTIONAL_NUMERIC = {
    "solver": ("load_steps", "tolerance", "max_iterations", "max_displacement")
    + ("regularization", "step_length"),
    "materials": MATERIAL_FIELDS,
    "joints": ("kn", "ks", "cohesion", "friction_deg", "tensile_strength")
    + ("dip_deg", "spacing", "persistence", "gap"),
}
_INT_FIELDS = ("load_steps", "max_iterations")


# --------------------------------------------------------------------------- value checks


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(
        x, (bool, np.bool_)
    )


def _fmt(x: Any) -> str:
    if isinstance(x, str):
        return repr(x)
    if isinstance(x, (np.integer, np.floating)):
        x = x.item()
    if isinstance(x, float):
        return repr(x)
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_fmt(e) for e in x) + "]"
    if isinstance(x, dict):
        return "a table"
    return repr(x) if isinstance(x, (int, bool)) else type(x).__name__


def _fmt_point(p: np.ndarray) -> str:
    return f"({float(p[0]):g}, {float(p[1]):g})"


def _number(value: Any, path: str) -> float:
    """A finite, not absurdly large number, as float."""
    if not _is_number(value):
        raise SceneError(path, f"must be a number (got {_fmt(value)})")
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        raise SceneError(path, f"must be finite (got {_fmt(value)})")
    if abs(value) > MAX_MAGNITUDE:
        raise SceneError(
            path, f"out of range: magnitude above {MAX_MAGNITUDE:g} (got {_fmt(value)})"
        )
    return float(value)


def _integer(value: Any, path: str) -> int:
    x = _number(value, path)
    if x != math.floor(x):
        raise SceneError(path, f"must be an integer (got {_fmt(value)})")
    return int(x)


def _in_range(
    x: float,
    raw: Any,
    path: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
) -> None:
    bad = (lo is not None and (x <= lo if lo_open else x < lo)) or (
        hi is not None and (x >= hi if hi_open else x > hi)
    )
    if not bad:
        return
    if lo is not None and hi is not None:
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        what = f"must be in {lb}{lo:g}, {hi:g}{rb}"
    elif lo is not None:
        what = f"must be {'>' if lo_open else '>='} {lo:g}"
    else:
        what = f"must be {'<' if hi_open else '<='} {hi:g}"
    raise SceneError(path, f"{what} (got {_fmt(raw)})")


def _string(value: Any, path: str, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(value, str):
        raise SceneError(path, f"must be a string (got {_fmt(value)})")
    if choices is not None and value not in choices:
        raise SceneError(path, f"must be one of {', '.join(choices)} (got {value!r})")
    return value


def _point(value: Any, path: str) -> np.ndarray:
    if isinstance(value, np.ndarray):  # programmatic scenes
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SceneError(path, f"must be a point [x, y] of two numbers (got {_fmt(value)})")
    xy = np.array([_number(value[k], f"{path}.{k}") for k in range(2)], dtype=np.float64)
    xy.setflags(write=False)
    return xy


def _table(value: Any, path: str, allowed: tuple[str, ...]) -> dict:
    if not isinstance(value, dict):
        raise SceneError(path, f"must be a table (got {_fmt(value)})")
    for key in value:
        if key not in allowed:
            raise SceneError(f"{path}.{key}", f"unknown field; allowed: {', '.join(allowed)}")
    return value


def _array_of_tables(data: dict, key: str) -> list:
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(e, dict) for e in value):
        raise SceneError(key, f"must be an array of tables ([[{key}]]), got {_fmt(value)}")
    return value


def _field(
    table: dict,
    key: str,
    path: str,
    *,
    required: bool = False,
    default: Any = None,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    integer: bool = False,
) -> Any:
    """A numeric field: required or default, finite, in range."""
    fpath = f"{path}.{key}"
    if key not in table:
        if required:
            raise SceneError(fpath, "required field is missing")
        return default
    raw = table[key]
    x = _integer(raw, fpath) if integer else _number(raw, fpath)
    _in_range(float(x), raw, fpath, lo, hi, lo_open, hi_open)
    return x


# --------------------------------------------------------------------------- sections


def _parse_solver(data: dict) -> SolverSettings:
    t = _table(data.get("solver", {}), "solver", SOLVER_FIELDS)
    d = SolverSettings()
    dtype = _string(t["dtype"], "solver.dtype", DTYPES) if "dtype" in t else d.dtype
    return SolverSettings(
        load_steps=_field(t, "load_steps", "solver", default=d.load_steps, lo=1, integer=True),
        tolerance=_field(
            t, "tolerance", "solver", default=d.tolerance, lo=0, hi=1, lo_open=True, hi_open=True
        ),
        max_iterations=_field(
            t, "max_iterations", "solver", default=d.max_iterations, lo=1, integer=True
        ),
        max_displacement=_field(t, "max_displacement", "solver", lo=0, lo_open=True),
        dtype=dtype,
        regularization=_field(
            t,
            "regularization",
            "solver",
            default=d.regularization,
            lo=0,
            hi=1,
            lo_open=True,
            hi_open=True,
        ),
        step_length=_field(t, "step_length", "solver", lo=0, lo_open=True),
    )


def _named_tables(data: dict, key: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise SceneError(key, f"must be a table of named tables ([{key}.NAME]), got {_fmt(value)}")
    return value


def _parse_materials(data: dict) -> dict[str, Material]:
    out = {}
    for name, raw in _named_tables(data, "materials").items():
        p = f"materials.{name}"
        t = _table(raw, p, MATERIAL_FIELDS)
        out[name] = Material(
            name=name,
            E=_field(t, "E", p, required=True, lo=0, lo_open=True),
            nu=_field(t, "nu", p, required=True, lo=0, hi=0.5, hi_open=True),
            unit_weight=_field(t, "unit_weight", p, required=True, lo=0),
            cohesion=_field(t, "cohesion", p, default=0.0, lo=0),
            friction_deg=_field(t, "friction_deg", p, default=45.0, lo=0, hi=90, hi_open=True),
            tensile_strength=_field(t, "tensile_strength", p, default=0.0, lo=0),
        )
    return out


def _parse_joints(data: dict) -> dict[str, Joint]:
    out = {}
    for name, raw in _named_tables(data, "joints").items():
        p = f"joints.{name}"
        t = _table(raw, p, JOINT_FIELDS)
        origin = None
        if "origin" in t:
            xy = _point(t["origin"], f"{p}.origin")
            origin = (float(xy[0]), float(xy[1]))
        out[name] = Joint(
            name=name,
            kn=_field(t, "kn", p, required=True, lo=0, lo_open=True),
            ks=_field(t, "ks", p, required=True, lo=0, lo_open=True),
            friction_deg=_field(t, "friction_deg", p, required=True, lo=0, hi=90, hi_open=True),
            cohesion=_field(t, "cohesion", p, default=0.0, lo=0),
            tensile_strength=_field(t, "tensile_strength", p, default=0.0, lo=0),
            dip_deg=_field(t, "dip_deg", p),
            spacing=_field(t, "spacing", p, lo=0, lo_open=True),
            origin=origin,
            persistence=_field(t, "persistence", p, lo=0, hi=1, lo_open=True),
            gap=_field(t, "gap", p, lo=0),
        )
    return out


def _check_polygon(v: np.ndarray, path: str) -> None:
    """Refuse repeated points, collinear, self-intersecting, degenerate, clockwise, non-convex."""
    diag = float(np.hypot(*(v.max(axis=0) - v.min(axis=0))))
    n = len(v)
    tol = 1e-9 * diag
    if geometry.has_repeated_points(v, tol):
        diff = v[:, None, :] - v[None, :, :]
        close = np.hypot(diff[..., 0], diff[..., 1]) <= tol
        i, j = next((i, j) for i in range(n) for j in range(i + 1, n) if close[i, j])
        raise SceneError(path, f"repeated point {_fmt_point(v[i])} at vertices {i} and {j}")
    # All points on one line: say "degenerate" rather than "self-intersecting".
    centred = v - v.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    thickness = float(np.ptp(centred @ vt[-1]))
    if thickness <= 1e-12 * diag:
        raise SceneError(
            path, "degenerate polygon: all vertices lie on one line (zero or near-zero area)"
        )
    if geometry.self_intersects(v):
        raise SceneError(path, "self-intersecting polygon: two of its edges cross or touch")
    area = geometry.signed_area(v)
    if abs(area) < 1e-12 * diag * diag:
        raise SceneError(path, f"degenerate polygon: near-zero area ({area:.3g} m2)")
    if area < 0.0:
        raise SceneError(path, "vertices are clockwise; list them counter-clockwise")
    s = geometry.corner_sines(v)
    for k in range(n):
        if abs(s[k]) <= 1e-9:
            raise SceneError(
                path,
                f"degenerate vertex {k} {_fmt_point(v[k])}: collinear with its neighbours "
                "(180-degree corner); remove it",
            )
    for k in range(n):
        if s[k] < 0.0:
            raise SceneError(
                path,
                f"is not convex at vertex {k} {_fmt_point(v[k])}; split it into convex blocks",
            )
    # Simple, counter-clockwise and turning left at every vertex: convex.


def _parse_blocks(data: dict, materials: dict[str, Material]) -> tuple[Block, ...]:
    raw_blocks = _array_of_tables(data, "blocks")
    if not raw_blocks:
        raise SceneError("blocks", "at least one block is needed ([[blocks]] vertices, material)")
    blocks = []
    for i, raw in enumerate(raw_blocks):
        p = f"blocks.{i}"
        t = _table(raw, p, BLOCK_FIELDS)
        if "vertices" not in t:
            raise SceneError(f"{p}.vertices", "required field is missing")
        vp = f"{p}.vertices"
        vs = t["vertices"]
        if isinstance(vs, (np.ndarray, tuple)):  # programmatic scenes
            vs = list(vs)
        if not isinstance(vs, list):
            raise SceneError(vp, f"must be a list of points [[x, y], ...] (got {_fmt(vs)})")
        if len(vs) < 3:
            raise SceneError(vp, f"needs at least 3 points (got {len(vs)})")
        v = np.array([_point(q, f"{vp}.{k}") for k, q in enumerate(vs)], dtype=np.float64)
        _check_polygon(v, vp)
        v.setflags(write=False)
        if "material" not in t:
            raise SceneError(f"{p}.material", "required field is missing")
        mat = _string(t["material"], f"{p}.material")
        if mat not in materials:
            defined = ", ".join(materials) or "none"
            raise SceneError(f"{p}.material", f"unknown material {mat!r}; defined: {defined}")
        fixed = t.get("fixed", False)
        if not isinstance(fixed, bool):
            raise SceneError(f"{p}.fixed", f"must be true or false (got {_fmt(fixed)})")
        blocks.append(Block(vertices=v, material=mat, fixed=fixed))
    return tuple(blocks)


def _check_overlaps(blocks: tuple[Block, ...]) -> None:
    polys = [b.vertices for b in blocks]
    areas = [geometry.signed_area(v) for v in polys]
    pairs = geometry.find_overlapping_pairs(polys, 1e-9 * min(areas))
    bad = []
    for i, j in pairs:
        a = geometry.overlap_area(polys[i], polys[j])
        if a > 1e-9 * min(areas[i], areas[j]):
            bad.append((j, i, a))
    if bad:
        j, i, a = min(bad)
        raise SceneError(f"blocks.{j}", f"overlaps blocks.{i} (area {a:.3g} m2)")


def _segment_touches_box(a: np.ndarray, b: np.ndarray, box: tuple, tol: float) -> bool:
    xmin, ymin, xmax, ymax = box
    for q in (a, b):
        if xmin - tol <= q[0] <= xmax + tol and ymin - tol <= q[1] <= ymax + tol:
            return True
    corners = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
    return any(
        geometry.segments_intersect(a, b, corners[k], corners[(k + 1) % 4], tol) for k in range(4)
    )


def _parse_discontinuities(
    data: dict, joints: dict[str, Joint], default_joint: str, box: tuple, tol: float
) -> tuple[Discontinuity, ...]:
    out = []
    for i, raw in enumerate(_array_of_tables(data, "discontinuities")):
        p = f"discontinuities.{i}"
        t = _table(raw, p, DISCONTINUITY_FIELDS)
        for key in ("from", "to"):
            if key not in t:
                raise SceneError(f"{p}.{key}", "required field is missing")
        a = _point(t["from"], f"{p}.from")
        b = _point(t["to"], f"{p}.to")
        if "joint" in t:
            joint = _string(t["joint"], f"{p}.joint")
            if joint not in joints:
                defined = ", ".join(joints) or "none"
                raise SceneError(f"{p}.joint", f"unknown joint {joint!r}; defined: {defined}")
        elif default_joint:
            joint = default_joint
        else:
            raise SceneError(f"{p}.joint", "required: no joints are defined to default to")
        if float(np.hypot(*(b - a))) <= tol:
            raise SceneError(
                f"{p}.to", f"same point as from {_fmt_point(a)}; a discontinuity needs two ends"
            )
        if not _segment_touches_box(a, b, box, tol):
            raise SceneError(
                p,
                f"joint outside the domain: {_fmt_point(a)}-{_fmt_point(b)} misses the blocks' "
                f"bounding box ({box[0]:g}, {box[1]:g})-({box[2]:g}, {box[3]:g})",
            )
        out.append(Discontinuity(start=a, end=b, joint=joint))
    return tuple(out)


def _side_segment(side: str, box: tuple) -> tuple[np.ndarray, np.ndarray]:
    xmin, ymin, xmax, ymax = box
    ends = {
        "left": ((xmin, ymin), (xmin, ymax)),
        "right": ((xmax, ymin), (xmax, ymax)),
        "bottom": ((xmin, ymin), (xmax, ymin)),
        "top": ((xmin, ymax), (xmax, ymax)),
    }[side]
    a, b = (np.array(e, dtype=np.float64) for e in ends)
    a.setflags(write=False)
    b.setflags(write=False)
    return a, b


def _parse_boundaries(data: dict, box: tuple, tol: float) -> tuple[Boundary, ...]:
    out = []
    for i, raw in enumerate(_array_of_tables(data, "boundaries")):
        p = f"boundaries.{i}"
        t = _table(raw, p, BOUNDARY_FIELDS)
        has_side = "side" in t
        has_ends = "from" in t or "to" in t
        if has_side and has_ends:
            raise SceneError(p, "give either side or from/to, not both")
        if not has_side and not has_ends:
            raise SceneError(p, f"needs side ({', '.join(SIDES)}) or from/to")
        if has_side:
            side = _string(t["side"], f"{p}.side", SIDES)
            a, b = _side_segment(side, box)
        else:
            side = None
            for key in ("from", "to"):
                if key not in t:
                    raise SceneError(f"{p}.{key}", "required with from/to (both ends are needed)")
            a = _point(t["from"], f"{p}.from")
            b = _point(t["to"], f"{p}.to")
            if float(np.hypot(*(b - a))) <= tol:
                raise SceneError(f"{p}.to", f"same point as from {_fmt_point(a)}")
        if "condition" not in t:
            raise SceneError(f"{p}.condition", f"required ({', '.join(CONDITIONS)})")
        cond = _string(t["condition"], f"{p}.condition", CONDITIONS)
        if cond == "traction":
            if "traction" not in t:
                raise SceneError(
                    f"{p}.traction", "required for condition 'traction' ([tx, ty] in kPa)"
                )
            tr = t["traction"]
            if not isinstance(tr, list) or len(tr) != 2:
                raise SceneError(f"{p}.traction", f"must be [tx, ty] in kPa (got {_fmt(tr)})")
            traction = np.array(
                [_number(tr[k], f"{p}.traction.{k}") for k in range(2)], dtype=np.float64
            )
        else:
            if "traction" in t:
                raise SceneError(
                    f"{p}.traction", f"only allowed with condition 'traction' (got {cond!r})"
                )
            traction = np.zeros(2)
        traction.setflags(write=False)
        out.append(Boundary(condition=cond, start=a, end=b, side=side, traction=traction))
    return tuple(out)


def _in_rock(q: np.ndarray, blocks: tuple[Block, ...], boxes: np.ndarray, tol: float) -> bool:
    near = np.nonzero(
        (boxes[:, 0] - tol <= q[0])
        & (q[0] <= boxes[:, 2] + tol)
        & (boxes[:, 1] - tol <= q[1])
        & (q[1] <= boxes[:, 3] + tol)
    )[0]
    return any(geometry.point_in_polygon(q, blocks[k].vertices, tol) for k in near)


def _parse_monitors(data: dict, blocks: tuple[Block, ...], tol: float) -> tuple[Monitor, ...]:
    boxes = np.array([geometry.bbox(b.vertices) for b in blocks])
    out = []
    seen: dict[str, int] = {}
    for i, raw in enumerate(_array_of_tables(data, "monitors")):
        p = f"monitors.{i}"
        t = _table(raw, p, MONITOR_FIELDS)
        if "name" not in t:
            raise SceneError(f"{p}.name", "required field is missing")
        name = _string(t["name"], f"{p}.name")
        if not name:
            raise SceneError(f"{p}.name", "must not be empty")
        if name in seen:
            raise SceneError(f"{p}.name", f"duplicate name {name!r} (also monitors.{seen[name]})")
        seen[name] = i
        has_point = "point" in t
        has_ends = "from" in t or "to" in t
        if has_point and has_ends:
            raise SceneError(p, "give either point = [x, y] or from/to (a section), not both")
        if not has_point and not has_ends:
            raise SceneError(p, "needs point = [x, y] or from/to (a section)")
        if has_point:
            keys = ("point",)
        else:
            keys = ("from", "to")
            for key in keys:
                if key not in t:
                    raise SceneError(f"{p}.{key}", "required for a section (from and to)")
        pts = {}
        for key in keys:
            q = _point(t[key], f"{p}.{key}")
            if not _in_rock(q, blocks, boxes, tol):
                raise SceneError(f"{p}.{key}", f"{_fmt_point(q)} is outside the rock")
            pts[key] = q
        if has_point:
            out.append(Monitor(name=name, kind="point", point=pts["point"]))
        else:
            if float(np.hypot(*(pts["to"] - pts["from"]))) <= tol:
                raise SceneError(f"{p}.to", f"same point as from {_fmt_point(pts['from'])}")
            out.append(Monitor(name=name, kind="section", start=pts["from"], end=pts["to"]))
    return tuple(out)


def _parse(data: Any, source: str) -> Scene:
    if not isinstance(data, dict):
        raise SceneError(source, f"a scene must be a table (got {_fmt(data)})")
    for key in data:
        if key in UNSUPPORTED_SECTIONS:
            raise SceneError(key, "not supported in this version (explicit-block scenes only)")
        if key not in SUPPORTED_SECTIONS:
            raise SceneError(key, f"unknown section; allowed: {', '.join(SUPPORTED_SECTIONS)}")

    if "scene" not in data:
        raise SceneError("scene.name", "required field is missing ([scene] name = ...)")
    head = _table(data["scene"], "scene", SCENE_FIELDS)
    if "name" not in head:
        raise SceneError("scene.name", "required field is missing")
    name = _string(head["name"], "scene.name")
    if not name.strip():
        raise SceneError("scene.name", "must not be empty")
    description = _string(head.get("description", ""), "scene.description")

    solver = _parse_solver(data)
    materials = _parse_materials(data)
    joints = _parse_joints(data)
    blocks = _parse_blocks(data, materials)

    if "default_joint" in head:
        default_joint = _string(head["default_joint"], "scene.default_joint")
        if default_joint not in joints:
            defined = ", ".join(joints) or "none"
            raise SceneError(
                "scene.default_joint", f"unknown joint {default_joint!r}; defined: {defined}"
            )
    elif joints:
        default_joint = next(iter(joints))
    else:
        default_joint = ""
    if not joints and len(blocks) > 1:
        raise SceneError("joints", "at least one joint is needed for contacts between blocks")

    _check_overlaps(blocks)

    allv = np.concatenate([b.vertices for b in blocks])
    box = geometry.bbox(allv)
    tol = 1e-9 * float(np.hypot(box[2] - box[0], box[3] - box[1]))
    discontinuities = _parse_discontinuities(data, joints, default_joint, box, tol)
    boundaries = _parse_boundaries(data, box, tol)
    monitors = _parse_monitors(data, blocks, tol)

    return Scene(
        name=name,
        description=description,
        default_joint=default_joint,
        solver=solver,
        materials=materials,
        joints=joints,
        blocks=blocks,
        discontinuities=discontinuities,
        boundaries=boundaries,
        monitors=monitors,
        data=copy.deepcopy(data),
        source=source,
    )


# --------------------------------------------------------------------------- public API


def parse_scene(data: dict, source: str = "<dict>") -> Scene:
    """Validate a parsed scene dict (as from TOML) into a ``Scene``; raises ``SceneError``.

    Example::

        >>> parse_scene({"scene": {"name": "s"}, "materials": {...}, "blocks": [...]})
    """
    try:
        return _parse(data, source)
    except SceneError:
        raise
    except Exception as exc:  # never let another type escape validation
        raise SceneError(source, f"invalid scene ({type(exc).__name__}: {exc})") from exc


def _read_toml(path: Path) -> dict:
    name = str(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise SceneError(name, f"cannot read scene file ({reason})") from exc
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(name, f"scene file is not UTF-8 text ({exc.reason})") from exc
    if not text.strip():
        raise SceneError(name, "scene file is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(name, f"invalid TOML ({exc})") from exc
    if not data:
        raise SceneError(name, "scene file is empty (only comments)")
    return data


def load_scene(path_or_text: str | Path | dict, *, set: Mapping[str, float] | None = None) -> Scene:
    """Load and validate a scene from a .toml path, TOML text, or an already-parsed dict.

    ``set`` holds overrides by dotted path (``{"joints.j.kn": 2e6}``), applied before
    validation. A string containing a newline is read as TOML text, any other string as
    a path. Raises ``SceneError`` for every problem, naming the file or the field.

    Example::

        >>> scene = load_scene("tunnel.toml", set={"materials.rock.E": 3e7})
    """
    if isinstance(path_or_text, dict):
        data, source = path_or_text, "<dict>"
    elif isinstance(path_or_text, str) and "\n" in path_or_text:
        source = "<string>"
        try:
            data = tomllib.loads(path_or_text)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(source, f"invalid TOML ({exc})") from exc
        if not data:
            raise SceneError(source, "scene text is empty")
    elif isinstance(path_or_text, (str, Path)):
        path = Path(path_or_text)
        data, source = _read_toml(path), str(path)
    else:
        raise SceneError(
            "<input>",
            f"expected a path, TOML text or a dict (got {type(path_or_text).__name__})",
        )
    if set:
        data = apply_overrides(data, set)
    return parse_scene(data, source=source)


def _walk_error(path: str, problem: str) -> SceneError:
    return SceneError(path, problem, prefix="--set ")


def apply_overrides(data: dict, overrides: Mapping[str, float]) -> dict:
    """A deep copy of ``data`` with numeric entries set by dotted path (``joints.j.kn``).

    List items are addressed by index (``boundaries.1.traction.0``). A path that does not
    exist, or that names a non-numeric entry, raises ``SceneError`` ("--set PATH: ...").
    An optional scalar field left out of the file (``joints.j.cohesion``) may be set when
    its table exists. Integer entries stay integers when the new value is integral.
    """
    try:
        out = copy.deepcopy(data)
    except Exception as exc:
        raise SceneError("<dict>", f"cannot copy scene data ({exc})") from exc
    if not isinstance(out, dict):
        raise SceneError("<dict>", f"a scene must be a table (got {_fmt(out)})")
    for dotted, value in overrides.items():
        if not isinstance(dotted, str) or not dotted:
            raise SceneError("--set", f"parameter path must be a non-empty string (got {dotted!r})")
        if not _is_number(value) or not math.isfinite(float(value)):
            raise _walk_error(dotted, f"value must be a finite number (got {_fmt(value)})")
        keys = dotted.split(".")
        node: Any = out
        for depth, key in enumerate(keys[:-1]):
            node = _step(node, key)
            if node is _MISSING:
                # [solver] is all-optional: allow creating it.
                if depth == 0 and key == "solver" and len(keys) == 2:
                    node = out.setdefault("solver", {})
                else:
                    raise _walk_error(dotted, "no such parameter")
        last = keys[-1]
        _set_leaf(node, last, value, dotted, keys)
    return out


_MISSING = object()


def _step(node: Any, key: str) -> Any:
    if isinstance(node, dict):
        return node.get(key, _MISSING)
    if isinstance(node, list):
        if not key.isdigit() or int(key) >= len(node):
            return _MISSING
        return node[int(key)]
    return _MISSING


def _set_leaf(node: Any, last: str, value: Any, dotted: str, keys: list[str]) -> None:
    if isinstance(node, list):
        if not last.isdigit() or int(last) >= len(node):
            raise _walk_error(dotted, "no such parameter")
        idx: Any = int(last)
        old = node[idx]
    elif isinstance(node, dict):
        if last not in node:
            section = keys[0]
            depth_ok = (section == "solver" and len(keys) == 2) or (
                section in ("materials", "joints") and len(keys) == 3
            )
            if depth_ok and last in _OPTIONAL_NUMERIC.get(section, ()):
                node[last] = _convert(value, last in _INT_FIELDS)
                return
            raise _walk_error(dotted, "no such parameter")
        idx = last
        old = node[idx]
    else:
        raise _walk_error(dotted, "no such parameter")
    if not _is_number(old):
        raise _walk_error(dotted, f"not a numeric parameter (its value is {_fmt(old)})")
    node[idx] = _convert(value, isinstance(old, (int, np.integer)))


def _convert(value: Any, as_int: bool) -> int | float:
    x = float(value)
    if as_int and x == math.floor(x) and abs(x) <= MAX_MAGNITUDE:
        return int(x)
    return int(value) if isinstance(value, (int, np.integer)) else x


def parse_set_arguments(items: list[str]) -> dict[str, float]:
    """Command-line ``--set PATH=VALUE`` strings -> ``{PATH: float(VALUE)}``.

    Malformed items raise ``SceneError`` with path ``"--set"``.

    Example::

        >>> parse_set_arguments(["joints.j.kn=2e6"])
        {'joints.j.kn': 2000000.0}
    """
    out: dict[str, float] = {}
    for item in items:
        if not isinstance(item, str) or "=" not in item:
            raise SceneError("--set", f"expected PATH=VALUE, e.g. joints.j.kn=2e6 (got {item!r})")
        path, _, text = item.partition("=")
        path, text = path.strip(), text.strip()
        parts = path.split(".")
        if not path or any(not p for p in parts) or any(c.isspace() for c in path):
            raise SceneError("--set", f"bad parameter path {path!r} in {item!r}")
        try:
            value = float(text)
        except ValueError:
            raise SceneError("--set", f"value of {path} must be a number (got {text!r})") from None
        if not math.isfinite(value):
            raise SceneError("--set", f"value of {path} must be finite (got {text!r})")
        out[path] = value
    return out
