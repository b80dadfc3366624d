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

A scene may hold explicit ``[[blocks]]``, a generated rock mass (``[domain]``, joint
sets, ``[[discontinuities]]``, ``[[zones]]``, ``[[excavations]]``; the blocks themselves
are made by :func:`jaxdem.rockmass.generate`), or both. ``[in_situ]``, ``[[bolts]]``,
``[[supports]]``, ``[water]`` and ``[[stages]]`` are parsed and validated here.

Documented extensions and choices:

- ``[[boundaries]] stage`` (traction boundaries only): the stage that applies
  the traction, ramped over its load steps and kept afterwards (a surcharge
  placed after excavation); without it the traction is an initial load.
- ``[solver] regularization`` (default 1e-6, in (0, 1)), ``step_length``
  (m, optional, > 0) and ``linear_solver`` ("auto", "dense", "sparse" or "cg";
  default "auto": dense LU up to 600 unknowns (1,800 on an accelerator), else
  sparse direct on a CPU
  and matrix-free CG on an accelerator or in a batch) are
  jaxdem extensions.
- ``[[discontinuities]] joint`` may be left out: the line then takes the scene's
  default joint.
- ``[[blocks]] joint`` (extension): the joint of the block's faces that lie on no
  discontinuity line. With several joints, ``[scene] default_joint`` is required when an
  explicit block without ``joint`` has a face no line covers; two blocks of different
  joints may share a face only where a line says which joint it is.
- ``stage`` (excavations, bolts, supports, traction boundaries) is a stage name or its
  1-based number; a stage that does not exist (or any stage without ``[[stages]]``) is
  refused, listing the stages.
- Joint sets may give ``dip`` and ``dip_direction`` ("left", "right" or an azimuth with
  ``[scene] section_azimuth``) instead of the trace angle ``dip_deg``
  (:func:`trace_angle`).
- Explicit blocks may overlap by up to ``OVERLAP_TOLERANCE`` of the smaller block's size
  in depth (rounded coordinates).
- The user reference of all of this is docs/scene-format.md.
- ``set``/overrides may also set an optional numeric field that the file leaves out
  (``joints.j.cohesion``), when its table exists; anything else unknown is refused.
