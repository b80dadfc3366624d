"""One value of a scene file: ``SceneError``, the magnitude and count limits, and the
checks that every section uses (a number in range, an integer, a string among choices, a
point, a list of points, a table of known fields, a reference to a defined name).

Plain Python and NumPy; imports nothing from jaxdem, and every other scene module imports
it. Raw TOML values come in, checked Python values go out (float, int, str, a read-only
(2,) float64 point, an (n, 2) float64 list of points), and the first problem is raised as
one ``SceneError`` whose message starts with the field's dotted path. Nothing here knows
which section it reads.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


class SceneError(ValueError):
    """An invalid scene: the message starts with the field path, then what is wrong.

    ``path`` is the dotted field path (``"blocks.3.vertices"``), the file name for
    file-level problems, or ``"--set"`` for malformed command-line overrides.
    """

    def __init__(self, path: str, problem: str, *, prefix: str = "") -> None:
        self.path = path
        self.problem = problem
        super().__init__(f"{prefix}{path}: {problem}")


MAX_MAGNITUDE = 1e15
"""Largest absolute value accepted for any number in a scene (typos such as 3e70)."""

MAX_STEPS = 10_000
"""Most load steps (``solver.load_steps``, ``stages.N.load_steps``) and Newton iterations
(``solver.max_iterations``) accepted: the defaults are 5 and 60, so more is a typo."""


def is_number(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(
        x, (bool, np.bool_)
    )


def fmt(x: Any) -> str:
    if isinstance(x, str):
        return repr(x)
    if isinstance(x, (np.integer, np.floating)):
        x = x.item()
    if isinstance(x, float):
        return repr(x)
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(fmt(e) for e in x) + "]"
    if isinstance(x, dict):
        return "a table"
    return repr(x) if isinstance(x, (int, bool)) else type(x).__name__


def fmt_point(p: np.ndarray) -> str:
    return f"({float(p[0]):g}, {float(p[1]):g})"


def read_number(value: Any, path: str) -> float:
    """A finite, not absurdly large number, as float."""
    if not is_number(value):
        raise SceneError(path, f"must be a number (got {fmt(value)})")
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        raise SceneError(path, f"must be finite (got {fmt(value)})")
    if abs(value) > MAX_MAGNITUDE:
        raise SceneError(
            path, f"out of range: magnitude above {MAX_MAGNITUDE:g} (got {fmt(value)})"
        )
    return float(value)


def _integer(value: Any, path: str) -> int:
    x = read_number(value, path)
    if x != math.floor(x):
        raise SceneError(path, f"must be an integer (got {fmt(value)})")
    return int(x)


def in_range(
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
    raise SceneError(path, f"{what} (got {fmt(raw)})")


def read_string(value: Any, path: str, choices: tuple[str, ...] | None = None) -> str:
    if not isinstance(value, str):
        raise SceneError(path, f"must be a string (got {fmt(value)})")
    if choices is not None and value not in choices:
        raise SceneError(path, f"must be one of {', '.join(choices)} (got {value!r})")
    return value


def read_option(t: dict, key: str, path: str, choices: tuple[str, ...] | None = None,
                default: str | None = None) -> str | None:
    """The string field ``key`` of table ``t`` (one of ``choices`` where given), or
    ``default`` where the table has none."""
    return read_string(t[key], f"{path}.{key}", choices) if key in t else default


def read_point(value: Any, path: str) -> np.ndarray:
    if isinstance(value, np.ndarray):  # programmatic scenes
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise SceneError(path, f"must be a point [x, y] of two numbers (got {fmt(value)})")
    xy = np.array([read_number(value[k], f"{path}.{k}") for k in range(2)], dtype=np.float64)
    xy.setflags(write=False)
    return xy


def read_vertices(vs: Any, vp: str, min_points: int = 3) -> np.ndarray:
    """A list of points [[x, y], ...] as an (n, 2) float array (not yet checked as a polygon)."""
    if isinstance(vs, (np.ndarray, tuple)):  # programmatic scenes
        vs = list(vs)
    if not isinstance(vs, list):
        raise SceneError(vp, f"must be a list of points [[x, y], ...] (got {fmt(vs)})")
    if len(vs) < min_points:
        raise SceneError(vp, f"needs at least {min_points} points (got {len(vs)})")
    return np.array([read_point(q, f"{vp}.{k}") for k, q in enumerate(vs)], dtype=np.float64)


def plain_vertices(vs: Any) -> np.ndarray | None:
    """What :func:`read_vertices` returns for ``vs`` when that is a list of at least 3 pairs
    ``[x, y]`` of plain numbers (int or float), finite and within MAX_MAGNITUDE: found with
    one conversion, not a call per point (a 10,000-block scene has 40,000 points). None for
    anything else; :func:`read_vertices` then reads it (and names what is wrong)."""
    if type(vs) is not list or len(vs) < 3:
        return None
    if not all(type(q) is list and len(q) == 2 and type(q[0]) in (int, float)
               and type(q[1]) in (int, float) for q in vs):
        return None
    try:
        v = np.array(vs, dtype=np.float64)
    except OverflowError:  # an integer beyond float range
        return None
    if not np.all(np.abs(v) <= MAX_MAGNITUDE):  # also NaN and infinity
        return None
    return v


def read_table(value: Any, path: str, allowed: tuple[str, ...]) -> dict:
    if not isinstance(value, dict):
        raise SceneError(path, f"must be a table (got {fmt(value)})")
    for key in value:
        if key not in allowed:
            raise SceneError(f"{path}.{key}", f"unknown field; allowed: {', '.join(allowed)}")
    return value


def read_array_of_tables(data: dict, key: str) -> list:
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(e, dict) for e in value):
        raise SceneError(key, f"must be an array of tables ([[{key}]]), got {fmt(value)}")
    return value


def read_field(
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
    x = _integer(raw, fpath) if integer else read_number(raw, fpath)
    in_range(float(x), raw, fpath, lo, hi, lo_open, hi_open)
    return x


def read_count(table: dict, key: str, path: str, default: int | None = None) -> int | None:
    """load_steps or max_iterations: an integer from 1 to MAX_STEPS."""
    n = read_field(table, key, path, default=default, lo=1, integer=True)
    if n is not None and n > MAX_STEPS:
        raise SceneError(f"{path}.{key}", f"must be <= {MAX_STEPS:,} (got {n:,})")
    return n


def defined_name(value: Any, path: str, kind: str, names, none: str = "none") -> str:
    """A string that names one of ``names`` (a material, joint, stage, ...), else SceneError."""
    name = read_string(value, path)
    if name not in names:
        defined = ", ".join(names) or none
        raise SceneError(path, f"unknown {kind} {name!r}; defined: {defined}")
    return name


def read_name(
    t: dict, path: str, seen: dict[str, int], section: str, default: str | None = None
) -> str:
    if "name" not in t:
        if default is None:
            raise SceneError(f"{path}.name", "required field is missing")
        name = default
    else:
        name = read_string(t["name"], f"{path}.name")
    if not name.strip():
        raise SceneError(f"{path}.name", "must not be empty")
    if name in seen:
        raise SceneError(f"{path}.name", f"duplicate name {name!r} (also {section}.{seen[name]})")
    seen[name] = len(seen)
    return name
