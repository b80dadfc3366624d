"""Scene files: loading, defaults, every refusal, overrides (jaxdem.scene)."""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxdem.scene import (
    InSitu,
    Joint,
    Scene,
    SceneError,
    SolverSettings,
    Support,
    apply_overrides,
    load_scene,
    parse_scene,
    parse_set_arguments,
)

VALID_TOML = """
[scene]
name = "two blocks on a base"
description = "two unit squares stacked on a fixed base"

[materials.rock]
E = 2.0e7
nu = 0.25
unit_weight = 26.0

[joints.j]
kn = 1.0e6
ks = 5.0e5
friction_deg = 30.0

[[blocks]]
vertices = [[0.0, 0.0], [4.0, 0.0], [4.0, 1.0], [0.0, 1.0]]
material = "rock"
fixed = true

[[blocks]]
vertices = [[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]]
material = "rock"

[[blocks]]
vertices = [[1.0, 2.0], [2.0, 2.0], [2.0, 3.0], [1.0, 3.0]]
material = "rock"

[[discontinuities]]
from = [0.0, 1.0]
to = [4.0, 1.0]
joint = "j"

[[boundaries]]
side = "bottom"
condition = "fixed"

[[boundaries]]
from = [1.0, 3.0]
to = [2.0, 3.0]
condition = "traction"
traction = [0.0, -100.0]

[[monitors]]
name = "top"
point = [1.5, 3.0]

[[monitors]]
name = "stack"
from = [1.5, 1.5]
to = [1.5, 2.5]
"""


def valid_scene_dict() -> dict:
    """The valid explicit-block scene as a fresh dict (mutate freely)."""
    return {
        "scene": {
            "name": "two blocks on a base",
            "description": "two unit squares stacked on a fixed base",
        },
        "materials": {"rock": {"E": 2.0e7, "nu": 0.25, "unit_weight": 26.0}},
        "joints": {"j": {"kn": 1.0e6, "ks": 5.0e5, "friction_deg": 30.0}},
        "blocks": [
            {
                "vertices": [[0.0, 0.0], [4.0, 0.0], [4.0, 1.0], [0.0, 1.0]],
                "material": "rock",
                "fixed": True,
            },
            {"vertices": [[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]], "material": "rock"},
            {"vertices": [[1.0, 2.0], [2.0, 2.0], [2.0, 3.0], [1.0, 3.0]], "material": "rock"},
        ],
        "discontinuities": [{"from": [0.0, 1.0], "to": [4.0, 1.0], "joint": "j"}],
        "boundaries": [
            {"side": "bottom", "condition": "fixed"},
            {
                "from": [1.0, 3.0],
                "to": [2.0, 3.0],
                "condition": "traction",
                "traction": [0.0, -100.0],
            },
        ],
        "monitors": [
            {"name": "top", "point": [1.5, 3.0]},
            {"name": "stack", "from": [1.5, 1.5], "to": [1.5, 2.5]},
        ],
    }


def _set(data: dict, dotted: str, value) -> None:
    *head, last = dotted.split(".")
    node = data
    for k in head:
        node = node[int(k)] if isinstance(node, list) else node[k]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value


def _del(data: dict, dotted: str) -> None:
    *head, last = dotted.split(".")
    node = data
    for k in head:
        node = node[int(k)] if isinstance(node, list) else node[k]
    del node[int(last) if isinstance(node, list) else last]


def setting(dotted: str, value) -> Callable[[dict], None]:
    return lambda d: _set(d, dotted, value)


def deleting(dotted: str) -> Callable[[dict], None]:
    return lambda d: _del(d, dotted)


def _load_mutated(mutation: Callable[[dict], None]) -> Scene:
    data = valid_scene_dict()
    mutation(data)
    return parse_scene(data)


# --------------------------------------------------------------------------- valid scene


def test_valid_scene_loads_with_defaults(tmp_path: Path):
    path = tmp_path / "scene.toml"
    path.write_text(VALID_TOML)
    scene = load_scene(path)
    assert scene.source == str(path)
    assert scene.name == "two blocks on a base"
    assert scene.default_joint == "j"  # first joint in the file
    assert scene.solver == SolverSettings()
    assert scene.solver.load_steps == 5 and isinstance(scene.solver.load_steps, int)
    assert scene.solver.max_displacement is None
    rock = scene.materials["rock"]
    assert (rock.E, rock.nu, rock.unit_weight) == (2.0e7, 0.25, 26.0)
    assert (rock.cohesion, rock.friction_deg, rock.tensile_strength) == (0.0, 45.0, 0.0)
    assert scene.joints["j"] == Joint(name="j", kn=1.0e6, ks=5.0e5, friction_deg=30.0)
    assert len(scene.blocks) == 3
    assert scene.blocks[0].fixed and not scene.blocks[1].fixed
    assert scene.blocks[1].vertices.dtype == np.float64
    assert scene.blocks[1].vertices.shape == (4, 2)
    assert not scene.blocks[1].vertices.flags.writeable
    assert scene.discontinuities[0].joint == "j"
    bottom, top = scene.boundaries
    assert bottom.side == "bottom" and bottom.condition == "fixed"
    np.testing.assert_array_equal(bottom.start, [0.0, 0.0])
    np.testing.assert_array_equal(bottom.end, [4.0, 0.0])
    np.testing.assert_array_equal(bottom.traction, [0.0, 0.0])
    assert top.side is None
    np.testing.assert_array_equal(top.traction, [0.0, -100.0])
    point, section = scene.monitors
    assert point.kind == "point" and point.start is None
    np.testing.assert_array_equal(point.point, [1.5, 3.0])
    assert section.kind == "section" and section.point is None
    np.testing.assert_array_equal(section.end, [1.5, 2.5])


def test_dict_and_text_and_file_agree(tmp_path: Path):
    path = tmp_path / "scene.toml"
    path.write_text(VALID_TOML)
    a = load_scene(str(path))
    b = load_scene(valid_scene_dict())
    c = load_scene(VALID_TOML)
    assert a.data == b.data == c.data
    assert b.source == "<dict>"


def test_side_segments_from_bounding_box():
    data = valid_scene_dict()
    data["boundaries"] = [
        {"side": s, "condition": "roller"} for s in ("left", "right", "bottom", "top")
    ]
    scene = parse_scene(data)
    ends = {b.side: (tuple(b.start), tuple(b.end)) for b in scene.boundaries}
    assert ends == {
        "left": ((0.0, 0.0), (0.0, 3.0)),
        "right": ((4.0, 0.0), (4.0, 3.0)),
        "bottom": ((0.0, 0.0), (4.0, 0.0)),
        "top": ((0.0, 3.0), (4.0, 3.0)),
    }


def test_explicit_defaults_and_extensions():
    data = valid_scene_dict()
    data["solver"] = {
        "load_steps": 10.0,  # integral float accepted for an int field
        "tolerance": 1e-8,
        "max_iterations": 100,
        "max_displacement": 0.5,
        "dtype": "float32",
        "regularization": 1e-4,
        "step_length": 0.01,
    }
    data["joints"]["set1"] = {
        "kn": 2e6,
        "ks": 1e6,
        "friction_deg": 35,
        "dip_deg": 60,
        "spacing": 0.5,
        "origin": [0, 0],
        "persistence": 1.0,
        "gap": 0.0,
    }
    data["scene"]["default_joint"] = "set1"
    # A joint set needs a domain to cut: one beside the explicit blocks.
    data["domain"] = {"outline": [[10, 0], [20, 0], [20, 10], [10, 10]], "material": "rock"}
    scene = parse_scene(data)
    assert scene.solver.load_steps == 10 and isinstance(scene.solver.load_steps, int)
    assert scene.solver.dtype == "float32"
    assert scene.solver.step_length == 0.01
    assert scene.default_joint == "set1"
    s1 = scene.joints["set1"]
    assert (s1.dip_deg, s1.spacing, s1.origin, s1.persistence) == (60.0, 0.5, (0.0, 0.0), 1.0)
    assert isinstance(s1.friction_deg, float)


