"""Time to answer: whole ``jaxdem`` commands, cold and warm, against a C DDA code (issue 18).

Each problem runs as the command a user types, in a fresh process, Python
start-up included::

    python -m jaxdem run SCENE.toml --out DIR [--no-figures]
    python -m jaxdem demo --out DIR [--no-figures]

"cold": an empty persistent compilation cache (``JAXDEM_CACHE_DIR``, a new
temporary folder per run); "warm": the same command again with the cache that
a first run filled; "similar": the cache filled by another scene of the same
size classes (the incline with a second block on the first, an 11 x 9 and a
21 x 19 grid): a new scene of a similar size. Wall time is the median over ``--repeats`` runs. The
phases come from the command's own marks (``$JAXDEM_PHASES``, see
jaxdem/cli/__init__.py) and ``result.json``'s timing:

- start: Python and the command line up to the command (the interpreter,
  argparse), measured from the launch of the process;
- load: reading and validating the scene file; import: ``jaxdem.solver`` (JAX);
- build: model and device arrays; trace: tracing and lowering of the increment
  program; compile: ``result.json``'s ``timing.compile_s``, the time the solve waited
  for its programs (XLA compilation, or a cache load when warm; both run on a
  background thread beside the in-situ preload, so their own time can be longer);
- solve: running the increments; other: the rest of ``solve`` (small programs
  compiled at first use, the in-situ preload, monitors, the result);
- answer: result.json and the summary; figures: the four PNGs.

Problems (scene files written to ``benchmarks/scenes/`` by this script):

- incline: a 1 m block on a 30 degree plane, joint friction 35 degrees
  (stays). Closed form (as tests/verification/test_incline.py): two point
  springs at the ends of the 1 m face, kn, ks from eqs. 6-7, here with the
  up-slope spring slipping (the overturning moment unloads it) and the
  down-slope one sticking (:func:`_incline_closed_form`); the error is the
  largest relative error of the centroid's displacement along and normal to
  the slope and its rotation.
- grid10, grid20: n x n square 1 m blocks on a fixed 1 m high base. No lateral
  load and no Poisson effect in rigid blocks: every column settles alike and
  the side contacts carry nothing, so each column is the stack of
  tests/verification/test_stack.py: the top block settles by
  sum_k W (n - k) / (k_k Le), W = gamma * 1 m^2, Le = 1 m,
  k_k = 1 / (h1/kn_i + h2/kn_i + 1/kn), h = 0.5 m (eqs. 4, 6, 7). The error is
  that of the middle column's top block's vertical displacement.
- demo: ``jaxdem demo`` (no closed form).
- grid40, grid70, grid100: the 40 x 40, 70 x 70 and 100 x 100 grids (as grid10; DDA's
  times from issue 30); grid40f32, grid70f32, grid100f32: the same in float32
  (``solver.dtype``).
- tunnel: the 596-block standing tunnel of bench_scaling.py (spacing 1.35 m;
  no closed form).
- ex4wet, ex2: seed examples 4 (wet slope and tunnel, 225 blocks) and 2 (tunnel and
  shear zone, 1,193 blocks) as shipped in examples/ (no closed form); ex2f32: seed
  example 2 in float32 (written to benchmarks/scenes/).
- ex3, ex3d: seed example 3 (two tunnels in meshed rock, 1,292 and 1,282 blocks), without
  and with the discontinuity D, at ``in_situ.k0`` = 1/3 (written to benchmarks/scenes/):
  as shipped (K0 = 0) the rock fails under its own weight and the initial state ends at
  the iteration limit after minutes (the scene's warning; examples/README.md). No closed
  form: the error column gives the status of a run that found no equilibrium.

Reference: Shi's DDA (the public ntdda C code) on the same machine kind,
solve only: incline 0.005 s, 10 x 10 0.17 s, 20 x 20 1.74 s (issue 18), 40 x 40 5.95 s,
70 x 70 78.7 s, 100 x 100 439 s (issue 30).

    PYTHONPATH=. python benchmarks/bench_time_to_answer.py                 # all, 3 repeats
    PYTHONPATH=. python benchmarks/bench_time_to_answer.py --cases incline grid10 --repeats 5
    PYTHONPATH=. python benchmarks/bench_time_to_answer.py --no-figures
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCENES = HERE / "scenes"
DDA = {"incline": 0.005, "grid10": 0.17, "grid20": 1.74, "grid40": 5.95, "grid70": 78.7,
       "grid100": 439.0}
EXAMPLES = {"ex4wet": "seed_example4_slope_wet.toml", "ex2": "seed_example2_tunnel.toml"}
ROCK = {"E": 1.0e7, "nu": 0.25, "unit_weight": 25.0}
JOINT = {"kn": 1.0e6, "ks": 5.0e5, "friction_deg": 35.0, "cohesion": 0.0}
ALPHA = 30.0


# ---------------------------------------------------------------------------
# Scenes


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return json.dumps(v)
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def to_toml(d: dict) -> str:
    """A scene dict as TOML (tables, arrays of tables, scalars and lists only)."""
    lines: list[str] = []

    def table(prefix: str, t: dict, array: bool = False) -> None:
        lines.append(f"\n[[{prefix}]]" if array else f"\n[{prefix}]")
        for k, v in t.items():
            if not isinstance(v, dict):
                lines.append(f"{k} = {_toml_value(v)}")
        for k, v in t.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}", v)

    for k, v in d.items():
        if isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                table(k, item, array=True)
        elif isinstance(v, dict):
            if all(isinstance(x, dict) for x in v.values()):
                for name, sub in v.items():
                    table(f"{k}.{name}", sub)
            else:
                table(k, v)
    return "\n".join(lines).lstrip() + "\n"


def _slope_frame():
    a = math.radians(ALPHA)
    return (math.cos(a), math.sin(a)), (-math.sin(a), math.cos(a))


def incline_scene(stacked: bool = False) -> dict:
    """1 m block on a 30 degree plane, friction 35 (tests/scenes.py's block_on_incline);
    ``stacked``: a second 1 m block on the first (the "similar" scene of the incline)."""
    (tx, ty), (nx, ny) = _slope_frame()
    ta = math.tan(math.radians(ALPHA))
    base = [[-1.0, -ta - 2.0], [12.0, -ta - 2.0], [12.0, 12.0 * ta], [-1.0, -ta]]
    s0 = 4.0
    p0 = (s0 * tx, s0 * ty)
    blk = [[p0[0], p0[1]], [p0[0] + tx, p0[1] + ty], [p0[0] + tx + nx, p0[1] + ty + ny],
           [p0[0] + nx, p0[1] + ny]]
    c = [sum(p[0] for p in blk) / 4, sum(p[1] for p in blk) / 4]
    blocks = [{"vertices": base, "material": "rock", "fixed": True},
              {"vertices": blk, "material": "rock"}]
    if stacked:
        blocks.append({"vertices": [[x + nx, y + ny] for x, y in blk], "material": "rock"})
    return {"scene": {"name": "incline 30/35"}, "solver": {"load_steps": 1},
            "materials": {"rock": dict(ROCK)}, "joints": {"base": dict(JOINT)},
            "blocks": blocks, "monitors": [{"name": "block", "point": c}]}


def grid_scene(n: int, m: int | None = None, dtype: str = "float64") -> dict:
    """n x n (or n columns of m) square 1 m blocks on a fixed base 1 m high; monitor: the
    middle column's top."""
    blocks = [{"vertices": [[-1.0, -1.0], [n + 1.0, -1.0], [n + 1.0, 0.0], [-1.0, 0.0]],
               "material": "rock", "fixed": True}]
    for i in range(n):
        for j in range(n if m is None else m):
            blocks.append({"vertices": [[i, j], [i + 1, j], [i + 1, j + 1], [i, j + 1]],
                           "material": "rock"})
    mid, rows = n // 2 + 0.5, n if m is None else m
    solver = {"load_steps": 1} if dtype == "float64" else {"load_steps": 1, "dtype": dtype}
    return {"scene": {"name": f"{n} x {rows} grid on a fixed base"}, "solver": solver,
            "materials": {"rock": dict(ROCK)},
            "joints": {"j": {"kn": 1.0e6, "ks": 1.0e6, "friction_deg": 35.0}},
            "blocks": blocks, "monitors": [{"name": "top", "point": [mid, rows - 0.5]}]}


def write_scenes() -> dict[str, Path]:
    sys.path.insert(0, str(HERE))
    from bench_scaling import scene as scaling_scene

    SCENES.mkdir(exist_ok=True)
    scenes = {"incline": incline_scene(), "grid10": grid_scene(10), "grid20": grid_scene(20),
              "grid40": grid_scene(40), "grid70": grid_scene(70), "grid100": grid_scene(100),
              **{f"grid{n}f32": grid_scene(n, dtype="float32") for n in (40, 70, 100)},
              "tunnel": scaling_scene(1.35, "auto"),
              # The "similar" scenes: other block counts in the same size classes.
              "incline-similar": incline_scene(stacked=True),
              "grid10-similar": grid_scene(11, 9), "grid20-similar": grid_scene(21, 19)}
    texts = {name: f"# Written by benchmarks/bench_time_to_answer.py ({name}).\n" + to_toml(d)
             for name, d in scenes.items()}
    # Shipped examples with one line changed: seed example 3 at k0 = 1/3 (its file's K0 = 0
    # fails before any excavation), seed example 2 in float32.
    derived = (("ex3", "seed_example3_without_D.toml", "\nk0 = 0.0\n", "\nk0 = 0.3333\n",
                "at k0 = 1/3"),
               ("ex3d", "seed_example3_with_D.toml", "\nk0 = 0.0\n", "\nk0 = 0.3333\n",
                "at k0 = 1/3"),
               ("ex2f32", "seed_example2_tunnel.toml", "[solver]\n",
                '[solver]\ndtype = "float32"\n', "in float32"))
    for name, file, old, new, what in derived:
        shipped = (HERE.parent / "examples" / file).read_text()
        assert old in shipped, f"{file}: its line {old!r} has changed"
        texts[name] = (f"# Written by benchmarks/bench_time_to_answer.py ({name}): examples/"
                       f"{file} {what}.\n" + shipped.replace(old, new, 1))
    paths = {}
    for name, text in texts.items():
        path = SCENES / f"{name}.toml"
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
        paths[name] = path
    # The seed examples as shipped (examples/README.md): no closed form.
    for name, file in EXAMPLES.items():
        paths[name] = HERE.parent / "examples" / file
    return paths


# ---------------------------------------------------------------------------
# Closed forms


def _intact(E=1e7, nu=0.25):
    return E / (1 - nu**2), E / (1 + nu)  # eq. 4 (Hamajima-Kawai)


def _k_eq(h1, h2, k_i, k0):
    return 1.0 / (h1 / k_i + h2 / k_i + 1.0 / k0)  # eqs. 6-7, per unit length


def _incline_closed_form(kn, ks, Ft, Fn, hc, Le, tanphi):
    """(u_t, u_n, theta) of the block on two point springs (kn, ks each) at s = -+Le/2.

    Unknowns du = (u_t, u_n, theta); the point at (s, -hc) in the slope frame moves
    (u_t + theta hc, u_n + theta s). Spring forces on the block: N = -kn (u_n + theta s),
    T = -ks (u_t + theta hc) when it sticks, T = tan(phi) N (resisting down-slope
    sliding) when it slips. Balance: sum T + Ft = 0, sum N + Fn = 0, sum (s N + hc T)
    = 0 (moments about the centroid). With friction 35 on 30 degrees the up-slope
    spring, unloaded by the overturning moment, slips while the block stays: the
    states are chosen as the consistent combination (Mohr-Coulomb at each point).
    """
    import itertools

    import numpy as np

    s = (-Le / 2, Le / 2)
    for slips in itertools.product((False, True), repeat=2):
        A, b = np.zeros((3, 3)), np.array([-Ft, -Fn, 0.0])
        for si, slip in zip(s, slips, strict=True):
            N = -kn * np.array([0.0, 1.0, si])
            T = tanphi * N if slip else -ks * np.array([1.0, 0.0, hc])
            A[0] += T
            A[1] += N
            A[2] += si * N + hc * T
        du = np.linalg.solve(A, b)
        ok = True
        for si, slip in zip(s, slips, strict=True):
            N = -kn * (du[1] + du[2] * si)
            T = tanphi * N if slip else -ks * (du[0] + du[2] * hc)
            ok &= N >= 0 and (abs(T) <= tanphi * N * (1 + 1e-12) if not slip
                              else du[0] + du[2] * hc < 0)
        if ok:
            return tuple(du)
    raise ValueError("no consistent state")


def incline_error(result: dict) -> float:
    kn_i, ks_i = _intact()
    a = math.radians(ALPHA)
    ta = math.tan(a)
    base = [[-1.0, -ta - 2.0], [12.0, -ta - 2.0], [12.0, 12.0 * ta], [-1.0, -ta]]
    # Centroid of the base polygon (shoelace), its distance from the slope line.
    A = cx = cy = 0.0
    for (x0, y0), (x1, y1) in zip(base, base[1:] + base[:1], strict=True):
        w = x0 * y1 - x1 * y0
        A += w
        cx += (x0 + x1) * w
        cy += (y0 + y1) * w
    cx, cy = cx / (3 * A), cy / (3 * A)
    h_base = abs(-math.sin(a) * cx + math.cos(a) * cy)
    hc, Le = 0.5, 1.0
    kn = _k_eq(hc, h_base, kn_i, JOINT["kn"])
    ks = _k_eq(hc, h_base, ks_i, JOINT["ks"])
    W = ROCK["unit_weight"]
    Ft, Fn = -W * math.sin(a), -W * math.cos(a)
    exp = _incline_closed_form(kn * Le / 2, ks * Le / 2, Ft, Fn, hc, Le,
                               math.tan(math.radians(JOINT["friction_deg"])))
    ux, uy, rot = result["blocks"][1]["u"]
    (tx, ty), (nx, ny) = _slope_frame()
    got = (ux * tx + uy * ty, ux * nx + uy * ny, rot)
    return max(abs(g / e - 1.0) for g, e in zip(got, exp, strict=True))


def grid_settlement(n: int) -> float:
    kn_i, _ = _intact()
    W = ROCK["unit_weight"] * 1.0
    return sum(W * (n - k) / _k_eq(0.5, 0.5, kn_i, 1.0e6) for k in range(n))


def grid_error(n: int, result: dict) -> float:
    uy = result["monitors"]["top"]["displacement"][1]
    return abs(-uy / grid_settlement(n) - 1.0)


def error_of(case: str, result: dict) -> str:
    if not result.get("converged", False):
        return result.get("status", "?")
    if case.endswith("-similar"):
        return "-"  # a scene that only fills the cache
    if case == "incline":
        return f"{incline_error(result):.1e}" if result["stable"] else "slid!"
    if case.startswith("grid"):
        return f"{grid_error(int(case[4:].removesuffix('f32')), result):.1e}"
    return "-"


# ---------------------------------------------------------------------------
# Runs


def run_once(case: str, path: Path | None, cache: str, figures: bool) -> dict:
    out = tempfile.mkdtemp(prefix=f"tta-{case}-")
    phases = os.path.join(out, "phases.json")
    cmd = [sys.executable, "-m", "jaxdem"]
    cmd += ["demo", "--out", out] if case == "demo" else ["run", str(path), "--out", out]
    if not figures:
        cmd.append("--no-figures")
    env = dict(os.environ, JAXDEM_CACHE_DIR=cache, JAXDEM_PHASES=phases)
    # Python's bytecode cached, as on a user's machine (pip writes it at install, Python at
    # an editable install's first import): a shell that turns it off (this project's
    # sandboxes do) made every run compile jaxdem's 41 modules again, 0.12 s.
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    t0 = time.time()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.time() - t0
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    m = json.loads(Path(phases).read_text())
    result = json.loads(Path(out, "result.json").read_text())
    shutil.rmtree(out, ignore_errors=True)
    t, inc = m["timing"], m["increment"]
    solve_total = m["solved"] - m["imported"]
    row = dict(wall=wall, start=m["start"] - t0, load=m["loaded"] - m["start"],
               imp=m["imported"] - m["loaded"], build=t["build_s"], trace=inc["lower_s"],
               compile=t["compile_s"], solve=t["solve_s"],
               answer=m["answered"] - m["solved"], figures=m["figures"] - m["answered"],
               blocks=len(result["blocks"]), error=error_of(case, result),
               status=result.get("status", "?"))
    row["other"] = solve_total - t["build_s"] - t["compile_s"] - t["solve_s"]
    return row


COLS = ("wall", "start", "load", "imp", "build", "trace", "compile", "solve", "other",
        "answer", "figures")


def cpu_model() -> str:
    """The processor's model name, with its family and model numbers and whether it has
    AVX-512 where Linux says (machines of the same name differ: an "AMD EPYC" of family 25
    model 17 with AVX-512 ran the cold demo in 4.4 s where one without took 7.3-12 s:
    BENCHMARKS.md, "Forty-second session"), and the time of a Python loop of 3 million
    additions (the median of 3), to scale figures taken on other machines by."""
    name, fields = platform.processor() or "processor unknown", {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    if "model name" in fields:
        name = fields["model name"]
        if "cpu family" in fields:
            wide = "avx512f" in fields.get("flags", "").split()
            name += (f" (family {fields['cpu family']} model {fields.get('model', '?')}, "
                     f"{'' if wide else 'no '}AVX-512)")
    return f"{name}, a Python loop of 3M additions {python_loop_s():.2f} s"


def python_loop_s() -> float:
    """Seconds for a Python loop of 3 million additions (the median of 3): how fast this
    machine runs the host's Python (tracing, lowering, the command line)."""
    times = []
    for _ in range(3):
        start, total = time.perf_counter(), 0
        for i in range(3_000_000):
            total += i
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["incline", "grid10", "grid20", "demo", "tunnel"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-figures", action="store_true")
    args = ap.parse_args()
    paths = write_scenes()
    import jax

    print(f"# {platform.machine()}, {cpu_model()}, {os.cpu_count()} cores, jax {jax.__version__}, "
          f"python {platform.python_version()}; medians of {args.repeats} runs (s); "
          f"figures {'off' if args.no_figures else 'on'}")
    head = f"{'case':>8} {'blocks':>6} {'cache':>7} " + " ".join(f"{c:>7}" for c in COLS)
    print(head + f" {'DDA':>6} {'error':>8}")
    for case in args.cases:
        modes = ("cold", "warm") + (("similar",) if f"{case}-similar" in paths else ())
        for mode in modes:
            rows = []
            warm_dir = tempfile.mkdtemp(prefix="tta-cache-") if mode != "cold" else None
            if warm_dir:  # fill it: with the same scene (warm) or a similar one
                fill = case if mode == "warm" else f"{case}-similar"
                run_once(fill, paths.get(fill), warm_dir, not args.no_figures)
            for _ in range(args.repeats):
                cache = warm_dir or tempfile.mkdtemp(prefix="tta-cache-")
                rows.append(run_once(case, paths.get(case), cache, not args.no_figures))
                if not warm_dir:
                    shutil.rmtree(cache, ignore_errors=True)
            if warm_dir:
                shutil.rmtree(warm_dir, ignore_errors=True)
            med = {c: statistics.median(r[c] for r in rows) for c in COLS}
            dda = f"{DDA[case]:>6.3f}" if case in DDA else f"{'-':>6}"
            print(f"{case:>8} {rows[0]['blocks']:>6} {mode:>7} "
                  + " ".join(f"{med[c]:>7.2f}" for c in COLS) + f" {dda} {rows[0]['error']:>8}",
                  flush=True)


if __name__ == "__main__":
    main()
