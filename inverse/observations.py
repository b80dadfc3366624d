"""Observations: what was measured, read from CSV or given in Python, checked against the
scene, and mapped onto the forward model's output.

Owns :class:`Observation`, :func:`read_observations`, the default std, and the checks
that name the file, row and field of a bad entry. Data flows one way: CSV or dicts ->
list of Observation (validated, default stds filled in) -> ``observed_model``, which
turns ``jaxdem.differentiable``'s dict of monitors into the vector of modelled
observations that :mod:`inverse.fit` fits. Takes only ``SceneError`` and ``Scene``
from jaxdem. Host code.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from jaxdem.scene import Scene, SceneError

DEFAULT_RELATIVE_STD = 0.05
"""Standard deviation of an observation given without one: 5 % of |value| ..."""
DEFAULT_STD_FLOOR = 1.0e-4
"""... but at least 0.1 mm (m): the resolution of a convergence tape, and what keeps a
zero reading (the horizontal displacement of a symmetric crown) from weighing infinitely."""

COMPONENTS = ("ux", "uy")
"""Components of a point monitor's displacement [ux, uy] (m) that can be observed."""


@dataclass(frozen=True)
class Observation:
    """One measured monitor value.

    Attributes:
      monitor: name of a ``[[monitors]]`` entry of the scene.
      value: the measurement, m: the convergence of a section (positive when it
        shortens) or one displacement component of a point.
      std: its standard deviation, m (> 0). None: ``DEFAULT_RELATIVE_STD`` (5 %) of
        |value|, at least ``DEFAULT_STD_FLOOR`` (0.1 mm).
      stage: the stage at whose end it was measured; None: the last stage.
      component: "ux" or "uy" for a point monitor (required there); None for a section.
      source: where it was read (``"obs.csv, row 3"``), named in error messages.

    Example::

        Observation("crown", -0.0081, std=0.0005, component="uy", stage="excavate")
    """

    monitor: str
    value: float
    std: float | None = None
    stage: str | None = None
    component: str | None = None
    source: str | None = field(default=None, compare=False)

    def label(self) -> str:
        """Short name for tables and figures: ``crown uy @ excavate``."""
        text = self.monitor
        if self.component:
            text += f" {self.component}"
        if self.stage:
            text += f" @ {self.stage}"
        return text


def default_std(value: float) -> float:
    """The standard deviation given to an observation without one (m): 5 % of |value|,
    at least 0.1 mm."""
    return max(DEFAULT_RELATIVE_STD * abs(float(value)), DEFAULT_STD_FLOOR)


CSV_COLUMNS = ("monitor", "value", "std", "stage", "component")
CSV_REQUIRED = ("monitor", "value")


def read_observations(path: str | Path) -> list[Observation]:
    """Read observations from a CSV file with a header row.

    Columns: ``monitor`` and ``value`` (m) are required; ``std`` (m; blank: the
    default, see :func:`default_std`), ``stage`` (blank: the last stage) and
    ``component`` (``ux`` or ``uy``, for point monitors) are optional. Column
    names are case-insensitive; blank rows are skipped. Rows are numbered as
    the file's lines (the header is row 1).

    Args:
      path: the CSV file.

    Returns:
      the observations, in file order, each with ``source`` = ``"FILE, row N"``.

    Raises:
      SceneError: unreadable or empty file, unknown or missing column, a value
        that is not a finite number, a std that is not > 0, an unknown component;
        the message names the file, row and column.

    Example::

        # obs.csv:
        #   monitor,value,std,component,stage
        #   section 1-1,0.0123,0.0005,,
        #   crown,-0.0081,0.0005,uy,excavate
        observations = read_observations("obs.csv")
    """
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")  # -sig: a BOM written by Excel
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(name, f"cannot read the observations file ({_reason(exc)})") from None
    reader = csv.reader(io.StringIO(text))
    header: list[str] | None = None
    out: list[Observation] = []
    try:
        for row in reader:
            if not any(cell.strip() for cell in row):
                continue
            if header is None:
                header = _csv_header(row, name)
                continue
            out.append(_csv_row(row, header, f"{name}, row {reader.line_num}"))
    except csv.Error as exc:
        raise SceneError(f"{name}, row {reader.line_num}", f"not valid CSV ({exc})") from None
    if header is None:
        raise SceneError(name, "empty file: expected a header (monitor,value,std) and one row "
                               "per observation")
    if not out:
        raise SceneError(name, "no observations: the file has a header but no rows")
    return out