- ``load_scene`` also accepts TOML text (a string containing a newline).
- ``[[zones]] name, vertices, material`` (extension): a region of another material inside
  the domain (the seed's shear zone). Later zones override earlier ones where they overlap.
- A joint set (``dip_deg`` and ``spacing`` both given) needs a ``[domain]``. Its traces
  are parallel lines ``spacing`` apart, at ``dip_deg`` counter-clockwise from +x, one of
  them through ``origin`` (default: the domain's centroid). With ``persistence`` p < 1 each
  line carries trace segments of length ``p / (1 - p) * gap`` separated by rock bridges of
  length ``gap`` (default ``gap = spacing``), so that p is the jointed fraction of the
  line; successive lines are shifted along the trace by half a period so that bridges
  stagger. ``gap`` without p < 1, or ``gap = 0`` with p < 1, is refused (contradictory).
- ``[[excavations]]``: ``name`` is required and unique; circles and the horseshoe's roof
  are discretised into inscribed polygons of n = clip(ceil(2 pi r / h), 24, 120) segments
  around the full circle (the roof arc takes ceil(n / 2)), h = ``domain.mesh_size`` if set,
  else half the smallest joint-set spacing, else r / 4. Excavations lie inside the domain
  (touching its outline is allowed) and do not overlap each other. ``stage`` names a
  ``[[stages]]`` entry; left out: the first stage (or the only analysis).
- ``[in_situ] mode`` defaults to ``"gravity"``; there ``surface_y`` defaults to the top of
  the rock (highest domain or block vertex) and is stored resolved. Fields of the other
  mode are refused rather than ignored.
- Monitor points and bolt ends must lie in rock: inside the domain and not strictly inside
  an excavation, or inside an explicit block. A boundary given by ``from``/``to`` must touch
  the rock; the excavations must leave some of the domain.
- Limits, so that a typo is refused rather than run out of time or memory: ``load_steps``
  and ``max_iterations`` at most ``MAX_STEPS``; a scene that would generate more than
  ``MAX_BLOCKS`` blocks (estimated from spacings, gaps and mesh size before generating);
  polygons of more than ``MAX_POLYGON_POINTS`` vertices; files over ``MAX_FILE_BYTES``;
  ``solver.max_displacement`` above 10 model sizes, ``solver.step_length`` outside 1e-6 to
  1 model size; coordinates beyond ``MAX_OFFSET`` model sizes from (0, 0). Material and
  joint names may not contain "." (they are segments of dotted paths). A key or table
  given twice in the TOML is refused naming its path and line.
"""

from __future__ import annotations

import ast
import copy
import math
import re
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
    "Bolt",
    "Boundary",
    "Discontinuity",
    "Domain",
    "Excavation",
    "InSitu",
    "Joint",
    "Material",
    "Monitor",
    "Scene",
    "SceneError",
    "SolverSettings",
    "Stage",
    "Support",
    "Water",
    "Zone",
    "apply_overrides",
    "load_scene",
    "parse_scene",
    "parse_set_arguments",
]

MAX_MAGNITUDE = 1e15
"""Largest absolute value accepted for any number in a scene (typos such as 3e70)."""

MAX_STEPS = 10_000
"""Most load steps (``solver.load_steps``, ``stages.N.load_steps``) and Newton iterations
(``solver.max_iterations``) accepted: the defaults are 5 and 60, so more is a typo."""

MAX_BLOCKS = 500_000
"""Most blocks a scene may generate (estimated from joint spacings and mesh size before
anything is generated): 50 times the largest model benchmarked (10,464 blocks, 2 GB)."""

MAX_POLYGON_POINTS = 1_000
"""Most vertices in one polygon (checking a polygon for crossings costs n^2)."""

MAX_FILE_BYTES = 64 * 2**20
"""Largest scene file read (64 MiB; a 10,000-block scene is about 1 MiB)."""

MAX_OFFSET = {"float64": 1e9, "float32": 1e3}

#: Two explicit blocks may overlap by at most this depth, relative to the smaller block's
#: size sqrt(area) (depth = 2 area / perimeter of the overlap, the thickness of a sliver):
#: coordinates rounded to 6 decimals (1e-6 m) pass for blocks of 0.1 m and larger. A
#: deeper overlap is refused; an accepted one is a contact already compressed by it.
OVERLAP_TOLERANCE = 1e-5

#: ``dip_direction`` words: the side of the section the joint dips towards.
DIP_SIDES = ("left", "right")
"""Coordinates may lie at most this many model sizes from (0, 0): beyond, the dtype resolves
less than about 1e-7 (float64) or 1e-4 (float32) of the model's size, the order of the
solver's contact tolerance (1e-6, float32 1e-4, of the block size)."""


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

    Optional set geometry (generated by :mod:`jaxdem.rockmass`): dip_deg (trace angle, deg
    counter-clockwise from +x), spacing (m), origin (x, y) (m; None: the domain centroid),
    persistence (0-1], gap (m, length of a rock bridge along a trace line).
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

    @property
    def is_set(self) -> bool:
        """True for a joint set (``dip_deg`` and ``spacing`` given): traces are generated."""
        return self.dip_deg is not None and self.spacing is not None

    @property
    def bridge_length(self) -> float:
        """Rock bridge between trace segments along a line (m): ``gap``, default ``spacing``;
        0 for a fully persistent set."""
        if self.persistence is None or self.persistence >= 1.0:
            return 0.0
        return float(self.gap if self.gap is not None else (self.spacing or 0.0))

    @property
    def trace_length(self) -> float:
        """Length of one trace segment (m): p / (1 - p) * bridge; inf when fully persistent."""
        p = self.persistence
        if p is None or p >= 1.0:
            return math.inf
        return p / (1.0 - p) * self.bridge_length


@dataclass(frozen=True, eq=False)
class Block:
    """Explicit block: vertices (n, 2) in m, counter-clockwise and convex (read-only array).

    ``joint``: the joint of its faces that lie on no ``[[discontinuities]]`` line (None:
    ``scene.default_joint``)."""

    vertices: np.ndarray
    material: str
    fixed: bool = False
    joint: str | None = None


@dataclass(frozen=True, eq=False)
class Discontinuity:
    """A joint trace from ``start`` to ``end`` (m, shape (2,)) carrying joint ``joint``."""

    start: np.ndarray
    end: np.ndarray
    joint: str


@dataclass(frozen=True, eq=False)
class Boundary:
    """A boundary condition on segment start-end (m); traction (tx, ty) in kPa, zeros unless
    condition == "traction". ``side`` is "left"|"right"|"bottom"|"top" or None for from/to.
    ``stage``: a traction that a stage applies (None: part of the initial loads)."""

    condition: str
    start: np.ndarray
    end: np.ndarray
    side: str | None
    traction: np.ndarray
    stage: str | None = None


@dataclass(frozen=True, eq=False)
class Monitor:
    """A point monitor (displacement of a rock point) or a section (convergence start-end), m."""

    name: str
    kind: str
    point: np.ndarray | None = None
    start: np.ndarray | None = None
    end: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Domain:
    """The rock mass to generate: ``outline`` (n, 2) m, simple and counter-clockwise (may be
    non-convex), its ``material``, optional ``mesh_size`` (m) for intact-rock cells and
    ``mesh_max_size`` (m): cells grow from ``mesh_size`` at the excavations to this size."""

    outline: np.ndarray
    material: str
    mesh_size: float | None = None
    mesh_max_size: float | None = None


@dataclass(frozen=True, eq=False)
class Zone:
    """A region of the domain made of another ``material`` (e.g. a shear zone); ``vertices``
    (n, 2) m, simple and counter-clockwise."""

    name: str
    vertices: np.ndarray
    material: str


@dataclass(frozen=True, eq=False)
class Excavation:
    """An opening: ``vertices`` (n, 2) m, counter-clockwise (circles and arcs discretised).

    ``shape`` is "circle" (``center``, ``radius``), "horseshoe" (``center`` = middle of the
    flat floor, ``width``, ``height``: vertical walls up to height - width/2, semicircular
    roof of radius width/2) or "polygon". ``stage``: the stage that excavates it (None: the
    first).
    """

    name: str
    shape: str
    vertices: np.ndarray
    stage: str | None = None
    center: np.ndarray | None = None
    radius: float | None = None
    width: float | None = None
    height: float | None = None


@dataclass(frozen=True)
class InSitu:
    """Initial stress. ``mode`` "gravity": sigma_yy = unit_weight * (surface_y - y),
    sigma_xx = k0 * sigma_yy (kPa, compression positive; ``surface_y`` in m). ``mode``
    "uniform": constant sigma_xx, sigma_yy, sigma_xy (kPa, compression positive)."""

    mode: str
    k0: float = 1.0
    surface_y: float | None = None
    sigma_xx: float = 0.0
    sigma_yy: float = 0.0
    sigma_xy: float = 0.0


@dataclass(frozen=True, eq=False)
class Bolt:
    """A rock bolt from ``start`` to ``end`` (m, shape (2,)): axial ``stiffness`` (kN/m),
    ``yield_force`` and ``anchor_capacity`` (kN) in tension, ``compression`` (kN) the force
    it carries in compression (0: none, a cable that goes slack), ``spacing`` out of plane
    (m; forces per metre are divided by it); installed in ``stage`` (None: the first)."""

    start: np.ndarray
    end: np.ndarray
    stiffness: float
    yield_force: float
    anchor_capacity: float
    spacing: float = 1.0
    stage: str | None = None
    compression: float = 0.0


@dataclass(frozen=True)
class Support:
    """Uniform normal ``pressure`` (kPa) on the faces of ``excavation``, from ``stage``."""

    excavation: str
    pressure: float
    stage: str | None = None


@dataclass(frozen=True, eq=False)
class Water:
    """Water table polyline ``table`` (n, 2) m, x strictly increasing; ``unit_weight`` kN/m3.
    Pore pressure below it: p = unit_weight * (y_table(x) - y)."""

    table: np.ndarray
    unit_weight: float = 9.81


@dataclass(frozen=True, eq=False)
class Stage:
    """An analysis stage: ``load_steps`` (None: ``solver.load_steps``) and an optional new
    ``water_table`` (n, 2) m. Excavations, bolts and supports name the stage they belong to."""

    name: str
    load_steps: int | None = None
    water_table: np.ndarray | None = None


@dataclass(frozen=True)
class SolverSettings:
    """Solver controls; max_displacement and step_length in m (None: the solver chooses)."""

    load_steps: int = 5
    tolerance: float = 1e-6
    max_iterations: int = 60
    max_displacement: float | None = None
    dtype: str = "float64"
    regularization: float = 1e-6
    step_length: float | None = None
    linear_solver: str = "auto"


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
    domain: Domain | None = None
    zones: tuple[Zone, ...] = ()
    excavations: tuple[Excavation, ...] = ()
    in_situ: InSitu | None = None
    bolts: tuple[Bolt, ...] = ()
    supports: tuple[Support, ...] = ()
    water: Water | None = None
    stages: tuple[Stage, ...] = ()

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
    "domain",
    "zones",
    "excavations",
    "in_situ",
    "bolts",
    "supports",
    "water",
    "stages",
)

SCENE_FIELDS = ("name", "description", "default_joint", "section_azimuth")
SOLVER_FIELDS = (
    "load_steps",
    "tolerance",
    "max_iterations",
    "max_displacement",
    "dtype",
    "regularization",
    "step_length",
    "linear_solver",
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
    "dip",
    "dip_direction",
)
BLOCK_FIELDS = ("vertices", "material", "fixed", "joint")
DISCONTINUITY_FIELDS = ("from", "to", "joint")
BOUNDARY_FIELDS = ("side", "from", "to", "condition", "traction", "stage")
MONITOR_FIELDS = ("name", "point", "from", "to")
DOMAIN_FIELDS = ("outline", "material", "mesh_size", "mesh_max_size")
ZONE_FIELDS = ("name", "vertices", "material")
EXCAVATION_FIELDS = ("name", "shape", "center", "radius", "width", "height", "vertices", "stage")
SHAPES = ("circle", "horseshoe", "polygon")
SHAPE_FIELDS = {
    "circle": ("center", "radius"),
    "horseshoe": ("center", "width", "height"),
    "polygon": ("vertices",),
}
IN_SITU_FIELDS = ("mode", "k0", "surface_y", "sigma_xx", "sigma_yy", "sigma_xy")
MODES = ("gravity", "uniform")
BOLT_FIELDS = ("from", "to", "stiffness", "yield_force", "anchor_capacity", "spacing", "stage",
               "compression")
SUPPORT_FIELDS = ("excavation", "pressure", "stage")
WATER_FIELDS = ("table", "unit_weight")
STAGE_FIELDS = ("name", "load_steps", "water_table")

SIDES = ("left", "right", "bottom", "top")
CONDITIONS = ("fixed", "roller", "traction")
DTYPES = ("float64", "float32")
LINEAR_SOLVERS = ("auto", "dense", "sparse", "cg")

# Scalar numeric fields that an override may add when the file leaves them out.
_OPTIONAL_NUMERIC = {
    "solver": ("load_steps", "tolerance", "max_iterations", "max_displacement")
    + ("regularization", "step_length"),
    "materials": MATERIAL_FIELDS,
    "joints": ("kn", "ks", "cohesion", "friction_deg", "tensile_strength")
    + ("dip_deg", "spacing", "persistence", "gap"),
    "domain": ("mesh_size", "mesh_max_size"),
    "in_situ": IN_SITU_FIELDS[1:],
    "water": ("unit_weight",),
    "bolts": ("spacing", "compression"),
    "stages": ("load_steps",),
}
# Sections whose optional fields sit at depth 2 (section.field) or 3 (section.NAME|i.field).
_DEPTH2 = ("solver", "domain", "in_situ", "water")
_DEPTH3 = ("materials", "joints", "bolts", "stages")
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


def _count(table: dict, key: str, path: str, default: int | None = None) -> int | None:
    """load_steps or max_iterations: an integer from 1 to MAX_STEPS."""
    n = _field(table, key, path, default=default, lo=1, integer=True)
    if n is not None and n > MAX_STEPS:
        raise SceneError(f"{path}.{key}", f"must be <= {MAX_STEPS:,} (got {n:,})")
    return n


# --------------------------------------------------------------------------- sections


def _parse_solver(data: dict) -> SolverSettings:
    t = _table(data.get("solver", {}), "solver", SOLVER_FIELDS)
    d = SolverSettings()
    dtype = _string(t["dtype"], "solver.dtype", DTYPES) if "dtype" in t else d.dtype
    return SolverSettings(
        load_steps=_count(t, "load_steps", "solver", default=d.load_steps),
        tolerance=_field(
            t, "tolerance", "solver", default=d.tolerance, lo=0, hi=1, lo_open=True, hi_open=True
        ),
        max_iterations=_count(t, "max_iterations", "solver", default=d.max_iterations),
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
        linear_solver=(_string(t["linear_solver"], "solver.linear_solver", LINEAR_SOLVERS)
                       if "linear_solver" in t else d.linear_solver),
    )


def _named_tables(data: dict, key: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise SceneError(key, f"must be a table of named tables ([{key}.NAME]), got {_fmt(value)}")
    return value


def _check_table_name(name: Any, path: str, example: str) -> None:
    """NAME of [materials.NAME] or [joints.NAME]: a segment of dotted parameter paths."""
    if not isinstance(name, str):
        raise SceneError(path, f"the name must be a string (got {_fmt(name)})")
    if not name.strip():
        raise SceneError(path, "the name must not be empty")
    if "." in name:
        raise SceneError(
            path,
            f"the name {name!r} contains '.', so its parameters ({path}.{example}, ...) "
            "could not be addressed by dotted path; rename it",
        )


def _parse_materials(data: dict) -> dict[str, Material]:
    out = {}
    for name, raw in _named_tables(data, "materials").items():
        p = f"materials.{name}"
        _check_table_name(name, p, "E")
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


def trace_angle(dip: float, dip_direction: str | float,
                section_azimuth: float | None = None) -> float:
    """Trace angle (deg, counter-clockwise from +x, in (-90, 90]) of a joint plane of
    geological ``dip`` (deg below horizontal, 0-90) in the section's x-y plane.

    ``dip_direction`` is "right" (the plane dips towards +x), "left" (towards -x), or the
    dip direction's azimuth (deg clockwise from north) together with ``section_azimuth``,
    the azimuth of the section's +x axis. The apparent dip in the section is
    tan(a) = tan(dip) cos(dip_direction - section_azimuth); a plane that dips towards +x
    descends as x grows, so its trace angle is -a (a set dipping 35 deg towards "right"
    has trace angle -35 deg, the same line as 145 deg). Example::

        >>> trace_angle(35.0, "right"), trace_angle(35.0, "left")
        (-35.0, 35.0)
        >>> round(trace_angle(35.0, 120.0, section_azimuth=90.0), 3)  # 30 deg off the section
        -31.228
    """
    if isinstance(dip_direction, str):
        c = 1.0 if dip_direction == "right" else -1.0
    else:
        c = math.cos(math.radians(float(dip_direction) - float(section_azimuth or 0.0)))
    if dip >= 90.0:
        return 90.0
    return -math.degrees(math.atan(math.tan(math.radians(dip)) * c))


def _geological_dip(t: dict, p: str, section_azimuth: float | None) -> float | None:
    """``dip`` with ``dip_direction`` -> the trace angle (deg), None when not given."""
    given = [k for k in ("dip", "dip_direction") if k in t]
    if not given:
        return None
    if "dip_deg" in t:
        raise SceneError(f"{p}.{given[0]}", "give either dip_deg (the trace angle) or dip and "
                         "dip_direction (geological), not both")
    for key, other in (("dip", "dip_direction"), ("dip_direction", "dip")):
        if key in t and other not in t:
            raise SceneError(f"{p}.{other}", f"required with {key} (a geological orientation "
                             "needs dip and dip_direction)")
    dip = _field(t, "dip", p, lo=0, hi=90)
    raw = t["dip_direction"]
    dp = f"{p}.dip_direction"
    if isinstance(raw, str):
        if raw not in DIP_SIDES:
            raise SceneError(dp, f"must be 'left', 'right' or an azimuth in degrees (got {raw!r})")
        direction: str | float = raw
    else:
        direction = _number(raw, dp)
        _in_range(direction, raw, dp, 0, 360)
        if section_azimuth is None:
            raise SceneError("scene.section_azimuth",
                             f"required with {dp} as an azimuth ({_fmt(raw)}): the azimuth of "
                             "the section's +x axis, degrees clockwise from north")
        if dip >= 90.0 and abs(math.cos(math.radians(direction - section_azimuth))) < 1e-9:
            raise SceneError(dp, "the joint plane is the section plane itself (vertical, "
                             "striking across the section): it has no trace")
    return trace_angle(dip, direction, section_azimuth)


def _parse_joints(data: dict, section_azimuth: float | None = None) -> dict[str, Joint]:
    out = {}
    for name, raw in _named_tables(data, "joints").items():
        p = f"joints.{name}"
        _check_table_name(name, p, "kn")
        t = _table(raw, p, JOINT_FIELDS)
        geological = _geological_dip(t, p, section_azimuth)
        if geological is not None:
            if "spacing" not in t:
                raise SceneError(f"{p}.spacing", "required with dip (a joint set needs both)")
            t = dict(t, dip_deg=geological)
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
        _check_set_geometry(out[name], t, p)
    return out


def _check_set_geometry(j: Joint, t: dict, p: str) -> None:
    """A set needs both dip_deg and spacing; the other set fields need a set."""
    if (j.dip_deg is None) != (j.spacing is None):
        given, missing = ("dip_deg", "spacing") if j.spacing is None else ("spacing", "dip_deg")
        raise SceneError(f"{p}.{missing}", f"required with {given} (a joint set needs both)")
    if not j.is_set:
        for key in ("origin", "persistence", "gap"):
            if key in t:
                raise SceneError(
                    f"{p}.{key}", "only for a joint set (give dip_deg and spacing as well)"
                )
        return
    persistent = j.persistence is None or j.persistence >= 1.0
    if j.gap is not None and persistent and j.gap > 0.0:
        raise SceneError(
            f"{p}.gap",
            "needs persistence < 1 (trace length = persistence / (1 - persistence) * gap)",
        )
    if j.gap is not None and not persistent and j.gap == 0.0:
        raise SceneError(
            f"{p}.gap", f"must be > 0 with persistence {j.persistence:g} < 1 (0 means no bridges)"
        )


def _check_polygon(v: np.ndarray, path: str, *, convex: bool = True) -> None:
    """Refuse repeated points, self-intersecting, degenerate, clockwise polygons and, when
    ``convex``, 180-degree corners and reflex corners."""
    n = len(v)
    if n > MAX_POLYGON_POINTS:
        raise SceneError(
            path, f"too many vertices (got {n:,}; at most {MAX_POLYGON_POINTS:,}); simplify it"
        )
    diag = float(np.hypot(*(v.max(axis=0) - v.min(axis=0))))
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
    if not convex:
        return
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


def _parse_blocks(
    data: dict, materials: dict[str, Material], has_domain: bool = False
) -> tuple[Block, ...]:
    raw_blocks = _array_of_tables(data, "blocks")
    if not raw_blocks and not has_domain:
        raise SceneError(
            "blocks",
            "at least one block is needed ([[blocks]] vertices, material), or a [domain]",
        )
    blocks = []
    for i, raw in enumerate(raw_blocks):
        p = f"blocks.{i}"
        t = _table(raw, p, BLOCK_FIELDS)
        if "vertices" not in t:
            raise SceneError(f"{p}.vertices", "required field is missing")
        vp = f"{p}.vertices"
        v = _vertices(t["vertices"], vp)
        _check_polygon(v, vp)
        v.setflags(write=False)
        mat = _material_ref(t, p, materials)
        fixed = t.get("fixed", False)
        if not isinstance(fixed, bool):
            raise SceneError(f"{p}.fixed", f"must be true or false (got {_fmt(fixed)})")
        joint = _string(t["joint"], f"{p}.joint") if "joint" in t else None
        blocks.append(Block(vertices=v, material=mat, fixed=fixed, joint=joint))
    return tuple(blocks)


def overlap_depth(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(area m2, depth m) of the overlap of two convex polygons; depth = 2 area / perimeter
    of the overlap, the thickness of a sliver (0, 0 when they do not overlap)."""
    clip = geometry.convex_clip(np.asarray(a, float), np.asarray(b, float))
    if len(clip) < 3:
        return 0.0, 0.0
    area = abs(geometry.signed_area(clip))
    perimeter = float(np.sum(np.hypot(*(np.roll(clip, -1, axis=0) - clip).T)))
    return area, (2.0 * area / perimeter if perimeter > 0.0 else 0.0)


def _check_overlaps(blocks: tuple[Block, ...]) -> None:
    """Refuse explicit blocks that overlap deeper than OVERLAP_TOLERANCE times the smaller
    block's size sqrt(area)."""
    if not blocks:
        return
    polys = [b.vertices for b in blocks]
    areas = [geometry.signed_area(v) for v in polys]
    pairs = geometry.find_overlapping_pairs(polys, 1e-9 * min(areas))
    bad = []
    for i, j in pairs:
        a, depth = overlap_depth(polys[i], polys[j])
        size = math.sqrt(min(areas[i], areas[j]))
        if depth > OVERLAP_TOLERANCE * size:
            bad.append((j, i, a, depth, size))
    if bad:
        j, i, a, depth, size = min(bad)
        raise SceneError(
            f"blocks.{j}",
            f"overlaps blocks.{i} (area {a:.3g} m2): {depth:.3g} m deep, where up to "
            f"{OVERLAP_TOLERANCE:g} of the smaller block's size ({OVERLAP_TOLERANCE * size:.3g} "
            "m) is accepted",
        )


def _shared_faces(blocks: tuple[Block, ...], tol: float) -> list[tuple[int, int, np.ndarray,
                                                                         np.ndarray]]:
    """(i, j, p, q): blocks i < j share the segment p-q of a face (anti-parallel edges on
    one line, overlapping by more than ``tol``)."""
    out = []
    boxes = np.array([geometry.bbox(b.vertices) for b in blocks]).reshape(-1, 4)
    for i in range(len(blocks)):
        near = np.nonzero((boxes[i + 1:, 0] <= boxes[i, 2] + tol)
                          & (boxes[i, 0] <= boxes[i + 1:, 2] + tol)
                          & (boxes[i + 1:, 1] <= boxes[i, 3] + tol)
                          & (boxes[i, 1] <= boxes[i + 1:, 3] + tol))[0] + i + 1
        va = blocks[i].vertices
        for j in near:
            vb = blocks[j].vertices
            for a0, a1 in zip(va, np.roll(va, -1, axis=0), strict=True):
                d = a1 - a0
                L = float(np.hypot(*d))
                t = d / L
                n = np.array([-t[1], t[0]])
                for b0, b1 in zip(vb, np.roll(vb, -1, axis=0), strict=True):
                    if abs((b0 - a0) @ n) > tol or abs((b1 - a0) @ n) > tol:
                        continue
                    lo = max(0.0, min((b0 - a0) @ t, (b1 - a0) @ t))
                    hi = min(L, max((b0 - a0) @ t, (b1 - a0) @ t))
                    if hi - lo > tol and (b1 - b0) @ t < 0.0:
                        out.append((i, int(j), a0 + lo * t, a0 + hi * t))
    return out


def _on_discontinuity(p: np.ndarray, q: np.ndarray, discs: tuple, tol: float) -> bool:
    """Whether the segment p-q lies on a [[discontinuities]] line (as the model reads it)."""
    for d in discs:
        e = d.end - d.start
        L = float(np.hypot(*e))
        t = e / L
        n = np.array([-t[1], t[0]])
        if abs((p - d.start) @ n) <= tol and abs((q - d.start) @ n) <= tol:
            sp, sq = (p - d.start) @ t, (q - d.start) @ t
            if min(sp, sq) >= -tol and max(sp, sq) <= L + tol:
                return True
    return False


def _check_block_joints(blocks: tuple[Block, ...], discs: tuple, joints: dict,
                        has_default: bool, default_joint: str, tol: float) -> None:
    """Which joint each explicit block face gets must be explicit.

    A face on a [[discontinuities]] line takes that line's joint; any other face takes its
    block's ``joint``, else ``scene.default_joint``. With several joints, a block that
    has neither and a face no line covers is ambiguous (refused). Two blocks whose joints
    differ may share a face only where a line says which joint it is.
    """
    if not blocks:
        return
    if len(joints) > 1 and not has_default:
        for i, b in enumerate(blocks):
            if b.joint is not None:
                continue
            v = b.vertices
            for k, (p, q) in enumerate(zip(v, np.roll(v, -1, axis=0), strict=True)):
                if not _on_discontinuity(p, q, discs, tol):
                    raise SceneError(
                        "scene.default_joint",
                        f"required when the scene has several joints ({', '.join(joints)}) "
                        f"and explicit blocks: face {k} of blocks.{i} ({_fmt_point(p)}-"
                        f"{_fmt_point(q)}) lies on no [[discontinuities]] line, so its joint "
                        "is not given; set [scene] default_joint = NAME, or joint = NAME on "
                        "the [[blocks]]",
                    )
    if len(joints) < 2 or all(b.joint is None for b in blocks):
        return
    own = [b.joint if b.joint is not None else default_joint for b in blocks]
    for i, j, p, q in _shared_faces(blocks, tol):
        if own[i] != own[j] and not _on_discontinuity(p, q, discs, tol):
            which = {i: "joint" if blocks[i].joint is not None else "default_joint",
                     j: "joint" if blocks[j].joint is not None else "default_joint"}
            path = f"blocks.{j}.joint" if blocks[j].joint is not None else f"blocks.{i}.joint"
            raise SceneError(
                path,
                f"blocks.{i} ({which[i]} {own[i]!r}) and blocks.{j} ({which[j]} {own[j]!r}) "
                f"share the face {_fmt_point(p)}-{_fmt_point(q)} but their joints differ; put a "
                "[[discontinuities]] line on that face to say which joint it is",
            )


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
            joint = _defined_name(t["joint"], f"{p}.joint", "joint", joints)
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
                f"joint outside the domain: {_fmt_point(a)}-{_fmt_point(b)} misses the rock's "
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


def _parse_boundaries(data: dict, box: tuple, tol: float, stages: tuple = (),
                      rock: _Rock | None = None) -> tuple[Boundary, ...]:
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
            if rock is not None and not rock.touches(a, b):
                raise SceneError(
                    p, f"segment {_fmt_point(a)}-{_fmt_point(b)} does not touch the rock"
                )
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
        if "stage" in t and cond != "traction":
            raise SceneError(f"{p}.stage", f"only allowed with condition 'traction' (got {cond!r})")
        stage = _stage_ref(t, p, stages)
        traction.setflags(write=False)
        out.append(Boundary(condition=cond, start=a, end=b, side=side, traction=traction,
                            stage=stage))
    return tuple(out)


class _Rock:
    """Where the rock is: the domain less its excavations, plus the explicit blocks."""

    def __init__(
        self,
        blocks: tuple[Block, ...],
        domain: Domain | None,
        excavations: tuple[Excavation, ...],
        tol: float,
    ) -> None:
        self.blocks = blocks
        self.boxes = np.array([geometry.bbox(b.vertices) for b in blocks]).reshape(-1, 4)
        self.domain = domain
        self.excavations = excavations
        self.tol = tol

    def excavation_at(self, q: np.ndarray) -> str | None:
        """Name of the excavation with ``q`` strictly inside (beyond tol), else None."""
        for e in self.excavations:
            if geometry.point_in_polygon(q, e.vertices) and (
                geometry.distance_to_boundary(q, e.vertices) > self.tol
            ):
                return e.name
        return None

    def contains(self, q: np.ndarray) -> bool:
        tol = self.tol
        b = self.boxes
        near = np.nonzero(
            (b[:, 0] - tol <= q[0])
            & (q[0] <= b[:, 2] + tol)
            & (b[:, 1] - tol <= q[1])
            & (q[1] <= b[:, 3] + tol)
        )[0]
        if any(geometry.point_in_polygon(q, self.blocks[k].vertices, tol) for k in near):
            return True
        if self.domain is None or not geometry.point_in_polygon(q, self.domain.outline, tol):
            return False
        return self.excavation_at(q) is None

    def touches(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether segment a-b meets a block or the domain (within 1e3 tol, as the model
        finds faces on a boundary)."""
        tol = 1e3 * self.tol
        lo, hi = np.minimum(a, b) - tol, np.maximum(a, b) + tol
        bx = self.boxes
        near = np.nonzero(
            (bx[:, 0] <= hi[0]) & (lo[0] <= bx[:, 2]) & (bx[:, 1] <= hi[1]) & (lo[1] <= bx[:, 3])
        )[0]
        polys = [self.blocks[k].vertices for k in near]
        if self.domain is not None:
            polys.append(self.domain.outline)
        for v in polys:
            if geometry.point_in_polygon(a, v, tol):
                return True
            edges = zip(v, np.roll(v, -1, axis=0), strict=True)
            if any(geometry.segments_intersect(a, b, p, q, tol) for p, q in edges):
                return True
        return False

    def where(self, q: np.ndarray) -> str:
        """Why ``q`` is not in rock, for messages."""
        name = self.excavation_at(q)
        if name is not None and self.domain is not None:
            return f"{_fmt_point(q)} is inside excavation {name!r}, not in rock"
        return f"{_fmt_point(q)} is outside the rock"


def _parse_monitors(data: dict, rock: _Rock) -> tuple[Monitor, ...]:
    tol = rock.tol
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
            if not rock.contains(q):
                raise SceneError(f"{p}.{key}", rock.where(q))
            pts[key] = q
        if has_point:
            out.append(Monitor(name=name, kind="point", point=pts["point"]))
        else:
            if float(np.hypot(*(pts["to"] - pts["from"]))) <= tol:
                raise SceneError(f"{p}.to", f"same point as from {_fmt_point(pts['from'])}")
            out.append(Monitor(name=name, kind="section", start=pts["from"], end=pts["to"]))
    return tuple(out)


def _vertices(vs: Any, vp: str, min_points: int = 3) -> np.ndarray:
    """A list of points [[x, y], ...] as an (n, 2) float array (not yet checked as a polygon)."""
    if isinstance(vs, (np.ndarray, tuple)):  # programmatic scenes
        vs = list(vs)
    if not isinstance(vs, list):
        raise SceneError(vp, f"must be a list of points [[x, y], ...] (got {_fmt(vs)})")
    if len(vs) < min_points:
        raise SceneError(vp, f"needs at least {min_points} points (got {len(vs)})")
    return np.array([_point(q, f"{vp}.{k}") for k, q in enumerate(vs)], dtype=np.float64)


def _polygon(t: dict, key: str, path: str, far: tuple[float, str] | None = None) -> np.ndarray:
    """A required simple CCW polygon field (may be non-convex), read-only. ``far``: (model
    size, dtype) to refuse first a vertex too far away (that spoils the checks' tolerance)."""
    if key not in t:
        raise SceneError(f"{path}.{key}", "required field is missing")
    v = _vertices(t[key], f"{path}.{key}")
    if far is not None:
        k = int(np.argmax(np.max(np.abs(v), axis=1)))
        _check_far(v[k], f"{path}.{key}.{k}", *far)
    _check_polygon(v, f"{path}.{key}", convex=False)
    v.setflags(write=False)
    return v


def _defined_name(value: Any, path: str, kind: str, names, none: str = "none") -> str:
    """A string that names one of ``names`` (a material, joint, stage, ...), else SceneError."""
    name = _string(value, path)
    if name not in names:
        defined = ", ".join(names) or none
        raise SceneError(path, f"unknown {kind} {name!r}; defined: {defined}")
    return name


def _material_ref(t: dict, path: str, materials: dict[str, Material]) -> str:
    if "material" not in t:
        raise SceneError(f"{path}.material", "required field is missing")
    return _defined_name(t["material"], f"{path}.material", "material", materials)


def _name(
    t: dict, path: str, seen: dict[str, int], section: str, default: str | None = None
) -> str:
    if "name" not in t:
        if default is None:
            raise SceneError(f"{path}.name", "required field is missing")
        name = default
    else:
        name = _string(t["name"], f"{path}.name")
    if not name.strip():
        raise SceneError(f"{path}.name", "must not be empty")
    if name in seen:
        raise SceneError(f"{path}.name", f"duplicate name {name!r} (also {section}.{seen[name]})")
    seen[name] = len(seen)
    return name


def _parse_domain(data: dict, materials: dict[str, Material]) -> Domain | None:
    if "domain" not in data:
        return None
    t = _table(data["domain"], "domain", DOMAIN_FIELDS)
    outline = _polygon(t, "outline", "domain")
    mat = _material_ref(t, "domain", materials)
    mesh = _field(t, "mesh_size", "domain", lo=0, lo_open=True)
    if mesh is not None:
        box = geometry.bbox(outline)
        size = max(box[2] - box[0], box[3] - box[1])
        if mesh > size:
            raise SceneError(
                "domain.mesh_size", f"larger than the domain ({mesh:g} m > {size:g} m)"
            )
    grown = _field(t, "mesh_max_size", "domain", lo=0, lo_open=True)
    if grown is not None:
        if mesh is None:
            raise SceneError("domain.mesh_max_size", "needs domain.mesh_size (the smallest cells)")
        if grown < mesh:
            raise SceneError("domain.mesh_max_size",
                             f"smaller than domain.mesh_size ({grown:g} m < {mesh:g} m)")
    return Domain(outline=outline, material=mat, mesh_size=mesh, mesh_max_size=grown)


def _check_blocks_outside_domain(blocks: tuple[Block, ...], domain: Domain | None) -> None:
    if domain is None or not blocks:
        return
    parts = geometry.convex_decompose(domain.outline, 0.0)
    dbox = geometry.bbox(domain.outline)
    for i, b in enumerate(blocks):
        bb = geometry.bbox(b.vertices)
        if bb[0] >= dbox[2] or dbox[0] >= bb[2] or bb[1] >= dbox[3] or dbox[1] >= bb[3]:
            continue
        a = sum(geometry.overlap_area(b.vertices, q) for q in parts)
        if a > 1e-9 * geometry.signed_area(b.vertices):
            raise SceneError(
                f"blocks.{i}",
                f"overlaps the domain (area {a:.3g} m2); explicit blocks lie outside it",
            )


def _parse_zones(data: dict, materials: dict[str, Material], domain: Domain | None,
                 far: tuple[float, str] | None = None) -> tuple:
    raw = _array_of_tables(data, "zones")
    if raw and domain is None:
        raise SceneError("zones", "needs a [domain] (a zone is a region of the generated rock)")
    out = []
    seen: dict[str, int] = {}
    for i, r in enumerate(raw):
        p = f"zones.{i}"
        t = _table(r, p, ZONE_FIELDS)
        name = _name(t, p, seen, "zones", default=f"zone{i}")
        v = _polygon(t, "vertices", p, far)
        mat = _material_ref(t, p, materials)
        assert domain is not None
        a = geometry.polygon_overlap_area(v, domain.outline)
        if a <= 1e-9 * abs(geometry.signed_area(v)):
            raise SceneError(p, "does not overlap the domain")
        out.append(Zone(name=name, vertices=v, material=mat))
    return tuple(out)


def _parse_stages(data: dict) -> tuple[Stage, ...]:
    out = []
    seen: dict[str, int] = {}
    for i, r in enumerate(_array_of_tables(data, "stages")):
        p = f"stages.{i}"
        t = _table(r, p, STAGE_FIELDS)
        name = _name(t, p, seen, "stages")
        steps = _count(t, "load_steps", p)
        table = _water_table(t["water_table"], f"{p}.water_table") if "water_table" in t else None
        out.append(Stage(name=name, load_steps=steps, water_table=table))
    return tuple(out)


def _stage_ref(t: dict, path: str, stages: tuple[Stage, ...]) -> str | None:
    """``stage``: a [[stages]] name, or its 1-based number (as RS2 and UDEC number them);
    returns the name. A stage that does not exist would never come: refused, with the
    stages that do."""
    if "stage" not in t:
        return None
    raw = t["stage"]
    sp = f"{path}.stage"
    names = [s.name for s in stages]
    listed = ", ".join(f"{k + 1} {n!r}" for k, n in enumerate(names))
    if not names:
        raise SceneError(sp, f"unknown stage {_fmt(raw)}: it never comes, the scene has no "
                         "[[stages]] "
                         "(define them, [[stages]] name = ..., or leave stage out: it then "
                         "acts from the first stage of the analysis)")
    if isinstance(raw, str):
        if raw not in names:
            raise SceneError(sp, f"unknown stage {raw!r} (it would never come): stages are "
                             f"{listed}")
        return raw
    if _is_number(raw):
        if raw != math.floor(raw) or not 1 <= raw <= len(names):
            raise SceneError(sp, f"stage {_fmt(raw)} does not exist: stages are {listed} "
                             "(a number counts from 1)")
        return names[int(raw) - 1]
    raise SceneError(sp, f"must be a stage name or its number from 1 (got {_fmt(raw)}); "
                     f"stages are {listed}")


def _segments_for(radius: float, h: float) -> int:
    """Segments around a full circle of ``radius`` for element size ``h`` (m)."""
    return math.ceil(min(max(2.0 * math.pi * radius / h, 24.0), 120.0))  # clip, then ceil: no inf


def _discretisation_length(domain: Domain | None, joints: dict[str, Joint], r: float) -> float:
    if domain is not None and domain.mesh_size is not None:
        return domain.mesh_size
    spacings = [j.spacing for j in joints.values() if j.is_set and j.spacing is not None]
    return min(spacings) / 2.0 if spacings else r / 4.0


def circle_vertices(center: np.ndarray, radius: float, n: int) -> np.ndarray:
    """Inscribed n-gon of a circle (m), counter-clockwise, first vertex at angle 0."""
    a = 2.0 * math.pi * np.arange(n) / n
    return np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], axis=1)


def horseshoe_vertices(center: np.ndarray, width: float, height: float, n: int) -> np.ndarray:
    """Flat floor centred at ``center``, vertical walls, semicircular roof of radius width/2
    discretised with ceil(n / 2) segments (m), counter-clockwise."""
    r = 0.5 * width
    wall = height - r
    cx, cy = float(center[0]), float(center[1])
    m = max(2, math.ceil(n / 2))
    a = math.pi * np.arange(m + 1) / m
    arc = np.stack([cx + r * np.cos(a), cy + wall + r * np.sin(a)], axis=1)
    pts = [[cx - r, cy], [cx + r, cy]]
    tol = 1e-9 * width
    if wall <= tol:
        arc = arc[1:-1]
    v = np.vstack([np.array(pts), arc])
    return v


def _parse_excavations(
    data: dict,
    domain: Domain | None,
    joints: dict[str, Joint],
    stages: tuple[Stage, ...],
    box: tuple,
    tol: float,
    far: tuple[float, str] | None = None,
) -> tuple[Excavation, ...]:
    out: list[Excavation] = []
    seen: dict[str, int] = {}
    for i, r in enumerate(_array_of_tables(data, "excavations")):
        p = f"excavations.{i}"
        t = _table(r, p, EXCAVATION_FIELDS)
        name = _name(t, p, seen, "excavations")
        if "shape" not in t:
            raise SceneError(f"{p}.shape", f"required ({', '.join(SHAPES)})")
        shape = _string(t["shape"], f"{p}.shape", SHAPES)
        for key in ("center", "radius", "width", "height", "vertices"):
            if key in t and key not in SHAPE_FIELDS[shape]:
                raise SceneError(f"{p}.{key}", f"not used by shape {shape!r}")
        center = radius = width = height = None
        if shape == "polygon":
            v = np.array(_polygon(t, "vertices", p, far))
        else:
            if "center" not in t:
                raise SceneError(f"{p}.center", "required field is missing")
            center = _point(t["center"], f"{p}.center")
            if shape == "circle":
                radius = _field(t, "radius", p, required=True, lo=0, lo_open=True)
                n = _segments_for(radius, _discretisation_length(domain, joints, radius))
                v = circle_vertices(center, radius, n)
            else:
                width = _field(t, "width", p, required=True, lo=0, lo_open=True)
                height = _field(t, "height", p, required=True, lo=0, lo_open=True)
                if height < 0.5 * width * (1.0 - 1e-12):
                    raise SceneError(
                        f"{p}.height",
                        f"must be >= width / 2 = {0.5 * width:g} (the roof is a semicircle "
                        f"of radius width / 2; got {height:g})",
                    )
                r = 0.5 * width
                n = _segments_for(r, _discretisation_length(domain, joints, r))
                v = horseshoe_vertices(center, width, height, n)
        v.setflags(write=False)
        stage = _stage_ref(t, p, stages)
        area = geometry.signed_area(v)
        if domain is not None:
            inside = geometry.polygon_overlap_area(v, domain.outline)
            if inside < area * (1.0 - 1e-9):
                raise SceneError(
                    p, f"outside the domain ({area - inside:.3g} m2 of {area:.3g} m2 outside)"
                )
        else:
            lo, hi = v.min(axis=0), v.max(axis=0)
            if (
                lo[0] < box[0] - tol
                or lo[1] < box[1] - tol
                or hi[0] > box[2] + tol
                or hi[1] > box[3] + tol
            ):
                raise SceneError(p, "outside the domain (beyond the blocks' bounding box)")
        for k, other in enumerate(out):
            a = geometry.polygon_overlap_area(v, other.vertices)
            if a > 1e-9 * min(area, geometry.signed_area(other.vertices)):
                raise SceneError(p, f"overlaps excavations.{k} ({other.name!r}, area {a:.3g} m2)")
        out.append(
            Excavation(
                name=name,
                shape=shape,
                vertices=v,
                stage=stage,
                center=center,
                radius=radius,
                width=width,
                height=height,
            )
        )
    if domain is not None and out:
        dug = sum(geometry.signed_area(e.vertices) for e in out)
        if dug >= geometry.signed_area(domain.outline) * (1.0 - 1e-9):
            raise SceneError(
                f"excavations.{len(out) - 1}",
                "the excavations remove the whole domain: no rock would be left",
            )
    return tuple(out)


def _check_block_count(
    domain: Domain | None,
    joints: dict[str, Joint],
    excavations: tuple[Excavation, ...],
    n_explicit: int,
) -> None:
    """Refuse a scene that would generate more than MAX_BLOCKS blocks, judged from an
    estimate made before anything is generated (which would exhaust time or memory).

    Per joint set: its trace lines across the domain and, with persistence < 1, its trace
    ends (each cuts a block); per pair of sets: their crossings, area sin(angle) p1 p2 /
    (s1 s2); a mesh: 2 triangles per square cell of mesh_size (graded: of mesh_max_size,
    plus 4 perimeter / mesh_size along the excavations), 2 more per cell that a trace or
    an excavation outline cuts. Within a factor 1.5 of the generated count on the examples.
    """
    if domain is None:
        return
    v = domain.outline
    area = geometry.signed_area(v)
    made: dict[str, float] = {}  # field path -> blocks it makes
    sets = []  # (name, dip (rad), spacing, persistence, joint)
    for name, j in joints.items():
        if j.dip_deg is not None and j.spacing is not None:
            sets.append((name, math.radians(j.dip_deg), j.spacing, j.persistence or 1.0, j))
    traces = 0.0  # total trace length (m), about
    for name, dip, spacing, persistence, j in sets:
        d = np.array([math.cos(dip), math.sin(dip)])
        lines = float(np.ptp(v @ np.array([-d[1], d[0]]))) / spacing
        along = float(np.ptp(v @ d))
        made[f"joints.{name}.spacing"] = lines
        traces += lines * along * persistence
        if math.isfinite(j.trace_length):
            key = f"joints.{name}.{'gap' if j.gap is not None else 'spacing'}"
            ends = 2.0 * lines * along / (j.trace_length + j.bridge_length)
            made[key] = made.get(key, 0.0) + ends
    for k, (na, dip_a, sa, pa, _) in enumerate(sets):
        for nb, dip_b, sb, pb, _ in sets[k + 1:]:
            key = f"joints.{na if sa <= sb else nb}.spacing"
            made[key] += area * abs(math.sin(dip_a - dip_b)) * pa * pb / sa / sb
    h, grown = domain.mesh_size, domain.mesh_max_size
    if h is not None:
        edges = [np.roll(e.vertices, -1, axis=0) - e.vertices for e in excavations]
        perimeter = sum(float(np.sum(np.hypot(e[:, 0], e[:, 1]))) for e in edges)
        if grown is not None and grown > h and excavations:
            cells = area / grown / grown + 4.0 * perimeter / h
        else:
            cells = area / h / h
        made["domain.mesh_size"] = 2.0 * (cells + (perimeter + traces) / h)
    total = n_explicit + 1.0 + sum(made.values())
    if total > MAX_BLOCKS:
        path = max(made, key=lambda key: made[key])
        raise SceneError(
            path,
            f"too small: the scene would generate about {total:.3g} blocks, more than the "
            f"{MAX_BLOCKS:,} accepted",
        )


def _check_coordinates(
    blocks: tuple[Block, ...],
    domain: Domain | None,
    joints: dict[str, Joint],
    box: tuple,
    size: float,
    solver: SolverSettings,
) -> None:
    """Coordinates the dtype can resolve, and solver lengths in proportion to the model."""
    if max(abs(x) for x in box) > MAX_OFFSET[solver.dtype] * size:
        polys = [("domain.outline", domain.outline)] if domain is not None else []
        polys += [(f"blocks.{i}.vertices", b.vertices) for i, b in enumerate(blocks)]
        path, v = max(polys, key=lambda pv: float(np.max(np.abs(pv[1]))))
        k = int(np.argmax(np.max(np.abs(v), axis=1)))
        _check_far(v[k], f"{path}.{k}", size, solver.dtype)
    for name, j in joints.items():
        if j.origin is not None:
            _check_far(np.array(j.origin), f"joints.{name}.origin", size, solver.dtype)
    # Substeps move at most step_length until a block has travelled max_displacement, and
    # contact detection looks 2 step_length ahead: bound both by the model's size.
    if solver.max_displacement is not None and solver.max_displacement > 10.0 * size:
        raise SceneError(
            "solver.max_displacement",
            f"larger than 10 times the model ({solver.max_displacement:g} m > "
            f"{10.0 * size:.3g} m): a block would have left the model long before",
        )
    step = solver.step_length
    if step is not None and not 1e-6 * size <= step <= size:
        raise SceneError(
            "solver.step_length",
            f"must be between 1e-6 times and once the model's size ({1e-6 * size:.3g} m to "
            f"{size:.3g} m; got {step:g})",
        )


def _check_far(q: np.ndarray, path: str, size: float, dtype: str) -> None:
    """Refuse a point so far from (0, 0) that ``dtype`` cannot resolve a model ``size`` m
    across there (MAX_OFFSET model sizes)."""
    limit = MAX_OFFSET[dtype] * size
    if float(np.max(np.abs(q))) > limit:
        raise SceneError(
            path,
            f"{_fmt_point(q)} is too far from (0, 0) for a model {size:.3g} m across "
            f"({dtype} resolves it only within {limit:.3g} m of (0, 0)); shift the "
            "coordinates towards (0, 0)",
        )


def _parse_in_situ(data: dict, top: float) -> InSitu | None:
    if "in_situ" not in data:
        return None
    p = "in_situ"
    t = _table(data["in_situ"], p, IN_SITU_FIELDS)
    mode = _string(t["mode"], f"{p}.mode", MODES) if "mode" in t else "gravity"
    if mode == "gravity":
        for key in ("sigma_xx", "sigma_yy", "sigma_xy"):
            if key in t:
                raise SceneError(f"{p}.{key}", "only with mode 'uniform' (gravity uses k0)")
        return InSitu(
            mode=mode,
            k0=_field(t, "k0", p, default=1.0, lo=0),
            surface_y=_field(t, "surface_y", p, default=top),
        )
    for key in ("k0", "surface_y"):
        if key in t:
            raise SceneError(f"{p}.{key}", "only with mode 'gravity'")
    return InSitu(
        mode=mode,
        sigma_xx=_field(t, "sigma_xx", p, required=True),
        sigma_yy=_field(t, "sigma_yy", p, required=True),
        sigma_xy=_field(t, "sigma_xy", p, default=0.0),
    )


def _water_table(value: Any, path: str) -> np.ndarray:
    v = _vertices(value, path, min_points=2)
    dx = np.diff(v[:, 0])
    if np.any(dx <= 0.0):
        k = int(np.nonzero(dx <= 0.0)[0][0])
        raise SceneError(
            path,
            f"not a function of x: x must increase strictly (point {k + 1} "
            f"{_fmt_point(v[k + 1])} after {_fmt_point(v[k])})",
        )
    v.setflags(write=False)
    return v


def _parse_water(data: dict) -> Water | None:
    if "water" not in data:
        return None
    t = _table(data["water"], "water", WATER_FIELDS)
    if "table" not in t:
        raise SceneError("water.table", "required field is missing")
    return Water(
        table=_water_table(t["table"], "water.table"),
        unit_weight=_field(t, "unit_weight", "water", default=9.81, lo=0, lo_open=True),
    )


def _parse_bolts(data: dict, rock: _Rock, stages: tuple[Stage, ...]) -> tuple[Bolt, ...]:
    out = []
    for i, r in enumerate(_array_of_tables(data, "bolts")):
        p = f"bolts.{i}"
        t = _table(r, p, BOLT_FIELDS)
        ends = {}
        for key in ("from", "to"):
            if key not in t:
                raise SceneError(f"{p}.{key}", "required field is missing")
            q = _point(t[key], f"{p}.{key}")
            if not rock.contains(q):
                raise SceneError(f"{p}.{key}", f"bolt end {rock.where(q)}")
            ends[key] = q
        if float(np.hypot(*(ends["to"] - ends["from"]))) <= rock.tol:
            raise SceneError(f"{p}.to", f"same point as from {_fmt_point(ends['from'])}")
        out.append(
            Bolt(
                start=ends["from"],
                end=ends["to"],
                stiffness=_field(t, "stiffness", p, required=True, lo=0, lo_open=True),
                yield_force=_field(t, "yield_force", p, required=True, lo=0, lo_open=True),
                anchor_capacity=_field(t, "anchor_capacity", p, required=True, lo=0, lo_open=True),
                spacing=_field(t, "spacing", p, default=1.0, lo=0, lo_open=True),
                stage=_stage_ref(t, p, stages),
                compression=_field(t, "compression", p, default=0.0, lo=0),
            )
        )
    return tuple(out)


def _parse_supports(
    data: dict, excavations: tuple[Excavation, ...], stages: tuple[Stage, ...]
) -> tuple[Support, ...]:
    out = []
    names = [e.name for e in excavations]
    for i, r in enumerate(_array_of_tables(data, "supports")):
        p = f"supports.{i}"
        t = _table(r, p, SUPPORT_FIELDS)
        if "excavation" not in t:
            raise SceneError(f"{p}.excavation", "required field is missing")
        exc = _defined_name(t["excavation"], f"{p}.excavation", "excavation", names)
        out.append(
            Support(
                excavation=exc,
                pressure=_field(t, "pressure", p, required=True, lo=0),
                stage=_stage_ref(t, p, stages),
            )
        )
    return tuple(out)


def _parse(data: Any, source: str) -> Scene:
    if not isinstance(data, dict):
        raise SceneError(source, f"a scene must be a table (got {_fmt(data)})")
    for key in data:
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

    section_azimuth = _field(head, "section_azimuth", "scene", lo=0, hi=360)
    solver = _parse_solver(data)
    materials = _parse_materials(data)
    joints = _parse_joints(data, section_azimuth)
    domain = _parse_domain(data, materials)
    blocks = _parse_blocks(data, materials, has_domain=domain is not None)
    if domain is None:
        for jn, j in joints.items():
            if j.is_set:
                raise SceneError(
                    f"joints.{jn}", "a joint set (dip_deg, spacing) needs a [domain] to cut"
                )

    if "default_joint" in head:
        default_joint = _defined_name(head["default_joint"], "scene.default_joint", "joint",
                                      joints)
    elif joints:
        default_joint = next(iter(joints))
    else:
        default_joint = ""
    if not joints and len(blocks) > 1:
        raise SceneError("joints", "at least one joint is needed for contacts between blocks")
    for i, b in enumerate(blocks):
        if b.joint is not None and b.joint not in joints:
            defined = ", ".join(joints) or "none"
            raise SceneError(f"blocks.{i}.joint", f"unknown joint {b.joint!r}; defined: {defined}")

    rock_points = [b.vertices for b in blocks]
    if domain is not None:
        rock_points.append(domain.outline)
    box = geometry.bbox(np.concatenate(rock_points))
    size = float(np.hypot(box[2] - box[0], box[3] - box[1]))
    tol = 1e-9 * size
    _check_coordinates(blocks, domain, joints, box, size, solver)

    _check_overlaps(blocks)
    _check_blocks_outside_domain(blocks, domain)

    far = (size, solver.dtype)
    zones = _parse_zones(data, materials, domain, far)
    stages = _parse_stages(data)
    excavations = _parse_excavations(data, domain, joints, stages, box, tol, far)
    _check_block_count(domain, joints, excavations, len(blocks))
    discontinuities = _parse_discontinuities(data, joints, default_joint, box, tol)
    _check_block_joints(blocks, discontinuities, joints, "default_joint" in head,
                        default_joint, 1e3 * tol)
    rock = _Rock(blocks, domain, excavations, tol)
    boundaries = _parse_boundaries(data, box, tol, stages, rock)
    # Lines may reach beyond the rock, but not beyond what the dtype resolves.
    ends = [("discontinuities", i, d) for i, d in enumerate(discontinuities)]
    ends += [("boundaries", i, b) for i, b in enumerate(boundaries) if b.side is None]
    for section, i, line in ends:
        _check_far(line.start, f"{section}.{i}.from", *far)
        _check_far(line.end, f"{section}.{i}.to", *far)
    in_situ = _parse_in_situ(data, top=box[3])
    water = _parse_water(data)
    bolts = _parse_bolts(data, rock, stages)
    supports = _parse_supports(data, excavations, stages)
    monitors = _parse_monitors(data, rock)

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
        domain=domain,
        zones=zones,
        excavations=excavations,
        in_situ=in_situ,
        bolts=bolts,
        supports=supports,
        water=water,
        stages=stages,
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
        with path.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)  # bounded: /dev/zero or a huge file
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise SceneError(name, f"cannot read scene file ({reason})") from exc
    if len(raw) > MAX_FILE_BYTES:
        raise SceneError(name, f"scene file is larger than {MAX_FILE_BYTES // 2**20} MiB")
    try:
        text = raw.decode("utf-8-sig")  # -sig: a byte-order mark some editors write
    except UnicodeDecodeError as exc:
        raise SceneError(name, f"scene file is not UTF-8 text ({exc.reason})") from exc
    if not text.strip():
        raise SceneError(name, "scene file is empty")
    data = _parse_toml(text, name)
    if not data:
        raise SceneError(name, "scene file is empty (only comments)")
    return data


def _parse_toml(text: str, source: str) -> dict:
    """TOML text -> dict; a syntax error, a key or table given twice, or an integer too
    long to read is a SceneError (a duplicate names the field path and the line)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _toml_error(str(exc), text, source) from None
    except ValueError as exc:  # e.g. an integer of more than 4,300 digits
        raise SceneError(source, f"invalid TOML ({exc})") from None


_HEADER = re.compile(r"^\s*(\[\[?)\s*([^\]]+?)\s*\]\]?")
_KEY = re.compile(r"^\s*([^=\[#]+?)\s*=")


def _toml_error(message: str, text: str, source: str) -> SceneError:
    """A TOML decode error as a SceneError; a key or table declared twice names its path."""
    at = re.search(r"\(at line (\d+), column \d+\)$", message)
    twice = re.match(r"Cannot declare (\(.*\)) twice", message)
    if at and twice:
        keys = ast.literal_eval(twice.group(1))
        return SceneError(".".join(map(str, keys)),
                          f"duplicate table: declared twice ({source}, line {at.group(1)})")
    if at and message.startswith("Cannot overwrite a value"):
        line = int(at.group(1))
        lines = text.splitlines()
        key = _KEY.match(lines[line - 1]) if line <= len(lines) else None
        if key:
            table: list[str] = []
            counts: dict[str, int] = {}
            for row in lines[: line - 1]:
                header = _HEADER.match(row)
                if header:
                    name = _dotted(header.group(2))
                    table = [name]
                    if header.group(1) == "[[":
                        counts[name] = counts.get(name, -1) + 1
                        table.append(str(counts[name]))
            path = ".".join([*table, _dotted(key.group(1))])
            return SceneError(path, f"duplicate key: given twice ({source}, line {line})")
    return SceneError(source, f"invalid TOML ({message})")


def _dotted(key: str) -> str:
    """A TOML key as written (``a . "b"``) -> dotted path ``a.b`` (for messages)."""
    return ".".join(part.strip().strip("\"'") for part in key.split("."))


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
        data = _parse_toml(path_or_text, source)
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
    if set is not None and not isinstance(set, Mapping):
        raise SceneError("set", f"expected {{path: value}} (got {type(set).__name__})")
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
    if not isinstance(overrides, Mapping):
        raise SceneError("set", f"expected {{path: value}} (got {type(overrides).__name__})")
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
        if not _is_index(key) or int(key) >= len(node):
            return _MISSING
        return node[int(key)]
    return _MISSING


def _is_index(key: str) -> bool:
    """A list index in a dotted path: ASCII digits only ('²'.isdigit() is True)."""
    return key.isascii() and key.isdigit()


def _set_leaf(node: Any, last: str, value: Any, dotted: str, keys: list[str]) -> None:
    if isinstance(node, list):
        if not _is_index(last) or int(last) >= len(node):
            raise _walk_error(dotted, "no such parameter")
        idx: Any = int(last)
        old = node[idx]
    elif isinstance(node, dict):
        if last not in node:
            section = keys[0]
            depth_ok = (section in _DEPTH2 and len(keys) == 2) or (
                section in _DEPTH3 and len(keys) == 3
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
        if path in out:
            raise SceneError("--set", f"{path} is given twice")
        out[path] = value
    return out
