"""VTK output (jaxdem.vtk, ``jaxdem run --vtk``): the written files read back."""

from __future__ import annotations

import numpy as np
import pytest
from test_plots import make_result

from jaxdem.vtk import write_vtk


def read_legacy_vtk(path) -> dict:
    """A small independent reader of legacy ASCII POLYDATA: points, cells, and the
    named SCALARS / VECTORS / TENSORS arrays of CELL_DATA and POINT_DATA."""
    tokens = path.read_text().split("\n")
    assert tokens[0].startswith("# vtk DataFile Version")
    assert tokens[2] == "ASCII" and tokens[3] == "DATASET POLYDATA"
    words = " ".join(tokens[4:]).split()
    out: dict = {"cell": {}, "point": {}}
    k, where = 0, None
    while k < len(words):
        w = words[k]
        if w == "POINTS":
            n = int(words[k + 1])
            out["points"] = np.array(words[k + 3:k + 3 + 3 * n], float).reshape(n, 3)
            k += 3 + 3 * n
        elif w in ("POLYGONS", "VERTICES", "LINES"):
            n, size = int(words[k + 1]), int(words[k + 2])
            flat = [int(x) for x in words[k + 3:k + 3 + size]]
            cells, j = [], 0
            for _ in range(n):
                cells.append(flat[j + 1:j + 1 + flat[j]])
                j += 1 + flat[j]
            out[w.lower()] = cells
            k += 3 + size
        elif w in ("CELL_DATA", "POINT_DATA"):
            where, count = ("cell" if w == "CELL_DATA" else "point"), int(words[k + 1])
            k += 2
        elif w == "SCALARS":
            name = words[k + 1]
            assert words[k + 4:k + 6] == ["LOOKUP_TABLE", "default"]
            out[where][name] = np.array(words[k + 6:k + 6 + count], float)
            k += 6 + count
        elif w in ("VECTORS", "TENSORS"):
            name, width = words[k + 1], 3 if w == "VECTORS" else 9
            out[where][name] = np.array(words[k + 3:k + 3 + width * count], float).reshape(
                (count, 3) if w == "VECTORS" else (count, 3, 3))
            k += 3 + width * count
        else:
            raise AssertionError(f"unexpected token {w!r} in {path}")
    return out


def test_synthetic_result_round_trips(tmp_path):
    result = make_result(moving=True)
    result.blocks[1]["stress"] = [100.0, 40.0, 30.0]
    result.blocks[2]["excavated"] = True
    paths = write_vtk(result, tmp_path)
    assert [p.name for p in paths] == ["blocks.vtk", "contacts.vtk"]
    b = read_legacy_vtk(paths[0])
    final = result.geometry["final_vertices"]
    assert len(b["polygons"]) == 3
    for cell, poly in zip(b["polygons"], final, strict=True):
        np.testing.assert_allclose(b["points"][cell, :2], poly)
    np.testing.assert_allclose(b["points"][:, 2], 0.0)
    u = np.array([blk["u"] for blk in result.blocks])
    np.testing.assert_allclose(b["cell"]["displacement"][:, :2], u[:, :2])
    np.testing.assert_allclose(b["cell"]["rotation"], u[:, 2])
    np.testing.assert_allclose(b["cell"]["stress"][1], [[100, 30, 0], [30, 40, 0], [0, 0, 0]])
    # Principal stresses of (100, 40, 30): 70 +- sqrt(30^2 + 30^2).
    r = np.hypot(30.0, 30.0)
    assert b["cell"]["sigma1"][1] == pytest.approx(70 + r)
    assert b["cell"]["sigma3"][1] == pytest.approx(70 - r)
    assert b["cell"]["fixed"].tolist() == [1, 0, 0]
    assert b["cell"]["excavated"].tolist() == [0, 0, 1]
    assert b["cell"]["moving"].tolist() == [0, 0, 1]

    c = read_legacy_vtk(paths[1])
    con = result.geometry["contacts"]
    np.testing.assert_allclose(c["points"][:, :2], con["points"])
    assert c["vertices"] == [[k] for k in range(5)]
    assert c["point"]["state"].tolist() == list(con["state"])
    np.testing.assert_allclose(c["point"]["fn"], con["fn"])
    # Normal (0, 1), fn = 1, fs = 0: force (0, 1).
    np.testing.assert_allclose(c["point"]["force"], np.tile([0.0, 1.0, 0.0], (5, 1)))