def test_single_block_needs_no_joint():
    data = valid_scene_dict()
    del data["joints"]
    del data["discontinuities"]
    data["blocks"] = data["blocks"][:1]
    data["monitors"] = [{"name": "m", "point": [2.0, 0.5]}]
    data["boundaries"] = data["boundaries"][:1]
    scene = parse_scene(data)
    assert scene.default_joint == "" and scene.joints == {}


def test_discontinuity_joint_defaults_to_default_joint():
    data = valid_scene_dict()
    del data["discontinuities"][0]["joint"]
    assert parse_scene(data).discontinuities[0].joint == "j"


# --------------------------------------------------------------------------- refusals

REFUSALS = [
    # (id, mutation, expected path at the start of the message, words in the message)
    # required fields
    ("no scene", deleting("scene"), "scene.name", "required"),
    ("no name", deleting("scene.name"), "scene.name", "required"),
    ("no blocks", deleting("blocks"), "blocks", "at least one block"),
    ("empty blocks", setting("blocks", []), "blocks", "at least one block"),
    ("unknown material", setting("blocks.1.material", "granite"), "blocks.1.material", "granite"),
    ("no material", deleting("blocks.1.material"), "blocks.1.material", "required"),
    ("no vertices", deleting("blocks.1.vertices"), "blocks.1.vertices", "required"),
    ("no E", deleting("materials.rock.E"), "materials.rock.E", "required"),
    ("no nu", deleting("materials.rock.nu"), "materials.rock.nu", "required"),
    ("no gamma", deleting("materials.rock.unit_weight"), "materials.rock.unit_weight", "required"),
    ("no kn", deleting("joints.j.kn"), "joints.j.kn", "required"),
    ("no ks", deleting("joints.j.ks"), "joints.j.ks", "required"),
    ("no phi", deleting("joints.j.friction_deg"), "joints.j.friction_deg", "required"),
    ("bad default", setting("scene.default_joint", "nope"), "scene.default_joint", "nope"),
    (
        "no joints",
        lambda d: (d.pop("joints"), d.pop("discontinuities")),
        "joints",
        "at least one joint is needed for contacts between blocks",
    ),
    # unknown and unsupported
    ("unknown section", setting("foo", {}), "foo", "unknown section"),
    ("unknown field", setting("materials.rock.G", 1.0), "materials.rock.G", "allowed: E, nu"),
    ("unknown scene field", setting("scene.author", "x"), "scene.author", "allowed"),
    ("unknown block field", setting("blocks.0.colour", "red"), "blocks.0.colour", "allowed"),
    ("unknown solver field", setting("solver", {"steps": 3}), "solver.steps", "allowed"),
    ("in_situ field", setting("in_situ", {"k": 0.5}), "in_situ.k", "allowed: mode, k0"),
    ("domain empty", setting("domain", {}), "domain.outline", "required"),
    ("excavations type", setting("excavations", {}), "excavations", "array of tables"),
    ("bolts type", setting("bolts", 3), "bolts", "array of tables"),
    ("supports type", setting("supports", {}), "supports", "array of tables"),
    ("water empty", setting("water", {}), "water.table", "required"),
    ("stages type", setting("stages", "a"), "stages", "array of tables"),
    (
        "set without domain",
        lambda d: d["joints"]["j"].update({"dip_deg": 30.0, "spacing": 1.0}),
        "joints.j",
        "needs a [domain]",
    ),
    ("dip without spacing", setting("joints.j.dip_deg", 30.0), "joints.j.spacing", "required"),
    # types
    ("E string", setting("materials.rock.E", "2e7"), "materials.rock.E", "must be a number"),
    ("E bool", setting("materials.rock.E", True), "materials.rock.E", "must be a number"),
    ("E nan", setting("materials.rock.E", math.nan), "materials.rock.E", "finite"),
    ("kn inf", setting("joints.j.kn", math.inf), "joints.j.kn", "finite"),
    ("vertex nan", setting("blocks.1.vertices.2.0", math.nan), "blocks.1.vertices.2.0", "finite"),
    ("E huge", setting("materials.rock.E", 1e16), "materials.rock.E", "out of range"),
    ("coord huge", setting("blocks.1.vertices.2", [1e20, 2.0]), "blocks.1.vertices.2.0", "range"),
    ("name type", setting("scene.name", 3), "scene.name", "must be a string"),
    ("material type", setting("blocks.1.material", 1), "blocks.1.material", "must be a string"),
    ("fixed type", setting("blocks.0.fixed", "yes"), "blocks.0.fixed", "true or false"),
    ("point short", setting("blocks.1.vertices.0", [1.0]), "blocks.1.vertices.0", "[x, y]"),
    ("point str", setting("blocks.1.vertices.0", "1,1"), "blocks.1.vertices.0", "[x, y]"),
    ("vertices type", setting("blocks.1.vertices", 5), "blocks.1.vertices", "list of points"),
    ("materials type", setting("materials", [1]), "materials", "table"),
    ("material type", setting("materials.rock", 3.0), "materials.rock", "table"),
    ("blocks type", setting("blocks", {"a": 1}), "blocks", "array of tables"),
    # ranges
    ("E <= 0", setting("materials.rock.E", -1), "materials.rock.E", "must be > 0 (got -1)"),
    ("E zero", setting("materials.rock.E", 0.0), "materials.rock.E", "> 0"),
    ("nu 0.5", setting("materials.rock.nu", 0.5), "materials.rock.nu", "[0, 0.5)"),
    ("nu < 0", setting("materials.rock.nu", -0.1), "materials.rock.nu", "[0, 0.5)"),
    ("gamma < 0", setting("materials.rock.unit_weight", -1.0), "materials.rock.unit_weight", ">="),
    ("c < 0", setting("materials.rock.cohesion", -1.0), "materials.rock.cohesion", ">= 0"),
    ("T < 0", setting("joints.j.tensile_strength", -1.0), "joints.j.tensile_strength", ">= 0"),
    ("phi 90", setting("joints.j.friction_deg", 90.0), "joints.j.friction_deg", "[0, 90)"),
    ("phi < 0", setting("materials.rock.friction_deg", -5), "materials.rock.friction_deg", "[0"),
    ("kn 0", setting("joints.j.kn", 0.0), "joints.j.kn", "> 0"),
    ("ks < 0", setting("joints.j.ks", -1.0), "joints.j.ks", "> 0"),
    ("load_steps 0", setting("solver", {"load_steps": 0}), "solver.load_steps", ">= 1"),
    ("load_steps 2.5", setting("solver", {"load_steps": 2.5}), "solver.load_steps", "integer"),
    ("tolerance 1", setting("solver", {"tolerance": 1.0}), "solver.tolerance", "(0, 1)"),
    ("tolerance 0", setting("solver", {"tolerance": 0.0}), "solver.tolerance", "(0, 1)"),
    ("max_it 0", setting("solver", {"max_iterations": 0}), "solver.max_iterations", ">= 1"),
    ("max_disp 0", setting("solver", {"max_displacement": 0}), "solver.max_displacement", "> 0"),
    ("reg 1", setting("solver", {"regularization": 1.0}), "solver.regularization", "(0, 1)"),
    ("step 0", setting("solver", {"step_length": 0.0}), "solver.step_length", "> 0"),
    ("dtype", setting("solver", {"dtype": "float16"}), "solver.dtype", "float64, float32"),
    ("linear solver", setting("solver", {"linear_solver": "lu"}), "solver.linear_solver",
     "auto, dense, sparse, cg"),
    ("bond failure", setting("solver", {"bond_failure": "event"}), "solver.bond_failure",
     "substep, events"),
    ("boundary stage on wall", setting("boundaries.0.stage", "dig"), "boundaries.0.stage",
     "only allowed with condition 'traction'"),
    ("spacing 0", setting("joints.j.spacing", 0.0), "joints.j.spacing", "> 0"),
    ("persistence 0", setting("joints.j.persistence", 0.0), "joints.j.persistence", "(0, 1]"),
    ("persistence >1", setting("joints.j.persistence", 1.5), "joints.j.persistence", "(0, 1]"),
    ("gap < 0", setting("joints.j.gap", -0.1), "joints.j.gap", ">= 0"),
    ("gap no set", setting("joints.j.gap", 0.5), "joints.j.gap", "only for a joint set"),
    ("origin", setting("joints.j.origin", [0.0]), "joints.j.origin", "[x, y]"),
    # polygons
    ("2 points", setting("blocks.1.vertices", [[1, 1], [2, 1]]), "blocks.1.vertices", "3 points"),
    (
        "repeated",
        setting("blocks.1.vertices", [[1, 1], [2, 1], [2, 2], [2, 2], [1, 2]]),
        "blocks.1.vertices",
        "repeated point",
    ),
    (
        "bow-tie",
        setting("blocks.1.vertices", [[1, 1], [2, 2], [2, 1], [1, 2]]),
        "blocks.1.vertices",
        "self-intersecting",
    ),
    (
        "zero area",
        setting("blocks.1.vertices", [[1, 1], [2, 1], [3, 1]]),
        "blocks.1.vertices",
        "degenerate",
    ),
    (
        "near-zero area",
        setting("blocks.1.vertices", [[1, 1], [2, 1], [3, 1 + 1e-14]]),
        "blocks.1.vertices",
        "degenerate",
    ),
    (
        "clockwise",
        setting("blocks.1.vertices", [[1, 1], [1, 2], [2, 2], [2, 1]]),
        "blocks.1.vertices",
        "vertices are clockwise; list them counter-clockwise",
    ),
    (
        "non-convex",
        setting("blocks.1.vertices", [[1, 1], [2, 1], [1.5, 1.5], [2, 2], [1, 2]]),
        "blocks.1.vertices",
        "is not convex at vertex 2",
    ),
    (
        "collinear vertex",
        setting("blocks.1.vertices", [[1, 1], [1.5, 1], [2, 1], [2, 2], [1, 2]]),
        "blocks.1.vertices",
        "degenerate vertex 1",
    ),
    (
        "overlap",
        setting("blocks.2.vertices", [[1, 1.5], [2, 1.5], [2, 2.5], [1, 2.5]]),
        "blocks.2",
        "overlaps blocks.1 (area 0.5 m2)",
    ),
    # discontinuities
    ("disc joint", setting("discontinuities.0.joint", "k"), "discontinuities.0.joint", "'k'"),
    ("disc same", setting("discontinuities.0.to", [0.0, 1.0]), "discontinuities.0.to", "same"),
    ("disc no from", deleting("discontinuities.0.from"), "discontinuities.0.from", "required"),
    (
        "disc outside",
        lambda d: d["discontinuities"][0].update({"from": [10, 10], "to": [12, 10]}),
        "discontinuities.0",
        "outside the domain",
    ),
    # boundaries
    (
        "side and from",
        setting("boundaries.0.from", [0, 0]),
        "boundaries.0",
        "either side or from/to",
    ),
    ("no side", deleting("boundaries.0.side"), "boundaries.0", "side"),
    ("bad side", setting("boundaries.0.side", "up"), "boundaries.0.side", "'up'"),
    ("only from", deleting("boundaries.1.to"), "boundaries.1.to", "required"),
    ("bad condition", setting("boundaries.0.condition", "free"), "boundaries.0.condition", "free"),
    ("no condition", deleting("boundaries.0.condition"), "boundaries.0.condition", "required"),
    ("no traction", deleting("boundaries.1.traction"), "boundaries.1.traction", "required"),
    (
        "traction on fixed",
        setting("boundaries.0.traction", [0, 1]),
        "boundaries.0.traction",
        "only allowed",
    ),
    ("traction 3", setting("boundaries.1.traction", [0, 1, 2]), "boundaries.1.traction", "[tx"),
    ("traction str", setting("boundaries.1.traction.1", "x"), "boundaries.1.traction.1", "number"),
    # monitors
    ("dup monitor", setting("monitors.1.name", "top"), "monitors.1.name", "duplicate name 'top'"),
    ("no monitor name", deleting("monitors.0.name"), "monitors.0.name", "required"),
    (
        "monitor outside",
        setting("monitors.0.point", [5, 9]),
        "monitors.0.point",
        "(5, 9) is outside the rock",
    ),
    (
        "monitor in the air",
        setting("monitors.0.point", [3.0, 2.0]),
        "monitors.0.point",
        "outside the rock",
    ),
    ("section outside", setting("monitors.1.to", [1.5, 3.5]), "monitors.1.to", "outside the rock"),
    ("monitor both", setting("monitors.0.from", [1.5, 1.5]), "monitors.0", "either point"),
    ("section half", deleting("monitors.1.to"), "monitors.1.to", "required"),
    ("monitor neither", deleting("monitors.0.point"), "monitors.0", "needs point"),
]


