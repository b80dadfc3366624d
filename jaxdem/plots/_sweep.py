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

    One panel per monitor, two panels to a row, each about 6.5 x (1.6 + 0.5 per bar)
    inches; its axis names the monitor and its quantity ("crown |u| (mm)", "span
    convergence (mm)": the bars' ``quantity``). One bar per parameter, largest swing on
    top, from the value at the parameter's low point (blue) to that at its high point
    (orange), about the base value (line). A bar whose end is a mechanism (no
    equilibrium) is marked "unstable".

    Args:
      tornado: :attr:`jaxdem.sweep.SweepResult.tornado`.
      path: PNG file to write.
    """
    names = list(tornado)
    rows = max((len(b) for b in tornado.values()), default=1)
    ncols = min(len(names), 2) or 1
    nrows = math.ceil(len(names) / ncols) or 1
    panel = (6.5, 0.5 * rows + 1.6)
    fig = Figure(figsize=(panel[0] * ncols, panel[1] * nrows + 0.4), layout="constrained")
    FigureCanvasAgg(fig)
    for k, name in enumerate(names):
        ax = fig.add_subplot(nrows, ncols, k + 1)
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
        quantity = bars[0].get("quantity", "value") if bars else "value"
        ax.set_xlabel(f"{name} {quantity} (mm)")
        ax.set_title(f"{name}: {quantity} {base:.4g} mm at the base point", fontsize=10)
    fig.legend(handles=[Patch(color="C0", label="parameter at its low point"),
                        Patch(color="C1", label="parameter at its high point")],
               loc="outside lower center", ncol=2, fontsize=8)
    return save_figure(fig, path)
