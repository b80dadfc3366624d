"""Parameter overrides by dotted path: ``--set PATH=VALUE`` on the command line,
``load_scene(..., set=...)``, ``Scene.with_overrides`` and the batched and differentiable
solves.

Works on the raw scene dict before validation: :func:`parse_set_arguments` turns the
command-line strings into ``{path: value}``, :func:`apply_overrides` returns a deep copy
of the dict with those numeric entries set (list items by index, ``boundaries.1.traction.0``;
an optional numeric field the file leaves out may be added where its table exists), and
the solver's choices (:data:`SOLVER_CHOICES`, ``solver.linear_solver=cg``) set to a word.
The result is validated again by :func:`jaxdem.scene.parse_scene` (a word that is not one
of a choice's values is refused there); a path that does not exist or names no number
raises ``SceneError`` ("--set PATH: ...").
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from jaxdem.scene._fields import MAX_MAGNITUDE, SceneError, fmt, is_number
from jaxdem.scene._schema import IN_SITU_FIELDS, MATERIAL_FIELDS

# Scalar numeric fields that an override may add when the file leaves them out.
_OPTIONAL_NUMERIC = {
    "solver": ("load_steps", "tolerance", "max_iterations", "max_displacement")
    + ("regularization", "step_length", "max_loose_volume", "max_step_cuts"),
    "materials": MATERIAL_FIELDS,
    "joints": ("kn", "ks", "cohesion", "friction_deg", "tensile_strength")
    + ("dip_deg", "spacing", "persistence", "gap"),
    "domain": ("mesh_size", "mesh_max_size", "min_block_area"),
    "in_situ": IN_SITU_FIELDS[1:],
    "water": ("unit_weight",),
    "bolts": ("spacing", "compression"),
    "stages": ("load_steps",),
}
# Sections whose optional fields sit at depth 2 (section.field) or 3 (section.NAME|i.field).
_DEPTH2 = ("solver", "domain", "in_situ", "water")
_DEPTH3 = ("materials", "joints", "bolts", "stages")
_INT_FIELDS = ("load_steps", "max_iterations")
#: The solver's settings that take a word (``--set solver.linear_solver=cg``): the only
#: entries an override sets to a string. They are settings, not parameters: ``--vary``,
#: sweeps and gradients take numbers alone.
SOLVER_CHOICES = ("dtype", "linear_solver", "loose_blocks", "bond_failure")


def _is_choice(dotted: str) -> bool:
    keys = dotted.split(".")
    return len(keys) == 2 and keys[0] == "solver" and keys[1] in SOLVER_CHOICES


def _walk_error(path: str, problem: str) -> SceneError:
    return SceneError(path, problem, prefix="--set ")


def apply_overrides(data: dict, overrides: Mapping[str, float | str]) -> dict:
    """A deep copy of ``data`` with numeric entries set by dotted path (``joints.j.kn``).

    List items are addressed by index (``boundaries.1.traction.0``). A path that does not
    exist, or that names a non-numeric entry, raises ``SceneError`` ("--set PATH: ...").
    An optional scalar field left out of the file (``joints.j.cohesion``) may be set when
    its table exists. Integer entries stay integers when the new value is integral. The
    solver's choices (:data:`SOLVER_CHOICES`) take a word, whether or not the file gives
    them (``{"solver.linear_solver": "cg"}``).
    """
    try:
        out = copy.deepcopy(data)
    except Exception as exc:
        raise SceneError("<dict>", f"cannot copy scene data ({exc})") from exc
    if not isinstance(out, dict):
        raise SceneError("<dict>", f"a scene must be a table (got {fmt(out)})")
    if not isinstance(overrides, Mapping):
        raise SceneError("set", f"expected {{path: value}} (got {type(overrides).__name__})")
    for dotted, value in overrides.items():
        if not isinstance(dotted, str) or not dotted:
            raise SceneError("--set", f"parameter path must be a non-empty string (got {dotted!r})")
        if _is_choice(dotted):
            if not isinstance(value, str):
                raise _walk_error(dotted, f"a choice: its value is a word, one of those in "
                                          f"docs/scene-format.md (got {fmt(value)})")
        elif not is_number(value) or not math.isfinite(float(value)):
            raise _walk_error(dotted, f"value must be a finite number (got {fmt(value)})")
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
        if _is_choice(dotted):
            # A word, set whether or not the file gives it; parse_scene checks it.
            node[last] = value
            return
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
    if not is_number(old):
        raise _walk_error(dotted, f"not a numeric parameter (its value is {fmt(old)})")
    node[idx] = _convert(value, isinstance(old, (int, np.integer)))


def _convert(value: Any, as_int: bool) -> int | float:
    x = float(value)
    if as_int and x == math.floor(x) and abs(x) <= MAX_MAGNITUDE:
        return int(x)
    return int(value) if isinstance(value, (int, np.integer)) else x


def parse_set_arguments(items: list[str]) -> dict[str, float | str]:
    """Command-line ``--set PATH=VALUE`` strings -> ``{PATH: float(VALUE)}``, or the word
    itself for the solver's choices (:data:`SOLVER_CHOICES`).

    Malformed items raise ``SceneError`` with path ``"--set"``.

    Example::

        >>> parse_set_arguments(["joints.j.kn=2e6", "solver.linear_solver=cg"])
        {'joints.j.kn': 2000000.0, 'solver.linear_solver': 'cg'}
    """
    out: dict[str, float | str] = {}
    for item in items:
        if not isinstance(item, str) or "=" not in item:
            raise SceneError("--set", f"expected PATH=VALUE, e.g. joints.j.kn=2e6 (got {item!r})")
        path, _, text = item.partition("=")
        path, text = path.strip(), text.strip()
        parts = path.split(".")
        if not path or any(not p for p in parts) or any(c.isspace() for c in path):
            raise SceneError("--set", f"bad parameter path {path!r} in {item!r}")
        if path in out:
            raise SceneError("--set", f"{path} is given twice")
        if _is_choice(path):
            out[path] = text
            continue
        try:
            value = float(text)
        except ValueError:
            raise SceneError("--set", f"value of {path} must be a number (got {text!r})") from None
        if not math.isfinite(value):
            raise SceneError("--set", f"value of {path} must be finite (got {text!r})")
        out[path] = value
    return out
