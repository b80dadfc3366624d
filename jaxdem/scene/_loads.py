"""What acts on the rock and where it is watched: ``[[boundaries]]``, ``[in_situ]``,
``[[bolts]]``, ``[[supports]]`` and ``[[monitors]]`` -> ``Boundary``, ``InSitu``,
``Bolt``, ``Support`` and ``Monitor`` records.

Read after the rock (:mod:`jaxdem.scene._rock`): bolt ends, monitor points and boundary
segments are checked against where the rock is (``Rock`` of
:mod:`jaxdem.scene._checks`), supports against the excavations, stage references against
the stages. Returns records to :func:`jaxdem.scene.parse_scene`.
"""

from __future__ import annotations

import numpy as np

from jaxdem.scene._checks import Rock
from jaxdem.scene._fields import (
    SceneError,
    defined_name,
    fmt,
    fmt_point,
    read_array_of_tables,
    read_field,
    read_number,
    read_option,
    read_point,
    read_string,
    read_table,
)
from jaxdem.scene._schema import (
    BOLT_FIELDS,
    BOUNDARY_FIELDS,
    CONDITIONS,
    IN_SITU_FIELDS,
    MODES,
    MONITOR_FIELDS,
    SIDES,
    SUPPORT_FIELDS,
    Bolt,
    Boundary,
    Excavation,
    InSitu,
    Monitor,
    Stage,
    Support,
)
from jaxdem.scene._stages import stage_ref


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


def parse_boundaries(data: dict, box: tuple, tol: float, stages: tuple = (),
                     rock: Rock | None = None) -> tuple[Boundary, ...]:
    out = []
    for i, raw in enumerate(read_array_of_tables(data, "boundaries")):
        p = f"boundaries.{i}"
        t = read_table(raw, p, BOUNDARY_FIELDS)
        has_side = "side" in t
        has_ends = "from" in t or "to" in t
        if has_side and has_ends:
            raise SceneError(p, "give either side or from/to, not both")
        if not has_side and not has_ends:
            raise SceneError(p, f"needs side ({', '.join(SIDES)}) or from/to")
        if has_side:
            side = read_string(t["side"], f"{p}.side", SIDES)
            a, b = _side_segment(side, box)
        else:
            side = None
            for key in ("from", "to"):
                if key not in t:
                    raise SceneError(f"{p}.{key}", "required with from/to (both ends are needed)")
            a = read_point(t["from"], f"{p}.from")
            b = read_point(t["to"], f"{p}.to")
            if float(np.hypot(*(b - a))) <= tol:
                raise SceneError(f"{p}.to", f"same point as from {fmt_point(a)}")
            if rock is not None and not rock.touches(a, b):
                raise SceneError(
                    p, f"segment {fmt_point(a)}-{fmt_point(b)} does not touch the rock"
                )
        if "condition" not in t:
            raise SceneError(f"{p}.condition", f"required ({', '.join(CONDITIONS)})")
        cond = read_string(t["condition"], f"{p}.condition", CONDITIONS)
        if cond == "traction":
            if "traction" not in t:
                raise SceneError(
                    f"{p}.traction", "required for condition 'traction' ([tx, ty] in kPa)"
                )
            tr = t["traction"]
            if not isinstance(tr, list) or len(tr) != 2:
                raise SceneError(f"{p}.traction", f"must be [tx, ty] in kPa (got {fmt(tr)})")
            traction = np.array(
                [read_number(tr[k], f"{p}.traction.{k}") for k in range(2)], dtype=np.float64
            )
        else:
            if "traction" in t:
                raise SceneError(
                    f"{p}.traction", f"only allowed with condition 'traction' (got {cond!r})"
                )
            traction = np.zeros(2)
        if "stage" in t and cond != "traction":
            raise SceneError(f"{p}.stage", f"only allowed with condition 'traction' (got {cond!r})")
        stage = stage_ref(t, p, stages)
        traction.setflags(write=False)
        out.append(Boundary(condition=cond, start=a, end=b, side=side, traction=traction,
                            stage=stage))
    return tuple(out)


