"""The figure of a parameter sweep: ``tornado.png`` (:func:`plot_tornado`), how far each
monitor moves when one parameter goes from its low to its high point.

:attr:`jaxdem.sweep.SweepResult.tornado` comes in, one PNG goes out, drawn on the canvas
of :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from jaxdem.plots._canvas import save_figure


def plot_tornado(tornado: dict[str, list[dict[str, Any]]], path: str | Path) -> Path:
    """Tornado plot of a sweep: for each monitor, how far it moves when one parameter
    goes from its low to its high point with the others at their base.

    One panel per monitor (mm: a section's convergence, a point's |u|); one bar
    per parameter, largest swing on top, from the value at the parameter's low
    point (blue) to that at its high point (orange), about the base value (line).
    A bar whose end is a mechanism (no equilibrium) is marked "unstable".

    Args:
      tornado: :attr:`jaxdem.sweep.SweepResult.tornado`.
      path: PNG file to write.
    """
    names = list(tornado)
    rows = max((len(b) for b in tornado.values()), default=1)
    fig = Figure(figsize=(6.5 * len(names), 0.6 * rows + 1.6))
    FigureCanvasAgg(fig)
    for k, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), k + 1)
        bars = tornado[name][::-1]
        base = 1e3 * bars[0]["at_base"] if bars else 0.0
        for i, bar in enumerate(bars):
            for end, color in (("at_low", "C0"), ("at_high", "C1")):
                value = 1e3 * bar[end]
                if math.isfinite(value) and math.isfinite(base):
                    ax.barh(i, value - base, left=base, color=color, height=0.6)
                else:
                    ax.text(base, i, f" unstable ({end[3:]})", va="center", fontsize=8)
        ax.axvline(base, color="k", lw=1)
        ax.set_yticks(range(len(bars)))
        ax.set_yticklabels([f"{b['path']}\n{b['low']:.4g} to {b['high']:.4g}" for b in bars],
                           fontsize=8)
        ax.set_xlabel(f"{name}: convergence or |u| (mm)")
        ax.set_title(name)
    fig.legend(handles=[Patch(color="C0", label="parameter at its low point"),
                        Patch(color="C1", label="parameter at its high point")],
               loc="lower center", ncol=2, fontsize=8, bbox_to_anchor=(0.5, -0.02))
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return save_figure(fig, path)
