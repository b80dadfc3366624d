"""Joint traces of a generated rock mass: the parallel lines of each joint set
(``Family``: spacing, origin, trace segments and rock bridges of a non-persistent set),
the ``[[discontinuities]]`` lines (``Line``), the ends of trace segments, and which edges
of the cut pieces lie on a trace and so are joints (``label_edges``).

Reads the joints and discontinuities of a validated :class:`jaxdem.scene.Scene`; the
lines go to the cutting (:mod:`jaxdem.rockmass._cutting`) and the labels to
:func:`jaxdem.rockmass.generate`. Host NumPy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jaxdem import geometry
from jaxdem.scene import Scene


@dataclass
class Family:
    """The parallel trace lines of a joint set: n . x = c0 + k spacing."""

    source: str
    joint: str
    normal: np.ndarray
    direction: np.ndarray
    c0: float
    spacing: float
    s0: float
    length: float  # trace segment length (m); inf when persistent
    period: float  # length + bridge (m)

    def covered(self, k: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Length (m) of [lo, hi] (along the trace) that lies on trace segments of line k."""
        if not math.isfinite(self.length):
            return hi - lo
        start = self.s0 + (np.mod(k, 2) * 0.5 * self.period) - 0.5 * self.length

        def cum(s: np.ndarray) -> np.ndarray:
            u = s - start
            return np.floor(u / self.period) * self.length + np.minimum(
                np.mod(u, self.period), self.length
            )

        return cum(hi) - cum(lo)

    def ends(self, k: int, smin: float, smax: float) -> np.ndarray:
        """Along-trace coordinates (m) of the segment ends of line k within [smin, smax]."""
        if not math.isfinite(self.length):
            return np.zeros(0)
        centre0 = self.s0 + (k % 2) * 0.5 * self.period
        m = np.arange(
            math.floor((smin - centre0) / self.period) - 1,
            math.ceil((smax - centre0) / self.period) + 2,
        )
        c = centre0 + m * self.period
        e = np.concatenate([c - 0.5 * self.length, c + 0.5 * self.length])
        return np.sort(e[(e >= smin) & (e <= smax)])


@dataclass
class Line:
    """One discontinuity: the line n . x = offset, a joint on [s0, s1] along d."""

    source: str
    joint: str
    normal: np.ndarray
    direction: np.ndarray
    offset: float
    s0: float
    s1: float