@pytest.mark.parametrize(
    ("mutation", "path", "words"),
    [pytest.param(m, p, w, id=i) for i, m, p, w in REFUSALS],
)
def test_refusal(mutation, path, words):
    with pytest.raises(SceneError) as info:
        _load_mutated(mutation)
    message = str(info.value)
    assert message.startswith(path + ":"), message
    assert info.value.path == path
    assert words in message, message


def test_refusals_do_not_mutate_input():
    data = valid_scene_dict()
    before = copy.deepcopy(data)
    parse_scene(data)
    assert data == before


def test_near_touching_blocks_are_not_overlaps():
    # A sliver of overlap from round-off (1e-12 m) is below 1e-9 of the block area.
    data = valid_scene_dict()
    data["blocks"][2]["vertices"] = [[1, 2 - 1e-12], [2, 2 - 1e-12], [2, 3], [1, 3]]
    parse_scene(data)


def test_file_errors_name_the_file(tmp_path: Path):
    missing = tmp_path / "missing.toml"
    with pytest.raises(SceneError, match="missing.toml") as info:
        load_scene(missing)
    assert info.value.path == str(missing)
    empty = tmp_path / "empty.toml"
    empty.write_text("  \n# nothing\n")
    with pytest.raises(SceneError, match="empty.toml.*empty"):
        load_scene(empty)
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene\nname = 1\n")
    with pytest.raises(SceneError, match="bad.toml.*invalid TOML"):
        load_scene(bad)
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(SceneError, match="binary.toml"):
        load_scene(binary)
    with pytest.raises(SceneError, match=str(tmp_path.name)):
        load_scene(tmp_path)  # a directory
    with pytest.raises(SceneError):
        load_scene(42)  # type: ignore[arg-type]


