"""The figure of a ground reaction curve: ``grc.png`` (:func:`plot_ground_reaction`),
support pressure against convergence for each monitor, the support line and where a
mechanism appears.

The content of ``grc.json`` (:meth:`jaxdem.grc.GroundReaction.to_dict`) comes in, one PNG
goes out, drawn on the canvas of :mod:`jaxdem.plots._canvas`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from jaxdem.plots._canvas import new_figure, save_figure


def plot_ground_reaction(curve: dict[str, Any], path: str | Path) -> Path:
    """Ground reaction curve: support pressure (kPa) against convergence (mm).

    One line per monitor (a section's convergence, a point's displacement towards
    the opening), a point per level;
    the monitor that the support line uses is drawn thicker. Levels without
    equilibrium are left out; the first pressure with a mechanism is a dashed
    horizontal line, its moving blocks named. With a support line: p_s(u) =
    min(k (u - u0), p_max) and the equilibrium point with its factor of safety.

    Args:
      curve: the content of ``grc.json`` (:meth:`jaxdem.grc.GroundReaction.to_dict`).
      path: PNG file to write.
    """
    fig, ax = new_figure((9.5, 5.0))
    p = np.array(curve["pressure"], float)
    u_max = 0.0
    for k, (name, values) in enumerate(curve["monitors"].items()):
        u = 1e3 * np.array([np.nan if v is None else v for v in values], float)
        ok = np.isfinite(u)
        if ok.any():
            u_max = max(u_max, float(np.abs(u[ok]).max()))
        main = name == curve["monitor"]
        kind = "inward u" if name in curve.get("displacements", {}) else "convergence"
        ax.plot(u[ok], p[ok], marker="o", ms=3.5 if main else 2.5, lw=2.2 if main else 1.2,
                color=f"C{k}", label=f"{name} ({kind})")
    m = curve.get("mechanism")
    if m is not None:
        label = f"mechanism from {m['pressure']:.4g} kPa"
        blocks = m.get("moving_blocks") or []
        if blocks:
            shown = ", ".join(str(b) for b in blocks[:8]) + (", ..." if len(blocks) > 8 else "")
            label += f" (blocks {shown})"
        ax.axhline(m["pressure"], color="tab:red", ls="--", lw=1.6, label=label, zorder=4)
    line, eq = curve.get("support"), curve.get("equilibrium")
    if line is not None:
        k, cap, u0 = line["stiffness"], line["capacity"], line["installed_at"]
        top = u0 + cap / k
        right = max(u_max / 1e3, top) * 1.15
        us = np.array([u0, top, right]) if right > top else np.array([u0, top])
        ax.plot(1e3 * us, np.minimum(k * (us - u0), cap), color="k", lw=1.4,
                label=f"support: {k:.3g} kPa/m from {1e3 * u0:.3g} mm, capacity {cap:.4g} kPa")
        if eq is not None and eq.get("pressure") is not None:
            fos = eq.get("factor_of_safety")
            text = f"equilibrium {eq['pressure']:.4g} kPa, {1e3 * eq['convergence']:.3g} mm"
            text += f", FoS {fos:.3g}" if fos is not None else ""
            ax.plot([1e3 * eq["convergence"]], [eq["pressure"]], marker="*", ms=13,
                    color="gold", mec="k", ls="none", zorder=5, label=text)
    ax.axhline(curve["p0"], color="0.6", lw=0.8, ls=":", label=f"p0 = {curve['p0']:.4g} kPa")
    ax.set_xlabel("convergence (mm): a section's shortening, a point's inward displacement")
    ax.set_ylabel("support pressure (kPa)")
    # A little room below 0 kPa: a mechanism at 0 stays in view.
    ax.set_ylim(bottom=-0.03 * max(curve["p0"], float(np.max(p))))
    ax.set_xlim(left=min(0.0, ax.get_xlim()[0]))
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.set_title(f"ground reaction curve of {curve['excavation']!r} ({curve['scene']})",
                 fontsize=10)
    ax.legend(fontsize=7.5, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return save_figure(fig, path)
