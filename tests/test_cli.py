"""The command line: run, check, exit statuses, error messages, progress output."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from jaxdem.cli import main
from jaxdem.cli._progress import ProgressBar
from jaxdem.core.state import STICK
from jaxdem.results import Result

ROOT = Path(__file__).resolve().parents[1]

# A 1 x 1 m block resting on a fixed 4 x 1 m base; one point monitor at its centroid.
SCENE = """
[scene]
name = "block on base"

[materials.rock]
E = {E}
nu = 0.25
unit_weight = 25.0

[joints.j]
kn = 1e7
ks = 1e7
friction_deg = 30.0

[[blocks]]
vertices = [[0.0, 0.0], [4.0, 0.0], [4.0, 1.0], [0.0, 1.0]]
material = "rock"
fixed = true

[[blocks]]
vertices = [[1.5, 1.0], [2.5, 1.0], [2.5, 2.0], [1.5, 2.0]]
material = "rock"

[[monitors]]
name = "top"
point = [2.0, 1.5]
"""

SPEC_KEYS = {
    "scene",
    "converged",
    "stable",
    "message",
    "monitors",
    "blocks",
    "contacts",
    "bolts",
    "stages",
    "timing",
}


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "block_on_base.toml"
    path.write_text(SCENE.format(E="1e7"))
    return path


def _no_traceback(captured) -> None:
    assert "Traceback" not in captured.err
    assert "Traceback" not in captured.out


# --------------------------------------------------------------------------- end to end


def test_run_end_to_end(scene_file, tmp_path, capsys):
    out = tmp_path / "out"
    status = main(["run", str(scene_file), "--out", str(out)])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    data = json.loads((out / "result.json").read_text())
    assert SPEC_KEYS <= set(data)
    assert data["stable"] is True
    assert "top" in data["monitors"]
    assert (out / "blocks.png").stat().st_size > 0
    assert (out / "monitors.png").stat().st_size > 0
    assert "2 blocks" in captured.out
    assert "step" in captured.err  # the progress lines
    _no_traceback(captured)


def test_check_writes_figure(scene_file, tmp_path, capsys):
    out = tmp_path / "chk"
    assert main(["check", str(scene_file), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.out.startswith("OK: 2 blocks, 1 joint, 1 monitor")  # "1 joint", not "1 joints"
    assert (out / "check.png").stat().st_size > 0


# --------------------------------------------------------------------------- invalid input: 2


@pytest.mark.parametrize("command", ["run", "check"])
def test_invalid_scene_exits_2_with_field_path(tmp_path, capsys, command):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.format(E="-1"))
    assert main([command, str(bad), "--out", str(tmp_path / "o")]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith("error: ")
    assert "materials.rock.E" in captured.err
    _no_traceback(captured)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("materials.rock.E=-5", "materials.rock.E"),
        ("nope.x=1", "nope"),
        ("materials.rock.E", "--set"),
        ("materials.rock.E=abc", "--set"),
    ],
)
def test_bad_set_exits_2(scene_file, tmp_path, capsys, override, field):
    status = main(["run", str(scene_file), "--out", str(tmp_path / "o"), "--set", override])
    assert status == 2
    captured = capsys.readouterr()
    assert "error: " in captured.err and field in captured.err
    _no_traceback(captured)


def test_missing_and_unreadable_files_exit_2(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing.toml")]) == 2
    garbage = tmp_path / "garbage.toml"
    garbage.write_text("[scene\nname = ")
    assert main(["check", str(garbage)]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("error: ") == 2
    assert "missing.toml" in captured.err and "garbage.toml" in captured.err
    _no_traceback(captured)


def test_usage_errors_and_help(capsys):
    assert main([]) == 2
    assert main(["run"]) == 2  # argparse: SCENE.toml is required
    assert main(["--help"]) == 0
    assert "demo" in capsys.readouterr().out


def test_help_does_not_import_plotting():
    # jaxdem/__init__.py imports jax (float64 switch); the command line adds nothing heavier.
    code = (
        "import sys\n"
        "from jaxdem.cli import main\n"
        "assert main(['--help']) == 0\n"
        "assert 'matplotlib' not in sys.modules and 'jaxdem.plots' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


def test_python_dash_m(tmp_path):
    """``python -m jaxdem`` ends its process at once after the command (cli.entry,
    os._exit): the exit status and everything printed to a pipe still come through."""
    proc = subprocess.run(
        [sys.executable, "-m", "jaxdem", "run", str(tmp_path / "nope.toml")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ") and "Traceback" not in proc.stderr
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "jaxdem", "run", str(ROOT / "examples" / "block_on_incline.toml"),
         "--out", str(out), "--no-figures"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.rstrip().splitlines()[-1] == f"wrote {out / 'result.json'}"
    assert json.loads((out / "result.json").read_text())["converged"]


# --------------------------------------------------------------------------- solver outcomes


def _synthetic_result(scene, status: str) -> Result:
    """A Result for ``scene`` as the solver would return it with this status."""
    initial = [np.asarray(b.vertices) for b in scene.blocks]
    moving = [1] if status == "mechanism" else []
    u = np.array([[0.0, 0.0, 0.0], [0.3 if moving else 1e-4, -1e-4, 0.0]])
    return Result(
        scene=scene.name,
        converged=status in ("converged", "mechanism"),
        stable=not moving,
        status=status,
        message=f"synthetic {status}",
        monitors={"top": {"displacement": u[1, :2].tolist()}},
        blocks=[
            {
                "id": i,
                "centroid": v.mean(axis=0).tolist(),
                "u": u[i].tolist(),
                "stress": [0.0, 0.0, 0.0],
                "fixed": bool(b.fixed),
            }
            for i, (v, b) in enumerate(zip(initial, scene.blocks, strict=True))
        ],
        contacts={"total": 2, "open": 0, "slipping": 0},
        bolts=[],
        stages=[
            {
                "name": "load",
                "converged": True,
                "stable": not moving,
                "iterations": [3, 2],
                "monitors": {"top": [1e-4, 1.4e-4]},
            }
        ],
        moving_blocks=moving,
        equilibrium={},
        timing={"build_s": 0.01, "compile_s": 0.5, "solve_s": 0.02},
        geometry={
            "initial_vertices": initial,
            "final_vertices": [v + d[:2] for v, d in zip(initial, u, strict=True)],
            "fixed": [b.fixed for b in scene.blocks],
            "walls": [],
            "contacts": {
                "points": np.array([[1.5, 1.0], [2.5, 1.0]]),
                "state": np.array([STICK, STICK]),
            },
            "monitors": {"top": np.array([2.0, 1.5])},
        },
        history=[
            {"stage": "load", "step": k, "load_factor": k / 2, "monitors": {"top": 7e-5 * k}}
            for k in (1, 2)
        ],
    )


@pytest.fixture
def fake_solver(monkeypatch):
    """Replace ``jaxdem.solver.solve``; returns a setter for the status to answer with.

    Where the real solver module is not importable a stand-in module is used, so
    that these tests check the command line alone.
    """
    try:
        from jaxdem import solver
    except ImportError:
        import jaxdem

        solver = types.ModuleType("jaxdem.solver")
        monkeypatch.setitem(sys.modules, "jaxdem.solver", solver)
        monkeypatch.setattr(jaxdem, "solver", solver, raising=False)
    answer = {"status": "converged"}

    def solve(scene, set=None, progress=None):
        for step in (1, 2):
            if progress is not None:
                progress(
                    {
                        "stage": "load",
                        "step": step,
                        "n_steps": 2,
                        "status": "converged",
                        "iterations": 3,
                        "substeps": 1,
                        "residual": 1e-12,
                    }
                )
        return _synthetic_result(scene, answer["status"])

    monkeypatch.setattr(solver, "solve", solve, raising=False)
    return lambda status: answer.update(status=status)


@pytest.mark.parametrize(
    ("status", "code"),
    [
        ("converged", 0),
        ("mechanism", 0),
        ("iteration_limit", 3),
        ("non_finite", 3),
        ("capacity_overflow", 3),
    ],
)
def test_exit_status_follows_solver_status(fake_solver, scene_file, tmp_path, capsys, status, code):
    fake_solver(status)
    out = tmp_path / "o"
    assert main(["run", str(scene_file), "--out", str(out)]) == code
    captured = capsys.readouterr()
    # result.json and figures are written in every case, to look at what went wrong
    data = json.loads((out / "result.json").read_text())
    assert SPEC_KEYS <= set(data) and data["status"] == status
    assert (out / "blocks.png").is_file() and (out / "monitors.png").is_file()
    assert f"status: {status}" in captured.out
    if status == "mechanism":
        assert "moving blocks: 1" in captured.out
    elif status == "converged":
        assert "stable: yes" in captured.out
    else:
        # No mechanism found, but no equilibrium either: not "stable: yes".
        assert f"stable: not known (no admissible equilibrium: {status})" in captured.out
        assert "stable: yes" not in captured.out
    _no_traceback(captured)


def test_run_prints_progress_monitors_and_times(fake_solver, scene_file, tmp_path, capsys):
    assert (
        main(
            [
                "run",
                str(scene_file),
                "--out",
                str(tmp_path / "o"),
                "--set",
                "joints.j.kn=2e7",
                "materials.rock.nu=0.3",
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.startswith("stage ")]
    assert len(lines) == 2  # stderr is not a terminal: one line per increment
    assert "step 2/2" in lines[-1] and "res 1.0e-12" in lines[-1]
    assert "top" in captured.out and "uy (mm)" in captured.out
    assert "compile 0.50 s" in captured.out
    assert "result.json" in captured.out and "blocks.png" in captured.out


def test_no_figures_and_the_answer_before_the_figures(fake_solver, scene_file, tmp_path,
                                                      capsys, monkeypatch):
    phases = tmp_path / "phases.json"
    monkeypatch.setenv("JAXDEM_PHASES", str(phases))
    out = tmp_path / "o"
    assert main(["run", str(scene_file), "--out", str(out), "--no-figures"]) == 0
    assert (out / "result.json").is_file() and not list(out.glob("*.png"))
    assert "status: converged" in capsys.readouterr().out
    marks = json.loads(phases.read_text())
    assert marks["solved"] <= marks["answered"] <= marks["figures"] <= marks["end"]
    # With figures: result.json and the summary are out before the first figure is drawn.
    import jaxdem.plots as plots

    seen = {}
    real = plots.write_figures

    def spy(result, folder):
        seen["json"] = (folder / "result.json").is_file()
        seen["summary"] = "status: converged" in capsys.readouterr().out
        return real(result, folder)

    monkeypatch.setattr(plots, "write_figures", spy)
    assert main(["run", str(scene_file), "--out", str(tmp_path / "f")]) == 0
    assert seen == {"json": True, "summary": True}
    assert (tmp_path / "f" / "blocks.png").is_file()


def test_default_out_dir(fake_solver, scene_file, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(scene_file)]) == 0
    assert (tmp_path / "out" / "block_on_base" / "result.json").is_file()


# --------------------------------------------------------------------------- progress bar


class _Stream:
    def __init__(self, tty: bool):
        self.text, self.tty = "", tty

    def write(self, s: str) -> None:
        self.text += s

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self.tty


def _event(stage: str, step: int, n_steps: int = 10) -> dict:
    return {
        "stage": stage,
        "step": step,
        "n_steps": n_steps,
        "status": "converged",
        "iterations": 12,
        "substeps": 1,
        "residual": 3.1e-11,
    }


def test_progress_bar_format():
    bar = ProgressBar(n_stages=2, stream=_Stream(False), width=10)
    assert (
        bar.format(_event("dig", 3)) == "stage 1/2 dig [###-------] step 3/10  it 12  res 3.1e-11"
    )
    assert bar.format(_event("bolt", 10)).startswith("stage 2/2 bolt [##########] step 10/10")


def test_progress_bar_terminal_redraws_in_place():
    stream = _Stream(True)
    with ProgressBar(stream=stream) as bar:
        bar(_event("a", 1, 2))
        bar(_event("a", 2, 2))
    assert stream.text.count("\r") == 2 and stream.text.endswith("\n")
    assert stream.text.count("\n") == 1


def test_demo_solves_the_bundled_tunnel(tmp_path, capsys):
    """The README's quick start: `jaxdem demo` solves the bundled tunnel and writes results."""
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["converged"] and result["stable"]
    assert result["monitors"]["span"]["convergence"] > 0  # the tunnel closes in
    assert all(b["state"] in ("elastic", "yielded", "pulled out") for b in result["bolts"])
    assert (out / "blocks.png").stat().st_size > 0


