"""Bad input is refused before any computation: one message naming the field, exit status 2,
no traceback (SPEC sections 2 and 3).

tests/test_scene.py holds the basic refusals of each field (REFUSALS, ROCK_REFUSALS); this
file covers the rest of the contract: every numeric and string field with a wrong value,
limits on sizes (steps, generated blocks, vertices, coordinates, files), polygons and
lines in every polygon-valued field, TOML-level mistakes (a key given twice), unreadable
files, the Python interface's exception type, and the command line: each category once
through ``main`` (exit 2, one line on stderr, nothing computed, no output folder) and once
through a real ``python -m jaxdem`` process.
"""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from test_cli import SCENE
from test_scene import _set, rock_scene_dict, setting, valid_scene_dict

import jaxdem
from jaxdem.cli import main
from jaxdem.scene import SceneError, apply_overrides, load_scene, parse_scene, parse_set_arguments
from jaxdem.scene import _toml as scene_toml

SQUARE = [[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]]


def _leaves(node, path: tuple = ()) -> Iterator[tuple[str, object]]:
    """(dotted path, value) of every scalar in a scene dict."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _leaves(value, (*path, str(i)))
    else:
        yield ".".join(path), node


def _refused(data: dict) -> SceneError:
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    return info.value


def _circle_points(n: int, r: float = 0.5, c: tuple = (1.5, 1.5)) -> list:
    return [[c[0] + r * math.cos(2 * math.pi * k / n), c[1] + r * math.sin(2 * math.pi * k / n)]
            for k in range(n)]


def _replace_excavation(index: int, table: dict) -> Callable[[dict], None]:
    return lambda d: d["excavations"].__setitem__(index, table)


# --------------------------------------------------------------------------- every field


BAD_NUMBERS = [math.nan, math.inf, -math.inf, 1e300, "1", True, [1.0]]
BAD_STRINGS = [3, 1.5, True, ["a"], {}]


@pytest.mark.parametrize("base", [valid_scene_dict, rock_scene_dict], ids=["blocks", "rock"])
def test_every_field_with_a_wrong_value_is_refused_naming_it(base):
    """NaN, inf, 1e300, a string, a boolean, a list in every numeric field (coordinates
    included); a number, a list or a table in every string field: SceneError at that path."""
    cases = 0
    for path, value in _leaves(base()):
        if isinstance(value, bool):
            bad = [1, "true"]
        elif isinstance(value, (int, float)):
            bad = BAD_NUMBERS
        else:
            bad = BAD_STRINGS
        for wrong in bad:
            data = base()
            _set(data, path, wrong)
            err = _refused(data)
            assert err.path == path, (path, wrong, str(err))
            assert str(err).startswith(f"{path}: "), str(err)
            cases += 1
    assert cases > 300


# --------------------------------------------------------------------------- scene gaps

BLOCK_GAPS = [
    # (id, mutation, path, words): refusals of the explicit-block scene
    ("load_steps 1e12", setting("solver", {"load_steps": 10**12}), "solver.load_steps",
     "must be <= 10,000"),
    ("load_steps 1e15 float", setting("solver", {"load_steps": 1e15}), "solver.load_steps",
     "<= 10,000"),
    ("max_iterations huge", setting("solver", {"max_iterations": 10**9}),
     "solver.max_iterations", "<= 10,000"),
    ("max_displacement huge", setting("solver", {"max_displacement": 1e12}),
     "solver.max_displacement", "larger than 10 times the model"),
    ("step_length tiny", setting("solver", {"step_length": 1e-14}), "solver.step_length",
     "between 1e-6 times and once the model's size"),
    ("step_length huge", setting("solver", {"step_length": 1e9}), "solver.step_length",
     "got 1e+09"),
    ("material name with dot", lambda d: d["materials"].update({"a.b": d["materials"]["rock"]}),
     "materials.a.b", "contains '.'"),
    ("material name empty", lambda d: d["materials"].update({" ": d["materials"]["rock"]}),
     "materials. ", "must not be empty"),
    ("joint name with dot", lambda d: d["joints"].update({"j.2": d["joints"]["j"]}),
     "joints.j.2", "joints.j.2.kn"),
    ("block of 1,001 vertices", setting("blocks.1.vertices", _circle_points(1001)),
     "blocks.1.vertices", "too many vertices (got 1,001; at most 1,000)"),
    ("closing point repeated", setting("blocks.1.vertices", [*SQUARE, SQUARE[0]]),
     "blocks.1.vertices", "repeated point (1, 1) at vertices 0 and 4"),
    ("coordinates 1e14", lambda d: [
        _set(d, f"blocks.{i}.vertices", [[x + 1e14, y] for x, y in b["vertices"]])
        for i, b in enumerate(d["blocks"])], "blocks.0.vertices.1", "too far from (0, 0)"),
    ("float32 far away", lambda d: (
        d.update(solver={"dtype": "float32"}),
        [_set(d, f"blocks.{i}.vertices", [[x + 1e4, y] for x, y in b["vertices"]])
         for i, b in enumerate(d["blocks"])]), "blocks.0.vertices.1", "float32"),
    ("discontinuity end far away", setting("discontinuities.0.to", [1e14, 1.0]),
     "discontinuities.0.to", "too far from (0, 0)"),
    ("boundary in the air", lambda d: d["boundaries"].append(
        {"from": [10.0, 10.0], "to": [12.0, 10.0], "condition": "fixed"}),
     "boundaries.2", "does not touch the rock"),
    ("boundary end far away", setting("boundaries.1.to", [1e14, 3.0]), "boundaries.1.to",
     "too far from (0, 0)"),
    ("vertices as tables", setting("blocks.1.vertices", [{"x": 1}, {"x": 2}, {"x": 3}]),
     "blocks.1.vertices.0", "[x, y]"),
    ("integer of 40 digits", setting("materials.rock.E", 10**40), "materials.rock.E",
     "out of range"),
    ("zones without domain", setting("zones", [{"name": "z", "vertices": SQUARE,
                                                "material": "rock"}]),
     "zones", "needs a [domain]"),
]

ROCK_GAPS = [
    # (id, mutation, path, words): refusals of the generated rock-mass scene
    ("mesh would make 1e11 blocks", setting("domain.mesh_size", 1e-4), "domain.mesh_size",
     "would generate about 2.4e+11 blocks, more than the 500,000 accepted"),
    ("graded mesh too fine", lambda d: d["domain"].update(mesh_size=1e-5, mesh_max_size=1e-3),
     "domain.mesh_size", "more than the 500,000"),
    ("spacing would make 1e7 blocks", setting("joints.set1.spacing", 1e-5),
     "joints.set1.spacing", "too small"),
    ("gap would make 1e9 trace ends", setting("joints.set2.gap", 1e-7), "joints.set2.gap",
     "too small"),
    ("joint origin far away", setting("joints.set1.origin", [1e14, 1e14]),
     "joints.set1.origin", "too far from (0, 0)"),
    ("outline repeated point", setting("domain.outline", [[0, 0], [40, 0], [40, 30], [40, 30],
                                                           [0, 30]]),
     "domain.outline", "repeated point (40, 30)"),
    ("outline closed", setting("domain.outline", [[0, 0], [40, 0], [40, 30], [0, 30], [0, 0]]),
     "domain.outline", "repeated point (0, 0) at vertices 0 and 4"),
    ("outline of 1,200 points", setting("domain.outline", _circle_points(1200, 15, (20, 15))),
     "domain.outline", "too many vertices"),
    ("outline degenerate", setting("domain.outline", [[0, 0], [40, 0], [80, 0]]),
     "domain.outline", "degenerate"),
    ("zone bow-tie", setting("zones.0.vertices", [[0, 20], [40, 24], [40, 22], [0, 22]]),
     "zones.0.vertices", "self-intersecting"),
    ("zone repeated point", setting("zones.0.vertices", [[0, 20], [40, 22], [40, 22], [40, 24],
                                                         [0, 22]]),
     "zones.0.vertices", "repeated point"),
    ("zone far away", setting("zones.0.vertices", [[0, 20], [1e14, 22], [1e14, 24], [0, 22]]),
     "zones.0.vertices.1", "too far"),
    ("opening bow-tie", _replace_excavation(1, {"name": "p", "shape": "polygon",
                                                "vertices": [[24, 2], [30, 8], [30, 2], [24, 8]]}),
     "excavations.1.vertices", "self-intersecting"),
    ("opening repeated point", _replace_excavation(
        1, {"name": "p", "shape": "polygon",
            "vertices": [[24, 2], [30, 2], [30, 2], [30, 8], [24, 8]]}),
     "excavations.1.vertices", "repeated point (30, 2)"),
    ("opening wholly outside", setting("excavations.0.center", [100, 100]), "excavations.0",
     "outside the domain"),
    ("opening radius 1e14", setting("excavations.0.radius", 1e14), "excavations.0",
     "outside the domain"),
    ("opening is the whole domain", lambda d: (
        d.update(excavations=[{"name": "all", "shape": "polygon",
                               "vertices": [[0, 0], [40, 0], [40, 30], [0, 30]]}]),
        d.pop("bolts"), d.pop("supports"), d.pop("monitors")),
     "excavations.0", "no rock would be left"),
    ("bolt end in a later opening", setting("bolts.0.to", [26, 8]), "bolts.0.to",
     "inside excavation 'b'"),
    ("bolt end of 3 numbers", setting("bolts.0.from", [1, 2, 3]), "bolts.0.from", "[x, y]"),
    ("water backtracks", setting("water.table", [[0, 25], [30, 25], [20, 20], [40, 20]]),
     "water.table", "not a function of x"),
    ("water vertical step", setting("stages.1.water_table", [[0, 15], [0, 10], [40, 15]]),
     "stages.1.water_table", "x must increase strictly"),
    ("water table a string", setting("water.table", "high"), "water.table", "list of points"),
    ("section end in an opening", lambda d: d["monitors"].append(
        {"name": "s", "from": [12, 13], "to": [12, 10]}), "monitors.1.to", "inside excavation"),
    ("monitor outside the domain", setting("monitors.0.point", [50, 8]), "monitors.0.point",
     "outside the rock"),
    ("stage steps huge", setting("stages.1.load_steps", 10**9), "stages.1.load_steps",
     "<= 10,000"),
    ("in_situ not a table", setting("in_situ", 0.5), "in_situ", "must be a table"),
]


@pytest.mark.parametrize(
    ("base", "mutation", "path", "words"),
    [pytest.param(valid_scene_dict, m, p, w, id=f"block: {i}") for i, m, p, w in BLOCK_GAPS]
    + [pytest.param(rock_scene_dict, m, p, w, id=f"rock: {i}") for i, m, p, w in ROCK_GAPS],
)
def test_scene_refusal(base, mutation, path, words):
    data = base()
    mutation(data)
    err = _refused(data)
    assert err.path == path, str(err)
    assert str(err).startswith(f"{path}: ") and words in str(err), str(err)


def test_block_count_estimate_accepts_a_real_fine_model():
    """The estimate refuses the absurd, not the large: 0.25 m cells (38,400 blocks) pass."""
    data = rock_scene_dict()
    data["domain"]["mesh_size"] = 0.25
    assert parse_scene(data).domain.mesh_size == 0.25


# --------------------------------------------------------------------------- files and TOML

# The command-line tests' block on a base, as a file's text (no leading blank line).
SCENE_TOML = SCENE.format(E="1e7").lstrip("\n")


def _after(marker: str, extra: str) -> str:
    """SCENE_TOML with ``extra`` inserted after the first line equal to ``marker``."""
    return SCENE_TOML.replace(marker + "\n", marker + "\n" + extra + "\n", 1)


TOML_REFUSALS = [
    # (id, text, path, words)
    ("key twice", _after("nu = 0.25", "E = 3e7"), "materials.rock.E",
     "duplicate key: given twice (<string>, line 7)"),
    ("table twice", SCENE_TOML + "\n[materials.rock]\nE = 1\n", "materials.rock",
     "duplicate table: declared twice"),
    ("key twice in an array item", SCENE_TOML + 'name = "again"\n', "monitors.0.name",
     "duplicate key"),
    ("key twice in the second block", _after('vertices = [[1.5, 1.0], [2.5, 1.0], [2.5, 2.0], '
                                             '[1.5, 2.0]]', 'material = "rock"'),
     "blocks.1.material", "duplicate key"),
    ("integer of 5,000 digits", _after("nu = 0.25", "cohesion = 1" + "0" * 5000), "<string>",
     "invalid TOML"),
    ("valid TOML, not a scene", '[project]\nname = "x"\n', "project", "unknown section"),
    ("a bare key", 'title = "x"\n', "title", "unknown section"),
    ("only [scene]", '[scene]\nname = "x"\n', "blocks", "at least one block"),
]


@pytest.mark.parametrize(
    ("text", "path", "words"), [pytest.param(t, p, w, id=i) for i, t, p, w in TOML_REFUSALS]
)
def test_toml_refusal(text, path, words):
    with pytest.raises(SceneError) as info:
        load_scene(text)
    assert info.value.path == path, str(info.value)
    assert str(info.value).startswith(f"{path}: ") and words in str(info.value)


def test_duplicate_key_in_a_file_names_the_file_and_line(tmp_path):
    path = tmp_path / "dup.toml"
    path.write_text(_after("[joints.j]", "kn = 5"))
    with pytest.raises(SceneError, match=r"^joints\.j\.kn: duplicate key: given twice \(.*"
                                         r"dup\.toml, line 11\)$"):
        load_scene(path)


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"", "scene file is empty"),
        (b" \n\t\n", "scene file is empty"),
        (SCENE_TOML.encode() + b"\x00", "invalid TOML"),
        (SCENE_TOML.replace('"block on base"', '"bl\xf6ck"').encode("latin-1"), "not UTF-8"),
    ],
    ids=["empty", "blank", "NUL byte", "latin-1"],
)
def test_unreadable_file_content_names_the_file(tmp_path, content, words):
    path = tmp_path / "scene.toml"
    path.write_bytes(content)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.path == str(path) and words in str(info.value)


def test_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + SCENE_TOML.encode())
    assert load_scene(path).name == "block on base"


def test_file_over_the_size_limit_is_refused_unread(tmp_path, monkeypatch):
    monkeypatch.setattr(scene_toml, "MAX_FILE_BYTES", 100)
    path = tmp_path / "big.toml"
    path.write_text(SCENE_TOML)
    with pytest.raises(SceneError, match="scene file is larger than"):
        load_scene(path)


def test_permission_denied_is_a_scene_error(tmp_path, monkeypatch):
    """(Simulated: the tests may run as root, who can read anything.)"""
    path = tmp_path / "locked.toml"
    path.write_text(SCENE_TOML)

    def denied(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "open", denied)
    with pytest.raises(SceneError, match=r"locked\.toml: cannot read scene file \(Permission"):
        load_scene(path)


# --------------------------------------------------------------------------- Python interface


@pytest.mark.parametrize(
    ("call", "path"),
    [
        (lambda: load_scene(valid_scene_dict(), set=["joints.j.kn=2e6"]), "set"),
        (lambda: apply_overrides(valid_scene_dict(), ["joints.j.kn"]), "set"),
        (lambda: load_scene(valid_scene_dict(), set={"blocks.\u00b2.fixed": 1.0}),
         "blocks.\u00b2.fixed"),
        (lambda: load_scene(valid_scene_dict(), set={3: 1.0}), "--set"),
        (lambda: parse_set_arguments(["joints.j.kn=1", "joints.j.kn=2"]), "--set"),
        (lambda: parse_scene({"scene": {"name": "x"}, "materials": {1: {}}, "blocks": []}),
         "materials.1"),
        (lambda: jaxdem.solve(load_scene(valid_scene_dict()), set=[("joints.j.kn", 1.0)]),
         "set"),
    ],
    ids=["set list", "overrides list", "superscript index", "int path", "--set twice",
         "int table name", "solve set list"],
)
def test_python_interface_raises_scene_error_naming_the_input(call, path):
    """Not TypeError, AttributeError or ValueError (int('\u00b2')), nor a SceneError that
    only names the whole scene: a SceneError naming what is wrong."""
    with pytest.raises(SceneError) as info:
        call()
    assert info.value.path == path, str(info.value)


# --------------------------------------------------------------------------- command line


@pytest.fixture
def no_computation(monkeypatch):
    """Make any solve, batch, model build or rock-mass generation fail the test."""
    from jaxdem import batch, rockmass, solver
    from jaxdem.core import model

    def forbidden(*args, **kwargs):
        raise AssertionError("computation started before the input was refused")

    for module, name in ((solver, "solve"), (batch, "solve_batch"), (model, "build"),
                         (rockmass, "generate")):
        monkeypatch.setattr(module, name, forbidden)


def _scene_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


def _edit(old: str, new: str) -> str:
    assert old in SCENE_TOML
    return SCENE_TOML.replace(old, new, 1)


CLI_SCENES = [
    # (id, scene text, path at the start of the message): one per category
    ("wrong type", _edit("E = 1e7", 'E = "1e7"'), "materials.rock.E: must be a number"),
    ("out of range", _edit("nu = 0.25", "nu = 0.7"), "materials.rock.nu: must be in [0, 0.5)"),
    ("NaN", _edit("kn = 1e7", "kn = nan"), "joints.j.kn: must be finite"),
    ("huge number", _edit("E = 1e7", "E = 1e300"), "materials.rock.E: out of range"),
    ("huge load_steps", SCENE_TOML + "[solver]\nload_steps = 1000000000000\n",
     "solver.load_steps: must be <= 10,000"),
    ("missing section", SCENE_TOML.split("[materials.rock]")[0], "blocks: at least one block"),
    ("undefined material", _edit('material = "rock"\nfixed', 'material = "granit"\nfixed'),
     "blocks.0.material: unknown material 'granit'"),
    ("duplicate name", SCENE_TOML + '[[monitors]]\nname = "top"\npoint = [2.0, 1.2]\n',
     "monitors.1.name: duplicate name 'top'"),
    ("TOML key twice", _edit("nu = 0.25", "nu = 0.25\nnu = 0.3"),
     "materials.rock.nu: duplicate key"),
    ("self-intersecting", _edit("[[1.5, 1.0], [2.5, 1.0], [2.5, 2.0], [1.5, 2.0]]",
                                "[[1.5, 1.0], [2.5, 2.0], [2.5, 1.0], [1.5, 2.0]]"),
     "blocks.1.vertices: self-intersecting polygon"),
    ("repeated point", _edit("[[1.5, 1.0], [2.5, 1.0], [2.5, 2.0], [1.5, 2.0]]",
                             "[[1.5, 1.0], [2.5, 1.0], [2.5, 2.0], [2.5, 2.0], [1.5, 2.0]]"),
     "blocks.1.vertices: repeated point"),
    ("opening outside", SCENE_TOML + '[[excavations]]\nname = "t"\nshape = "circle"\n'
     "center = [9.0, 9.0]\nradius = 0.5\n", "excavations.0: outside the domain"),
    ("bolt end outside", SCENE_TOML + "[[bolts]]\nfrom = [2.0, 1.5]\nto = [2.0, 3.0]\n"
     "stiffness = 1e4\nyield_force = 100\nanchor_capacity = 100\n",
     "bolts.0.to: bolt end (2, 3) is outside the rock"),
    ("water table not f(x)", SCENE_TOML + "[water]\ntable = [[0.0, 3.0], [2.0, 3.0], [1.0, 2.0]]\n",
     "water.table: not a function of x"),
    ("monitor outside", _edit("point = [2.0, 1.5]", "point = [3.0, 1.5]"),
     "monitors.0.point: (3, 1.5) is outside the rock"),
    ("valid TOML, not a scene", '[tool.poetry]\nname = "x"\n', "tool: unknown section"),
]


@pytest.mark.parametrize(
    ("text", "message"), [pytest.param(t, m, id=i) for i, t, m in CLI_SCENES]
)
@pytest.mark.parametrize("command", ["run", "check"])
def test_cli_refuses_bad_scene(tmp_path, capsys, no_computation, command, text, message):
    out = tmp_path / "out"
    status = main([command, str(_scene_file(tmp_path, text)), "--out", str(out)])
    captured = capsys.readouterr()
    assert status == 2
    assert captured.err.startswith("error: " + message), captured.err
    assert len(captured.err.splitlines()) == 1 and "Traceback" not in captured.err
    assert captured.out == ""
    assert not out.exists()


@pytest.fixture
def good_scene(tmp_path) -> Path:
    path = tmp_path / "good.toml"
    path.write_text(SCENE_TOML)
    return path


@pytest.fixture
def observations(tmp_path) -> Callable[[str], Path]:
    def write(text: str) -> Path:
        path = tmp_path / "obs.csv"
        path.write_text(text)
        return path

    return write


CLI_ARGUMENTS = [
    # (id, arguments after the command with {scene}, {dir}, {file}, {csv}, message start)
    ("set missing path", ["run", "{scene}", "--set", "materials.rock.G=1"],
     "--set materials.rock.G: no such parameter"),
    ("set deeper than a number", ["run", "{scene}", "--set", "materials.rock.E.x=1"],
     "--set materials.rock.E.x: no such parameter"),
    ("set superscript index", ["run", "{scene}", "--set", "blocks.\u00b2.fixed=1"],
     "--set blocks.\u00b2.fixed: no such parameter"),
    ("set bad value", ["run", "{scene}", "--set", "materials.rock.E=abc"],
     "--set: value of materials.rock.E must be a number"),
    ("set inf", ["run", "{scene}", "--set", "materials.rock.E=1e400"],
     "--set: value of materials.rock.E must be finite"),
    ("set out of range", ["run", "{scene}", "--set", "solver.load_steps=1e9"],
     "solver.load_steps: must be <= 10,000"),
    ("set twice", ["run", "{scene}", "--set", "joints.j.kn=1", "joints.j.kn=2"],
     "--set: joints.j.kn is given twice"),
    ("scene is a folder", ["run", "{dir}"], "{dir}: cannot read scene file"),
    ("scene missing", ["check", "{dir}/none.toml"], "{dir}/none.toml: cannot read scene file"),
    ("out is a file", ["run", "{scene}", "--out", "{file}"],
     "--out {file}: {file} exists and is not a folder"),
    ("out under a file", ["check", "{scene}", "--out", "{file}/sub"],
     "--out {file}/sub: {file} exists and is not a folder"),
    ("usage: bad int", ["sweep", "{scene}", "--vary", "joints.j.kn=1:2", "--samples", "x"],
     "--samples: invalid int value: 'x'"),
    ("usage: missing argument", ["run"], "jaxdem run: the following arguments are required"),
    ("usage: unknown option", ["run", "{scene}", "--frobnicate"],
     "jaxdem: unrecognized arguments: --frobnicate"),
    ("usage: bad float", ["fos", "{scene}", "--tolerance", "x"], "--tolerance: invalid float"),
    ("sweep chunk 0", ["sweep", "{scene}", "--vary", "joints.j.kn=1:2", "--samples", "2",
                       "--chunk", "0"], "--chunk must be >= 1"),
    ("sweep seed < 0", ["sweep", "{scene}", "--vary", "joints.j.kn=1:2", "--samples", "2",
                        "--seed", "-1"], "--seed must be >= 0"),
    ("sweep samples huge", ["sweep", "{scene}", "--vary", "joints.j.kn=1:2", "--samples",
                            "1000000000000"], "--samples: 1,000,000,000,000 solves"),
    ("sweep unknown path", ["sweep", "{scene}", "--vary", "joints.q.kn=1:2", "--samples", "2"],
     "--vary joints.q.kn:"),
    ("fos trials huge", ["fos", "{scene}", "--trials", "5000"],
     "--trials must be an integer from 2 to 1024"),
    ("fit iterations huge", ["back-analyse", "{scene}", "--observed", "{csv}", "--fit",
                             "joints.j.kn", "--max-iterations", "20000"],
     "--max-iterations must be <= 10,000"),
]


@pytest.mark.parametrize(
    ("arguments", "message"), [pytest.param(a, m, id=i) for i, a, m in CLI_ARGUMENTS]
)
def test_cli_refuses_bad_arguments(tmp_path, capsys, no_computation, good_scene, observations,
                                   arguments, message):
    csv = observations("monitor,value,std,component\ntop,0.001,0.0001,uy\n")
    names = dict(scene=good_scene, dir=tmp_path, file=good_scene, csv=csv)
    argv = [a.format(**names) for a in arguments]
    if "--out" not in argv and len(argv) > 1:
        argv += ["--out", str(tmp_path / "out")]
    status = main(argv)
    captured = capsys.readouterr()
    assert status == 2
    assert captured.err.startswith("error: " + message.format(**names)), captured.err
    assert len(captured.err.splitlines()) == 1 and "Traceback" not in captured.err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("csv", "message"),
    [
        ("monitor,value,std\nnope,0.01,0.001\n", "row 2, monitor: no monitor named 'nope'"),
        ("monitor,value,std,component\ntop,abc,0.001,uy\n", "row 2, value: must be a number"),
        ("monitor,value,std,component\ntop,0.01,0,uy\n", "row 2, std: must be > 0"),
        ("monitor,value,std,component\ntop,0.01,-1,uy\n", "row 2, std: must be > 0"),
        ("", "empty file"),
        ("monitor,value,std\n", "no observations"),
    ],
    ids=["unknown monitor", "not a number", "zero std", "negative std", "empty", "header only"],
)
def test_cli_refuses_bad_observations(tmp_path, capsys, no_computation, good_scene,
                                      observations, csv, message):
    path = observations(csv)
    status = main(["back-analyse", str(good_scene), "--observed", str(path), "--fit",
                   "joints.j.kn", "--out", str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert status == 2
    assert captured.err.startswith(f"error: {path}") and message in captured.err, captured.err
    assert len(captured.err.splitlines()) == 1 and "Traceback" not in captured.err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["run", "{bad}", "--out", "{out}"], "error: blocks.1.vertices: self-intersecting"),
        (["fos", "{bad}", "--trials", "x"], "error: --trials: invalid int value: 'x'"),
    ],
    ids=["bad scene", "usage"],
)
def test_real_process_exits_2_with_one_line(tmp_path, arguments, message):
    """``python -m jaxdem``: exit status 2, one line on stderr, no traceback, no output."""
    bad = _scene_file(tmp_path, _edit("[[1.5, 1.0], [2.5, 1.0], [2.5, 2.0], [1.5, 2.0]]",
                                      "[[1.5, 1.0], [2.5, 2.0], [2.5, 1.0], [1.5, 2.0]]"))
    out = tmp_path / "out"
    argv = [a.format(bad=bad, out=out) for a in arguments]
    proc = subprocess.run([sys.executable, "-m", "jaxdem", *argv], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith(message), proc.stderr
    assert len(proc.stderr.splitlines()) == 1 and "Traceback" not in proc.stderr
    assert proc.stdout == "" and not out.exists()