def _reason(exc: Exception) -> str:
    return getattr(exc, "strerror", None) or str(exc)


def _csv_header(row: list[str], name: str) -> list[str]:
    header = [cell.strip().lower() for cell in row]
    where = f"{name}, row 1 (header)"
    for column in header:
        if column not in CSV_COLUMNS:
            raise SceneError(where, f"unknown column {column!r}; allowed: {', '.join(CSV_COLUMNS)}")
        if header.count(column) > 1:
            raise SceneError(where, f"column {column!r} appears twice")
    for column in CSV_REQUIRED:
        if column not in header:
            raise SceneError(where, f"missing column {column!r} (columns: monitor,value,std, "
                                    "optionally stage and component)")
    return header


def _csv_row(row: list[str], header: list[str], where: str) -> Observation:
    if len(row) > len(header):
        raise SceneError(where, f"{len(row)} cells but the header has {len(header)} columns")
    cells = {column: (row[k].strip() if k < len(row) else "") for k, column in enumerate(header)}
    monitor = cells["monitor"]
    if not monitor:
        raise SceneError(f"{where}, monitor", "empty: name a [[monitors]] entry")
    value = _csv_number(cells["value"], f"{where}, value")
    std = None
    if cells.get("std"):
        std = _csv_number(cells["std"], f"{where}, std")
        if std <= 0.0:
            raise SceneError(f"{where}, std", f"must be > 0 (got {cells['std']}); leave it blank "
                                              "for the default")
    component = cells.get("component", "").lower() or None
    if component is not None and component not in COMPONENTS:
        raise SceneError(f"{where}, component",
                         f"must be ux or uy, or blank for a section (got {cells['component']!r})")
    stage = cells.get("stage") or None
    return Observation(monitor, value, std, stage=stage, component=component, source=where)


def _csv_number(text: str, where: str) -> float:
    if not text:
        raise SceneError(where, "empty: a number is required")
    try:
        value = float(text)
    except ValueError:
        raise SceneError(where, f"must be a number (got {text!r})") from None
    if not math.isfinite(value):
        raise SceneError(where, f"must be finite (got {text!r})")
    return value


def as_observations(observed: Any) -> list[Observation]:
    """``observed`` (dict or sequence of Observation) -> list of Observation."""
    if isinstance(observed, Mapping):
        out = []
        for monitor, entry in observed.items():
            where = f"observed[{monitor!r}]"
            if isinstance(entry, (tuple, list)):
                if len(entry) != 2:
                    raise SceneError(where, f"expected a value or (value, std) (got {entry!r})")
                value, std = entry
            else:
                value, std = entry, None
            out.append(Observation(monitor, value, std, source=where))
        return out
    if isinstance(observed, (str, bytes)) or not isinstance(observed, Sequence):
        raise SceneError("observed", "expected {monitor: value}, {monitor: (value, std)} or a "
                                     f"list of Observation (got {type(observed).__name__})")
    for i, item in enumerate(observed):
        if not isinstance(item, Observation):
            raise SceneError(f"observed.{i}", f"expected an Observation (got {item!r})")
    return list(observed)


def _where(obs: Observation, i: int, name: str) -> str:
    """Field path of ``name`` of observation ``i`` for messages."""
    return f"{obs.source}, {name}" if obs.source else f"observed.{i}.{name}"


def checked_observations(observations: list[Observation],
                          scene: Scene | None) -> list[Observation]:
    """Validate against the scene (monitors, kinds, stages) and fill in default stds."""
    if not observations:
        raise SceneError("observed", "no observations given")
    monitors = {m.name: m.kind for m in scene.monitors} if scene is not None else None
    stage_names = [s.name for s in scene.stages] if scene is not None else None
    out = []
    for i, obs in enumerate(observations):
        if not isinstance(obs.monitor, str) or not obs.monitor:
            raise SceneError(_where(obs, i, "monitor"), "must be a monitor name")
        value = finite_number(obs.value, _where(obs, i, "value"))
        std = obs.std
        if std is None:
            std = default_std(value)
        else:
            std = finite_number(std, _where(obs, i, "std"))
            if std <= 0.0:
                raise SceneError(_where(obs, i, "std"), f"must be > 0 (got {std:g})")
        if obs.component is not None and obs.component not in COMPONENTS:
            raise SceneError(_where(obs, i, "component"),
                             f"must be ux or uy, or None for a section (got {obs.component!r})")
        if monitors is not None:
            _check_monitor(obs, i, monitors)
        if obs.stage is not None and stage_names is not None and obs.stage not in stage_names:
            known = ", ".join(stage_names) if stage_names else "none ([[stages]] name = ...)"
            raise SceneError(_where(obs, i, "stage"),
                             f"no stage named {obs.stage!r} in the scene (stages: {known})")
        out.append(replace(obs, value=value, std=std))
    return out


