"""VTK output for ParaView (``jaxdem run --vtk``): the final state as legacy ASCII ``.vtk``
POLYDATA files, and every stage as XML PolyData (``.vtp``) files with ``.pvd``
collections that ParaView steps through.

ParaView, VisIt and the VTK readers of UDEC, 3DEC and YADE users open both formats
directly; they are written here with NumPy, so no dependency is added. The final state:

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

``bolts.vtk`` (a scene with bolts)
    One line per bolt between its two current anchor points (m), in the order of
    result.json's ``bolts``, cell data: ``id``; ``force`` (kN per bolt, tension positive)
    and ``force_per_m`` (kN/m), as in result.json; ``state``, an integer
    (:data:`jaxdem.results.BOLT_STATE_CODES`): 0 elastic, 1 yielded, 2 pulled out,
    3 slack, 4 yielded in compression, -1 not installed (its stage never ran).

Every stage (from :func:`jaxdem.solve`: ``Result.geometry["stages"]``): the same three
datasets at the end of each stage (the last one where the analysis stopped) as
``stages/blocks_K.vtp``, ``stages/contacts_K.vtp`` and ``stages/bolts_K.vtp``, K = 0 for
the initial state (loading or in-situ) and the stage's number (``stage = K`` in the
file) after it, listed in order by ``blocks.pvd``, ``contacts.pvd`` and ``bolts.pvd``
with ``timestep = K``: open a ``.pvd`` in ParaView and step through the stages with the
time controls. ``moving`` is set in the last one only.

Example::

    result = jaxdem.solve(jaxdem.load_scene("examples/staged_tunnel.toml"))
    write_vtk(result, "out/tunnel")  # blocks.vtk, contacts.vtk, bolts.vtk, blocks.pvd, ...
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from jaxdem.results import BOLT_STATE_CODES

__all__ = ["write_vtk"]

# A dataset: points (n, 2) m; cells (lists of point indices) of one kind ("polygons",
# "lines" or "vertices"); its arrays on the cells or the points ("cell" or "point"), each
# (name, values, "int" or "double"): values (m,) a scalar, (m, 3) a vector, (m, 3, 3) a tensor.
_Dataset = dict[str, Any]


def _fmt(values: np.ndarray) -> str:
    return "\n".join(" ".join(repr(float(x)) for x in row) for row in np.atleast_2d(values))


def _principal(stress: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sxx, syy, sxy = stress[:, 0], stress[:, 1], stress[:, 2]
    c, r = 0.5 * (sxx + syy), np.hypot(0.5 * (sxx - syy), sxy)
    return c + r, c - r


def _vector(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy, float).reshape(-1, 2)
    return np.column_stack([xy, np.zeros(len(xy))])


def _blocks(vertices: list, u: np.ndarray, stress: np.ndarray, fixed, excavated,
            moving) -> _Dataset:
    """Blocks as polygons at ``vertices`` with their displacement ``u`` (n, 3) and stress."""
    polys = [np.asarray(v, float).reshape(-1, 2) for v in vertices]
    n = len(polys)
    u = np.asarray(u, float).reshape(n, 3)
    stress = np.asarray(stress, float).reshape(n, 3)
    sizes = [len(p) for p in polys]
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int) if polys else []
    s1, s3 = _principal(stress)
    tensors = np.zeros((n, 3, 3))
    tensors[:, 0, 0], tensors[:, 1, 1] = stress[:, 0], stress[:, 1]
    tensors[:, 0, 1] = tensors[:, 1, 0] = stress[:, 2]
    as_int = lambda x: np.asarray(x, int).reshape(n)  # noqa: E731
    return dict(
        points=np.concatenate(polys) if polys else np.zeros((0, 2)), kind="polygons",
        cells=[list(range(s, s + m)) for s, m in zip(starts, sizes, strict=True)], on="cell",
        arrays=[("id", np.arange(n), "int"), ("displacement", _vector(u[:, :2]), "double"),
                ("rotation", u[:, 2], "double"), ("stress", tensors, "double"),
                ("sigma1", s1, "double"), ("sigma3", s3, "double"),
                ("fixed", as_int(fixed), "int"), ("excavated", as_int(excavated), "int"),
                ("moving", as_int(moving), "int")])


def _contacts(c: dict) -> _Dataset:
    """Contact spring points with their state and forces (``Result.geometry["contacts"]``)."""
    pts = np.asarray(c.get("points", np.zeros((0, 2))), float).reshape(-1, 2)
    m = len(pts)
    normal = np.asarray(c.get("normals", np.zeros((0, 2))), float).reshape(m, 2)
    fn = np.asarray(c.get("fn", np.zeros(0)), float).reshape(m)
    fs = np.asarray(c.get("fs", np.zeros(0)), float).reshape(m)
    state = np.asarray(c.get("state", np.zeros(0)), int).reshape(m)
    tangent = np.column_stack([-normal[:, 1], normal[:, 0]])
    force = fn[:, None] * normal + fs[:, None] * tangent
    return dict(points=pts, kind="vertices", cells=[[k] for k in range(m)], on="point",
                arrays=[("state", state, "int"), ("fn", fn, "double"), ("fs", fs, "double"),
                        ("normal", _vector(normal), "double"),
                        ("force", _vector(force), "double")])


def _bolts(anchors: list, records: list[dict]) -> _Dataset:
    """Bolts as lines between their anchors, with result.json's force and state (coded)."""
    ends = np.asarray(anchors, float).reshape(-1, 2, 2)
    n = len(ends)
    rec = [records[k] if k < len(records) else {} for k in range(n)]
    state = [BOLT_STATE_CODES[r.get("state", "elastic")] for r in rec]
    return dict(points=ends.reshape(-1, 2), kind="lines",
                cells=[[2 * k, 2 * k + 1] for k in range(n)], on="cell",
                arrays=[("id", np.arange(n), "int"),
                        ("force", np.array([r.get("force", 0.0) for r in rec], float), "double"),
                        ("force_per_m", np.array([r.get("force_per_m", 0.0) for r in rec], float),
                         "double"),
                        ("state", np.array(state, int), "int")])


