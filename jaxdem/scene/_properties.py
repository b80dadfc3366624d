"""Property tables: ``[solver]`` -> ``SolverSettings``, ``[materials.NAME]`` ->
``Material``, ``[joints.NAME]`` -> ``Joint`` (with a joint set's geometry, a geological
dip and dip direction converted to the trace angle, :func:`trace_angle`).

Reads the raw scene dict section by section with the checks of
:mod:`jaxdem.scene._fields`; returns records of :mod:`jaxdem.scene._schema` to
:func:`jaxdem.scene.parse_scene`, which reads the other sections with them.
"""

from __future__ import annotations

import math
from typing import Any

from jaxdem.scene._fields import (
    SceneError,
    fmt,
    in_range,
    read_count,
    read_field,
    read_number,
    read_option,
    read_point,
    read_table,
)
from jaxdem.scene._schema import (
    BOND_FAILURES,
    DTYPES,
    JOINT_FIELDS,
    LINEAR_SOLVERS,
    LOOSE_BLOCKS,
    MATERIAL_FIELDS,
    MAX_STEP_CUTS,
    SOLVER_FIELDS,
    Joint,
    Material,
    SolverSettings,
)

#: ``dip_direction`` words: the side of the section the joint dips towards.
DIP_SIDES = ("left", "right")


def parse_solver(data: dict) -> SolverSettings:
    t = read_table(data.get("solver", {}), "solver", SOLVER_FIELDS)
    d = SolverSettings()
    return SolverSettings(
        load_steps=read_count(t, "load_steps", "solver", default=d.load_steps),
        tolerance=read_field(
            t, "tolerance", "solver", default=d.tolerance, lo=0, hi=1, lo_open=True, hi_open=True
        ),
        max_iterations=read_count(t, "max_iterations", "solver", default=d.max_iterations),
        max_displacement=read_field(t, "max_displacement", "solver", lo=0, lo_open=True),
        dtype=read_option(t, "dtype", "solver", DTYPES, d.dtype),
        regularization=read_field(
            t,
            "regularization",
            "solver",
            default=d.regularization,
            lo=0,
            hi=1,
            lo_open=True,
            hi_open=True,
        ),
        step_length=read_field(t, "step_length", "solver", lo=0, lo_open=True),
        linear_solver=read_option(t, "linear_solver", "solver", LINEAR_SOLVERS,
                                  d.linear_solver),
        loose_blocks=read_option(t, "loose_blocks", "solver", LOOSE_BLOCKS, d.loose_blocks),
        max_loose_volume=read_field(t, "max_loose_volume", "solver", lo=0),
        max_step_cuts=read_field(t, "max_step_cuts", "solver", default=d.max_step_cuts, lo=0,
                                 hi=MAX_STEP_CUTS, integer=True),
        bond_failure=read_option(t, "bond_failure", "solver", BOND_FAILURES, d.bond_failure),
    )


def _named_tables(data: dict, key: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise SceneError(key, f"must be a table of named tables ([{key}.NAME]), got {fmt(value)}")
    return value


def _check_table_name(name: Any, path: str, example: str) -> None:
    """NAME of [materials.NAME] or [joints.NAME]: a segment of dotted parameter paths."""
    if not isinstance(name, str):
        raise SceneError(path, f"the name must be a string (got {fmt(name)})")
    if not name.strip():
        raise SceneError(path, "the name must not be empty")
    if "." in name:
        raise SceneError(
            path,
            f"the name {name!r} contains '.', so its parameters ({path}.{example}, ...) "
            "could not be addressed by dotted path; rename it",
        )


def parse_materials(data: dict) -> dict[str, Material]:
    out = {}
    for name, raw in _named_tables(data, "materials").items():
        p = f"materials.{name}"
        _check_table_name(name, p, "E")
        t = read_table(raw, p, MATERIAL_FIELDS)
        out[name] = Material(
            name=name,
            E=read_field(t, "E", p, required=True, lo=0, lo_open=True),
            nu=read_field(t, "nu", p, required=True, lo=0, hi=0.5, hi_open=True),
            unit_weight=read_field(t, "unit_weight", p, required=True, lo=0),
            cohesion=read_field(t, "cohesion", p, default=0.0, lo=0),
            friction_deg=read_field(t, "friction_deg", p, default=45.0, lo=0, hi=90, hi_open=True),
            tensile_strength=read_field(t, "tensile_strength", p, default=0.0, lo=0),
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
    dip = read_field(t, "dip", p, lo=0, hi=90)
    raw = t["dip_direction"]
    dp = f"{p}.dip_direction"
    if isinstance(raw, str):
        if raw not in DIP_SIDES:
            raise SceneError(dp, f"must be 'left', 'right' or an azimuth in degrees (got {raw!r})")
        direction: str | float = raw
    else:
        direction = read_number(raw, dp)
        in_range(direction, raw, dp, 0, 360)
        if section_azimuth is None:
            raise SceneError("scene.section_azimuth",
                             f"required with {dp} as an azimuth ({fmt(raw)}): the azimuth of "
                             "the section's +x axis, degrees clockwise from north")
        if dip >= 90.0 and abs(math.cos(math.radians(direction - section_azimuth))) < 1e-9:
            raise SceneError(dp, "the joint plane is the section plane itself (vertical, "
                             "striking across the section): it has no trace")
    return trace_angle(dip, direction, section_azimuth)


def parse_joints(data: dict, section_azimuth: float | None = None) -> dict[str, Joint]:
    out = {}
    for name, raw in _named_tables(data, "joints").items():
        p = f"joints.{name}"
        _check_table_name(name, p, "kn")
        t = read_table(raw, p, JOINT_FIELDS)
        geological = _geological_dip(t, p, section_azimuth)
        if geological is not None:
            if "spacing" not in t:
                raise SceneError(f"{p}.spacing", "required with dip (a joint set needs both)")
            t = dict(t, dip_deg=geological)
        origin = None
        if "origin" in t:
            xy = read_point(t["origin"], f"{p}.origin")
            origin = (float(xy[0]), float(xy[1]))
        out[name] = Joint(
            name=name,
            kn=read_field(t, "kn", p, required=True, lo=0, lo_open=True),
            ks=read_field(t, "ks", p, required=True, lo=0, lo_open=True),
            friction_deg=read_field(t, "friction_deg", p, required=True, lo=0, hi=90, hi_open=True),
            cohesion=read_field(t, "cohesion", p, default=0.0, lo=0),
            tensile_strength=read_field(t, "tensile_strength", p, default=0.0, lo=0),
            dip_deg=read_field(t, "dip_deg", p),
            spacing=read_field(t, "spacing", p, lo=0, lo_open=True),
            origin=origin,
            persistence=read_field(t, "persistence", p, lo=0, hi=1, lo_open=True),
            gap=read_field(t, "gap", p, lo=0),
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
