"""Progress on stderr while the command line solves: :class:`ProgressBar` over stages and
load increments (``jaxdem run``, ``demo``), :class:`SampleBar` over the samples of a sweep.

Each is a context manager and a callable that the solver (or the sweep) calls with one
event per increment (sample); on a terminal one line is redrawn in place, elsewhere one
line is printed per event. Plain Python, no JAX: imported by :mod:`jaxdem.cli._commands`.
"""

from __future__ import annotations

import sys
from contextlib import AbstractContextManager
from typing import Any, TextIO


class SampleBar(AbstractContextManager):
    """Progress over the samples of a sweep, on stderr: ``samples [####------] 256/1024``."""

    def __init__(self, stream: TextIO | None = None, width: int = 20):
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.tty = self.stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        filled = int(self.width * done / max(total, 1))
        line = f"samples [{'#' * filled}{'-' * (self.width - filled)}] {done}/{total}"
        self.stream.write(("\r" + line) if self.tty else line + "\n")
        self.stream.flush()

    def __exit__(self, *exc: object) -> None:
        if self.tty:
            self.stream.write("\n")


# The solver's names of the initial state's increments, as the progress line shows them.
_INITIAL_NAMES = {"initial": "in-situ", "loading": "loading"}


class ProgressBar(AbstractContextManager):
    """Text progress over stages and load increments, on stderr.

    Called by the solver once per increment with a dict: ``stage`` (name),
    ``step`` (1-based), ``n_steps``, ``status``, ``cut`` (tried again with half the
    load step: :func:`jaxdem.solver.ramp`), ``iterations``, ``substeps``,
    ``residual``, ``stage_index`` and ``n_stages``. Stages are counted as the scene file
    counts them: ``stage = 2`` (the second ``[[stages]]``) is "stage 2/N", N the
    number of stages; the initial state before them (the loading, or the in-situ
    state) is named, not counted. On a terminal one line is redrawn in place::

        initial state (in-situ) [##########] step 1/1  it 3  res 2.0e-12
        stage 1/2 excavate [###-------] step 3/10  it 12  res 3.1e-11

    elsewhere (a log file, CI) one line is printed per increment. An event without
    ``stage_index`` counts each new stage name as the next stage, of ``n_stages``.
    """

    def __init__(self, n_stages: int = 0, stream: TextIO | None = None, width: int = 20):
        self.stream = sys.stderr if stream is None else stream
        self.n_stages = n_stages
        self.width = width
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._stages: list[str] = []
        self._open_line = False

    def __call__(self, event: dict[str, Any]) -> None:
        line = self.format(event)
        if self.tty:
            self.stream.write("\r\033[K" + line)
            self._open_line = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def format(self, event: dict[str, Any]) -> str:
        stage = str(event.get("stage", ""))
        step = int(event.get("step", 0))
        n_steps = max(int(event.get("n_steps", 0)), 1)
        filled = min(self.width, round(self.width * step / n_steps))
        bar = "#" * filled + "-" * (self.width - filled)
        parts = [self._where(stage, event)]
        parts.append(f"[{bar}] step {step}/{n_steps}")
        text = " ".join(parts)
        text += f"  it {int(event.get('iterations', 0))}"
        substeps = int(event.get("substeps", 1) or 1)
        if substeps > 1:
            text += f"  sub {substeps}"
        residual = event.get("residual")
        if residual is not None:
            text += f"  res {float(residual):.1e}"
        status = str(event.get("status", ""))
        if status and status != "converged":
            text += f"  {status}"
        if event.get("cut"):
            text += ": the load step cut in two"
        return text

    def _where(self, stage: str, event: dict[str, Any]) -> str:
        """'initial state (loading)', 'initial state (in-situ)' or 'stage k/N name'."""
        if "stage_index" in event:
            index = int(event["stage_index"])
            total = int(event.get("n_stages", self.n_stages))
            if index == 0:
                return f"initial state ({_INITIAL_NAMES.get(stage, stage)})"
        else:
            if not self._stages or self._stages[-1] != stage:
                self._stages.append(stage)
            index = len(self._stages)
            total = max(self.n_stages, index)
        return f"stage {index}/{total}" + (f" {stage}" if stage else "")

    def __exit__(self, *exc: object) -> None:
        if self._open_line:
            self.stream.write("\n")
            self.stream.flush()
            self._open_line = False