# --------------------------------------------------------------------------- issue 19: console


def test_version(capsys):
    from jaxdem import __version__

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxdem {__version__}"


def test_the_command_collects_garbage_less_often_and_main_leaves_the_callers_setting(capsys):
    """``jaxdem`` (:func:`entry`) raises the collector's youngest threshold for its own
    process (the collector's walks of JAX's objects cost the demo 0.47 s cold); a Python
    caller of :func:`main` keeps its own."""
    import gc
    import subprocess
    import sys

    from jaxdem.cli import GC_YOUNG

    before = gc.get_threshold()
    assert main(["--version"]) == 0
    assert gc.get_threshold() == before
    probe = ("import gc, jaxdem.cli as cli\n"
             "cli.main = lambda: print(gc.get_threshold()[0], flush=True) or 0\n"
             "cli.entry()\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True).stdout
    assert int(out) == GC_YOUNG > 700


def test_help_names_the_real_default_out_dir(capsys):
    assert main(["run", "--help"]) == 0
    out = capsys.readouterr().out
    assert "out/<file name without .toml>" in out and "<scene name>" not in out


def test_scene_summary_counts_generated_blocks_and_plurals(scene_file):
    from jaxdem.cli._summaries import scene_summary
    from jaxdem.rockmass import generate
    from jaxdem.scene import load_scene

    assert scene_summary(load_scene(scene_file)) == "2 blocks, 1 joint, 1 monitor"
    demo = load_scene("jaxdem/data/demo.toml")
    n = len(generate(demo).pieces)
    assert n > 400
    assert scene_summary(demo).startswith(f"{n:,} blocks ({n:,} generated), 2 joints")


def test_stage_counter_counts_the_stages_the_solver_reports():
    from jaxdem.cli._summaries import stage_count
    from jaxdem.scene import load_scene

    # The demo: the in-situ state, then one excavation stage, "stage 1/1" (the initial
    # state is named, not counted).
    assert stage_count(load_scene("jaxdem/data/demo.toml")) == 1
    # Two [[stages]] after the in-situ state: stage = 2 in the file is "stage 2/2".
    assert stage_count(load_scene("examples/staged_tunnel.toml")) == 2
    bar = ProgressBar(n_stages=2, stream=_Stream(False), width=10)
    seen = [bar.format(dict(_event(stage, 1), stage_index=k, n_stages=2)).split(" [")[0]
            for k, stage in enumerate(("initial", "heading", "bench"))]
    assert seen == ["initial state (in-situ)", "stage 1/2 heading", "stage 2/2 bench"]


def test_set_is_shown_with_the_scene_name(fake_solver, scene_file, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["run", str(scene_file), "--out", str(out), "--set", "joints.j.kn=2e7"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("block on base (--set joints.j.kn=2e+07): 2 blocks")
    data = json.loads((out / "result.json").read_text())
    assert data["scene"] == "block on base"
    assert data["overrides"] == {"joints.j.kn": 2e7}


def test_set_takes_a_word_for_a_solver_choice(fake_solver, scene_file, tmp_path, capsys,
                                              monkeypatch):
    """``--set solver.linear_solver=sparse`` reaches the scene the solver gets, and the
    name and result.json say so as for a number."""
    from jaxdem import solver

    seen = []
    answer = solver.solve
    monkeypatch.setattr(solver, "solve",
                        lambda scene, **kw: seen.append(scene) or answer(scene, **kw))
    out = tmp_path / "o"
    assert main(["run", str(scene_file), "--out", str(out), "--set", "joints.j.kn=2e7",
                 "solver.linear_solver=sparse"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("block on base (--set joints.j.kn=2e+07 solver.linear_solver=sparse)")
    assert seen[-1].solver.linear_solver == "sparse"
    data = json.loads((out / "result.json").read_text())
    assert data["overrides"] == {"joints.j.kn": 2e7, "solver.linear_solver": "sparse"}
    # A word that is none of the choice's values: refused before any computation.
    assert main(["run", str(scene_file), "--out", str(out), "--set",
                 "solver.linear_solver=lu"]) == 2
    assert "solver.linear_solver: must be one of auto, dense, sparse, cg" in capsys.readouterr().err


def test_sweep_says_what_it_will_solve_before_starting(scene_file, tmp_path, capsys,
                                                       monkeypatch):
    import importlib

    sweep_module = importlib.import_module("jaxdem.sweep")  # jaxdem.sweep is also the function

    # Not an Exception: the command line turns a solver's exceptions into exit 3.
    class Started(BaseException):
        pass

    def sweep(*args, **kwargs):
        raise Started

    monkeypatch.setattr(sweep_module, "sweep", sweep)
    with pytest.raises(Started):
        main(["sweep", str(scene_file), "--vary", "joints.j.kn=1e6:1e7:log",
              "joints.j.friction_deg=20:40", "--samples", "16", "--out", str(tmp_path / "s")])
    out = capsys.readouterr().out
    assert ("sweep grid: 16 levels x 2 parameters = 256 solves (--samples is the levels per "
            "parameter), plus 5 for the tornado") in out
    with pytest.raises(Started):
        main(["sweep", str(scene_file), "--vary", "joints.j.kn=1e6:1e7:log", "--samples", "16",
              "--method", "lhs", "--out", str(tmp_path / "s")])
    assert "sweep lhs: 16 samples (seed 0), plus 3 for the tornado" in capsys.readouterr().out
    with pytest.raises(Started):  # a grid's ends are the tornado's: solved once
        main(["sweep", str(scene_file), "--vary", "joints.j.kn=1e6:1e7:log", "--samples", "16",
              "--out", str(tmp_path / "s")])
    assert ("16 solves (--samples is the levels per parameter), plus 1 for the tornado (2 of "
            "its 3 points are samples)") in capsys.readouterr().out


def test_bad_vary_path_names_the_parameter_not_a_sample(scene_file, tmp_path, capsys):
    code = main(["sweep", str(scene_file), "--vary", "joints.nope.kn=1e6:1e7", "--samples", "2",
                 "--out", str(tmp_path / "s")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --vary joints.nope.kn: no such parameter in the scene")
    assert "sample" not in err


def test_sweep_to_csv_without_a_path_returns_the_text(tmp_path):
    from jaxdem.batch import BatchResult
    from jaxdem.sweep import SweepResult, Variable

    batch = BatchResult(params=["joints.j.kn"], theta=np.array([[1e6], [2e6]]),
                        monitors={"top": np.array([[0.0, -1e-3], [0.0, -5e-4]])},
                        status=["converged", "mechanism"], stable=np.array([True, False]),
                        converged=np.array([True, False]), iterations=np.array([3, 9]),
                        timing={}, stopped=[None, {"stage": "loading", "load_factor": 0.5}],
                        moving_volume=np.array([0.0, 0.02]),
                        small_mechanism=np.array([False, True]), loose_blocks=[[3, 4], []])
    result = SweepResult(variables=[Variable.parse("joints.j.kn=1e6:2e6")], method="grid",
                         seed=0, batch=batch, tornado={}, probability={}, mode="batched")
    text = result.to_csv()
    assert isinstance(text, str)
    assert text.splitlines() == [
        "sample,joints.j.kn,top.ux,top.uy,stable,converged,status,stopped_stage,"
        "stopped_load_factor,moving_volume,small_mechanism,loose_blocks",
        "0,1000000.0,0.0,-0.001,True,True,converged,,nan,0.0,False,2",
        "1,2000000.0,0.0,-0.0005,False,False,mechanism,loading,0.5,0.02,True,0",
    ]
    path = result.to_csv(tmp_path / "sweep.csv")
    assert path.read_bytes().decode() == text  # the same CSV (csv.writer line ends)


def test_the_sweep_summary_says_where_the_samples_without_an_answer_stopped():
    """Two samples at the iteration limit in the excavation (at 1/2 and 3/4 of it), one
    in the loading, a mechanism and an equilibrium: the summary groups those without an
    answer by stage with their load factors (a mechanism is an answer, not listed)."""
    from jaxdem.batch import BatchResult
    from jaxdem.cli._summaries import sweep_summary
    from jaxdem.sweep import SweepResult, Variable, probability_of_instability

    status = ["iteration_limit", "converged", "iteration_limit", "mechanism", "non_finite"]
    stopped = [{"stage": "excavation", "load_factor": 0.75}, None,
               {"stage": "excavation", "load_factor": 0.5},
               {"stage": "excavation", "load_factor": 0.25},
               {"stage": "loading", "load_factor": 1.0}]
    arr = np.array(status)
    batch = BatchResult(params=["joints.j.kn"], theta=np.ones((5, 1)), monitors={},
                        status=status, stable=arr != "mechanism", converged=arr == "converged",
                        iterations=np.zeros(5, int),
                        timing=dict(solve_s=1.0, compile_s=0.5, chunk=5), stopped=stopped)
    result = SweepResult(variables=[Variable.parse("joints.j.kn=1e6:2e6")], method="grid",
                         seed=0, batch=batch, tornado={},
                         probability=probability_of_instability(batch), mode="batched")
    lines = sweep_summary(result).splitlines()
    assert lines[0].startswith("5 samples: 1 in equilibrium, 1 mechanisms, 3 without an answer")
    assert ("2 without an answer stopped in stage excavation at load factor 0.5 to 0.75 "
            "(sweep.csv: stopped_stage, stopped_load_factor)") in lines
    assert ("1 without an answer stopped in stage loading at load factor 1 "
            "(sweep.csv: stopped_stage, stopped_load_factor)") in lines
    assert not any("0.25" in line for line in lines)
    assert not any("small" in line for line in lines)
    # The mechanism's blocks together 0.02 m3/m, no larger than max_loose_volume: said so.
    assert not any("loose" in line for line in lines)
    small = dataclasses.replace(batch, moving_volume=np.array([0.0, 0.0, 0.0, 0.02, 0.0]),
                                small_mechanism=np.array([False, False, False, True, False]),
                                loose_blocks=[[], [7, 8], [], [], []])
    result = dataclasses.replace(result, batch=small,
                                 probability=probability_of_instability(small))
    assert result.probability["small"] == 1
    said = sweep_summary(result)
    assert ("1 of the 1 mechanisms are small: their moving blocks together no larger than "
            "solver.max_loose_volume") in said
    assert "1 samples removed loose blocks that fell free" in said


# --------------------------------------------------------------------------- --view


def test_view_sets_the_second_panel_of_blocks_png(fake_solver, scene_file, tmp_path,
                                                  monkeypatch):
    import jaxdem.plots._canvas as canvas

    limits = {}

    def keep(fig, path):
        if path.name == "blocks.png":
            limits["axes"] = [(ax.get_xlim(), ax.get_ylim()) for ax in fig.axes]

    monkeypatch.setattr(canvas, "inspect", keep)
    out = tmp_path / "o"
    assert main(["run", str(scene_file), "--out", str(out), "--view", "0", "1", "0.5",
                 "1.5"]) == 0
    assert len(limits["axes"]) == 2
    assert limits["axes"][1] == (pytest.approx((0.0, 1.0)), pytest.approx((0.5, 1.5)))


@pytest.mark.parametrize("view", [["1", "0", "0", "1"], ["0", "1", "2", "2"],
                                  ["0", "nan", "0", "1"]])
def test_bad_view_exits_2_before_solving(scene_file, tmp_path, capsys, view):
    status = main(["run", str(scene_file), "--out", str(tmp_path / "o"), "--view", *view])
    assert status == 2
    captured = capsys.readouterr()
    assert "error: " in captured.err and "--view" in captured.err
    assert not (tmp_path / "o" / "result.json").exists()
    _no_traceback(captured)
