"""Mesh cells of a generated rock mass (step 6 of :mod:`jaxdem.rockmass`): every piece
clipped by the square grid of ``domain.mesh_size`` or by graded quadtree squares (size
``mesh_size`` at the openings, growing by ``GROWTH`` with the distance to them, up to
``mesh_max_size``), then split into triangles, the constant-strain cells the solver makes
deformable.

Works on the ``Work`` of :mod:`jaxdem.rockmass._cutting` in place, called by
:func:`jaxdem.rockmass.generate`. Host NumPy with :mod:`jaxdem.geometry`.
"""

from __future__ import annotations

import math

import numpy as np

from jaxdem import geometry
from jaxdem.rockmass._cutting import Work, clip, piece_area


def mesh_pieces(work: Work, h: float, origin: np.ndarray, tol: float) -> None:
    new = Work()
    ex = np.array([1.0, 0.0])
    ey = np.array([0.0, 1.0])
    for i, v in enumerate(work.polys):
        lo, hi = v.min(axis=0), v.max(axis=0)
        xs = origin[0] + h * np.arange(
            math.ceil((lo[0] - origin[0] + tol) / h), math.floor((hi[0] - origin[0] - tol) / h) + 1
        )
        for strip in geometry.slice_convex(v, ex, xs, tol):
            slo, shi = strip[:, 1].min(), strip[:, 1].max()
            ys = origin[1] + h * np.arange(
                math.ceil((slo - origin[1] + tol) / h), math.floor((shi - origin[1] - tol) / h) + 1
            )
            for cell in geometry.slice_convex(strip, ey, ys, tol):
                new.add(cell, work.material[i], work.excavation[i], i)
    work.__dict__.update(new.__dict__)


GROWTH = 0.25
"""Graded mesh: a cell at distance d from an excavation is at most mesh_size + GROWTH d."""


def graded_squares(box, h: float, h_max: float, outlines: list) -> np.ndarray:
    """Quadtree squares (x0, y0, size) covering ``box``: size h at the excavation outlines.

    Roots of size h 2^k (the largest not above ``h_max``) on the grid from the box's
    lower-left corner; a square splits in four while it is larger than
    h + GROWTH d, d the distance from the square to the nearest outline.
    """
    segs = np.concatenate([np.stack([v, np.roll(v, -1, axis=0)], axis=1) for v in outlines])
    p0, d = segs[:, 0], segs[:, 1] - segs[:, 0]
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)

    def distance(c):  # (M, 2) points -> (M,) distance to the nearest outline segment
        t = np.clip(np.einsum("mij,ij->mi", c[:, None, :] - p0, d) / dd, 0.0, 1.0)
        q = p0 + t[..., None] * d
        return np.min(np.linalg.norm(c[:, None, :] - q, axis=-1), axis=1)

    size = h * 2 ** math.floor(math.log2(h_max / h))
    nx = math.ceil((box[2] - box[0]) / size - 1e-9)
    ny = math.ceil((box[3] - box[1]) / size - 1e-9)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    todo = np.stack([box[0] + ix.ravel() * size, box[1] + iy.ravel() * size,
                     np.full(ix.size, size)], axis=1)
    leaves = []
    while len(todo):
        s = todo[:, 2]
        gap = np.maximum(distance(todo[:, :2] + 0.5 * s[:, None]) - s / math.sqrt(2.0), 0.0)
        split = s > h + GROWTH * gap + 1e-9 * h
        leaves.append(todo[~split])
        q = todo[split]
        half = 0.5 * q[:, 2:3]
        todo = np.concatenate([np.concatenate([q[:, :2] + half * off, half], axis=1)
                               for off in np.array([[0, 0], [1, 0], [0, 1], [1, 1]])]) \
            if len(q) else np.zeros((0, 3))
    return np.concatenate(leaves)


def mesh_by_squares(work: Work, squares: np.ndarray, tol: float) -> None:
    """Clip every piece by the squares (x0, y0, size) that overlap it."""
    new = Work()
    ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    lo_sq, hi_sq = squares[:, :2], squares[:, :2] + squares[:, 2:3]
    for i, v in enumerate(work.polys):
        lo, hi = v.min(axis=0), v.max(axis=0)
        hit = np.nonzero(np.all(lo_sq < hi - tol, axis=1) & np.all(hi_sq > lo + tol, axis=1))[0]
        for k in hit:
            (x0, y0), (x1, y1) = lo_sq[k], hi_sq[k]
            cell = clip(v, [(ex, x0, False), (ex, x1, True), (ey, y0, False), (ey, y1, True)],
                        tol)
            if cell is not None and piece_area(cell) > tol * tol:
                new.add(cell, work.material[i], work.excavation[i], i)
    work.__dict__.update(new.__dict__)


def triangulate(work: Work, h: float, origin: np.ndarray, tol: float) -> None:
    """Split every cell outside the excavations into triangles (constant-strain cells).

    A triangle keeps its shape; a quadrilateral splits along its shorter
    diagonal, equal diagonals (grid squares) alternating with the parity of the
    grid cell, so that the mesh has no preferred direction; larger polygons fan
    from their centroid. Cells of an excavation are removed before anything
    deforms and stay whole.
    """
    new = Work()
    for i, v in enumerate(work.polys):
        tags = (work.material[i], work.excavation[i], work.parent[i])
        v = geometry.drop_collinear(v, tol)
        if work.excavation[i] is not None or len(v) == 3:
            new.add(v, *tags)
            continue
        if len(v) == 4:
            d02 = np.linalg.norm(v[2] - v[0])
            d13 = np.linalg.norm(v[3] - v[1])
            if abs(d02 - d13) <= 1e-6 * max(d02, d13):
                c = geometry.centroid(v)
                k = np.floor((c - origin) / h).astype(int)
                split02 = (k[0] + k[1]) % 2 == 0
            else:
                split02 = d02 < d13
            tris = [v[[0, 1, 2]], v[[0, 2, 3]]] if split02 else [v[[0, 1, 3]], v[[1, 2, 3]]]
        else:
            c = geometry.centroid(v)
            tris = [np.array([c, v[k], v[(k + 1) % len(v)]]) for k in range(len(v))]
        for t in tris:
            new.add(t, *tags)
    work.__dict__.update(new.__dict__)