_LEGACY_CELLS = {"polygons": "POLYGONS", "lines": "LINES", "vertices": "VERTICES"}


def _write_legacy(path: Path, title: str, ds: _Dataset) -> Path:
    """A legacy ASCII POLYDATA file of a dataset."""
    points, cells, arrays = ds["points"], ds["cells"], ds["arrays"]
    size = sum(1 + len(c) for c in cells)
    lines = ["# vtk DataFile Version 3.0", title[:255].replace("\n", " "), "ASCII",
             "DATASET POLYDATA", f"POINTS {len(points)} double",
             _fmt(_vector(points)) if len(points) else "",
             f"{_LEGACY_CELLS[ds['kind']]} {len(cells)} {size}"]
    lines += [" ".join(map(str, [len(c), *c])) for c in cells]
    on_cells = ds["on"] == "cell"
    lines += [f"{'CELL' if on_cells else 'POINT'}_DATA {len(cells if on_cells else points)}"]
    for name, values, kind in arrays:
        values = np.asarray(values)
        if values.ndim == 1:
            lines += [f"SCALARS {name} {kind} 1", "LOOKUP_TABLE default",
                      "\n".join(str(int(v)) if kind == "int" else repr(float(v)) for v in values)]
        elif values.ndim == 2:
            lines += [f"VECTORS {name} double", _fmt(values) if len(values) else ""]
        else:
            lines += [f"TENSORS {name} double", "\n\n".join(_fmt(t) for t in values)]
    path.write_text("\n".join(line for line in lines if line != "") + "\n")
    return path


_XML_CELLS = {"polygons": "Polys", "lines": "Lines", "vertices": "Verts"}


def _data_array(name: str, values: np.ndarray, kind: str) -> str:
    values = np.asarray(values)
    width = int(np.prod(values.shape[1:], dtype=int))
    text = " ".join(str(int(v)) if kind == "int" else repr(float(v)) for v in values.ravel())
    return (f'<DataArray type="{"Int32" if kind == "int" else "Float64"}" Name={quoteattr(name)}'
            f' NumberOfComponents="{width}" format="ascii">{text}</DataArray>')


