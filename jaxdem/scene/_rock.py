"""The rock's geometry: ``[[blocks]]``, ``[[discontinuities]]``, ``[domain]``,
``[[zones]]`` and ``[[excavations]]`` (circles and horseshoes discretised into
counter-clockwise polygons) -> ``Block``, ``Discontinuity``, ``Domain``, ``Zone`` and
``Excavation`` records.

Raw section dicts and the materials, joints and stages already read come in; validated
records go out to :func:`jaxdem.scene.parse_scene`. The blocks of a ``[domain]`` are not
made here but by :func:`jaxdem.rockmass.generate`, from these records.
"""

from __future__ import annotations

import math

import numpy as np

from jaxdem import geometry
from jaxdem.scene._checks import (
    check_polygon,
    convex_polygons_pass,
    read_polygon,
    segment_touches_box,
)
from jaxdem.scene._fields import (
    SceneError,
    defined_name,
    fmt,
    fmt_point,
    plain_vertices,
    read_array_of_tables,
    read_field,
    read_name,
    read_option,
    read_point,
    read_string,
    read_table,
    read_vertices,
)
from jaxdem.scene._schema import (
    BLOCK_FIELDS,
    DISCONTINUITY_FIELDS,
    DOMAIN_FIELDS,
    EXCAVATION_FIELDS,
    SHAPE_FIELDS,
    SHAPES,
    ZONE_FIELDS,
    Block,
    Discontinuity,
    Domain,
    Excavation,
    Joint,
    Material,
    Stage,
    Zone,
)
from jaxdem.scene._stages import read_release, stage_ref


def _material_ref(t: dict, path: str, materials: dict[str, Material]) -> str:
    if "material" not in t:
        raise SceneError(f"{path}.material", "required field is missing")
    return defined_name(t["material"], f"{path}.material", "material", materials)


def parse_blocks(
    data: dict, materials: dict[str, Material], has_domain: bool = False
) -> tuple[Block, ...]:
    raw_blocks = read_array_of_tables(data, "blocks")
    if not raw_blocks and not has_domain:
        raise SceneError(
            "blocks",
            "at least one block is needed ([[blocks]] vertices, material), or a [domain]",
        )
    # The polygons given as plain lists of numbers are read and checked all at once; any
    # other, or one that the batch does not clear, is read and checked in turn below
    # (where the first problem, in block order, is named).
    plain = [plain_vertices(raw.get("vertices")) for raw in raw_blocks]
    listed = [i for i, v in enumerate(plain) if v is not None]
    cleared = np.zeros(len(raw_blocks), dtype=bool)
    cleared[listed] = convex_polygons_pass([plain[i] for i in listed])
    blocks = []
    for i, raw in enumerate(raw_blocks):
        p = f"blocks.{i}"
        t = read_table(raw, p, BLOCK_FIELDS)
        if "vertices" not in t:
            raise SceneError(f"{p}.vertices", "required field is missing")
        vp = f"{p}.vertices"
        if cleared[i]:
            v = plain[i]
        else:
            v = read_vertices(t["vertices"], vp)
            check_polygon(v, vp)
        v.setflags(write=False)
        mat = _material_ref(t, p, materials)
        fixed = t.get("fixed", False)
        if not isinstance(fixed, bool):
            raise SceneError(f"{p}.fixed", f"must be true or false (got {fmt(fixed)})")
        joint = read_option(t, "joint", p)
        blocks.append(Block(vertices=v, material=mat, fixed=fixed, joint=joint))
    return tuple(blocks)


def parse_discontinuities(
    data: dict, joints: dict[str, Joint], default_joint: str, box: tuple, tol: float
) -> tuple[Discontinuity, ...]:
    out = []
    for i, raw in enumerate(read_array_of_tables(data, "discontinuities")):
        p = f"discontinuities.{i}"
        t = read_table(raw, p, DISCONTINUITY_FIELDS)
        for key in ("from", "to"):
            if key not in t:
                raise SceneError(f"{p}.{key}", "required field is missing")
        a = read_point(t["from"], f"{p}.from")
        b = read_point(t["to"], f"{p}.to")
        if "joint" in t:
            joint = defined_name(t["joint"], f"{p}.joint", "joint", joints)
        elif default_joint:
            joint = default_joint
        else:
            raise SceneError(f"{p}.joint", "required: no joints are defined to default to")
        if float(np.hypot(*(b - a))) <= tol:
            raise SceneError(
                f"{p}.to", f"same point as from {fmt_point(a)}; a discontinuity needs two ends"
            )
        if not segment_touches_box(a, b, box, tol):
            raise SceneError(
                p,
                f"joint outside the domain: {fmt_point(a)}-{fmt_point(b)} misses the rock's "
                f"bounding box ({box[0]:g}, {box[1]:g})-({box[2]:g}, {box[3]:g})",
            )
        out.append(Discontinuity(start=a, end=b, joint=joint))
    return tuple(out)