def parse_in_situ(data: dict, top: float) -> InSitu | None:
    if "in_situ" not in data:
        return None
    p = "in_situ"
    t = read_table(data["in_situ"], p, IN_SITU_FIELDS)
    mode = read_option(t, "mode", p, MODES, "gravity")
    if mode == "gravity":
        for key in ("sigma_xx", "sigma_yy", "sigma_xy"):
            if key in t:
                raise SceneError(f"{p}.{key}", "only with mode 'uniform' (gravity uses k0)")
        return InSitu(
            mode=mode,
            k0=read_field(t, "k0", p, default=1.0, lo=0),
            surface_y=read_field(t, "surface_y", p, default=top),
        )
    for key in ("k0", "surface_y"):
        if key in t:
            raise SceneError(f"{p}.{key}", "only with mode 'gravity'")
    return InSitu(
        mode=mode,
        sigma_xx=read_field(t, "sigma_xx", p, required=True),
        sigma_yy=read_field(t, "sigma_yy", p, required=True),
        sigma_xy=read_field(t, "sigma_xy", p, default=0.0),
    )


def parse_bolts(data: dict, rock: Rock, stages: tuple[Stage, ...]) -> tuple[Bolt, ...]:
    out = []
    for i, r in enumerate(read_array_of_tables(data, "bolts")):
        p = f"bolts.{i}"
        t = read_table(r, p, BOLT_FIELDS)
        ends = {}
        for key in ("from", "to"):
            if key not in t:
                raise SceneError(f"{p}.{key}", "required field is missing")
            q = read_point(t[key], f"{p}.{key}")
            if not rock.contains(q):
                raise SceneError(f"{p}.{key}", f"bolt end {rock.where(q)}")
            ends[key] = q
        if float(np.hypot(*(ends["to"] - ends["from"]))) <= rock.tol:
            raise SceneError(f"{p}.to", f"same point as from {fmt_point(ends['from'])}")
        out.append(
            Bolt(
                start=ends["from"],
                end=ends["to"],
                stiffness=read_field(t, "stiffness", p, required=True, lo=0, lo_open=True),
                yield_force=read_field(t, "yield_force", p, required=True, lo=0, lo_open=True),
                anchor_capacity=read_field(t, "anchor_capacity", p, required=True, lo=0,
                                           lo_open=True),
                spacing=read_field(t, "spacing", p, default=1.0, lo=0, lo_open=True),
                stage=stage_ref(t, p, stages),
                compression=read_field(t, "compression", p, default=0.0, lo=0),
            )
        )
    return tuple(out)


def parse_supports(
    data: dict, excavations: tuple[Excavation, ...], stages: tuple[Stage, ...]
) -> tuple[Support, ...]:
    out = []
    names = [e.name for e in excavations]
    for i, r in enumerate(read_array_of_tables(data, "supports")):
        p = f"supports.{i}"
        t = read_table(r, p, SUPPORT_FIELDS)
        if "excavation" not in t:
            raise SceneError(f"{p}.excavation", "required field is missing")
        exc = defined_name(t["excavation"], f"{p}.excavation", "excavation", names)
        out.append(
            Support(
                excavation=exc,
                pressure=read_field(t, "pressure", p, required=True, lo=0),
                stage=stage_ref(t, p, stages),
            )
        )
    return tuple(out)


def parse_monitors(data: dict, rock: Rock) -> tuple[Monitor, ...]:
    tol = rock.tol
    out = []
    seen: dict[str, int] = {}
    for i, raw in enumerate(read_array_of_tables(data, "monitors")):
        p = f"monitors.{i}"
        t = read_table(raw, p, MONITOR_FIELDS)
        if "name" not in t:
            raise SceneError(f"{p}.name", "required field is missing")
        name = read_string(t["name"], f"{p}.name")
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
            q = read_point(t[key], f"{p}.{key}")
            if not rock.contains(q):
                raise SceneError(f"{p}.{key}", rock.where(q))
            pts[key] = q
        if has_point:
            out.append(Monitor(name=name, kind="point", point=pts["point"]))
        else:
            if float(np.hypot(*(pts["to"] - pts["from"]))) <= tol:
                raise SceneError(f"{p}.to", f"same point as from {fmt_point(pts['from'])}")
            out.append(Monitor(name=name, kind="section", start=pts["from"], end=pts["to"]))
    return tuple(out)
