#!/usr/bin/env bash
# The GPU check of issue 30, prepared to run as one call of the device tool (a task that is
# lent a GPU): at most DEADLINE s (default 540), every step capped by a timeout, logs
# under $OUT.
#
#   bash benchmarks/gpu_check.sh        # from the repository root; PYTHONPATH is set here
#   FLOAT32=0 DEADLINE=300 bash benchmarks/gpu_check.sh   # float64 and the sweep only
#
# What it runs, float64 and float32 (solver.dtype), each a whole `jaxdem` command:
#   - `jaxdem demo` (cold, then warm: the program store in a cache folder of its own);
#   - seed example 2 (1,193 blocks, deformable cells);
#   - the 100 x 100 grid of 1 m blocks on a base (10,001 blocks; benchmarks/bench_time_to_answer.py);
#   - a 1,024-sample batch of the 52-block benchmark tunnel (benchmarks/bench_throughput.py).
# On a GPU "auto" takes the dense path up to 32,000 unknowns (jaxdem.core.model; LU, and
# Cholesky where the matrix is symmetric, since the twenty-eighth session): these are
# timings of that choice on a GPU (the first, 2026-11-27, an H100: BENCHMARKS.md "GPU").
# Put the table it prints in BENCHMARKS.md, "GPU".
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
OUT="${OUT:-/tmp/jaxdem-gpu-check}"
mkdir -p "$OUT"
WORK="$(mktemp -d)"
export JAXDEM_CACHE_DIR="$WORK/cache"

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c "import jax; print('jax', jax.__version__, jax.devices())" | tee -a "$OUT/gpu.txt"

# Scene files: the grid from the time-to-answer benchmark, float32 copies of each scene.
python3 - "$WORK" <<'EOF'
import sys
from pathlib import Path
sys.path.insert(0, "benchmarks")
from bench_time_to_answer import grid_scene, to_toml
work = Path(sys.argv[1])
scenes = {"grid100": to_toml(grid_scene(100)),
          "ex2": Path("examples/seed_example2_tunnel.toml").read_text(),
          "demo": Path("jaxdem/data/demo.toml").read_text()}
for name, text in scenes.items():
    (work / f"{name}-float64.toml").write_text(text)
    # float32: a dtype line in the [solver] table (every scene here has one).
    (work / f"{name}-float32.toml").write_text(text.replace("[solver]\n", "[solver]\ndtype = \"float32\"\n", 1))
EOF

row() {  # name, seconds, result folder: one line of the table
  python3 - "$1" "$2" "$3" <<'EOF'
import json, sys
name, wall, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
try:
    r = json.load(open(f"{out}/result.json"))
except OSError:
    print(f"{name:22s} {wall:7.1f}  no result.json (timed out or failed)"); sys.exit()
t = r["timing"]
its = [i for s in r["stages"] for i in s["iterations"]]
mon = {k: round(v.get("convergence", (v.get("displacement") or [0, 0])[1]) * 1e3, 4)
       for k, v in list(r["monitors"].items())[:3]}
print(f"{name:22s} {wall:7.1f} {t['build_s']:6.2f} {t['compile_s']:7.2f} {t['solve_s']:7.2f} "
      f"{r['status']:>16s} {max(its) if its else 0:5d} {sorted(its)[len(its) // 2] if its else 0:5d}  {mon} mm")
EOF
}

START=$(date +%s)
DEADLINE="${DEADLINE:-540}"  # s for the whole script: each step's limit is cut to what is left

left() {  # seconds left before the deadline, at most $1
  local rest=$((DEADLINE - ($(date +%s) - START)))
  echo $((rest < $1 ? rest : $1))
}

run() {  # name, limit (s), jaxdem arguments ...
  local name=$1 limit; limit=$(left "$2"); shift 2
  local out="$WORK/out-$name" t0 t1
  if [ "$limit" -lt 5 ]; then echo "$name: skipped, the deadline" | tee -a "$OUT/table.txt"; return; fi
  t0=$(date +%s.%N)
  timeout "$limit" python3 -m jaxdem "$@" --out "$out" --no-figures > "$OUT/$name.log" 2>&1
  t1=$(date +%s.%N)
  row "$name" "$(python3 -c "print($t1 - $t0)")" "$out" | tee -a "$OUT/table.txt"
}

echo "case                      wall  build compile   solve           status maxit medit  monitors" | tee "$OUT/table.txt"
# Most wanted first (float64), then float32; the deadline cuts what does not fit.
run demo-float64-cold 90 run "$WORK/demo-float64.toml"
run demo-float64-warm 60 run "$WORK/demo-float64.toml"
run ex2-float64 120 run "$WORK/ex2-float64.toml"
run grid100-float64 150 run "$WORK/grid100-float64.toml"
limit=$(left 90)
if [ "$limit" -ge 5 ]; then
  timeout "$limit" python3 benchmarks/bench_throughput.py --spacings 7.0 --samples 1024 --loop 16 \
    --repeats 1 2>&1 | tee "$OUT/throughput.txt"
fi
if [ "${FLOAT32:-1}" = 1 ]; then  # FLOAT32=0: the float64 cases and the sweep alone
  run demo-float32 60 run "$WORK/demo-float32.toml"
  run ex2-float32 90 run "$WORK/ex2-float32.toml"
  run grid100-float32 120 run "$WORK/grid100-float32.toml"
fi