def _check_monitor(obs: Observation, i: int, monitors: dict[str, str]) -> None:
    kind = monitors.get(obs.monitor)
    if kind is None:
        known = ", ".join(monitors) if monitors else "none ([[monitors]] name = ...)"
        raise SceneError(_where(obs, i, "monitor"),
                         f"no monitor named {obs.monitor!r} in the scene (monitors: {known})")
    if kind == "point" and obs.component is None:
        raise SceneError(_where(obs, i, "component"),
                         f"{obs.monitor!r} is a point monitor: say which displacement was "
                         "measured, ux or uy")
    if kind == "section" and obs.component is not None:
        raise SceneError(_where(obs, i, "component"),
                         f"{obs.monitor!r} is a section (one convergence): leave component blank")


def finite_number(value: Any, where: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise SceneError(where, f"must be a number (got {value!r})") from None
    if not math.isfinite(x):
        raise SceneError(where, f"must be finite (got {value!r})")
    return x


def observed_model(f: Callable, observations: list[Observation], stages: list[str] | None,
                    last_stage: str | None) -> Callable:
    """theta -> the model value of each observation, shape (n,), from ``f``'s dict."""

    def model(theta):
        out = f(theta)
        values = []
        for i, obs in enumerate(observations):
            block = out
            if stages is not None:
                stage = obs.stage or last_stage
                if stage not in out:
                    raise SceneError(_where(obs, i, "stage"),
                                     f"the model gives no values for stage {stage!r}")
                block = out[stage]
            if obs.monitor not in block:
                raise SceneError(_where(obs, i, "monitor"),
                                 f"the model gives no monitor named {obs.monitor!r}")
            values.append(_component(jnp.asarray(block[obs.monitor]), obs, i))
        return jnp.stack(values)

    return model


def _component(value: jax.Array, obs: Observation, i: int) -> jax.Array:
    if value.shape == (2,):  # a point monitor: [ux, uy]
        if obs.component is None:
            raise SceneError(_where(obs, i, "component"),
                             f"{obs.monitor!r} is a point monitor: say which displacement was "
                             "measured, ux or uy")
        return value[COMPONENTS.index(obs.component)]
    if value.shape == ():  # a section: its convergence
        if obs.component is not None:
            raise SceneError(_where(obs, i, "component"),
                             f"{obs.monitor!r} is a section (one convergence): leave component "
                             "blank")
        return value
    raise SceneError(_where(obs, i, "monitor"),
                     f"the model gives {obs.monitor!r} with shape {value.shape}; expected (2,) "
                     "for a point or () for a section")


def resolve_stages(observations: list[Observation], scene: Scene | None,
                    stages: Sequence[str] | None) -> tuple[list[str] | None, str | None]:
    """The stages to ask the model for (None: only the end of the analysis) and the name
    of the last stage, which observations without a stage belong to."""
    scene_stages = [s.name for s in scene.stages] if scene is not None else []
    named = [obs.stage for obs in observations if obs.stage is not None]
    if stages is None and not named:
        return None, None
    if scene is not None and named and not scene_stages:
        i = next(i for i, obs in enumerate(observations) if obs.stage is not None)
        raise SceneError(_where(observations[i], i, "stage"),
                         "the scene has no [[stages]]: leave the stage out (the end of the "
                         "analysis)")
    if stages is not None:
        stages = [str(s) for s in stages]
        last = scene_stages[-1] if scene_stages else (stages[-1] if stages else None)
        for i, obs in enumerate(observations):
            if (obs.stage or last) not in stages:
                raise SceneError(_where(obs, i, "stage"),
                                 f"stage {obs.stage or last!r} is not among stages= {stages}")
        return stages, last
    if not scene_stages:
        raise SceneError("stages", "observations name stages: pass the scene, or stages=[...] "
                                   "in the order the model reports them")
    last = scene_stages[-1]
    wanted = set(named) | ({last} if any(obs.stage is None for obs in observations) else set())
    return [s for s in scene_stages if s in wanted], last