def test_run_vtk_writes_the_solved_blocks(tmp_path, capsys):
    from test_cli import SCENE

    from jaxdem.cli import main

    scene = tmp_path / "block.toml"
    scene.write_text(SCENE.format(E="1e7"))
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "--vtk"]) == 0
    import json

    result = json.loads((out / "result.json").read_text())
    b = read_legacy_vtk(out / "blocks.vtk")
    assert len(b["polygons"]) == len(result["blocks"]) == 2
    u = np.array([blk["u"] for blk in result["blocks"]])
    np.testing.assert_allclose(b["cell"]["displacement"][:, :2], u[:, :2], rtol=1e-12)
    stress = np.array([blk["stress"] for blk in result["blocks"]])
    np.testing.assert_allclose(b["cell"]["stress"][:, 0, 0], stress[:, 0], rtol=1e-12)
    # The resting block's weight (25 kN/m3 x 1 m2) is carried by its contacts.
    c = read_legacy_vtk(out / "contacts.vtk")
    assert len(c["points"]) == result["contacts"]["total"] > 0
    assert c["point"]["force"][:, 1].sum() == pytest.approx(25.0, rel=1e-5)
    assert c["point"]["state"].tolist() == [1] * len(c["points"])  # stuck
    assert "blocks.vtk" in capsys.readouterr().out


# --------------------------------------------------------------------------- bolts and stages


def read_vtp(path) -> dict:
    """A small independent reader of ASCII XML PolyData (.vtp): points, the cells of each
    kind (Verts, Lines, Polys) from connectivity and offsets, and the named arrays of
    CellData and PointData, shaped (n, components)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "PolyData"
    piece = root.find("PolyData/Piece")

    def values(array):
        kind = float if array.get("type").startswith("Float") else int
        flat = np.array([kind(x) for x in (array.text or "").split()])
        width = int(array.get("NumberOfComponents", "1"))
        return flat.reshape(-1, width) if width > 1 else flat

    out = {"points": values(piece.find("Points/DataArray")).reshape(-1, 3), "cell": {},
           "point": {}}
    assert len(out["points"]) == int(piece.get("NumberOfPoints"))
    for tag in ("Verts", "Lines", "Polys"):
        node = piece.find(tag)
        cells = []
        if node is not None:
            arrays = {a.get("Name"): values(a) for a in node.findall("DataArray")}
            starts = np.concatenate([[0], arrays["offsets"][:-1]]).astype(int)
            cells = [arrays["connectivity"][s:e].tolist()
                     for s, e in zip(starts, arrays["offsets"], strict=True)]
        assert len(cells) == int(piece.get(f"NumberOf{tag}")), tag
        out[tag.lower()] = cells
    for where, tag in (("cell", "CellData"), ("point", "PointData")):
        node = piece.find(tag)
        for a in [] if node is None else node.findall("DataArray"):
            out[where][a.get("Name")] = values(a)
    return out


def read_pvd(path) -> list[tuple[int, str, str]]:
    """(timestep, file, name) of each DataSet of a ParaView Data collection, in order."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    return [(int(d.get("timestep")), d.get("file"), d.get("name"))
            for d in root.findall("Collection/DataSet")]


def _staged_key_block(weight: bool):
    """tests/test_bolt_install.py's key block: two 20 kN bolts in stage 1, one in stage 2;
    with its weight the wedge falls in stage 1 (stage 2 never runs), without it every
    stage runs."""
    from test_bolt_install import _scene

    import jaxdem
    from jaxdem.scene import parse_scene

    d = _scene()
    if not weight:
        d["materials"]["rock"]["unit_weight"] = 0.0
    return jaxdem.solve(parse_scene(d))


