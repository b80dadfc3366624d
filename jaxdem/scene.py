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

Where it lives (this module is the public face: it holds ``Scene`` and the order in which
the sections are read and checked, and imports the modules below; each of them imports
only modules listed above it):

- :mod:`jaxdem.scene_fields`: ``SceneError``, limits, the checks of one value;
- :mod:`jaxdem.scene_schema`: the records (``Material``, ``Joint``, ...) and accepted fields;
- :mod:`jaxdem.scene_properties`: ``[solver]``, ``[materials]``, ``[joints]``;
- :mod:`jaxdem.scene_checks`: polygons, overlaps, coordinates, block count, where the rock is;
- :mod:`jaxdem.scene_stages`: ``[[stages]]``, ``[water]``, stage references;
- :mod:`jaxdem.scene_rock`: blocks, discontinuities, domain, zones, excavations;
- :mod:`jaxdem.scene_loads`: boundaries, in-situ stress, bolts, supports, monitors;
- :mod:`jaxdem.scene_toml`: reading files and TOML text;
- :mod:`jaxdem.scene_overrides`: ``--set`` and ``apply_overrides``.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxdem import geometry
from jaxdem.scene_checks import (
    MAX_BLOCKS,
    MAX_OFFSET,
    MAX_POLYGON_POINTS,
    OVERLAP_TOLERANCE,
    _check_block_count,
    _check_block_joints,
    _check_blocks_outside_domain,
    _check_coordinates,
    _check_far,
    _check_overlaps,
    _Rock,
    overlap_depth,
)
from jaxdem.scene_fields import (
    MAX_MAGNITUDE,
    MAX_STEPS,
    SceneError,
    _defined_name,
    _field,
    _fmt,
    _string,
    _table,
)
from jaxdem.scene_loads import (
    _parse_bolts,
    _parse_boundaries,
    _parse_in_situ,
    _parse_monitors,
    _parse_supports,
)
from jaxdem.scene_overrides import apply_overrides, parse_set_arguments
from jaxdem.scene_properties import _parse_joints, _parse_materials, _parse_solver, trace_angle
from jaxdem.scene_rock import (
    _parse_blocks,
    _parse_discontinuities,
    _parse_domain,
    _parse_excavations,
    _parse_zones,
    circle_vertices,
    horseshoe_vertices,
)
from jaxdem.scene_schema import (
    SCENE_FIELDS,
    SUPPORTED_SECTIONS,
    Block,
    Bolt,
    Boundary,
    Discontinuity,
    Domain,
    Excavation,
    InSitu,
    Joint,
    Material,
    Monitor,
    SolverSettings,
    Stage,
    Support,
    Water,
    Zone,
)
from jaxdem.scene_stages import _parse_stages, _parse_water
from jaxdem.scene_toml import MAX_FILE_BYTES, _parse_toml, _read_toml

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
    # The limits and helpers the format reference above names (homes in the list above).
    "MAX_BLOCKS",
    "MAX_FILE_BYTES",
    "MAX_MAGNITUDE",
    "MAX_OFFSET",
    "MAX_POLYGON_POINTS",
    "MAX_STEPS",
    "OVERLAP_TOLERANCE",
    "circle_vertices",
    "horseshoe_vertices",
    "overlap_depth",
    "trace_angle",
]


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
