"""``[[stages]]`` and ``[water]``: the analysis stages (load steps, a new water table),
references to a stage by name or 1-based number (``stage = 2``), and water tables
(polylines, x strictly increasing).

Raw section dicts in, ``Stage`` and ``Water`` records out; the stage references are
resolved here for excavations, bolts, supports and traction boundaries
(:mod:`jaxdem.scene._rock`, :mod:`jaxdem.scene._loads`), and so is an excavation's
``release`` over its stage and the stages after it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxdem.scene._fields import (
    SceneError,
    fmt,
    fmt_point,
    is_number,
    read_array_of_tables,
    read_count,
    read_field,
    read_name,
    read_number,
    read_table,
    read_vertices,
)
from jaxdem.scene._schema import STAGE_FIELDS, WATER_FIELDS, Stage, Water


def parse_stages(data: dict) -> tuple[Stage, ...]:
    out = []
    seen: dict[str, int] = {}
    for i, r in enumerate(read_array_of_tables(data, "stages")):
        p = f"stages.{i}"
        t = read_table(r, p, STAGE_FIELDS)
        name = read_name(t, p, seen, "stages")
        steps = read_count(t, "load_steps", p)
        table = _water_table(t["water_table"], f"{p}.water_table") if "water_table" in t else None
        out.append(Stage(name=name, load_steps=steps, water_table=table))
    return tuple(out)


def stage_ref(t: dict, path: str, stages: tuple[Stage, ...]) -> str | None:
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
        raise SceneError(sp, f"unknown stage {fmt(raw)}: it never comes, the scene has no "
                         "[[stages]] "
                         "(define them, [[stages]] name = ..., or leave stage out: it then "
                         "acts from the first stage of the analysis)")
    if isinstance(raw, str):
        if raw not in names:
            raise SceneError(sp, f"unknown stage {raw!r} (it would never come): stages are "
                             f"{listed}")
        return raw
    if is_number(raw):
        if raw != math.floor(raw) or not 1 <= raw <= len(names):
            raise SceneError(sp, f"stage {fmt(raw)} does not exist: stages are {listed} "
                             "(a number counts from 1)")
        return names[int(raw) - 1]
    raise SceneError(sp, f"must be a stage name or its number from 1 (got {fmt(raw)}); "
                     f"stages are {listed}")


RELEASE_SUM_TOLERANCE = 1e-9
"""How far from 1 the fractions of an excavation's ``release`` may sum (rounding in a file)."""


def read_release(t: dict, path: str, stage: str | None, stages: tuple[Stage, ...]
                 ) -> tuple[float, ...]:
    """``release``: the fractions of an excavation's load released in its stage and in each
    stage after it (RS2's load split, the relaxation of the convergence-confinement method);
    each in (0, 1], summing to 1 within RELEASE_SUM_TOLERANCE, with a stage for each.
    Default (1.0,): all of it in its own stage. ``stage`` is the excavation's (resolved)."""
    if "release" not in t:
        return (1.0,)
    raw, rp = t["release"], f"{path}.release"
    if not isinstance(raw, (list, tuple)) or not raw:
        raise SceneError(rp, "must be a list of the fractions of the excavation's load released "
                         "in its stage and in each stage after it, summing to 1, e.g. "
                         f"[0.4, 0.6] (got {fmt(raw)})")
    fractions = tuple(read_number(x, f"{rp}.{k}") for k, x in enumerate(raw))
    for k, x in enumerate(fractions):
        if not 0.0 < x <= 1.0:
            raise SceneError(f"{rp}.{k}", f"must be in (0, 1]: a fraction of the load, released "
                             f"in a stage (got {fmt(raw[k])})")
    total = math.fsum(fractions)
    if abs(total - 1.0) > RELEASE_SUM_TOLERANCE:
        raise SceneError(rp, f"the fractions must sum to 1, all of the load released in the end "
                         f"(got {' + '.join(f'{x:g}' for x in fractions)} = {total:.12g})")
    names, n = [s.name for s in stages], len(fractions)
    if n == 1:
        return fractions
    if not names:
        raise SceneError(rp, f"{n} fractions need {n} stages, but the scene has no [[stages]] "
                         "(its excavations are released in one stage); define [[stages]]")
    first = names.index(stage) if stage is not None else 0
    left = len(names) - first
    if n > left:
        listed = ", ".join(f"{k + 1} {name!r}" for k, name in enumerate(names))
        raise SceneError(rp, f"{n} fractions need {n} stages from its stage {first + 1} "
                         f"{names[first]!r} on, but only {left} {'is' if left == 1 else 'are'} "
                         f"left (stages are {listed})")
    return fractions


def _water_table(value: Any, path: str) -> np.ndarray:
    v = read_vertices(value, path, min_points=2)
    dx = np.diff(v[:, 0])
    if np.any(dx <= 0.0):
        k = int(np.nonzero(dx <= 0.0)[0][0])
        raise SceneError(
            path,
            f"not a function of x: x must increase strictly (point {k + 1} "
            f"{fmt_point(v[k + 1])} after {fmt_point(v[k])})",
        )
    v.setflags(write=False)
    return v


def parse_water(data: dict) -> Water | None:
    if "water" not in data:
        return None
    t = read_table(data["water"], "water", WATER_FIELDS)
    if "table" not in t:
        raise SceneError("water.table", "required field is missing")
    return Water(
        table=_water_table(t["table"], "water.table"),
        unit_weight=read_field(t, "unit_weight", "water", default=9.81, lo=0, lo_open=True),
    )
