"""Speed against error: solve time and error over mesh size, load steps, tolerance and dtype.

Three problems:

- **Kirsch** (``bench_kirsch.scene``, K = 1): a circular opening of radius a = 1 m in
  deformable constant-strain triangles of mesh size h at the opening. Error: the mean
  of the horizontal and vertical convergences against the closed form (Kirsch 1898;
  Jaeger, Cook & Zimmerman 8.4), which holds the discretisation error and the solver's
  together. At the base mesh a second column gives the solver's part alone: the
  difference from the same mesh solved with tolerance 1e-12, 8 load steps, float64.
- **Jointed tunnel** (``bench_tunnel.scene`` at joint spacing 1.8 m: 364 rigid blocks,
  two joint sets, gravity in-situ stress, excavation). No closed form: error is the
  larger relative difference of the two convergences from a reference solved with
  tolerance 1e-12, 64 load steps, max_iterations 500, float64. The joint spacing *is*
  the problem here (it sets the blocks, and so the answer), and the blocks are rigid
  (no ``mesh_size``), so there is no mesh factor: load steps, tolerance and dtype only.
- **Slipping tunnel** (the same at spacing 1.5 m: 492 blocks). Joints slip around the
  opening in the last load steps and Newton converges only linearly there, so tolerance
  and ``max_iterations`` matter; same kind of reference.

Around the base settings (jaxdem/scene/_schema.py's defaults: load_steps 5, tolerance 1e-9,
max_iterations 60, float64; Kirsch at h = 0.5 m) one factor varies at a time, plus a few
combinations. Configurations that share a compiled program (same mesh and dtype) run
in one fresh process, one group at a time. Times: ``solve s`` is the median of the
repeats' ``result.timing["solve_s"]`` after the first (compiling) solve; ``compile s``
is that first solve's ``timing["compile_s"]`` (the jitted increment), and ``other
first-call s`` the rest of the first solve's extra wall time (other jitted helpers,
first SciPy calls). Both belong to the program, so configurations sharing it show
the same values. The Pareto front is over solve time and error among the
configurations that converged.

    python benchmarks/bench_speed_error.py            # ~12 min on a shared 2-core CPU
    python benchmarks/bench_speed_error.py --quick    # ~2.5 min subset
    python benchmarks/bench_speed_error.py --case tunnel --spacing 2.0
    python benchmarks/bench_speed_error.py --replot RUN.json   # from a --json file

The compilation cache is off in the measuring processes (``JAXDEM_COMPILATION_CACHE=0``):
with it, a second run loads the compiled programs instead.

Figures: ``benchmarks/figures/speed_error_{kirsch,tunnel,tunnel-slip}.png`` (``--quick``:
``..._quick.png``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# This working tree's jaxdem, whatever the installed copy points to.
sys.path[:0] = [str(HERE), str(ROOT)]

import bench_kirsch  # noqa: E402
import bench_tunnel  # noqa: E402

# jaxdem/scene/_schema.py's SolverSettings defaults, repeated here so that the table can say whether
# they are on the front; checked against jaxdem at run time.
DEFAULTS = dict(load_steps=5, tolerance=1e-9, max_iterations=60, dtype="float64")
KIRSCH_H = 0.5
TUNNEL_SPACING = 1.8
SLIP_SPACING = 1.5
FACTORS = ("base", "mesh", "load steps", "tolerance", "dtype", "max iterations", "combination",
           "reference")


def cfg(factor: str, mesh: float | None = None, **solver) -> dict:
    """A configuration: the factor it belongs to, the Kirsch mesh size h (m) and solver entries."""
    return dict(factor=factor, mesh=mesh, solver=dict(DEFAULTS, **solver))


def kirsch_configs(quick: bool) -> list[dict]:
    if quick:
        h = 1.0
        return [cfg("base", h), cfg("load steps", h, load_steps=1),
                cfg("tolerance", h, tolerance=1e-4), cfg("dtype", h, dtype="float32"),
                cfg("reference", h, load_steps=8, tolerance=1e-12, max_iterations=500)]
    h = KIRSCH_H
    out = [cfg("base", h)]
    out += [cfg("mesh", m) for m in (1.0, 0.25, 0.125)]
    out += [cfg("load steps", h, load_steps=n) for n in (1, 2, 4, 8)]
    out += [cfg("tolerance", h, tolerance=t) for t in (1e-4, 1e-6, 1e-8, 1e-10)]
    out += [cfg("dtype", h, dtype="float32"),
            cfg("dtype", h, dtype="float32", tolerance=1e-4)]
    out += [cfg("combination", m, load_steps=1, tolerance=1e-6) for m in (1.0, 0.5, 0.25, 0.125)]
    out += [cfg("combination", h, dtype="float32", load_steps=1)]
    out += [cfg("reference", h, load_steps=8, tolerance=1e-12, max_iterations=500)]
    return out


def tunnel_configs(quick: bool) -> list[dict]:
    ref = cfg("reference", load_steps=16 if quick else 64, tolerance=1e-12, max_iterations=500)
    if quick:
        return [cfg("base"), cfg("load steps", load_steps=1), cfg("tolerance", tolerance=1e-4),
                cfg("dtype", dtype="float32"), ref]
    out = [cfg("base")]
    out += [cfg("load steps", load_steps=n) for n in (1, 2, 4, 8)]
    out += [cfg("tolerance", tolerance=t) for t in (1e-4, 1e-6, 1e-8, 1e-10)]
    out += [cfg("dtype", dtype="float32"), cfg("dtype", dtype="float32", tolerance=1e-4)]
    out += [cfg("combination", load_steps=n, tolerance=1e-6) for n in (1, 2)]
    out += [cfg("combination", load_steps=1, tolerance=1e-4),
            cfg("combination", load_steps=8, tolerance=1e-6),
            cfg("combination", dtype="float32", load_steps=1)]
    out += [ref]
    return out


def slip_configs(quick: bool) -> list[dict]:
    """The 492-block tunnel (joint spacing 1.5 m), where joint slip makes Newton converge
    slowly (linearly) in the last load steps."""
    ref = cfg("reference", load_steps=16 if quick else 64, tolerance=1e-12, max_iterations=1000)
    if quick:
        return [cfg("base"), cfg("tolerance", tolerance=1e-6), ref]
    out = [cfg("base"), cfg("max iterations", max_iterations=400)]
    out += [cfg("load steps", load_steps=n) for n in (1, 2, 8)]
    out += [cfg("tolerance", tolerance=t) for t in (1e-4, 1e-6)]
    out += [cfg("dtype", dtype="float32")]
    out += [cfg("combination", load_steps=2, tolerance=1e-6),
            cfg("combination", load_steps=1, tolerance=1e-4),
            cfg("combination", max_iterations=400, tolerance=1e-6)]
    return out + [ref]


def scene_dict(case: str, c: dict, spacing: float) -> dict:
    if case == "kirsch":
        d = bench_kirsch.scene(c["mesh"], k0=1.0)
    elif case == "tunnel-slip":
        d = bench_tunnel.scene(SLIP_SPACING)
    else:
        d = bench_tunnel.scene(spacing)
    d["solver"] = dict(c["solver"])
    return d


def label(c: dict) -> str:
    """A short name of the configuration: what differs from the base settings."""
    s = c["solver"]
    parts = [f"h={c['mesh']:g}"] if c["mesh"] is not None else []
    if s["load_steps"] != DEFAULTS["load_steps"]:
        parts.append(f"steps={s['load_steps']}")
    if s["tolerance"] != DEFAULTS["tolerance"]:
        parts.append(f"tol={s['tolerance']:.0e}")
    if s["dtype"] != DEFAULTS["dtype"]:
        parts.append("f32")
    if s["max_iterations"] != DEFAULTS["max_iterations"]:
        parts.append(f"maxit={s['max_iterations']}")
    return " ".join(parts) or "defaults"


# ---------------------------------------------------------------------------
# Worker: one group of configurations sharing a compiled program, in a fresh process

def _solve_once(sc) -> tuple[dict, object]:
    import jaxdem
    jaxdem.config.configure()  # float64, one OpenBLAS thread, the program cache

    t0 = time.perf_counter()
    r = jaxdem.solve(sc)
    return dict(wall=time.perf_counter() - t0, **r.timing), r


def worker(spec: dict) -> None:
    """Solves each configuration of the group ``repeats`` times, round-robin (so that a burst
    of load from other users spreads over the group instead of spoiling one
    configuration); one extra first solve compiles the program. A configuration stops
    repeating once its timed solves exceed ``budget_s``."""
    from jaxdem.scene import parse_scene

    configs = spec["configs"]
    scenes = [parse_scene(scene_dict(spec["case"], c, spec["spacing"])) for c in configs]
    cold: list[list[dict]] = [[] for _ in configs]
    warm: list[list[dict]] = [[] for _ in configs]
    last: list = [None] * len(configs)
    errors: list[str | None] = [None] * len(configs)

    def once(i: int) -> None:
        try:
            run, last[i] = _solve_once(scenes[i])
        except Exception as exc:  # a crashing configuration is a result too
            errors[i] = f"{type(exc).__name__}: {exc}"[:120]
            return
        (cold[i] if run["compile_s"] > 0 else warm[i]).append(run)

    once(0)
    for rep in range(spec["repeats"]):
        for i in range(len(configs)):
            if errors[i] is None and (rep == 0 or sum(x["wall"] for x in warm[i])
                                      <= spec["budget_s"]):
                once(i)
    for i in range(len(configs)):  # a run that recompiled (capacity growth) is not timed
        while errors[i] is None and not warm[i] and len(cold[i]) < 3:
            once(i)
    for i, c in enumerate(configs):
        r, w = last[i], warm[i] or cold[i]
        out = dict(label=label(c), factor=c["factor"], mesh=c["mesh"], solver=c["solver"],
                   cold=cold[i], runs=len(warm[i]))
        if r is None:
            out.update(blocks=0, status="error", error_message=errors[i], converged=False,
                       stable=False, monitors={}, iterations=0, residual=float("nan"),
                       solve_s=float("nan"), solve_spread=[], wall_s=float("nan"))
        else:
            out.update(
                blocks=len(r.blocks), status=r.status, converged=bool(r.converged),
                stable=bool(r.stable), error_message=errors[i],
                monitors={k: v["convergence"] for k, v in r.monitors.items()},
                iterations=sum(sum(s["iterations"]) for s in r.stages),
                residual=max((max(s["residual"]) for s in r.stages if s["residual"]),
                             default=0.0),
                solve_s=statistics.median(x["solve_s"] for x in w),
                solve_spread=[min(x["solve_s"] for x in w), max(x["solve_s"] for x in w)],
                wall_s=statistics.median(x["wall"] for x in w))
        print("RESULT " + json.dumps(out), flush=True)


# ---------------------------------------------------------------------------
# Driver

def run_case(case: str, configs: list[dict], spacing: float, repeats: int,
             budget_s: float) -> list[dict]:
    """Runs the configurations group by group (mesh, dtype), each group in a fresh process."""
    groups: dict[tuple, list[dict]] = {}
    for c in configs:
        groups.setdefault((c["mesh"], c["solver"]["dtype"]), []).append(c)
    results = []
    for key, group in groups.items():
        spec = dict(case=case, configs=group, spacing=spacing, repeats=repeats,
                    budget_s=budget_s)
        t0 = time.perf_counter()
        # Without the persistent compilation cache: compile time is the point here.
        proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)],
                              capture_output=True, text=True,
                              env=dict(os.environ, JAXDEM_COMPILATION_CACHE="0"))
        rows = [json.loads(line[7:]) for line in proc.stdout.splitlines()
                if line.startswith("RESULT ")]
        if proc.returncode or len(rows) < len(group):
            err = (proc.stderr.strip().splitlines() or ["?"])[-1]
            print(f"  group {key} failed: {err}", flush=True)
            rows = [dict(label=label(c), factor=c["factor"], mesh=c["mesh"], solver=c["solver"],
                         status="crashed", error_message=err[:120], converged=False,
                         stable=False, monitors={}, blocks=0, iterations=0,
                         residual=float("nan"), runs=0, solve_s=float("nan"), solve_spread=[],
                         wall_s=float("nan"), cold=[]) for c in group]
        # The program's first-call cost, from the group's first configuration.
        first = rows[0]
        compile_s = sum(x["compile_s"] for x in first["cold"])
        other = sum(x["wall"] for x in first["cold"]) - compile_s - first["wall_s"]
        for r in rows:
            r["compile_s"] = compile_s + sum(x["compile_s"] for x in r["cold"] if r is not first)
            r["other_first_s"] = max(other, 0.0)
        print(f"  group mesh={key[0]} {key[1]}: {len(group)} configurations, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        results += rows
    return results


def add_errors(case: str, rows: list[dict]) -> None:
    """Kirsch: error against the closed form (and against the fine solve at the same mesh);
    tunnel: against the reference configuration."""
    ref = next(r for r in rows if r["factor"] == "reference")
    for r in rows:
        m = r["monitors"]
        r["error_ref"] = None
        if not m:
            r["error"] = float("nan")
            continue
        if case == "kirsch":
            ch, cv = bench_kirsch.closed_form(1.0)
            r["ratio"] = 0.5 * (m["h"] / ch + m["v"] / cv)
            r["error"] = abs(r["ratio"] - 1.0)
            if r["mesh"] == ref["mesh"] and ref["monitors"] and r is not ref:
                mean = 0.5 * (m["h"] + m["v"])
                mref = 0.5 * (ref["monitors"]["h"] + ref["monitors"]["v"])
                r["error_ref"] = abs(mean / mref - 1.0)
        else:
            rm = ref["monitors"]
            r["error"] = (max(abs(m[k] / rm[k] - 1.0) for k in rm) if rm and r is not ref
                          else 0.0)


def pareto(rows: list[dict], key: str = "error", same: float = 0.02) -> list[dict]:
    """The converged configurations not dominated in (solve time, ``key``).

    Errors within ``same`` (relative) of each other count as equal: they differ in digits
    that mean nothing, so the faster configuration dominates."""
    ok = [r for r in rows if r["converged"] and r["factor"] != "reference"
          and r.get(key) is not None and r[key] == r[key]]

    def dominates(q: dict, r: dict) -> bool:
        if q is r or q["solve_s"] > r["solve_s"] or q[key] > r[key] * (1 + same):
            return False
        return q["solve_s"] < r["solve_s"] or q[key] < r[key] * (1 - same)

    return [r for r in ok if not any(dominates(q, r) for q in ok)]


def table(case: str, rows: list[dict]) -> str:
    front = {id(r) for r in pareto(rows)}
    head = ["configuration", "factor", "blocks", "status", "Newton its", "compile s",
            "other first-call s", "solve s (median, n)", "error"]
    if case == "kirsch":
        head += ["vs fine, same mesh"]
    head += ["front"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["label"], r["factor"], f"{r['blocks']:,}", r["status"], str(r["iterations"]),
                 f"{r['compile_s']:.1f}", f"{r['other_first_s']:.1f}",
                 f"{r['solve_s']:.2f} ({r['runs']})",
                 "0 (by definition)" if case != "kirsch" and r["factor"] == "reference"
                 else f"{r['error']:.2e}"]
        if case == "kirsch":
            cells.append("" if r["error_ref"] is None else f"{r['error_ref']:.1e}")
        cells.append("yes" if id(r) in front else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


MARKERS = {"base": ("*", "black"), "mesh": ("s", "tab:blue"), "load steps": ("o", "tab:orange"),
           "tolerance": ("^", "tab:green"), "dtype": ("D", "tab:red"),
           "max iterations": ("v", "tab:brown"),
           "combination": ("P", "tab:purple"), "reference": ("X", "tab:gray")}


def _panel(ax, rows: list[dict], key: str, ylabel: str, quiet: tuple = ()) -> None:
    """One log-log panel: the configurations by factor (hollow: not converged), their labels
    (stacked where points crowd; none for those in ``quiet`` off the front) and the Pareto
    front as a staircase."""
    pts = [r for r in rows if r["solve_s"] == r["solve_s"] and r.get(key) is not None
           and r[key] == r[key]]
    errs = [r[key] for r in pts if r[key] > 0]
    floor = min(errs) / 3 if errs else 1e-12
    for factor in FACTORS:
        m, col = MARKERS[factor]
        for failed in (False, True):
            s = [r for r in pts if r["factor"] == factor and r["converged"] == (not failed)]
            if s:
                ax.scatter([r["solve_s"] for r in s], [max(r[key], floor) for r in s],
                           marker=m, s=120 if factor == "base" else 55,
                           facecolors="none" if failed else col, edgecolors=col,
                           label=factor + (" (not converged)" if failed else ""), zorder=3)
    front = sorted(pareto(rows, key), key=lambda r: r["solve_s"])
    placed: list[tuple[float, float, int]] = []
    for r in sorted(pts, key=lambda r: (r["solve_s"], r[key])):
        if r in quiet and not any(r is f for f in front):
            continue
        x, y = math.log10(r["solve_s"]), math.log10(max(r[key], floor))
        n = sum(1 for px, py, _ in placed if abs(px - x) < 0.12 and abs(py - y) < 0.04)
        placed.append((x, y, n))
        text = r["label"] + (" (0)" if r[key] == 0 else "")
        ax.annotate(text, (r["solve_s"], max(r[key], floor)), fontsize=6.5,
                    xytext=(5, 3 - 8 * n), textcoords="offset points", color="0.25")
    if front:
        ax.step([r["solve_s"] for r in front], [max(r[key], floor) for r in front],
                where="post", color="gold", lw=6, alpha=0.5, zorder=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("solve time after compile, s (median of repeats)")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")


def plot(case: str, rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if case == "kirsch":
        fig, axes = plt.subplots(1, 2, figsize=(14, 5.8))
        quiet = tuple(r for r in rows if r["mesh"] == KIRSCH_H and r["factor"] != "base")
        _panel(axes[0], rows, "error", "error of the mean convergence against Kirsch", quiet)
        axes[0].set_title("all configurations (discretisation + solver error)", fontsize=9)
        _panel(axes[1], [r for r in rows if r.get("error_ref") is not None], "error_ref",
               "difference from the fine solve at the same mesh")
        axes[1].set_title(f"h = {KIRSCH_H} m only: the solver settings' own error "
                          "(0 drawn at the floor, labelled (0))", fontsize=9)
    else:
        fig, ax = plt.subplots(figsize=(9, 5.8))
        _panel(ax, [r for r in rows if r["factor"] != "reference"], "error",
               "error against the fine reference (larger of the 2 convergences)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(case: str, rows: list[dict], spacing: float, quick: bool) -> None:
    """Prints the table and the Pareto fronts and draws the figure."""
    print(table(case, rows), flush=True)
    for r in rows:
        if r.get("error_message"):
            print(f"  {r['label']}: {r['error_message']}")
    base = next(r for r in rows if r["factor"] == "base")
    keys = ("error", "error_ref") if case == "kirsch" else ("error",)
    for key in keys:
        front = pareto(rows, key)
        what = "against the closed form" if key == "error" and case == "kirsch" else (
            "against the fine solve at the same mesh" if key == "error_ref" else "")
        print(f"Pareto front {what}: " + ", ".join(
            r["label"] for r in sorted(front, key=lambda r: r["solve_s"])))
        print(f"  defaults ({base['label']}) on it: "
              f"{'yes' if any(r is base for r in front) else 'no'}", flush=True)
    if case == "kirsch":
        title = f"Kirsch opening, K = 1 (mesh h = {KIRSCH_H} m unless h= is shown)"
    else:
        ref = next(r for r in rows if r["factor"] == "reference")["solver"]
        title = (f"Jointed tunnel, joint spacing {spacing} m, {base['blocks']} rigid blocks; "
                 f"reference: tolerance {ref['tolerance']:.0e}, {ref['load_steps']} load steps, "
                 "float64")
    suffix = "_quick" if quick else ""
    plot(case, rows, HERE / "figures" / f"speed_error_{case}{suffix}.png", title)


def _revision() -> str:
    """The commit and whether jaxdem/ has local changes (the tree may change under a run)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "jaxdem"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
    except OSError:
        return "git: unavailable"
    return f"commit {head}" + (" + local changes in jaxdem/" if dirty else "")


