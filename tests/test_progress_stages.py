"""The progress line (jaxdem.cli._progress.ProgressBar, on stderr) counts stages as the
scene file does: ``stage = 2`` (the second ``[[stages]]``) is "stage 2/N", N the number
of ``[[stages]]``; the initial state the solver adds before them (the loading, or the
in-situ state) is named "initial state", not counted as stage 1. The events are the
solver's own, from real solves, written to a captured stream."""

from __future__ import annotations

import io

from verification.test_bolts import key_block

import jaxdem
from jaxdem.cli._progress import ProgressBar
from jaxdem.scene import parse_scene


def _lines(d: dict) -> list[str]:
    d["materials"]["rock"]["unit_weight"] = 0.0  # every stage runs to its end
    stream = io.StringIO()  # not a terminal: one line per increment
    with ProgressBar(stream=stream) as bar:
        jaxdem.solve(parse_scene(d), progress=bar)
    return [line.split(" [")[0] for line in stream.getvalue().splitlines()]


def test_in_situ_state_then_the_file_stages_numbered_as_in_the_file():
    d = key_block([((0.0, 0.5), (0.0, 2.5))], in_situ=True,
                  stages=[{"name": "first", "load_steps": 2}, {"name": "second"}])
    d["bolts"][0]["stage"] = 2
    assert _lines(d) == ["initial state (in-situ)", "stage 1/2 first", "stage 1/2 first",
                         "stage 2/2 second"]


def test_loading_is_the_initial_state_and_a_scene_without_stages_has_none():
    d = key_block([((0.0, 0.5), (0.0, 2.5))], stages=[{"name": "only"}])
    d["solver"]["load_steps"] = 2
    assert _lines(d) == ["initial state (loading)"] * 2 + ["stage 1/1 only"] * 2
    del d["stages"]
    assert _lines(d) == ["initial state (loading)"] * 2


def test_the_stopping_stage_keeps_its_number():
    # The wedge falls in stage 1 (the bolt comes in stage 2): the last line is stage 1's,
    # with the mechanism, and stage 2 is never shown.
    d = key_block([((0.0, 0.5), (0.0, 2.5))], in_situ=True,
                  stages=[{"name": "first"}, {"name": "second"}])
    d["bolts"][0]["stage"] = "second"
    stream = io.StringIO()
    with ProgressBar(stream=stream) as bar:
        jaxdem.solve(parse_scene(d), progress=bar)
    lines = stream.getvalue().splitlines()
    assert lines[-1].startswith("stage 1/2 first [") and lines[-1].endswith("mechanism")
    assert not any("second" in line for line in lines)
