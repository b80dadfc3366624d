"""Small joint-bounded blocks bonded to a neighbour (step 8 of :mod:`jaxdem.rockmass`).

A block, to the solver, is what joints bound: the pieces that intact-rock faces join
(the cuts that make a region convex, an opening's ray cuts, mesh cells) move as one
rock body until a bond breaks. Where the joint pattern cut by an opening leaves such a
body on the opening's outline smaller than ``domain.min_block_area``, it is merged into
the neighbour with which it shares the longest joint: the faces they share become intact
rock (both sides), which is how the model represents a block that is not convex (convex
pieces bonded by intact rock). Geometry is untouched: areas, vertices and the piece
count stay as they are; only edge labels change. Bodies away from the openings (against
the domain's outline, on a slope's face) are left as they are: they are part of the
model's boundary or of the slope's own answer, and they do not fall into an opening.

Host NumPy; works on the labelled pieces of :func:`jaxdem.rockmass.generate`.
"""

from __future__ import annotations

import heapq

import numpy as np

from jaxdem import geometry

INTACT = ("intact", None)


def shared_faces(polys: list[np.ndarray], quantum: float) -> list[tuple[int, int, int, int]]:
    """Faces that two pieces share whole: (i, k, j, m), edge k of piece i running from
    the end to the start of edge m of piece j (i < j), ends equal to ``quantum`` (m)."""
    ends: dict[tuple, tuple[int, int]] = {}
    for i, v in enumerate(polys):
        key = np.round(np.asarray(v, float) / quantum).astype(np.int64)
        nxt = np.roll(key, -1, axis=0)
        for k in range(len(v)):
            ends[(*key[k], *nxt[k])] = (i, k)
    out = []
    for (x0, y0, x1, y1), (i, k) in ends.items():
        other = ends.get((x1, y1, x0, y0))
        if other is not None and i < other[0]:
            out.append((i, k, *other))
    return out


class _Bodies:
    """Union-find of pieces into rock bodies, with each body's area (m2)."""

    def __init__(self, areas: np.ndarray) -> None:
        self.root = list(range(len(areas)))
        self.area = [float(a) for a in areas]
        self.members = [[i] for i in range(len(areas))]

    def find(self, i: int) -> int:
        while self.root[i] != i:
            self.root[i] = self.root[self.root[i]]
            i = self.root[i]
        return i

    def join(self, i: int, j: int) -> int:
        a, b = self.find(i), self.find(j)
        if a != b:
            a, b = min(a, b), max(a, b)
            self.root[b] = a
            self.area[a] += self.area[b]
            self.members[a] += self.members[b]
            self.members[b] = []
        return a


def bond_small_blocks(pieces: list, min_area: float, quantum: float) -> int:
    """Bond each rock body (pieces joined by intact faces) on an excavation's outline and
    smaller than ``min_area`` (m2) to the neighbouring body of the same material and
    excavation with which it shares the most joint length, smallest first, until none is
    left below ``min_area`` that has such a neighbour. Pieces are
    :class:`jaxdem.rockmass.Piece`; their ``edge_labels`` change in place. Only faces
    that the two pieces share whole are considered (an excavation's cut makes its two
    sides alike).

    Returns:
      the number of bodies merged.
    """
    if min_area <= 0.0 or len(pieces) < 2:
        return 0
    polys = [p.vertices for p in pieces]
    bodies = _Bodies(geometry.signed_areas(polys))
    faces = shared_faces(polys, quantum)
    joints = []
    opening = np.zeros(len(pieces), bool)  # on an excavation's outline
    for i, k, j, m in faces:
        a, b = pieces[i], pieces[j]
        if a.excavation != b.excavation:
            opening[[i, j]] = True
            continue
        kinds = (a.edge_labels[k][0], b.edge_labels[m][0])
        if kinds == ("intact", "intact"):
            bodies.join(i, j)
        elif "joint" in kinds and a.material == b.material:
            joints.append((i, k, j, m))
    lengths = {f: float(np.hypot(*(polys[f[0]][(f[1] + 1) % len(polys[f[0]])]
                                   - polys[f[0]][f[1]]))) for f in joints}
    faces_of: list[list] = [[] for _ in pieces]
    for f in joints:
        faces_of[f[0]].append(f)
        faces_of[f[2]].append(f)
    at_opening = {bodies.find(i) for i in np.nonzero(opening)[0].tolist()}
    heap = [(bodies.area[r], r) for r in at_opening if bodies.area[r] < min_area]
    heapq.heapify(heap)
    merged = 0
    while heap:
        area, r = heapq.heappop(heap)
        if bodies.find(r) != r or bodies.area[r] != area:
            continue  # merged since, or grown: its current entry is elsewhere
        mine = {f for i in bodies.members[r] for f in faces_of[i]}
        shared: dict[int, float] = {}
        for f in mine:
            a, b = bodies.find(f[0]), bodies.find(f[2])
            if a != b:
                other = b if a == r else a
                shared[other] = shared.get(other, 0.0) + lengths[f]
        if not shared:
            continue  # nothing to bond to: it stays a block (a loose one, if it falls)
        best = max(shared, key=lambda s: (shared[s], -s))
        for i, k, j, m in mine:
            if {bodies.find(i), bodies.find(j)} == {r, best}:
                pieces[i].edge_labels[k] = INTACT
                pieces[j].edge_labels[m] = INTACT
        new = bodies.join(r, best)
        merged += 1
        if bodies.area[new] < min_area:
            heapq.heappush(heap, (bodies.area[new], new))
    return merged
