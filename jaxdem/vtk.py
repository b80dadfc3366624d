"""VTK output for ParaView (``jaxdem run --vtk``): legacy ASCII ``.vtk`` POLYDATA files.

ParaView, VisIt and the VTK readers of UDEC, 3DEC and YADE users open the legacy format
directly; it is written here with NumPy, so no dependency is added. Two files:

``blocks.vtk``
    One polygon per block at its final position (z = 0), cell data:
    ``id``; ``displacement`` (m; ux, uy, 0: the centroid's, as in result.json, counted
    from the state before the first stage); ``rotation`` (rad, counter-clockwise);
    ``stress`` (kPa, compression positive, a 3x3 tensor with sxx, syy, sxy in the
    x-y block); ``sigma1``, ``sigma3`` (kPa, major and minor principal stress);
    ``fixed``, ``excavated`` and ``moving`` (1 or 0; ``moving``: a block of the
    mechanism). Filter ``excavated = 0`` (Threshold) to hide excavated rock.

``contacts.vtk``
    One vertex per contact spring point in contact (m), point data: ``state``
    (0 open, 1 stuck, 2 slipping); ``fn``, ``fs`` (kN/m, the spring's normal and shear
    force as the solver stores them: fn compression positive); ``normal`` (unit) and
    ``force`` = fn * normal + fs * tangent, tangent = (-normal_y, normal_x) (kN/m), for
    glyphs.

Example::

    result = jaxdem.solve(jaxdem.load_scene("examples/slide_and_stop.toml"))
    write_vtk(result, "out/slide")     # [Path("out/slide/blocks.vtk"), ...contacts.vtk]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_vtk"]


def _fmt(values: np.ndarray) -> str:
    return "\n".join(" ".join(repr(float(x)) for x in row) for row in np.atleast_2d(values))


def _header(title: str) -> list[str]:
    return ["# vtk DataFile Version 3.0", title[:255].replace("\n", " "), "ASCII",
            "DATASET POLYDATA"]


def _scalars(name: str, values: np.ndarray, kind: str = "double") -> list[str]:
    return [f"SCALARS {name} {kind} 1", "LOOKUP_TABLE default",
            "\n".join(str(int(v)) if kind == "int" else repr(float(v)) for v in values)]


def _principal(stress: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sxx, syy, sxy = stress[:, 0], stress[:, 1], stress[:, 2]
    c, r = 0.5 * (sxx + syy), np.hypot(0.5 * (sxx - syy), sxy)
    return c + r, c - r


def write_vtk(result: Any, out_dir: str | Path) -> list[Path]:
    """Write ``blocks.vtk`` and ``contacts.vtk`` of a :class:`jaxdem.Result` to ``out_dir``.

    Returns the paths written (see the module for their content).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    g = result.geometry
    polys = [np.asarray(v, float).reshape(-1, 2) for v in g["final_vertices"]]
    n = len(polys)
    blocks = result.blocks
    u = np.array([b["u"] for b in blocks], float).reshape(n, 3)
    stress = np.array([b["stress"] for b in blocks], float).reshape(n, 3)
    fixed = np.array([b.get("fixed", False) for b in blocks], int)
    excavated = np.array([b.get("excavated", False) for b in blocks], int)
    moving = np.zeros(n, int)
    moving[[i for i in result.moving_blocks if 0 <= i < n]] = 1
    points = np.concatenate(polys) if polys else np.zeros((0, 2))
    sizes = [len(p) for p in polys]
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int) if polys else []
    lines = _header(f"jaxdem blocks: {result.scene}")
    lines += [f"POINTS {len(points)} double",
              _fmt(np.column_stack([points, np.zeros(len(points))]))]
    lines += [f"POLYGONS {n} {n + sum(sizes)}"]
    lines += [" ".join(map(str, [m, *range(s, s + m)])) for s, m in zip(starts, sizes,
                                                                         strict=True)]
    s1, s3 = _principal(stress)
    tensors = np.zeros((n, 3, 3))
    tensors[:, 0, 0], tensors[:, 1, 1] = stress[:, 0], stress[:, 1]
    tensors[:, 0, 1] = tensors[:, 1, 0] = stress[:, 2]
    lines += [f"CELL_DATA {n}"]
    lines += _scalars("id", np.arange(n), "int")
    lines += ["VECTORS displacement double",
              _fmt(np.column_stack([u[:, :2], np.zeros(n)]))]
    lines += _scalars("rotation", u[:, 2])
    lines += ["TENSORS stress double",
              "\n\n".join(_fmt(t) for t in tensors)]
    lines += _scalars("sigma1", s1) + _scalars("sigma3", s3)
    lines += _scalars("fixed", fixed, "int") + _scalars("excavated", excavated, "int")
    lines += _scalars("moving", moving, "int")
    blocks_path = out / "blocks.vtk"
    blocks_path.write_text("\n".join(lines) + "\n")

    c = g.get("contacts", {})
    pts = np.asarray(c.get("points", np.zeros((0, 2))), float).reshape(-1, 2)
    m = len(pts)
    normal = np.asarray(c.get("normals", np.zeros((0, 2))), float).reshape(m, 2)
    fn = np.asarray(c.get("fn", np.zeros(0)), float).reshape(m)
    fs = np.asarray(c.get("fs", np.zeros(0)), float).reshape(m)
    state = np.asarray(c.get("state", np.zeros(0)), int).reshape(m)
    tangent = np.column_stack([-normal[:, 1], normal[:, 0]])
    force = fn[:, None] * normal + fs[:, None] * tangent
    lines = _header(f"jaxdem contacts: {result.scene}")
    lines += [f"POINTS {m} double", _fmt(np.column_stack([pts, np.zeros(m)])) if m else ""]
    lines += [f"VERTICES {m} {2 * m}"] + [f"1 {k}" for k in range(m)]
    lines += [f"POINT_DATA {m}"]
    lines += _scalars("state", state, "int") + _scalars("fn", fn) + _scalars("fs", fs)
    lines += ["VECTORS normal double", _fmt(np.column_stack([normal, np.zeros(m)])) if m else ""]
    lines += ["VECTORS force double", _fmt(np.column_stack([force, np.zeros(m)])) if m else ""]
    contacts_path = out / "contacts.vtk"
    contacts_path.write_text("\n".join(line for line in lines if line != "") + "\n")
    return [blocks_path, contacts_path]
