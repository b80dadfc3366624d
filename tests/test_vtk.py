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
        elif w in ("POLYGONS", "VERTICES"):
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