def test_bolts_are_lines_with_the_forces_and_states_of_result_json(tmp_path):
    result = _staged_key_block(weight=True)
    paths = write_vtk(result, tmp_path)
    assert [p.name for p in paths][:3] == ["blocks.vtk", "contacts.vtk", "bolts.vtk"]
    b = read_legacy_vtk(tmp_path / "bolts.vtk")
    data = result.to_dict()["bolts"]
    assert b["lines"] == [[0, 1], [2, 3], [4, 5]]
    for k, anchors in enumerate(result.geometry["bolts"]):
        np.testing.assert_allclose(b["points"][2 * k:2 * k + 2, :2], anchors)
    np.testing.assert_allclose(b["cell"]["force"], [x["force"] for x in data], rtol=1e-15)
    np.testing.assert_allclose(b["cell"]["force_per_m"], [x["force_per_m"] for x in data])
    # yielded, yielded, not installed (the analysis stopped in stage 1).
    assert [x["state"] for x in data] == ["yielded", "yielded", "not installed"]
    assert b["cell"]["state"].tolist() == [1, 1, -1]


def test_one_file_per_stage_in_a_pvd_collection(tmp_path):
    result = _staged_key_block(weight=False)
    names = [s["name"] for s in result.stages]
    assert names == ["initial", "first", "second"]
    write_vtk(result, tmp_path)
    for kind in ("blocks", "contacts", "bolts"):
        entries = read_pvd(tmp_path / f"{kind}.pvd")
        # The initial state is timestep 0, stage k (stage = k in the file) timestep k.
        assert entries == [(k, f"stages/{kind}_{k}.vtp", name) for k, name in enumerate(names)]
        for _, file, _ in entries:
            assert (tmp_path / file).is_file()
    # The last stage's files are the final state, as result.json and the .vtk files have it.
    last = read_vtp(tmp_path / "stages/blocks_2.vtp")
    final = read_legacy_vtk(tmp_path / "blocks.vtk")
    assert last["polys"] == final["polygons"]
    np.testing.assert_allclose(last["points"], final["points"], rtol=1e-15)
    u = np.array([blk["u"] for blk in result.blocks])
    np.testing.assert_allclose(last["cell"]["displacement"][:, :2], u[:, :2], rtol=1e-12)
    np.testing.assert_allclose(last["cell"]["stress"], final["cell"]["stress"].reshape(-1, 9))
    # Displacements count from the initial state: zero there.
    np.testing.assert_array_equal(read_vtp(tmp_path / "stages/blocks_0.vtp")["cell"][
        "displacement"], 0.0)
    # Bolts: none installed in the initial state, the stage-1 pair from stage 1, all three
    # from stage 2 (weightless: elastic at 0 kN, their real state).
    states = [read_vtp(tmp_path / f"stages/bolts_{k}.vtp")["cell"]["state"].tolist()
              for k in range(3)]
    assert states == [[-1, -1, -1], [0, 0, -1], [0, 0, 0]]
    contacts = read_vtp(tmp_path / "stages/contacts_2.vtp")
    assert len(contacts["verts"]) == len(contacts["points"]) == result.contacts["total"]


def test_a_stage_that_stopped_is_the_last_file(tmp_path):
    result = _staged_key_block(weight=True)
    assert result.status == "mechanism"
    write_vtk(result, tmp_path)
    assert [e[0] for e in read_pvd(tmp_path / "blocks.pvd")] == [0, 1]  # stage 2 never ran
    last = read_vtp(tmp_path / "stages/blocks_1.vtp")
    np.testing.assert_allclose(last["cell"]["displacement"][:, :2],
                               np.array([blk["u"] for blk in result.blocks])[:, :2], rtol=1e-12)
    assert last["cell"]["moving"].tolist() == [1, 0, 0, 0]  # the wedge
    bolts = read_vtp(tmp_path / "stages/bolts_1.vtp")
    np.testing.assert_allclose(bolts["cell"]["force"], [b["force"] for b in result.bolts])
    assert bolts["cell"]["state"].tolist() == [1, 1, -1]