def parse_domain(data: dict, materials: dict[str, Material]) -> Domain | None:
    if "domain" not in data:
        return None
    t = read_table(data["domain"], "domain", DOMAIN_FIELDS)
    outline = read_polygon(t, "outline", "domain")
    mat = _material_ref(t, "domain", materials)
    mesh = read_field(t, "mesh_size", "domain", lo=0, lo_open=True)
    if mesh is not None:
        box = geometry.bbox(outline)
        size = max(box[2] - box[0], box[3] - box[1])
        if mesh > size:
            raise SceneError(
                "domain.mesh_size", f"larger than the domain ({mesh:g} m > {size:g} m)"
            )
    grown = read_field(t, "mesh_max_size", "domain", lo=0, lo_open=True)
    if grown is not None:
        if mesh is None:
            raise SceneError("domain.mesh_max_size", "needs domain.mesh_size (the smallest cells)")
        if grown < mesh:
            raise SceneError("domain.mesh_max_size",
                             f"smaller than domain.mesh_size ({grown:g} m < {mesh:g} m)")
    merge = read_field(t, "min_block_area", "domain", lo=0)
    return Domain(outline=outline, material=mat, mesh_size=mesh, mesh_max_size=grown,
                  min_block_area=merge)


def parse_zones(data: dict, materials: dict[str, Material], domain: Domain | None,
                far: tuple[float, str] | None = None) -> tuple:
    raw = read_array_of_tables(data, "zones")
    if raw and domain is None:
        raise SceneError("zones", "needs a [domain] (a zone is a region of the generated rock)")
    out = []
    seen: dict[str, int] = {}
    for i, r in enumerate(raw):
        p = f"zones.{i}"
        t = read_table(r, p, ZONE_FIELDS)
        name = read_name(t, p, seen, "zones", default=f"zone{i}")
        v = read_polygon(t, "vertices", p, far)
        mat = _material_ref(t, p, materials)
        assert domain is not None
        a = geometry.polygon_overlap_area(v, domain.outline)
        if a <= 1e-9 * abs(geometry.signed_area(v)):
            raise SceneError(p, "does not overlap the domain")
        out.append(Zone(name=name, vertices=v, material=mat))
    return tuple(out)


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


def parse_excavations(
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
    for i, r in enumerate(read_array_of_tables(data, "excavations")):
        p = f"excavations.{i}"
        t = read_table(r, p, EXCAVATION_FIELDS)
        name = read_name(t, p, seen, "excavations")
        if "shape" not in t:
            raise SceneError(f"{p}.shape", f"required ({', '.join(SHAPES)})")
        shape = read_string(t["shape"], f"{p}.shape", SHAPES)
        for key in ("center", "radius", "width", "height", "vertices"):
            if key in t and key not in SHAPE_FIELDS[shape]:
                raise SceneError(f"{p}.{key}", f"not used by shape {shape!r}")
        center = radius = width = height = None
        if shape == "polygon":
            v = np.array(read_polygon(t, "vertices", p, far))
        else:
            if "center" not in t:
                raise SceneError(f"{p}.center", "required field is missing")
            center = read_point(t["center"], f"{p}.center")
            if shape == "circle":
                radius = read_field(t, "radius", p, required=True, lo=0, lo_open=True)
                n = _segments_for(radius, _discretisation_length(domain, joints, radius))
                v = circle_vertices(center, radius, n)
            else:
                width = read_field(t, "width", p, required=True, lo=0, lo_open=True)
                height = read_field(t, "height", p, required=True, lo=0, lo_open=True)
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
        stage = stage_ref(t, p, stages)
        release = read_release(t, p, stage, stages)
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
                release=release,
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