def test_not_a_table_is_a_scene_error():
    with pytest.raises(SceneError):
        parse_scene([1, 2, 3])  # type: ignore[arg-type]


def test_toml_nan_is_refused():
    text = VALID_TOML.replace("E = 2.0e7", "E = nan")
    with pytest.raises(SceneError, match=r"^materials\.rock\.E: must be finite"):
        load_scene(text)


# --------------------------------------------------------------------------- overrides


def test_set_changes_the_joint():
    scene = load_scene(valid_scene_dict(), set={"joints.j.kn": 2e6})
    assert scene.joints["j"].kn == 2e6
    assert scene.data["joints"]["j"]["kn"] == 2e6


def test_with_overrides_revalidates_and_keeps_original():
    scene = load_scene(valid_scene_dict())
    new = scene.with_overrides({"materials.rock.E": 3e7, "solver.load_steps": 8.0})
    assert new.materials["rock"].E == 3e7
    assert new.solver.load_steps == 8 and isinstance(new.solver.load_steps, int)
    assert scene.materials["rock"].E == 2e7
    assert new.source == scene.source
    with pytest.raises(SceneError, match=r"^materials\.rock\.E: must be > 0"):
        scene.with_overrides({"materials.rock.E": -1.0})


def test_override_array_element_and_optional_field():
    scene = load_scene(valid_scene_dict())
    new = scene.with_overrides(
        {"boundaries.1.traction.0": 5.0, "blocks.2.vertices.2.1": 3.5, "joints.j.cohesion": 10.0}
    )
    np.testing.assert_array_equal(new.boundaries[1].traction, [5.0, -100.0])
    assert new.blocks[2].vertices[2, 1] == 3.5
    assert new.joints["j"].cohesion == 10.0


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ("joints.set9.kn", "--set joints.set9.kn: no such parameter"),
        ("joints.j.stiffness", "--set joints.j.stiffness: no such parameter"),
        ("blocks.9.fixed", "--set blocks.9.fixed: no such parameter"),
        ("boundaries.1.traction.2", "--set boundaries.1.traction.2: no such parameter"),
        ("blocks.0.fixed", "--set blocks.0.fixed: not a numeric parameter"),
        ("scene.name", "--set scene.name: not a numeric parameter"),
        ("blocks.0.vertices", "--set blocks.0.vertices: not a numeric parameter"),
        ("in_situ.k0", "--set in_situ.k0: no such parameter"),
        ("bolts.0.stiffness", "--set bolts.0.stiffness: no such parameter"),
    ],
)
def test_override_refused(path, message):
    scene = load_scene(valid_scene_dict())
    with pytest.raises(SceneError) as info:
        scene.with_overrides({path: 1.0})
    assert str(info.value).startswith(message)
    assert info.value.path == path


def test_apply_overrides_copies_and_checks_values():
    data = valid_scene_dict()
    out = apply_overrides(data, {"joints.j.kn": 3e6, "solver.max_iterations": 80})
    assert data["joints"]["j"]["kn"] == 1e6
    assert out["joints"]["j"]["kn"] == 3e6
    assert out["solver"] == {"max_iterations": 80}
    with pytest.raises(SceneError, match="finite"):
        apply_overrides(data, {"joints.j.kn": math.nan})
    with pytest.raises(SceneError, match="number"):
        apply_overrides(data, {"joints.j.kn": "2e6"})


def test_parse_set_arguments():
    assert parse_set_arguments(["joints.j.kn=2e6"]) == {"joints.j.kn": 2e6}
    assert parse_set_arguments(["a.b = 1", "c.0.d=-0.5"]) == {"a.b": 1.0, "c.0.d": -0.5}
    assert parse_set_arguments([]) == {}


def test_the_solver_choices_take_a_word():
    """``--set solver.linear_solver=cg`` (and dtype, loose_blocks, bond_failure) sets the
    word, whether or not the file gives the field; the scene's own check refuses a word
    that is not one of the choice's values, and a number is refused for a choice as a
    word is for a number."""
    assert parse_set_arguments(["solver.linear_solver=cg", "joints.j.kn=2e6"]) == {
        "solver.linear_solver": "cg", "joints.j.kn": 2e6}
    scene = load_scene(valid_scene_dict())
    new = scene.with_overrides(parse_set_arguments(
        ["solver.linear_solver=sparse", "solver.dtype=float32", "solver.bond_failure=substep",
         "solver.loose_blocks=stop"]))
    assert (new.solver.linear_solver, new.solver.dtype, new.solver.bond_failure,
            new.solver.loose_blocks) == ("sparse", "float32", "substep", "stop")
    assert scene.solver.linear_solver == "auto"
    with pytest.raises(SceneError, match=r"^solver\.linear_solver: must be one of auto, dense, "
                                         r"sparse, cg \(got 'lu'\)"):
        scene.with_overrides({"solver.linear_solver": "lu"})
    with pytest.raises(SceneError, match=r"^--set solver\.dtype: a choice"):
        scene.with_overrides({"solver.dtype": 32.0})
    # A word is still refused for every other entry, on the command line and in Python.
    with pytest.raises(SceneError, match=r"^--set: value of solver\.tolerance must be a number"):
        parse_set_arguments(["solver.tolerance=small"])
    with pytest.raises(SceneError, match="number"):
        scene.with_overrides({"scene.name": "other"})


@pytest.mark.parametrize("item", ["joints.j.kn", "=3", "joints..kn=3", "joints.j.kn=abc", "x=nan"])
def test_parse_set_arguments_refused(item):
    with pytest.raises(SceneError) as info:
        parse_set_arguments([item])
    assert info.value.path == "--set"
    assert str(info.value).startswith("--set: ")


# --------------------------------------------------------------------------- properties


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(3, 12),
    radius=st.floats(1e-3, 1e3),
    angle=st.floats(0.0, 2.0 * math.pi),
    cx=st.floats(-1e5, 1e5),
)
def test_regular_polygons_accepted_and_reversed_refused(n, radius, angle, cx):
    k = np.arange(n)
    v = np.stack(
        [
            cx + radius * np.cos(angle + 2 * np.pi * k / n),
            radius * np.sin(angle + 2 * np.pi * k / n),
        ],
        axis=1,
    )
    data = {
        "scene": {"name": "one"},
        "materials": {"rock": {"E": 1e7, "nu": 0.2, "unit_weight": 25.0}},
        "blocks": [{"vertices": v.tolist(), "material": "rock"}],
        "monitors": [{"name": "c", "point": [cx, 0.0]}],
    }
    scene = parse_scene(data)
    np.testing.assert_allclose(scene.blocks[0].vertices, v)
    data["blocks"][0]["vertices"] = v[::-1].tolist()
    with pytest.raises(SceneError, match=r"^blocks\.0\.vertices: vertices are clockwise"):
        parse_scene(data)


def test_numpy_arrays_accepted_in_programmatic_scenes():
    data = valid_scene_dict()
    data["blocks"][1]["vertices"] = np.array(data["blocks"][1]["vertices"])
    data["monitors"][0]["point"] = np.array([1.5, 3.0])
    assert parse_scene(data).blocks[1].vertices.shape == (4, 2)