def _write_vtp(path: Path, ds: _Dataset) -> Path:
    """An XML PolyData (``.vtp``, ASCII) file of a dataset."""
    points, cells, on = ds["points"], ds["cells"], ds["on"]
    counts = {tag: (len(cells) if tag == _XML_CELLS[ds["kind"]] else 0)
              for tag in ("Verts", "Lines", "Strips", "Polys")}
    offsets = np.cumsum([len(c) for c in cells]).astype(int)
    connectivity = np.array([i for c in cells for i in c], int)
    data = "\n".join(_data_array(*a) for a in ds["arrays"])
    tag = _XML_CELLS[ds["kind"]]
    text = "\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">',
        "<PolyData>",
        f'<Piece NumberOfPoints="{len(points)}" '
        + " ".join(f'NumberOf{k}="{v}"' for k, v in counts.items()) + ">",
        f"<{'CellData' if on == 'cell' else 'PointData'}>", data,
        f"</{'CellData' if on == 'cell' else 'PointData'}>",
        "<Points>", _data_array("Points", _vector(points), "double"), "</Points>",
        f"<{tag}>", _data_array("connectivity", connectivity, "int"),
        _data_array("offsets", offsets, "int"), f"</{tag}>",
        "</Piece>", "</PolyData>", "</VTKFile>", ""])
    path.write_text(text)
    return path


def _write_pvd(path: Path, entries: list[tuple[int, str, str]]) -> Path:
    """A ParaView Data collection: one DataSet per (timestep, file, stage name), in order."""
    rows = [f'<DataSet timestep="{k}" group="" part="0" file={quoteattr(f)} '
            f'name={quoteattr(name)}/>' for k, f, name in entries]
    path.write_text("\n".join([
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "<Collection>", *rows, "</Collection>", "</VTKFile>", ""]))
    return path


def _write_stages(out: Path, frames: list[dict], moving: np.ndarray,
                  with_bolts: bool) -> list[Path]:
    """Each stage's blocks, contacts (and bolts) under ``out/stages`` and their ``.pvd``."""
    folder = out / "stages"
    folder.mkdir(exist_ok=True)
    kinds = ["blocks", "contacts"] + (["bolts"] if with_bolts else [])
    entries: dict[str, list] = {kind: [] for kind in kinds}
    for i, f in enumerate(frames):
        k = int(f["index"])
        last = i == len(frames) - 1
        n = len(f["final_vertices"])
        sets = {"blocks": _blocks(f["final_vertices"], f["u"], f["stress"], f["fixed"],
                                  f["excavated"], moving if last else np.zeros(n, int)),
                "contacts": _contacts(f["contacts"]),
                "bolts": _bolts(f["bolts"], f["bolt_records"])}
        for kind in kinds:
            name = f"{kind}_{k}.vtp"
            _write_vtp(folder / name, sets[kind])
            entries[kind].append((k, f"stages/{name}", str(f["name"])))
    return [_write_pvd(out / f"{kind}.pvd", entries[kind]) for kind in kinds]


def write_vtk(result: Any, out_dir: str | Path) -> list[Path]:
    """Write the VTK files of a :class:`jaxdem.Result` to ``out_dir``: ``blocks.vtk``,
    ``contacts.vtk``, ``bolts.vtk`` (when there are bolts) of the final state, and, for a
    result of :func:`jaxdem.solve`, every stage's files under ``stages/`` with their
    ``.pvd`` collections (see the module for their content).

    Returns the paths written in ``out_dir`` itself (the ``.pvd`` files list the stages'
    files).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    g = result.geometry
    blocks = result.blocks
    n = len(g["final_vertices"])
    moving = np.zeros(n, int)
    moving[[i for i in result.moving_blocks if 0 <= i < n]] = 1
    final = _blocks(g["final_vertices"], [b["u"] for b in blocks],
                    [b["stress"] for b in blocks], [b.get("fixed", False) for b in blocks],
                    [b.get("excavated", False) for b in blocks], moving)
    written = [_write_legacy(out / "blocks.vtk", f"jaxdem blocks: {result.scene}", final),
               _write_legacy(out / "contacts.vtk", f"jaxdem contacts: {result.scene}",
                             _contacts(g.get("contacts", {})))]
    with_bolts = bool(result.bolts)
    if with_bolts:
        written.append(_write_legacy(out / "bolts.vtk", f"jaxdem bolts: {result.scene}",
                                     _bolts(g.get("bolts") or [], result.bolts)))
    frames = g.get("stages") or []
    if frames:
        written += _write_stages(out, frames, moving, with_bolts)
    return written
