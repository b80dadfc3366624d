"""How an increment ended: the status enumeration and the tolerances of an admissible answer.

Owns :class:`Status` (with its message to the user), the admissibility
tolerances :data:`OVERLAP_TOL`, :data:`STRENGTH_TOL`, :data:`IMBALANCE_FACTOR`,
the slip warning threshold :data:`LARGE_SLIP`, and the global imbalance measure
(:func:`global_imbalance` on the host, :func:`global_imbalance_jax` inside jit).

Data flow: the bottom of the solver; it imports nothing from jaxdem. The
increment (:mod:`jaxdem.core.increment`) sets a status from these tolerances, the
host driver (:mod:`jaxdem.solver`) reads it, and :mod:`jaxdem.results` reports
it (the contact states OPEN, STICK, SLIP live lower still, in
:mod:`jaxdem.core.state`).
"""

from __future__ import annotations

import enum

import jax.numpy as jnp
import numpy as np

# Admissibility of a converged increment (result.json "admissibility"): what
# "converged" requires besides each block's residual below the tolerance.
OVERLAP_TOL = 0.1
"""Largest overlap of two blocks at a contact, relative to the smaller one's size
(its largest centroid-to-vertex distance). A joint spring's compression is its
force over kn, a joint's closure: a few mm under some MPa, which on the small
blocks of a generated rock mass (0.1-0.2 m) is a few percent of their size (the
bundled demo reaches 2.2%). Ten percent is far beyond any closure and well below
a block sunk into its neighbour (the jammed key block of issue 16 was 16%)."""
STRENGTH_TOL = 1e-3
"""Largest excess of a contact's forces over its strength (shear beyond
c share + fn tan(phi), tension beyond the cut-off), relative to the force scale
of its blocks (the scale of the equilibrium test)."""
IMBALANCE_FACTOR = 100.0
"""Largest global imbalance |applied + reactions| of the free blocks, relative to
the forces in play (:func:`global_imbalance`), in units of ``solver.tolerance`` (each
block balances to the tolerance; their sum to about ten times it, tests/test_properties.py):
1e-4 at the default tolerance."""


LARGE_SLIP = 0.05
"""Joint slip in one increment, relative to the smaller block's size, above which the
command line warns ("stable, but joint slip of ... at blocks ...: review"): a block
that slid 5% of its size has moved far for an elastic answer, though it came to rest."""


class Status(str, enum.Enum):
    """Outcome of an increment or a solve, with the message shown to the user.

    A ``str`` enumeration: each member equals its label (``Status.CONVERGED ==
    "converged"``), which is what ``result.json`` and the command line print. Inside jit
    the increment carries the integer :attr:`code` (the order below);
    :meth:`of` turns it back into the member. The members:

    - ``converged``: static equilibrium, admissible;
    - ``mechanism``: blocks kept moving beyond ``solver.max_displacement`` (where the
      scene leaves it out, each block's own size) (an answer);
    - ``iteration_limit``: ``solver.max_iterations`` reached before equilibrium;
    - ``capacity_overflow``: the contact list overflowed (the driver grows it and repeats);
    - ``non_finite``: NaN or infinity appeared;
    - ``overlap``, ``law_violation``, ``imbalance``: balance was found, but not an
      admissible state (blocks overlap, a contact exceeds its strength, or the blocks do
      not balance the loads as a whole).
    """

    CONVERGED = "converged"
    MECHANISM = "mechanism"
    ITERATION_LIMIT = "iteration_limit"
    CAPACITY_OVERFLOW = "capacity_overflow"
    NON_FINITE = "non_finite"
    OVERLAP = "overlap"
    LAW_VIOLATION = "law_violation"
    IMBALANCE = "imbalance"

    def __str__(self) -> str:
        return self.value

    @property
    def code(self) -> int:
        """The integer the device carries (0 converged, 1 mechanism, ...: the order above)."""
        return list(Status).index(self)

    @classmethod
    def of(cls, code) -> Status:
        """The member of an integer :attr:`code` (a Python, NumPy or 0-d JAX integer)."""
        return list(cls)[int(code)]

    @property
    def message(self) -> str:
        return {
            Status.CONVERGED: "Static equilibrium found.",
            Status.MECHANISM: "No equilibrium: blocks kept moving beyond max_displacement "
            "or their own size (a group's, where they move together) (a mechanism). The named "
            "blocks fall, slide or topple.",
            Status.ITERATION_LIMIT: "The iteration limit was reached before equilibrium. "
            "Try increasing solver.max_iterations or solver.load_steps.",
            Status.CAPACITY_OVERFLOW: "The contact list overflowed its capacity.",
            Status.NON_FINITE: "The solution became non-finite (NaN or infinity).",
            Status.OVERLAP: "Balance was found, but with blocks overlapping by more than "
            f"{OVERLAP_TOL:.0%} of the adjacent block's size: not an admissible state.",
            Status.LAW_VIOLATION: "Balance was found, but a contact carries more than its "
            "strength allows (Mohr-Coulomb or tension cut-off): not an admissible state.",
            Status.IMBALANCE: "The blocks do not balance the loads as a whole (global "
            f"imbalance over {IMBALANCE_FACTOR:g} x solver.tolerance): not an admissible state.",
        }[self]

    @property
    def label(self) -> str:
        """The member's label, ``"converged"`` (its value)."""
        return self.value


def global_imbalance_jax(balance):
    """:func:`global_imbalance` on the device (a traced scalar)."""
    f = balance.applied[:2] + balance.reaction[:2]
    return jnp.linalg.norm(f) / jnp.maximum(balance.scale, jnp.finfo(f.dtype).tiny)


def global_imbalance(balance) -> float:
    """Global force balance of the free blocks, relative.

    |applied + reaction| over the larger of the summed magnitudes of the
    block loads and of the reactions (forces from fixed blocks, walls and
    their bolts), so that it stays meaningful when the loads cancel out (an
    in-situ state held by walls on all sides), and of the largest spring
    force carried (no load and no net reaction: a self-balanced in-situ
    stress; see :func:`jaxdem.core._substep.commit_substep`).
    """
    applied = np.asarray(balance.applied)[:2]  # sliced on the host: no program to compile
    reaction = np.asarray(balance.reaction)[:2]
    return float(np.linalg.norm(applied + reaction) / max(float(balance.scale), 1e-300))
