"""Scene files and dicts -> the validated ``Scene``: :func:`load_scene`, :func:`parse_scene`
and the :class:`Scene` record (the package docstring, :mod:`jaxdem.scene`, says what is
checked and how)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxdem import geometry
from jaxdem.scene._checks import (
    MAX_BLOCKS,
    MAX_OFFSET,
    MAX_POLYGON_POINTS,
    OVERLAP_TOLERANCE,
    Rock,
    check_block_count,
    check_block_joints,
    check_blocks_outside_domain,
    check_coordinates,
    check_far,
    check_overlaps,
    in_situ_strength_warnings,
    overlap_depth,
    plausibility_warnings,
)
from jaxdem.scene._fields import (
    MAX_MAGNITUDE,
    MAX_STEPS,
    SceneError,
    defined_name,
    fmt,
    read_field,
    read_string,
    read_table,
)
from jaxdem.scene._loads import (
    parse_bolts,
    parse_boundaries,
    parse_in_situ,
    parse_monitors,
    parse_supports,
)
from jaxdem.scene._overrides import apply_overrides, parse_set_arguments
from jaxdem.scene._properties import parse_joints, parse_materials, parse_solver, trace_angle
from jaxdem.scene._rock import (
    circle_vertices,
    horseshoe_vertices,
    parse_blocks,
    parse_discontinuities,
    parse_domain,
    parse_excavations,
    parse_zones,
)
from jaxdem.scene._schema import (
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
from jaxdem.scene._stages import parse_stages, parse_water
from jaxdem.scene._toml import MAX_FILE_BYTES, parse_toml, read_toml

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
    """A validated scene. ``data`` is the raw parsed TOML (for overrides); ``source`` its origin;
    ``warnings`` the plausibility warnings (values most likely in the wrong unit, an
    in-situ state the intact rock cannot carry)."""

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
    warnings: tuple[str, ...] = ()
    """Plausibility warnings: valid values most likely in the wrong unit, each starting
    with the field's path (:func:`jaxdem.scene._checks.plausibility_warnings`), and a
    gravity in-situ state the intact rock cannot carry
    (:func:`jaxdem.scene._checks.in_situ_strength_warnings`)."""

    def with_overrides(self, overrides: Mapping[str, float | str]) -> Scene:
        """A new Scene re-validated from ``data`` with numeric entries (and the solver's
        choices, :func:`jaxdem.scene.apply_overrides`) set by dotted path."""
        return parse_scene(apply_overrides(self.data, overrides), source=self.source)


def _parse(data: Any, source: str) -> Scene:
    if not isinstance(data, dict):
        raise SceneError(source, f"a scene must be a table (got {fmt(data)})")
    for key in data:
        if key not in SUPPORTED_SECTIONS:
            raise SceneError(key, f"unknown section; allowed: {', '.join(SUPPORTED_SECTIONS)}")

    if "scene" not in data:
        raise SceneError("scene.name", "required field is missing ([scene] name = ...)")
    head = read_table(data["scene"], "scene", SCENE_FIELDS)
    if "name" not in head:
        raise SceneError("scene.name", "required field is missing")
    name = read_string(head["name"], "scene.name")
    if not name.strip():
        raise SceneError("scene.name", "must not be empty")
    description = read_string(head.get("description", ""), "scene.description")

    section_azimuth = read_field(head, "section_azimuth", "scene", lo=0, hi=360)
    solver = parse_solver(data)
    materials = parse_materials(data)
    joints = parse_joints(data, section_azimuth)
    domain = parse_domain(data, materials)
    blocks = parse_blocks(data, materials, has_domain=domain is not None)
    if domain is None:
        for jn, j in joints.items():
            if j.is_set:
                raise SceneError(
                    f"joints.{jn}", "a joint set (dip_deg, spacing) needs a [domain] to cut"
                )

    if "default_joint" in head:
        default_joint = defined_name(head["default_joint"], "scene.default_joint", "joint",
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
    check_coordinates(blocks, domain, joints, box, size, solver)

    check_overlaps(blocks)
    check_blocks_outside_domain(blocks, domain)

    far = (size, solver.dtype)
    zones = parse_zones(data, materials, domain, far)
    stages = parse_stages(data)
    excavations = parse_excavations(data, domain, joints, stages, box, tol, far)
    check_block_count(domain, joints, excavations, len(blocks))
    discontinuities = parse_discontinuities(data, joints, default_joint, box, tol)
    check_block_joints(blocks, discontinuities, joints, "default_joint" in head,
                       default_joint, 1e3 * tol)
    rock = Rock(blocks, domain, excavations, tol)
    boundaries = parse_boundaries(data, box, tol, stages, rock)
    # Lines may reach beyond the rock, but not beyond what the dtype resolves.
    ends = [("discontinuities", i, d) for i, d in enumerate(discontinuities)]
    ends += [("boundaries", i, b) for i, b in enumerate(boundaries) if b.side is None]
    for section, i, line in ends:
        check_far(line.start, f"{section}.{i}.from", *far)
        check_far(line.end, f"{section}.{i}.to", *far)
    in_situ = parse_in_situ(data, top=box[3])
    water = parse_water(data)
    bolts = parse_bolts(data, rock, stages)
    supports = parse_supports(data, excavations, stages)
    monitors = parse_monitors(data, rock)

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
        warnings=(plausibility_warnings(materials, joints)
                  + in_situ_strength_warnings(in_situ, domain, zones, materials)),
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
        data = parse_toml(path_or_text, source)
        if not data:
            raise SceneError(source, "scene text is empty")
    elif isinstance(path_or_text, (str, Path)):
        path = Path(path_or_text)
        data, source = read_toml(path), str(path)
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
