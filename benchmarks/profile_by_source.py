"""Where a warm solve's device time goes, by jaxdem source line, and what its increment
program is made of (a diagnostic, not a benchmark: it measures no error).

jaxdem compiles its programs without source locations (``compile_cache._without_locations``:
they make a stored program a fifth larger). This script compiles them with the locations,
into a cache directory of its own, and dumps XLA's optimised increment; it then solves the
scene again under ``jax.profiler`` and charges each XLA operation's own time (its
children's taken out) to the innermost source line of the operation's stack frame in the
dump (a fusion takes the line of its root: the operation the others were fused into).
Also printed: the optimised increment's HLO instructions by function (a program's size
is its time to compile and to load).

    PYTHONPATH=. python benchmarks/profile_by_source.py                  # the demo
    PYTHONPATH=. python benchmarks/profile_by_source.py examples/seed_example2_tunnel.toml
    PYTHONPATH=. python benchmarks/profile_by_source.py SCENE --quick     # LLVM level 0

``--quick`` compiles the increment as a brief single solve is (the demo is, whatever
this flag says: ``compile_cache.QUICK_WORK``).
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _tables(text: str):
    """The dump's stack-frame tables: frame id -> (file, function, line), parent id."""
    lines = text.splitlines()

    def table(name):
        out = {}
        if name not in lines:
            return out
        for line in lines[lines.index(name) + 1:]:
            m = re.match(r"^(\d+) (.*)$", line)
            if not m:
                break
            out[int(m.group(1))] = m.group(2)
        return out

    def fields(s):
        return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", s)}

    files = {k: Path(v.strip('"')).name for k, v in table("FileNames").items()}
    funcs = {k: v.strip('"') for k, v in table("FunctionNames").items()}
    locs = {k: fields(v) for k, v in table("FileLocations").items()}
    frames = {}
    for k, v in table("StackFrames").items():
        loc = locs[fields(v)["file_location_id"]]
        frames[k] = (files[loc["file_name_id"]], funcs[loc["function_name_id"]], loc["line"])
    return frames


def _own_times(trace_dir: str):
    """Each XLA operation's own time (us) and call count in a jax.profiler trace."""
    path = glob.glob(f"{trace_dir}/**/*.trace.json.gz", recursive=True)[0]
    events = [e for e in json.load(gzip.open(path))["traceEvents"] if e.get("ph") == "X"]
    by_thread = collections.defaultdict(list)
    for e in events:
        if not e["name"].startswith(("$", "np.asarray")):
            by_thread[e["tid"]].append(e)
    own, calls = collections.Counter(), collections.Counter()
    for es in by_thread.values():
        es.sort(key=lambda e: (e["ts"], -e["dur"]))
        stack = []
        for e in es:
            while stack and stack[-1]["ts"] + stack[-1]["dur"] <= e["ts"]:
                stack.pop()
            if stack:
                own[stack[-1]["name"]] -= e["dur"]
            own[e["name"]] += e["dur"]
            calls[e["name"]] += 1
            stack.append(e)
    return own, calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", default=str(HERE.parent / "jaxdem" / "data"
                                                          / "demo.toml"))
    parser.add_argument("--quick", action="store_true", help="compile at LLVM level 0")
    parser.add_argument("--top", type=int, default=25)
    args = parser.parse_args()

    work = tempfile.mkdtemp(prefix="jaxdem-profile-")
    dump = os.path.join(work, "dump")
    os.environ["JAXDEM_CACHE_DIR"] = os.path.join(work, "cache")
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --xla_dump_to={dump}"
                               " --xla_dump_hlo_as_text --xla_dump_hlo_pass_re=^$")
    import jax

    import jaxdem
    from jaxdem import solver
    from jaxdem.core import compile_cache

    compile_cache._without_locations = lambda lowered: lowered
    if args.quick:
        solver.QUICK_WORK = compile_cache.QUICK_WORK = 10**12
    jaxdem.config.configure()
    scene = jaxdem.load_scene(args.scene)
    jaxdem.solve(scene)  # compiles (and dumps)
    trace = os.path.join(work, "trace")
    jax.profiler.start_trace(trace)
    result = jaxdem.solve(scene)
    jax.profiler.stop_trace()
    its = sum(sum(s["iterations"]) for s in result.to_dict()["stages"])

    texts = sorted(glob.glob(f"{dump}/*jit_increment.cpu_after_optimizations.txt"),
                   key=os.path.getsize)
    if not texts:
        sys.exit("no optimised increment in the dump")
    text = Path(texts[-1]).read_text()
    frames = _tables(text)
    frame_of = {m.group(1): int(m.group(2)) for m in re.finditer(
        r"^\s*(?:ROOT )?%([\w.\-]+) = .*?stack_frame_id=(\d+)", text, re.M)}

    def where(fid):
        """(source line, function) of a stack frame."""
        if fid not in frames:
            return "(no location)", "(no location)"
        file, function, line = frames[fid]
        return f"{file}:{line} {function}", f"{file} {function}"

    own, calls = _own_times(trace)
    by_line, by_function = collections.Counter(), collections.Counter()
    for name, us in own.items():
        if "Execute" in name or "wait" in name:
            continue
        line, function = where(frame_of.get(name))
        by_line[line] += us
        by_function[function] += us
    total = sum(by_line.values())
    print(f"# {args.scene}: solve {result.timing['solve_s']:.2f} s, {its} Newton iterations;"
          f" device time {total / 1e3:.0f} ms (own times, profiler on)")
    for title, counter in (("source line", by_line), ("function", by_function)):
        print(f"\n{'ms':>8} {'%':>5}  {title}")
        for at, us in counter.most_common(args.top):
            print(f"{us / 1e3:8.1f} {100 * us / total:5.1f}  {at}")
    size = collections.Counter(where(int(f))[1]
                               for f in re.findall(r"stack_frame_id=(\d+)", text))
    print(f"\n{'instr':>8}  HLO instructions of the optimised increment by function "
          f"({sum(size.values())} with a source location)")
    for at, n in size.most_common(args.top):
        print(f"{n:8d}  {at}")
    print(f"\n(dump and trace in {work})")


if __name__ == "__main__":
    main()