def test_ten_thousand_blocks_validate_quickly():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    data = valid_scene_dict()
    data["blocks"] = [
        {"vertices": (square + [i, j]).tolist(), "material": "rock"}
        for i in range(100)
        for j in range(100)
    ]
    data["discontinuities"] = []
    data["boundaries"] = [{"side": "bottom", "condition": "fixed"}]
    data["monitors"] = [{"name": "m", "point": [50.5, 50.5]}]
    t0 = time.perf_counter()
    scene = parse_scene(data)
    elapsed = time.perf_counter() - t0
    assert len(scene.blocks) == 10_000
    assert elapsed < 10.0, f"validating 10,000 blocks took {elapsed:.1f} s"
    data["blocks"][4321]["vertices"] = (square + [43.5, 21.0]).tolist()
    with pytest.raises(SceneError, match=r"^blocks\.4421: overlaps blocks\.4321 \(area 0\.5 m2\)"):
        parse_scene(data)


# ------------------------------------------------------------------- blocks checked in a batch
# Plain [[blocks]] polygons are read and cleared all at once (convex_polygons_pass); what the
# batch does not clear goes through check_polygon, so the first problem in block order is
# still the one named.


def _many_blocks(n: int = 300) -> dict:
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    data = valid_scene_dict()
    data["blocks"] = [{"vertices": (square + [i % 20, i // 20]).tolist(), "material": "rock"}
                      for i in range(n)]
    data["discontinuities"] = []
    data["boundaries"] = []
    data["monitors"] = [{"name": "m", "point": [0.5, 0.5]}]
    return data


@pytest.mark.parametrize(
    ("changes", "path", "words"),
    [
        ({150: lambda v: v[::-1]}, "blocks.150.vertices", "vertices are clockwise"),
        ({150: lambda v: v[:1] + [[v[0][0] + 0.5, v[0][1]]] + v[1:]}, "blocks.150.vertices",
         "degenerate vertex 1 (10.5, 7): collinear"),
        ({150: lambda v: v[:1] + [[v[0][0] + 1e-12, v[0][1]]] + v[1:]}, "blocks.150.vertices",
         "repeated point"),
        ({150: lambda v: [v[0], v[2], v[1], v[3]]}, "blocks.150.vertices", "self-intersecting"),
        ({150: lambda v: [v[0], v[1], [v[0][0] + 0.5, v[0][1] + 0.2], v[3]]},
         "blocks.150.vertices", "is not convex at vertex 2"),
        ({150: lambda v: [[True, 7.0]] + v[1:]}, "blocks.150.vertices.0.0", "must be a number"),
        ({150: lambda v: [[math.nan, 7.0]] + v[1:]}, "blocks.150.vertices.0.0", "must be finite"),
        ({150: lambda v: v[:2]}, "blocks.150.vertices", "needs at least 3 points"),
        # The first problem in block order, whatever its kind.
        ({40: "material", 150: lambda v: v[::-1]}, "blocks.40.material", "unknown material"),
        ({40: lambda v: v[::-1], 150: "material"}, "blocks.40.vertices", "clockwise"),
    ],
)
def test_blocks_checked_in_a_batch_name_the_first_problem(changes, path, words):
    data = _many_blocks()
    parse_scene(copy.deepcopy(data))
    for i, change in changes.items():
        if change == "material":
            data["blocks"][i]["material"] = "granite"
        else:
            data["blocks"][i]["vertices"] = change(data["blocks"][i]["vertices"])
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == path
    assert words in str(info.value)


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(3, 10),
    angles=st.lists(st.floats(0.0, 2.0 * math.pi), min_size=10, max_size=10),
    radii=st.lists(st.floats(0.2, 1.0), min_size=10, max_size=10),
    scale=st.floats(1e-3, 1e3),
    centre=st.floats(-1e5, 1e5),
    order=st.sampled_from(["sorted", "reversed", "as drawn"]),
    nudge=st.sampled_from([0.0, 1e-13, 1e-10, 1e-8]),
)
def test_batch_clears_only_what_check_polygon_accepts(n, angles, radii, scale, centre, order,
                                                      nudge):
    from jaxdem.scene._checks import check_polygon, convex_polygons_pass

    a = np.array(angles[:n])
    a = {"sorted": np.sort(a), "reversed": np.sort(a)[::-1], "as drawn": a}[order]
    v = centre + scale * np.array(radii[:n])[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1)
    # A vertex moved onto (or just off) the midpoint of an edge or onto a neighbour.
    polys = [v, np.insert(v, 1, 0.5 * (v[0] + v[1]) + nudge * scale, axis=0),
             np.insert(v, 1, v[0] + nudge * scale, axis=0)]
    for p, cleared in zip(polys, convex_polygons_pass(polys), strict=True):
        try:
            check_polygon(p, "p")
            accepted = True
        except SceneError:
            accepted = False
        assert accepted or not cleared


# --------------------------------------------------------------------------- rock-mass sections


def rock_scene_dict() -> dict:
    """A generated rock mass with every section in use (mutate freely)."""
    return {
        "scene": {"name": "tunnel"},
        "materials": {
            "rock": {"E": 4e7, "nu": 0.25, "unit_weight": 26.0},
            "shear": {"E": 4e6, "nu": 0.3, "unit_weight": 26.0},
        },
        "joints": {
            "set1": {"kn": 1e6, "ks": 1e5, "friction_deg": 25.0, "dip_deg": 30.0, "spacing": 2.0},
            "set2": {
                "kn": 1e6,
                "ks": 2.6e4,
                "friction_deg": 20.0,
                "dip_deg": 120.0,
                "spacing": 2.0,
                "persistence": 0.8,
            },
            "D": {"kn": 1e6, "ks": 1e5, "friction_deg": 20.0},
        },
        "domain": {"outline": [[0, 0], [40, 0], [40, 30], [0, 30]], "material": "rock"},
        "zones": [
            {"name": "sz", "vertices": [[0, 20], [40, 22], [40, 24], [0, 22]], "material": "shear"}
        ],
        "discontinuities": [{"from": [5, 0], "to": [15, 30], "joint": "D"}],
        "excavations": [
            {"name": "a", "shape": "circle", "center": [12, 10], "radius": 3.0},
            {
                "name": "b",
                "shape": "horseshoe",
                "center": [26, 6],
                "width": 6,
                "height": 7,
                "stage": "bench",
            },
        ],
        "in_situ": {"mode": "gravity", "k0": 0.5},
        "bolts": [
            {
                "from": [15, 10],
                "to": [18, 10],
                "stiffness": 5e4,
                "yield_force": 150,
                "anchor_capacity": 200,
                "stage": "bench",
            }
        ],
        "supports": [{"excavation": "a", "pressure": 80.0}],
        "water": {"table": [[0, 25], [40, 20]]},
        "stages": [
            {"name": "heading"},
            {"name": "bench", "load_steps": 8, "water_table": [[0, 15], [40, 15]]},
        ],
        "boundaries": [{"side": "bottom", "condition": "fixed"}],
        "monitors": [{"name": "crown", "point": [12, 13]}],
    }


def test_rock_scene_loads_with_defaults():
    scene = parse_scene(rock_scene_dict())
    assert scene.blocks == ()
    assert scene.domain.material == "rock" and scene.domain.mesh_size is None
    assert scene.domain.outline.shape == (4, 2) and not scene.domain.outline.flags.writeable
    assert scene.joints["set1"].is_set and not scene.joints["D"].is_set
    s2 = scene.joints["set2"]
    assert s2.bridge_length == 2.0 and s2.trace_length == pytest.approx(8.0)
    assert scene.joints["set1"].trace_length == math.inf
    assert scene.zones[0].name == "sz" and scene.zones[0].material == "shear"
    a, b = scene.excavations
    assert (a.name, a.shape, a.stage, a.radius) == ("a", "circle", None, 3.0)
    # h = min spacing / 2 = 1 m: ceil(2 pi 3 / 1) = 19 -> at least 24 segments.
    assert len(a.vertices) == 24
    np.testing.assert_allclose(np.hypot(*(a.vertices - [12, 10]).T), 3.0)
    assert b.stage == "bench" and b.vertices[:, 1].max() == pytest.approx(13.0)
    assert scene.in_situ == InSitu(mode="gravity", k0=0.5, surface_y=30.0)
    bolt = scene.bolts[0]
    assert (bolt.stiffness, bolt.spacing, bolt.stage) == (5e4, 1.0, "bench")
    np.testing.assert_array_equal(bolt.end, [18.0, 10.0])
    assert scene.supports == (Support(excavation="a", pressure=80.0, stage=None),)
    assert scene.water.unit_weight == 9.81 and scene.water.table.shape == (2, 2)
    assert [s.name for s in scene.stages] == ["heading", "bench"]
    assert scene.stages[0].load_steps is None and scene.stages[1].load_steps == 8
    assert scene.stages[1].water_table.shape == (2, 2)
    assert scene.boundaries[0].end.tolist() == [40.0, 0.0]


def test_uniform_in_situ_and_mesh_size_discretisation():
    data = rock_scene_dict()
    data["in_situ"] = {"mode": "uniform", "sigma_xx": 500.0, "sigma_yy": 1000.0}
    data["domain"]["mesh_size"] = 0.25
    scene = parse_scene(data)
    assert scene.in_situ == InSitu(mode="uniform", sigma_xx=500.0, sigma_yy=1000.0)
    assert len(scene.excavations[0].vertices) == 76  # ceil(2 pi 3 / 0.25)
    data["excavations"][0]["radius"] = 9.0
    data["excavations"][0]["center"] = [12, 12]
    data["bolts"] = []
    data["monitors"] = []
    assert len(parse_scene(data).excavations[0].vertices) == 120  # clipped


def test_l_shaped_domain_and_polygon_excavation_accepted():
    data = rock_scene_dict()
    data["domain"]["outline"] = [[0, 0], [40, 0], [40, 15], [20, 15], [20, 30], [0, 30]]
    data["zones"][0]["vertices"] = [[0, 20], [20, 22], [20, 24], [0, 22]]
    data["excavations"][1] = {
        "name": "b",
        "shape": "polygon",
        "vertices": [[24, 2], [30, 2], [30, 8], [27, 5], [24, 8]],
    }
    del data["bolts"]
    scene = parse_scene(data)
    assert scene.excavations[1].vertices.shape == (5, 2)


def test_rock_scene_overrides():
    scene = parse_scene(rock_scene_dict())
    new = scene.with_overrides(
        {
            "in_situ.k0": 1.5,
            "bolts.0.stiffness": 1e5,
            "supports.0.pressure": 0.0,
            "water.unit_weight": 10.0,
            "domain.mesh_size": 1.0,
            "bolts.0.spacing": 2.0,
            "excavations.0.radius": 2.5,
            "joints.set1.spacing": 1.5,
        }
    )
    assert new.in_situ.k0 == 1.5
    assert new.bolts[0].stiffness == 1e5 and new.bolts[0].spacing == 2.0
    assert new.supports[0].pressure == 0.0
    assert new.water.unit_weight == 10.0
    assert new.domain.mesh_size == 1.0
    assert new.excavations[0].radius == 2.5
    with pytest.raises(SceneError, match=r"^in_situ\.k0: must be >= 0"):
        scene.with_overrides({"in_situ.k0": -1.0})


def _load_rock_mutated(mutation: Callable[[dict], None]) -> Scene:
    data = rock_scene_dict()
    mutation(data)
    return parse_scene(data)


ROCK_REFUSALS = [
    # domain
    ("domain type", setting("domain", 3), "domain", "must be a table"),
    ("domain field", setting("domain.size", 3), "domain.size", "allowed: outline"),
    ("domain material", setting("domain.material", "x"), "domain.material", "unknown material"),
    ("domain no material", deleting("domain.material"), "domain.material", "required"),
    (
        "domain clockwise",
        setting("domain.outline", [[0, 0], [0, 30], [40, 30], [40, 0]]),
        "domain.outline",
        "clockwise",
    ),
    (
        "domain bow-tie",
        setting("domain.outline", [[0, 0], [40, 30], [40, 0], [0, 30]]),
        "domain.outline",
        "self-intersecting",
    ),
    ("mesh 0", setting("domain.mesh_size", 0.0), "domain.mesh_size", "> 0"),
    ("mesh str", setting("domain.mesh_size", "1"), "domain.mesh_size", "number"),
    ("mesh huge", setting("domain.mesh_size", 100.0), "domain.mesh_size", "larger than"),
    ("mesh max 0", setting("domain.mesh_max_size", 0.0), "domain.mesh_max_size", "> 0"),
    ("mesh max alone", setting("domain.mesh_max_size", 2.0), "domain.mesh_max_size",
     "needs domain.mesh_size"),
    (
        "mesh max < mesh",
        lambda d: (_set(d, "domain.mesh_size", 2.0), _set(d, "domain.mesh_max_size", 1.0)),
        "domain.mesh_max_size",
        "smaller than",
    ),
    (
        "block on domain",
        setting("blocks", [{"vertices": [[1, 1], [2, 1], [2, 2], [1, 2]], "material": "rock"}]),
        "blocks.0",
        "overlaps the domain",
    ),
    # joint sets
    ("persistence gap 0", setting("joints.set2.gap", 0.0), "joints.set2.gap", "must be > 0"),
    ("gap persistent", setting("joints.set1.gap", 1.0), "joints.set1.gap", "persistence < 1"),
    ("spacing neg", setting("joints.set1.spacing", -2.0), "joints.set1.spacing", "> 0"),
    # zones
    ("zone material", setting("zones.0.material", "clay"), "zones.0.material", "clay"),
    (
        "zone outside",
        setting("zones.0.vertices", [[50, 0], [60, 0], [60, 5]]),
        "zones.0",
        "does not overlap the domain",
    ),
    ("zone dup", lambda d: d["zones"].append(dict(d["zones"][0])), "zones.1.name", "duplicate"),
    # excavations
    ("exc no name", deleting("excavations.0.name"), "excavations.0.name", "required"),
    ("exc dup", setting("excavations.1.name", "a"), "excavations.1.name", "duplicate name 'a'"),
    ("exc shape", setting("excavations.0.shape", "oval"), "excavations.0.shape", "circle"),
    ("exc no shape", deleting("excavations.0.shape"), "excavations.0.shape", "required"),
    ("exc radius 0", setting("excavations.0.radius", 0.0), "excavations.0.radius", "> 0"),
    ("exc radius str", setting("excavations.0.radius", "3"), "excavations.0.radius", "number"),
    ("exc no radius", deleting("excavations.0.radius"), "excavations.0.radius", "required"),
    ("exc no center", deleting("excavations.0.center"), "excavations.0.center", "required"),
    ("exc width on circle", setting("excavations.0.width", 2.0), "excavations.0.width", "not used"),
    ("horseshoe low", setting("excavations.1.height", 2.0), "excavations.1.height", "width / 2"),
    (
        "exc outside",
        setting("excavations.0.center", [1.0, 10.0]),
        "excavations.0",
        "outside the domain",
    ),
    (
        "exc overlap",
        setting("excavations.1.center", [15, 8]),
        "excavations.1",
        "overlaps excavations.0",
    ),
    (
        "exc polygon clockwise",
        lambda d: d["excavations"].__setitem__(
            1, {"name": "p", "shape": "polygon", "vertices": [[24, 2], [24, 8], [30, 8], [30, 2]]}
        ),
        "excavations.1.vertices",
        "clockwise",
    ),
    ("exc stage", setting("excavations.1.stage", "top"), "excavations.1.stage", "unknown stage"),
    # in situ
    ("mode", setting("in_situ.mode", "tectonic"), "in_situ.mode", "gravity, uniform"),
    ("k0 < 0", setting("in_situ.k0", -0.5), "in_situ.k0", ">= 0"),
    ("k0 str", setting("in_situ.k0", "0.5"), "in_situ.k0", "number"),
    ("sigma with gravity", setting("in_situ.sigma_xx", 1.0), "in_situ.sigma_xx", "uniform"),
    (
        "uniform needs sigma",
        setting("in_situ", {"mode": "uniform", "sigma_xx": 1.0}),
        "in_situ.sigma_yy",
        "required",
    ),
    (
        "k0 with uniform",
        setting("in_situ", {"mode": "uniform", "sigma_xx": 1.0, "sigma_yy": 1.0, "k0": 1}),
        "in_situ.k0",
        "gravity",
    ),
    ("surface nan", setting("in_situ.surface_y", math.nan), "in_situ.surface_y", "finite"),
    # bolts
    ("bolt stiffness", setting("bolts.0.stiffness", 0.0), "bolts.0.stiffness", "> 0"),
    ("bolt yield", setting("bolts.0.yield_force", -1.0), "bolts.0.yield_force", "> 0"),
    ("bolt no anchor", deleting("bolts.0.anchor_capacity"), "bolts.0.anchor_capacity", "required"),
    ("bolt spacing", setting("bolts.0.spacing", 0.0), "bolts.0.spacing", "> 0"),
    ("bolt in tunnel", setting("bolts.0.from", [12, 10]), "bolts.0.from", "inside excavation 'a'"),
    ("bolt outside", setting("bolts.0.to", [50, 10]), "bolts.0.to", "outside the rock"),
    ("bolt zero", setting("bolts.0.to", [15, 10]), "bolts.0.to", "same point"),
    ("bolt stage", setting("bolts.0.stage", "x"), "bolts.0.stage", "unknown stage 'x'"),
    # supports
    ("support exc", setting("supports.0.excavation", "c"), "supports.0.excavation", "unknown"),
    ("support p < 0", setting("supports.0.pressure", -1.0), "supports.0.pressure", ">= 0"),
    ("support no p", deleting("supports.0.pressure"), "supports.0.pressure", "required"),
    ("support stage", setting("supports.0.stage", "z"), "supports.0.stage", "unknown stage"),
    # water
    (
        "water not function",
        setting("water.table", [[0, 25], [20, 22], [20, 21], [40, 20]]),
        "water.table",
        "not a function of x",
    ),
    ("water one point", setting("water.table", [[0, 25]]), "water.table", "at least 2 points"),
    ("water gamma", setting("water.unit_weight", 0.0), "water.unit_weight", "> 0"),
    ("water field", setting("water.level", 3.0), "water.level", "allowed"),
    # stages
    ("stage dup", setting("stages.1.name", "heading"), "stages.1.name", "duplicate"),
    ("stage no name", deleting("stages.0.name"), "stages.0.name", "required"),
    ("stage steps", setting("stages.1.load_steps", 0), "stages.1.load_steps", ">= 1"),
    (
        "stage table",
        setting("stages.1.water_table", [[10, 1], [0, 2]]),
        "stages.1.water_table",
        "not a function of x",
    ),
    ("stage field", setting("stages.0.excavate", "a"), "stages.0.excavate", "allowed"),
    # monitors
    ("monitor in tunnel", setting("monitors.0.point", [12, 10]), "monitors.0.point", "excavation"),
]


@pytest.mark.parametrize(
    ("mutation", "path", "words"),
    [pytest.param(m, p, w, id=i) for i, m, p, w in ROCK_REFUSALS],
)
def test_rock_refusal(mutation, path, words):
    with pytest.raises(SceneError) as info:
        _load_rock_mutated(mutation)
    message = str(info.value)
    assert message.startswith(path + ":"), message
    assert info.value.path == path
    assert words in message, message


def test_rock_scene_check_figure(tmp_path: Path):
    from jaxdem.plots._scene import plot_scene_check

    path = plot_scene_check(parse_scene(rock_scene_dict()), tmp_path / "check.png")
    assert path.stat().st_size > 10_000


# --------------------------------------------------------------------------- issue 19 / 16


def two_joint_dict() -> dict:
    """The valid scene with a second joint "weak" defined before "j"."""
    data = valid_scene_dict()
    data["joints"] = {"weak": {"kn": 1e5, "ks": 1e4, "friction_deg": 10.0},
                      "j": data["joints"]["j"]}
    return data


def test_several_joints_without_default_joint_are_refused():
    # Before: the first joint in the file ("weak") silently applied to the faces between
    # the two stacked blocks; swapping the sections changed the answer.
    with pytest.raises(SceneError) as info:
        parse_scene(two_joint_dict())
    assert info.value.path == "scene.default_joint"
    assert "required when the scene has several joints (weak, j)" in str(info.value)
    assert "blocks.0" in str(info.value)


def test_default_joint_or_block_joint_settles_the_faces():
    from jaxdem.core.model import build

    data = two_joint_dict()
    data["scene"]["default_joint"] = "j"
    scene = parse_scene(data)
    assert scene.default_joint == "j"
    model, _, _ = build(scene)
    # The stacked blocks' faces lie on no discontinuity: -1, the default joint's row
    # (the last) in the contact kernel, which holds joint "j".
    ej = np.asarray(model.edge_joint)
    assert set(ej[2, :4]) == {-1}
    assert float(model.joint_kn[model.joint_kn.shape[0] - 1]) == 1e6

    data = two_joint_dict()
    for b in data["blocks"]:
        b["joint"] = "weak"
    scene = parse_scene(data)
    assert [b.joint for b in scene.blocks] == ["weak"] * 3
    model, _, _ = build(scene)
    ej = np.asarray(model.edge_joint)
    assert set(ej[2, :4]) == {0}  # "weak" is row 0
    # The base's top face lies on the discontinuity of joint "j" (row 1): the line wins.
    assert ej[0, 2] == 1


def test_order_of_joint_sections_does_not_matter_with_default_joint():
    from jaxdem.core.model import build

    rows = []
    for order in (("weak", "j"), ("j", "weak")):
        data = two_joint_dict()
        data["joints"] = {k: data["joints"][k] for k in order}
        data["scene"]["default_joint"] = "j"
        model, _, _ = build(parse_scene(data))
        ej = np.asarray(model.edge_joint)[2, :4]
        assert set(ej) == {-1}
        rows.append(float(np.asarray(model.joint_kn)[ej[0]]))  # -1: the default row
    assert rows == [1e6, 1e6]


def test_blocks_with_different_joints_sharing_a_face_need_a_line():
    data = two_joint_dict()
    data["scene"]["default_joint"] = "j"
    data["blocks"][2]["joint"] = "weak"  # the top block; its lower face is block 1's top
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == "blocks.2.joint"
    message = str(info.value)
    assert "blocks.1 (default_joint 'j') and blocks.2 (joint 'weak')" in message
    assert "share the face (2, 2)-(1, 2)" in message
    # A discontinuity on the shared face says which joint it is.
    data["discontinuities"].append({"from": [0.0, 2.0], "to": [4.0, 2.0], "joint": "weak"})
    parse_scene(data)


def test_unknown_block_joint_is_refused():
    data = two_joint_dict()
    data["scene"]["default_joint"] = "j"
    data["blocks"][1]["joint"] = "strong"
    with pytest.raises(SceneError, match=r"^blocks\.1\.joint: unknown joint 'strong'; "
                                         r"defined: weak, j$"):
        parse_scene(data)


def test_single_joint_scenes_need_no_default_joint():
    scene = parse_scene(valid_scene_dict())
    assert scene.default_joint == "j"


def _staged(data: dict, ref) -> dict:
    data["stages"] = [{"name": "excavate"}, {"name": "bolt"}]
    data["excavations"][1]["stage"] = ref
    data["bolts"][0]["stage"] = ref
    data["supports"][0]["stage"] = ref
    return data


def test_stage_by_number_is_the_stage_of_that_number():
    scene = parse_scene(_staged(rock_scene_dict(), 2))
    assert scene.excavations[1].stage == "bolt"
    assert scene.bolts[0].stage == "bolt"
    assert scene.supports[0].stage == "bolt"
    assert parse_scene(_staged(rock_scene_dict(), 1)).bolts[0].stage == "excavate"
    assert parse_scene(_staged(rock_scene_dict(), "bolt")).bolts[0].stage == "bolt"


@pytest.mark.parametrize(("ref", "words"), [
    (3, "stage 3 does not exist: stages are 1 'excavate', 2 'bolt' (a number counts from 1)"),
    (0, "stage 0 does not exist: stages are 1 'excavate', 2 'bolt'"),
    (1.5, "stage 1.5 does not exist"),
    ("blot", "unknown stage 'blot' (it would never come): stages are 1 'excavate', 2 'bolt'"),
    (True, "must be a stage name or its number from 1 (got True)"),
])
def test_wrong_stage_reference_lists_the_stages(ref, words):
    data = _staged(rock_scene_dict(), "bolt")
    data["bolts"][0]["stage"] = ref
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == "bolts.0.stage"
    assert words in str(info.value)


@pytest.mark.parametrize("section", ["bolts", "supports", "excavations"])
def test_stage_that_never_comes_is_refused(section):
    # No [[stages]] at all: a stage reference names a stage that never comes.
    data = rock_scene_dict()
    del data["stages"]
    data["excavations"][1].pop("stage")
    data["bolts"][0].pop("stage")
    data[section][-1]["stage"] = 2
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == f"{section}.{len(data[section]) - 1}.stage"
    assert "never comes, the scene has no [[stages]]" in str(info.value)


def test_trace_angle_closed_forms():
    from jaxdem.scene import trace_angle

    # Dipping 35 deg towards +x ("right"): the trace descends with x, -35 deg (= 145 deg).
    assert trace_angle(35.0, "right") == pytest.approx(-35.0, abs=1e-12)
    assert trace_angle(35.0, "left") == pytest.approx(35.0, abs=1e-12)
    # Azimuths: section +x towards east (90); dip direction east = "right", west = "left".
    assert trace_angle(35.0, 90.0, section_azimuth=90.0) == pytest.approx(-35.0, abs=1e-12)
    assert trace_angle(35.0, 270.0, section_azimuth=90.0) == pytest.approx(35.0, abs=1e-12)
    # 60 deg off the section: apparent dip tan(a) = tan 35 cos 60.
    a = math.degrees(math.atan(math.tan(math.radians(35.0)) * 0.5))
    assert trace_angle(35.0, 150.0, section_azimuth=90.0) == pytest.approx(-a, abs=1e-12)
    # Striking along the section: a horizontal trace. Vertical: a vertical trace.
    assert trace_angle(35.0, 0.0, section_azimuth=90.0) == pytest.approx(0.0, abs=1e-12)
    assert trace_angle(90.0, "right") == 90.0


def test_geological_dip_gives_the_same_set_as_the_trace_angle():
    data = rock_scene_dict()
    data["joints"]["set1"] = {"kn": 1e6, "ks": 1e5, "friction_deg": 25.0, "dip": 35.0,
                              "dip_direction": "right", "spacing": 2.0}
    scene = parse_scene(data)
    assert scene.joints["set1"].dip_deg == pytest.approx(-35.0)
    data["scene"]["section_azimuth"] = 45.0
    data["joints"]["set1"]["dip_direction"] = 225.0  # towards -x
    assert parse_scene(data).joints["set1"].dip_deg == pytest.approx(35.0)


@pytest.mark.parametrize(("change", "path", "words"), [
    ({"dip": 35.0, "dip_direction": "right", "dip_deg": 10.0}, "joints.set1.dip",
     "either dip_deg"),
    ({"dip": 35.0}, "joints.set1.dip_direction", "required with dip"),
    ({"dip_direction": "left"}, "joints.set1.dip", "required with dip_direction"),
    ({"dip": 95.0, "dip_direction": "left"}, "joints.set1.dip", "must be in [0, 90]"),
    ({"dip": 35.0, "dip_direction": "up"}, "joints.set1.dip_direction", "'left', 'right'"),
    ({"dip": 35.0, "dip_direction": 120.0}, "scene.section_azimuth", "required with"),
    ({"dip": 35.0, "dip_direction": 400.0}, "joints.set1.dip_direction", "[0, 360]"),
])
def test_geological_dip_refusals(change, path, words):
    data = rock_scene_dict()
    joint = {"kn": 1e6, "ks": 1e5, "friction_deg": 25.0, "spacing": 2.0}
    joint.update(change)
    data["joints"]["set1"] = joint
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == path
    assert words in str(info.value)


def test_vertical_joint_in_the_section_plane_is_refused():
    data = rock_scene_dict()
    data["scene"]["section_azimuth"] = 90.0
    data["joints"]["set1"] = {"kn": 1e6, "ks": 1e5, "friction_deg": 25.0, "spacing": 2.0,
                              "dip": 90.0, "dip_direction": 0.0}
    with pytest.raises(SceneError, match=r"^joints\.set1\.dip_direction: .*section plane"):
        parse_scene(data)


def test_rounded_coordinates_overlap_within_tolerance_is_accepted():
    # The case: coordinates rounded to 6 decimals make neighbours overlap by
    # about 1e-6 m; that is below OVERLAP_TOLERANCE (1e-5) of a 1 m block: accepted.
    from jaxdem.scene import OVERLAP_TOLERANCE, overlap_depth

    data = valid_scene_dict()
    data["blocks"][2]["vertices"] = [[1, 1.999999], [2, 1.999999], [2, 3], [1, 3]]
    scene = parse_scene(data)
    area, depth = overlap_depth(scene.blocks[1].vertices, scene.blocks[2].vertices)
    assert area == pytest.approx(1e-6, rel=1e-6)
    assert depth == pytest.approx(2e-6 / 2.000002, rel=1e-6)
    assert depth < OVERLAP_TOLERANCE * 1.0
    # Twenty times deeper (2e-5 m > 1e-5 m): refused, with the tolerance stated.
    data["blocks"][2]["vertices"] = [[1, 1.99998], [2, 1.99998], [2, 3], [1, 3]]
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    assert info.value.path == "blocks.2"
    assert "1e-05 of the smaller block's size (1e-05 m) is accepted" in str(info.value)
