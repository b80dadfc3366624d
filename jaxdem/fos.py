"""Factor of safety by strength reduction (``jaxdem fos``).

The strengths are divided by a trial factor F,

    tan(phi_F) = tan(phi) / F,    c_F = c / F,

for every joint (the default joint included: it shares its set's row) and,
with ``intact=True``, for the intact rock of every material. The factor of
safety is the largest F at which the scene still finds equilibrium (Dawson,
Roth & Drescher 1999, "Slope stability factors of safety by strength
reduction", Geotechnique 49(6); the method of UDEC and RS2). Tensile strength
is left as it is unless ``tensile=True`` divides it by F too: the SPEC reduces
tan(phi) and cohesion, and a joint's tension cut-off rarely governs a
sliding or falling mechanism.

Every trial factor is a full solve of the scene from its initial state, and
the trials of a round are solved together (:func:`jaxdem.batch.solve_batch`:
one compiled, vmapped increment for the whole round). Round 1 spreads
``trials`` factors geometrically over the starting bracket, with F = 1 among
them when it lies inside (the scene as given: stable or not). Each later round
puts ``trials`` factors inside the bracket [largest stable F below the smallest
unstable F, that unstable F], which cuts its width by about ``trials + 1``, until
(hi - lo) / lo <= ``rtol``. From the default bracket (0.25, 8) with 8 trials
that is 4 rounds for rtol = 0.5%. When every trial is stable the bracket
grows upwards, when every trial fails downwards, within ``limits``; beyond
them the answer is "F > limit" or "F < limit".

Outcomes that are neither equilibrium nor a mechanism (iteration limit,
non-finite values) are counted as unstable, which can only lower F, and are
reported: when the unstable end of the final bracket is such a trial, F's
upper bound is a numerical failure, not a proven mechanism
(:attr:`FactorOfSafety.decided` is False). A stable factor above an unstable
one (the outcome is not monotone in F) is reported too, never smoothed over.

Example::

    scene = jaxdem.load_scene("examples/block_on_incline.toml")
    fos = jaxdem.factor_of_safety(scene)
    print(fos.factor_of_safety, fos.bracket, fos.message)
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxdem.config import float64
from jaxdem.results import SMALL_MECHANISM, jsonable, write_json
from jaxdem.scene import SceneError

#: Outcome labels of a trial (from :class:`jaxdem.core.status.Status`).
STABLE, MECHANISM = "converged", "mechanism"
#: Statuses of a factor-of-safety search.
CONVERGED = "converged"          # bracket narrowed to rtol
ROUND_LIMIT = "round_limit"      # max_rounds reached first: the bracket is the answer
ABOVE_LIMIT = "above_limit"      # stable at every factor up to limits[1]
BELOW_LIMIT = "below_limit"      # unstable at every factor down to limits[0]


@dataclasses.dataclass
class FactorOfSafety:
    """Outcome of a strength-reduction search.

    Attributes:
      factor_of_safety: the largest factor found stable (-), the conservative
        end of ``bracket``; None when no factor tried was stable.
      bracket: [stable F, unstable F]: the factor of safety lies between. The
        upper end is None when every factor up to ``limits[1]`` was stable.
      status: ``"converged"`` (bracket within ``rtol``), ``"round_limit"``,
        ``"above_limit"`` or ``"below_limit"``.
      message: one paragraph for a rock engineer: F, its bracket, warnings.
      rounds: per batched solve: ``round``, ``factors`` (ascending),
        ``outcomes`` (solver status label of each trial: "converged" = stable,
        "mechanism", "iteration_limit", "non_finite", ...) and ``bracket``
        after the round.
      solves: trial solves in all (rounds x trials).
      reduced: parameter path -> its value in the scene (file units), the
        strengths divided by F.
      undecided: factors whose trial neither converged nor found a mechanism
        (counted as unstable).
      non_monotone: stable factors above the smallest unstable factor.
      at_factor_1: outcome of the scene as given (F = 1) when it was tried.
      options: intact, tensile, trials, rtol, start bracket, limits, max_rounds.
      timing: build_s, compile_s, solve_s (summed over rounds), total_s (s).
      mechanism: filled in by :func:`write_outputs`: the single solve at the
        unstable end of the bracket (factor, status, moving blocks, figure, message; a
        ``note`` where it found no mechanism, or a small one).
    """

    factor_of_safety: float | None
    bracket: list
    status: str
    message: str
    rounds: list[dict]
    solves: int
    reduced: dict[str, float]
    undecided: list[float]
    non_monotone: list[float]
    at_factor_1: str | None
    options: dict[str, Any]
    timing: dict[str, float]
    mechanism: dict[str, Any] | None = None

    @property
    def decided(self) -> bool:
        """True unless the unstable end of the bracket is a trial that neither converged
        nor found a mechanism (then F's upper bound is a numerical failure)."""
        hi = self.bracket[1]
        return hi is None or hi not in self.undecided

    def to_dict(self) -> dict[str, Any]:
        """The content of ``fos.json``: plain JSON types only."""
        return jsonable(finite=True, x=dict(
            factor_of_safety=self.factor_of_safety, bracket=list(self.bracket),
            status=self.status, decided=self.decided, message=self.message,
            at_factor_1=self.at_factor_1, reduced=self.reduced, options=self.options,
            rounds=self.rounds, n_rounds=len(self.rounds), solves=self.solves,
            undecided=self.undecided, non_monotone=self.non_monotone,
            mechanism=self.mechanism, timing=self.timing))


def strength_parameters(scene, *, intact: bool = False, tensile: bool = False) -> dict[str, float]:
    """The strength parameters that strength reduction divides: path -> value (file units).

    Joint friction_deg and cohesion of every joint (zero values left out: there
    is nothing to divide); with ``intact`` the same for every material; with
    ``tensile`` their tensile_strength too.
    """
    fields = ("friction_deg", "cohesion") + (("tensile_strength",) if tensile else ())
    out: dict[str, float] = {}
    tables = [("joints", scene.joints)] + ([("materials", scene.materials)] if intact else [])
    for section, table in tables:
        for name, item in table.items():
            for field in fields:
                value = float(getattr(item, field))
                if value > 0.0:
                    out[f"{section}.{name}.{field}"] = value
    return out


def reduce_strength(path: str, value: float, factor: float) -> float:
    """The value of strength parameter ``path`` divided by ``factor``: friction angles
    (deg) by tan(phi_F) = tan(phi) / F, cohesion and tensile strength (kPa) by c / F."""
    if path.endswith("friction_deg"):
        return math.degrees(math.atan(math.tan(math.radians(value)) / factor))
    return value / factor


def strength_overrides(scene, factor: float, *, intact: bool = False,
                       tensile: bool = False) -> dict[str, float]:
    """``--set`` overrides that divide the scene's strengths by ``factor``.

    Example::

        result = jaxdem.solve(scene, set=strength_overrides(scene, 1.5))
    """
    return {p: reduce_strength(p, v, factor)
            for p, v in strength_parameters(scene, intact=intact, tensile=tensile).items()}


@float64
def factor_of_safety(scene, *, intact: bool = False, tensile: bool = False, trials: int = 8,
                     rtol: float = 0.005, bracket: tuple[float, float] = (0.25, 8.0),
                     limits: tuple[float, float] = (0.01, 100.0), max_rounds: int = 8,
                     chunk: int | None = None, devices=None,
                     progress: Callable[[dict], None] | None = None) -> FactorOfSafety:
    """Factor of safety of ``scene`` by strength reduction, bracketed by batched solves.

    Args:
      scene: a validated scene (:func:`jaxdem.load_scene`).
      intact: also reduce the intact rock's friction and cohesion (materials).
      tensile: also divide tensile strengths by F (default: left as they are).
      trials: factors solved together per round (>= 2).
      rtol: stop when (unstable F - stable F) / stable F <= rtol.
      bracket: (low, high) factors of the first round, 0 < low < high.
      limits: (lowest, highest) factor the bracket may grow to.
      max_rounds: most batched solves.
      chunk, devices: see :func:`jaxdem.batch.solve_batch`.
      progress: optional callable, called after each round with its record
        (``round``, ``factors``, ``outcomes``, ``bracket``).
    Returns:
      a :class:`FactorOfSafety`.

    Raises:
      SceneError: a bad option, or a scene with no strength to reduce.

    Example::

        fos = jaxdem.factor_of_safety(jaxdem.load_scene("examples/block_on_incline.toml"))
        fos.factor_of_safety, fos.bracket    # 1.238, [1.238, 1.239]: tan 30 / tan 25 = 1.2381
    """
    from jaxdem.batch import solve_batch

    _check_options(trials, rtol, bracket, limits, max_rounds)
    base = strength_parameters(scene, intact=intact, tensile=tensile)
    if not base:
        where = "joints (and materials)" if intact else "joints"
        raise SceneError(where, "no strength to reduce: every friction_deg and cohesion is 0")
    paths = list(base)
    t0 = time.perf_counter()
    outcome: dict[float, str] = {}
    rounds: list[dict] = []
    timing = dict(build_s=0.0, compile_s=0.0, solve_s=0.0)
    lo0, hi0 = float(bracket[0]), float(bracket[1])
    factors = _first_round(lo0, hi0, trials)
    status = ROUND_LIMIT
    lo = hi = None
    for k in range(1, max_rounds + 1):
        theta = np.array([[reduce_strength(p, base[p], f) for p in paths] for f in factors])
        b = solve_batch(scene, paths, theta, chunk=chunk, devices=devices)
        for key in timing:
            timing[key] += float(b.timing.get(key, 0.0))
        outcome.update({float(f): s for f, s in zip(factors, b.status, strict=True)})
        lo, hi = _bracket(outcome)
        rounds.append(dict(round=k, factors=[float(f) for f in factors], outcomes=list(b.status),
                           bracket=[lo, hi]))
        if progress is not None:
            progress(rounds[-1])
        tried = sorted(outcome)
        if hi is None:                      # every factor stable: grow upwards
            if tried[-1] >= limits[1]:
                status = ABOVE_LIMIT
                break
            top = min(tried[-1] * hi0 / lo0, limits[1])
            factors = _geometric(tried[-1], top, trials + 1)[1:]
        elif lo is None:                    # every factor unstable: grow downwards
            if tried[0] <= limits[0]:
                status = BELOW_LIMIT
                break
            bottom = max(tried[0] * lo0 / hi0, limits[0])
            factors = _geometric(bottom, tried[0], trials + 1)[:-1]
        elif (hi - lo) / lo <= rtol:
            status = CONVERGED
            break
        else:
            factors = _geometric(lo, hi, trials + 2)[1:-1]
    undecided = sorted(f for f, s in outcome.items() if s not in (STABLE, MECHANISM))
    non_monotone = ([] if hi is None else
                    sorted(f for f, s in outcome.items() if s == STABLE and f > hi))
    timing["total_s"] = time.perf_counter() - t0
    options = dict(intact=intact, tensile=tensile, trials=trials, rtol=rtol,
                   bracket=[lo0, hi0], limits=list(limits), max_rounds=max_rounds)
    result = FactorOfSafety(
        factor_of_safety=lo, bracket=[lo, hi], status=status, message="", rounds=rounds,
        solves=sum(len(r["factors"]) for r in rounds), reduced=dict(base), undecided=undecided,
        non_monotone=non_monotone, at_factor_1=outcome.get(1.0), options=options,
        timing=timing)
    result.message = _message(result, outcome)
    return result


def solve_at(scene, factor: float, *, intact: bool = False, tensile: bool = False,
             progress=None):
    """One ordinary solve of ``scene`` with its strengths divided by ``factor``
    (a :class:`jaxdem.results.Result`): the mechanism or the state at that factor."""
    from jaxdem.solver import solve

    return solve(scene, set=strength_overrides(scene, factor, intact=intact, tensile=tensile),
                 progress=progress)


def write_outputs(fos: FactorOfSafety, scene, out_dir: str | Path) -> list[Path]:
    """Draw the mechanism and the trials, and write ``fos.json``.

    Solves the scene once at the unstable end of the bracket (the first
    factor found unstable above F) and draws it to ``mechanism.png``
    (:func:`jaxdem.plots.plot_blocks`: moving blocks in red, contacts by
    state, displacements); ``fos.png`` shows every trial factor by round and
    outcome. The mechanism solve is recorded in ``fos.mechanism``.

    Returns:
      the paths written: fos.json, mechanism.png (when there is an unstable
      factor), fos.png.
    """
    from jaxdem.plots import plot_blocks

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    hi = fos.bracket[1]
    if hi is not None:
        o = fos.options
        result = solve_at(scene, hi, intact=o["intact"], tensile=o["tensile"])
        title = f"{result.scene}, strengths / {hi:.4g}"
        figure = plot_blocks(dataclasses.replace(result, scene=title), out / "mechanism.png")
        fos.mechanism = dict(factor=hi, status=result.status, stable=result.stable,
                             moving_blocks=list(result.moving_blocks), figure=figure.name,
                             message=result.message)
        if result.converged:
            fos.mechanism["note"] = ("the single solve at this factor found equilibrium "
                                     "although the batched trial did not: the figure shows "
                                     "that equilibrium")
        elif result.stable:
            fos.mechanism["note"] = (f"the single solve at this factor ended as "
                                     f"{result.status}, not a mechanism: the figure shows "
                                     "where it stopped")
        else:
            # A mechanism of small pieces (a sliver of a mesh at an opening) sets F as any
            # mechanism does: say so (jaxdem.results.small_mechanism).
            small = [w for w in result.warnings if w.startswith(SMALL_MECHANISM)]
            if small:
                fos.mechanism["note"] = small[0]
        written.append(figure)
    written.insert(0, write_json(fos.to_dict(), out / "fos.json"))
    written.append(plot_trials(fos, out / "fos.png"))
    return written


def plot_trials(fos: FactorOfSafety, path: str | Path) -> Path:
    """How the answer was found: one panel per round, zoomed to that round's trial
    factors, each marked by outcome, with the bracket after the round shaded."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FormatStrFormatter

    from jaxdem.plots import save_figure

    n = max(len(fos.rounds), 1)
    fig = Figure(figsize=(8, 0.5 + 1.1 * n))
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, squeeze=False)[:, 0]
    style = {STABLE: ("o", "tab:green", "stable"), MECHANISM: ("x", "tab:red", "mechanism")}
    seen: set = set()
    for ax, r in zip(axes, fos.rounds, strict=False):
        f = np.asarray(r["factors"])
        for x, s in zip(f, r["outcomes"], strict=True):
            marker, colour, label = style.get(s, ("s", "tab:orange", "undecided (as unstable)"))
            ax.scatter([x], [0.0], marker=marker, color=colour, s=40, zorder=3,
                       label=None if label in seen else label)
            seen.add(label)
        lo, hi = r["bracket"]
        if lo is not None and hi is not None:
            ax.axvspan(lo, hi, color="0.85", zorder=1,
                       label=None if "bracket" in seen else "bracket after the round")
            seen.add("bracket")
        if r["round"] == 1 or f.max() / f.min() > 3:
            ax.set_xscale("log")
        pad = 0.06 * (f.max() - f.min())
        ax.set_xlim(f.min() - pad if ax.get_xscale() == "linear" else f.min() / 1.1,
                    f.max() + pad if ax.get_xscale() == "linear" else f.max() * 1.1)
        if ax.get_xscale() == "log":
            ax.set_xticks(f)            # a log axis of a few decades: label the trials
        ax.xaxis.set_major_formatter(FormatStrFormatter("%.4g"))
        ax.xaxis.set_minor_formatter(FormatStrFormatter(""))
        ax.set_yticks([])
        ax.set_ylabel(f"round {r['round']}", rotation=0, ha="right", va="center")
    axes[-1].set_xlabel("strength reduction factor F (tan phi / F, c / F)")
    F = fos.factor_of_safety
    axes[0].set_title("factor of safety " + (f"{F:.4g}" if F is not None else "not found")
                      + f" ({fos.status}, {len(fos.rounds)} rounds, {fos.solves} trial solves)")
    fig.legend(loc="upper left", bbox_to_anchor=(0.91, 0.95), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 0.9, 1))
    return save_figure(fig, path)


# ---------------------------------------------------------------------------
# Host helpers


def _check_options(trials, rtol, bracket, limits, max_rounds) -> None:
    if isinstance(trials, bool) or not isinstance(trials, (int, np.integer)) or trials < 2:
        raise SceneError("trials", f"must be an integer >= 2 (got {trials!r})")
    if not (isinstance(rtol, (int, float)) and math.isfinite(rtol) and rtol > 0):
        raise SceneError("tolerance", f"must be a number > 0 (got {rtol!r})")
    for name, pair in (("bracket", bracket), ("limits", limits)):
        ok = (len(pair) == 2 and all(isinstance(x, (int, float)) and math.isfinite(x)
                                     for x in pair) and 0 < pair[0] < pair[1])
        if not ok:
            raise SceneError(name, f"must be (low, high) with 0 < low < high (got {pair!r})")
    if not limits[0] <= bracket[0] < bracket[1] <= limits[1]:
        raise SceneError("bracket", f"{tuple(bracket)} must lie within limits {tuple(limits)}")
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, (int, np.integer)) \
            or max_rounds < 1:
        raise SceneError("max_rounds", f"must be an integer >= 1 (got {max_rounds!r})")


def _geometric(lo: float, hi: float, n: int) -> np.ndarray:
    """n factors from lo to hi (both included, exactly), evenly spaced in log F."""
    f = np.exp(np.linspace(math.log(lo), math.log(hi), n))
    f[0], f[-1] = lo, hi
    return f


def _first_round(lo: float, hi: float, trials: int) -> np.ndarray:
    """``trials`` factors over [lo, hi]; the one nearest F = 1 moved to 1 when 1 is inside."""
    f = _geometric(lo, hi, trials)
    if lo < 1.0 < hi:
        f[np.argmin(np.abs(np.log(f)))] = 1.0
    return f


def _bracket(outcome: dict[float, str]) -> tuple[float | None, float | None]:
    """[largest stable F below the smallest unstable F, that unstable F]; a trial that is
    not stable (mechanism or undecided) counts as unstable."""
    unstable = [f for f, s in outcome.items() if s != STABLE]
    hi = min(unstable) if unstable else None
    stable = [f for f, s in outcome.items() if s == STABLE and (hi is None or f < hi)]
    return (max(stable) if stable else None), hi


def _message(r: FactorOfSafety, outcome: dict[float, str]) -> str:
    o = r.options
    what = "joint tan(phi) and cohesion" + (" and intact rock's" if o["intact"] else "")
    if o["tensile"]:
        what += " (tensile strength too)"
    lo, hi = r.bracket
    n = f"{len(r.rounds)} rounds of {o['trials']} batched trials"
    if r.status == ABOVE_LIMIT:
        text = (f"Stable at every factor tried, up to F = {lo:.4g} ({what} divided by F): "
                f"F > {lo:.4g} ({n}).")
    elif r.status == BELOW_LIMIT:
        text = (f"Unstable at every factor tried, down to F = {hi:.4g}: F < {hi:.4g}; the "
                f"mechanism hardly depends on the {what} ({n}).")
    else:
        text = (f"Factor of safety F = {lo:.4g}: stable with {what} divided by {lo:.4g}, "
                f"unstable at {hi:.4g} ({n}).")
        if r.status == ROUND_LIMIT:
            text += (f" The bracket is wider than rtol = {o['rtol']:g} after max_rounds = "
                     f"{o['max_rounds']}.")
    if r.at_factor_1 is not None:
        text += (" The scene as given (F = 1) is "
                 + ("stable." if r.at_factor_1 == STABLE else f"not stable ({r.at_factor_1})."))
    # Undecided trials above the bracket lie beyond failure and do not move F;
    # at or below its unstable end they set (or could have set) the bracket.
    above = [f for f in r.undecided if hi is not None and f > hi]
    within = [f for f in r.undecided if f not in above]
    if within:
        listed = ", ".join(f"{f:.4g} ({outcome[f]})" for f in within[:6])
        text += (f" WARNING: {len(within)} trial(s) at or below the bracket neither "
                 f"converged nor found a mechanism (F = {listed}); they are counted as "
                 f"unstable, which can only lower F.")
        if not r.decided:
            text += (f" The unstable end of the bracket, {hi:.4g}, is such a trial, not a "
                     f"proven mechanism: F may be higher (try more solver.max_iterations "
                     f"or load_steps).")
    if above:
        text += (f" {len(above)} trial(s) above the bracket (beyond failure) stopped at "
                 f"{outcome[above[0]]} rather than a mechanism; they do not change F.")
    if r.non_monotone:
        listed = ", ".join(f"{f:.4g}" for f in r.non_monotone[:6])
        text += (f" WARNING: not monotone in F: stable at F = {listed} above the smallest "
                 f"unstable factor {hi:.4g} ({outcome[hi]}); F is the bracket below it.")
    return text


__all__ = ["FactorOfSafety", "factor_of_safety", "plot_trials", "reduce_strength", "solve_at",
           "strength_overrides", "strength_parameters", "write_outputs"]