def _unit(angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    d = np.array([math.cos(angle_rad), math.sin(angle_rad)])
    return d, np.array([-d[1], d[0]])


def joint_families(scene: Scene, origin_default: np.ndarray) -> list[Family]:
    out = []
    for name, j in scene.joints.items():
        if not j.is_set:
            continue
        d, n = _unit(math.radians(float(j.dip_deg)))  # type: ignore[arg-type]
        o = np.array(j.origin, dtype=float) if j.origin is not None else origin_default
        length = j.trace_length
        out.append(
            Family(
                source=f"joints.{name}",
                joint=name,
                normal=n,
                direction=d,
                c0=float(n @ o),
                spacing=float(j.spacing),  # type: ignore[arg-type]
                s0=float(d @ o),
                length=length,
                period=length + j.bridge_length if math.isfinite(length) else math.inf,
            )
        )
    return out


def discontinuity_lines(scene: Scene) -> list[Line]:
    out = []
    for i, disc in enumerate(scene.discontinuities):
        a = np.asarray(disc.start, float)
        b = np.asarray(disc.end, float)
        d = (b - a) / float(np.hypot(*(b - a)))
        n = np.array([-d[1], d[0]])
        out.append(
            Line(
                source=f"discontinuities.{i}",
                joint=disc.joint,
                normal=n,
                direction=d,
                offset=float(n @ a),
                s0=float(d @ a),
                s1=float(d @ b),
            )
        )
    return out


def trace_ends(
    families: list[Family], lines: list[Line], outline: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, trace direction) of every trace segment end that may lie in the domain."""
    out = []
    box = geometry.bbox(outline)
    corners = np.array([[box[0], box[1]], [box[2], box[1]], [box[2], box[3]], [box[0], box[3]]])
    for fam in families:
        if not math.isfinite(fam.length):
            continue
        pn = corners @ fam.normal
        ps = corners @ fam.direction
        kmin = math.ceil((pn.min() - fam.c0) / fam.spacing)
        kmax = math.floor((pn.max() - fam.c0) / fam.spacing)
        for k in range(kmin, kmax + 1):
            c = fam.c0 + k * fam.spacing
            for s in fam.ends(k, float(ps.min()), float(ps.max())):
                out.append((c * fam.normal + s * fam.direction, fam.direction))
    for line in lines:
        for s in (line.s0, line.s1):
            out.append((line.offset * line.normal + s * line.direction, line.direction))
    return out


def label_edges(
    polys: list[np.ndarray],
    outline: np.ndarray,
    families: list[Family],
    lines: list[Line],
    tol: float,
) -> tuple[np.ndarray, list[str | None], list[str | None], np.ndarray]:
    """Per edge of all pieces (concatenated): kind (0 intact, 1 joint, 2 outer), joint name,
    source of the cut line it lies on (``joints.NAME``/``discontinuities.i``), piece offsets."""
    counts = np.array([len(v) for v in polys])
    starts = np.concatenate([[0], np.cumsum(counts)])
    A = np.concatenate(polys)
    ne = len(A)
    following = np.arange(1, ne + 1)  # the next vertex of each piece, cyclically
    following[starts[1:] - 1] = starts[:-1]
    B = A[following]
    kind = np.zeros(ne, dtype=np.int8)
    name_idx = np.full(ne, -1)
    src_idx = np.full(ne, -1)
    names: list[str] = []
    sources: list[str] = []

    m = len(outline)
    for k in range(m):
        p, q = outline[k], outline[(k + 1) % m]
        e = q - p
        le = float(np.hypot(*e))
        u = e / le
        nn = np.array([-u[1], u[0]])
        da, db = np.abs((A - p) @ nn), np.abs((B - p) @ nn)
        ta, tb = (A - p) @ u, (B - p) @ u
        on = (da <= tol) & (db <= tol)
        on &= (np.minimum(ta, tb) >= -tol) & (np.maximum(ta, tb) <= le + tol)
        kind[on] = 2

    for fam in families:
        pa = A @ fam.normal - fam.c0
        pb = B @ fam.normal - fam.c0
        ka = np.rint(pa / fam.spacing)
        kb = np.rint(pb / fam.spacing)
        on = (
            (np.abs(pa - ka * fam.spacing) <= tol)
            & (np.abs(pb - kb * fam.spacing) <= tol)
            & (ka == kb)
            & (src_idx < 0)
        )
        idx = np.nonzero(on)[0]
        if not len(idx):
            continue
        sources.append(fam.source)
        src_idx[idx] = len(sources) - 1
        sa, sb = A[idx] @ fam.direction, B[idx] @ fam.direction
        lo, hi = np.minimum(sa, sb), np.maximum(sa, sb)
        cov = fam.covered(ka[idx], lo, hi)
        joint = idx[(cov >= 0.5 * (hi - lo)) & (kind[idx] == 0)]
        names.append(fam.joint)
        kind[joint] = 1
        name_idx[joint] = len(names) - 1

    for line in lines:
        pa = A @ line.normal - line.offset
        pb = B @ line.normal - line.offset
        on = (np.abs(pa) <= tol) & (np.abs(pb) <= tol)
        idx = np.nonzero(on)[0]
        if not len(idx):
            continue
        sources.append(line.source)
        src_idx[idx[src_idx[idx] < 0]] = len(sources) - 1
        sa, sb = A[idx] @ line.direction, B[idx] @ line.direction
        lo, hi = np.minimum(sa, sb), np.maximum(sa, sb)
        s0, s1 = min(line.s0, line.s1), max(line.s0, line.s1)
        cov = np.clip(np.minimum(hi, s1) - np.maximum(lo, s0), 0.0, None)
        joint = idx[(cov >= 0.5 * (hi - lo)) & (kind[idx] == 0)]
        names.append(line.joint)
        kind[joint] = 1
        name_idx[joint] = len(names) - 1

    name_of = [names[k] if k >= 0 else None for k in name_idx]
    src_of = [sources[k] if k >= 0 else None for k in src_idx]
    return kind, name_of, src_of, starts
