"""Figures of a solved model (``blocks.png``, ``monitors.png``, ``stresses.png``,
``sections.png``) and of a scene (``check.png``).

Host code only: NumPy and matplotlib's object interface with the Agg renderer
(no display, and pyplot's global state is left alone, so importing this module
does not change a notebook's backend). Every function writes one PNG, releases
its figure and returns the path. Collections
(``PolyCollection``, ``LineCollection``, ``scatter``, ``quiver``) carry all the
blocks and contacts of a layer in one artist, so a model of 10,000 blocks
draws in seconds.

Example::

    from jaxdem import load_scene, solve
    from jaxdem.plots import write_figures
    result = solve(load_scene("tunnel.toml"))
    write_figures(result, "out/tunnel")   # [out/tunnel/blocks.png, out/tunnel/monitors.png, ...]

Where the figures are drawn (this module is the public face and writes the figures of a
solve; each module imports only those above it):

- :mod:`jaxdem.plots._canvas`: figure, save, axes, label placement, round scales;
- :mod:`jaxdem.plots._layers`: outlines, contacts, arrows, bolts, monitors, water table;
- :mod:`jaxdem.plots._loose`: the loose blocks removed, on ``blocks.png``;
- :mod:`jaxdem.plots._model`: ``blocks.png``, ``stresses.png``;
- :mod:`jaxdem.plots._monitors`: ``monitors.png``, ``sections.png``;
- :mod:`jaxdem.plots._scene`: ``check.png``;
- :mod:`jaxdem.plots._sweep`: ``tornado.png``;
- :mod:`jaxdem.plots._grc`: ``grc.png`` (ground reaction curve).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from jaxdem.plots._canvas import (
    DPI,
    format_length,
    nice_ceil,
    nice_magnification,
    save_figure,
    warm_up,
)
from jaxdem.plots._grc import plot_ground_reaction
from jaxdem.plots._model import (
    plot_blocks,
    plot_principal_stresses,
    principal_stresses,
    stress_crosses,
)
from jaxdem.plots._monitors import plot_monitor_history, plot_sections, stage_axis
from jaxdem.plots._scene import plot_scene_check
from jaxdem.plots._sweep import plot_tornado
from jaxdem.results import Result

__all__ = [
    "DPI",
    "format_length",
    "nice_ceil",
    "nice_magnification",
    "plot_blocks",
    "plot_ground_reaction",
    "plot_monitor_history",
    "plot_principal_stresses",
    "plot_scene_check",
    "plot_sections",
    "plot_tornado",
    "principal_stresses",
    "save_figure",
    "stage_axis",
    "stress_crosses",
    "warm_up",
    "write_figures",
]


def write_figures(result: Result, out_dir: str | Path, *,
                  view: Sequence[float] | None = None) -> list[Path]:
    """Write the figures of a solve to ``out_dir``.

    ``blocks.png`` always (with a second panel around the excavations, or on ``view`` =
    (x0, x1, y0, y1) m when given: :func:`plot_blocks`); ``monitors.png`` (monitor
    histories) and
    ``sections.png`` (monitors at the end of each stage) when there are
    monitors; ``stresses.png`` (principal-stress crosses) when a block
    carries a stress.

    Returns:
      The paths written, in the order blocks, monitors, stresses, sections.
    """
    out_dir = Path(out_dir)
    paths = [plot_blocks(result, out_dir / "blocks.png", view=view)]
    for plot, name in (
        (plot_monitor_history, "monitors.png"),
        (plot_principal_stresses, "stresses.png"),
        (plot_sections, "sections.png"),
    ):
        written = plot(result, out_dir / name)
        if written is not None:
            paths.append(written)
    return paths