def check_defaults() -> None:
    from jaxdem.scene import SolverSettings

    d = SolverSettings()
    now = dict(load_steps=d.load_steps, tolerance=d.tolerance, max_iterations=d.max_iterations,
               dtype=d.dtype)
    if now != DEFAULTS:
        print(f"note: jaxdem's defaults are now {now}; this script's base is {DEFAULTS}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a ~2 minute subset")
    ap.add_argument("--case", choices=("kirsch", "tunnel", "tunnel-slip", "all"),
                    default="all", help="tunnel-slip: the 492-block tunnel at spacing 1.5 m")
    ap.add_argument("--spacing", type=float, default=TUNNEL_SPACING,
                    help="joint spacing of the tunnel, m")
    ap.add_argument("--repeats", type=int, help="timed solves per configuration (3; quick: 1)")
    ap.add_argument("--budget", type=float, default=30.0,
                    help="stop repeating a configuration after this many seconds (after 1)")
    ap.add_argument("--json", type=Path, help="also write all measurements here")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--replot", type=Path, help="tables and figures from a --json file")
    args = ap.parse_args()
    if args.worker:
        worker(json.loads(args.worker))
        return
    if args.replot:
        for case, v in json.loads(args.replot.read_text()).items():
            report(case, v["rows"], v["spacing"], args.quick)
        return
    import jax

    check_defaults()
    repeats = args.repeats or (1 if args.quick else 3)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}, jax {jax.__version__} ({jax.devices()[0].platform}); "
          f"load average at start {os.getloadavg()[0]:.1f}; {_revision()}", flush=True)
    t_start = time.perf_counter()
    out = {}
    cases = ("kirsch", "tunnel", "tunnel-slip") if args.case == "all" else (args.case,)
    for case in cases:
        configs = (kirsch_configs(args.quick) if case == "kirsch" else slip_configs(args.quick)
                   if case == "tunnel-slip" else tunnel_configs(args.quick))
        spacing = SLIP_SPACING if case == "tunnel-slip" else args.spacing
        print(f"{case}: {len(configs)} configurations", flush=True)
        rows = run_case(case, configs, spacing, repeats, args.budget)
        add_errors(case, rows)
        out[case] = dict(rows=rows, spacing=spacing)
        report(case, rows, spacing, args.quick)
    print(f"total {time.perf_counter() - t_start:.0f} s; load average at end "
          f"{os.getloadavg()[0]:.1f}; {_revision()}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
