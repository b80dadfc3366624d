"""The loose blocks of a solve on a block figure: where each block that fell free and was
removed (``Result.loose_blocks``, README "Loose blocks") was before it fell, shaded and
cross-hatched, with its id.

Used by ``blocks.png`` (:mod:`jaxdem.plots._model`); draws with matplotlib collections.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.patches import Patch

LOOSE_COLOUR = "#e8a33d"  # amber: removed, not excavated


def draw_loose_blocks(ax: Any, initial: list[np.ndarray], loose: list[dict], lw: float) -> list:
    """Initial outlines of the ``loose`` blocks (dicts with ``id``), hatched; returns the
    legend handle ("loose, removed (n)"), or none when no block was removed."""
    ids = [int(b["id"]) for b in loose if 0 <= int(b["id"]) < len(initial)]
    if not ids:
        return []
    ax.add_collection(PolyCollection(
        [initial[i] for i in ids], closed=True, facecolors=LOOSE_COLOUR, alpha=0.35,
        edgecolors=LOOSE_COLOUR, hatch="xxx", linewidths=max(lw, 0.6), zorder=1.5))
    for i in ids:
        c = np.asarray(initial[i], float).mean(axis=0)
        ax.annotate(str(i), c, fontsize=6, color="#8a5a12", ha="center", va="center",
                    zorder=5)
    return [Patch(facecolor=LOOSE_COLOUR, alpha=0.35, edgecolor=LOOSE_COLOUR, hatch="xxx",
                  label=f"loose, removed ({len(ids)})")]
