"""Scene (host) -> device Model and initial State.

Host code: NumPy. Everything the jitted solver needs is laid out here once:
padded vertices, material compliances, joint table, external loads, rigid
boundary walls, scales and capacities.

Choices made here (documented for users in the README):
- Rigid boundary walls are fixed blocks outside the rock along each fixed or
  roller boundary segment; contacts with them are bonded (no strength limit,
  no opening) and have no joint term: k = kn_i / h of the rock block alone.
- A traction boundary applies ``traction`` (kPa, global x and y components)
  to the block faces lying on its segment, as a dead load.
- Scales: L = median size sqrt(area) of the free blocks. Detection margin 2 * step_length;
  step_length defaults to L / 20; touch tolerance 1e-6 L (1e-4 L in float32);
  max_displacement defaults to L (a block that moves its own size in one
  increment without finding equilibrium is falling or sliding away).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from jaxdem import geometry
from jaxdem.laws import intact_stiffness
from jaxdem.state import ROCK, WALL_FIXED, WALL_ROLLER, Model, State, empty_history

_USE_CELLS_ABOVE = 400  # blocks; below this all-pairs boxes are cheaper
_DENSE_UP_TO = 600  # blocks (1,800 unknowns); above this matrix-free CG


@dataclasses.dataclass
class Layout:
    """Host-side bookkeeping of a built model.

    Attributes:
      n_rock: number of rock blocks (the first n_rock entries of the model).
      polygons: initial rock-block vertices, list of (n_i, 2) arrays (m).
      centroids: (n_rock, 2) initial centroids (m).
      walls: list of (2, 2) wall segments, for figures.
      monitors: name -> dict(kind, blocks, offsets, points) with the rock block
        holding each monitored point and its offset from that block's centroid.
      length: median block size L (m).
      dtype: NumPy dtype of the solve.
      load_steps: increments of the load.
    """

    n_rock: int
    polygons: list
    centroids: np.ndarray
    walls: list
    monitors: dict
    length: float
    dtype: type
    load_steps: int


def _wall_polygon(p0, p1, inside_point, thickness):
    """Rectangle on the side of segment p0-p1 away from ``inside_point``, CCW."""
    d = p1 - p0
    n = np.array([d[1], -d[0]]) / np.linalg.norm(d)
    if np.dot(inside_point - p0, n) > 0:
        n = -n
    quad = np.array([p0, p1, p1 + thickness * n, p0 + thickness * n])
    if geometry.signed_area(quad) < 0:
        quad = quad[::-1]
    return quad


def _faces_on_segment(poly, p0, p1, tol):
    """(start, end) of the parts of a polygon's faces lying on segment p0-p1."""
    d = p1 - p0
    L = np.linalg.norm(d)
    t = d / L
    n = np.array([-t[1], t[0]])
    out = []
    m = len(poly)
    for k in range(m):
        a, b = poly[k], poly[(k + 1) % m]
        if abs(np.dot(a - p0, n)) > tol or abs(np.dot(b - p0, n)) > tol:
            continue
        sa, sb = np.dot(a - p0, t), np.dot(b - p0, t)
        lo, hi = max(min(sa, sb), 0.0), min(max(sa, sb), L)
        if hi - lo > tol:
            out.append((p0 + lo * t, p0 + hi * t))
    return out


def _edge_joints(polys, V, scene, joint_index, tol):
    """(n, V) joint id of each face lying on a discontinuity, -1 elsewhere."""
    out = np.full((len(polys), V), -1, np.int32)
    for disc in scene.discontinuities:
        p0, p1 = np.asarray(disc.start, float), np.asarray(disc.end, float)
        d = p1 - p0
        L = np.linalg.norm(d)
        t = d / L
        n = np.array([-t[1], t[0]])
        for i, poly in enumerate(polys):
            m = len(poly)
            a = poly
            b = np.roll(poly, -1, axis=0)
            on = (np.abs((a - p0) @ n) <= tol) & (np.abs((b - p0) @ n) <= tol)
            sa, sb = (a - p0) @ t, (b - p0) @ t
            on &= (np.minimum(sa, sb) >= -tol) & (np.maximum(sa, sb) <= L + tol)
            out[i, :m][on] = joint_index[disc.joint]
    return out


def build(scene, capacity: int | None = None) -> tuple[Model, State, Layout]:
    """Lay a validated Scene out as device arrays.

    Returns the Model (constants), the initial State and the host Layout.
    """
    s = scene.solver
    dtype = np.float64 if s.dtype == "float64" else np.float32
    polys = [np.asarray(b.vertices, float) for b in scene.blocks]
    n_rock = len(polys)
    areas = np.array([geometry.signed_area(p) for p in polys])
    cents = np.array([geometry.centroid(p) for p in polys])
    free_rock = np.array([not b.fixed for b in scene.blocks])
    L = float(np.median(np.sqrt(areas[free_rock] if free_rock.any() else areas)))
    allv = np.concatenate(polys)
    lo, hi = allv.min(0), allv.max(0)
    size = float(np.linalg.norm(hi - lo))
    tol_geo = 1e-9 * size

    step_length = s.step_length if s.step_length is not None else L / 20.0
    max_disp = s.max_displacement if s.max_displacement is not None else L
    touch_tol = L * (1e-6 if dtype == np.float64 else 1e-4)

    # Rigid walls along fixed and roller boundaries.
    walls, wall_kind = [], []
    inside = 0.5 * (lo + hi)
    for bd in scene.boundaries:
        if bd.condition in ("fixed", "roller"):
            p0, p1 = np.asarray(bd.start, float), np.asarray(bd.end, float)
            thick = max(0.1 * np.linalg.norm(p1 - p0), 2 * L)
            walls.append(_wall_polygon(p0, p1, inside, thick))
            wall_kind.append(WALL_FIXED if bd.condition == "fixed" else WALL_ROLLER)
    all_polys = polys + walls
    N = len(all_polys)
    V = max(len(p) for p in all_polys)
    verts = np.zeros((N, V, 2))
    nv = np.zeros(N, np.int32)
    for i, p in enumerate(all_polys):
        verts[i, : len(p)] = p
        verts[i, len(p):] = p[0]
        nv[i] = len(p)
    vmask = np.arange(V)[None, :] < nv[:, None]
    wall_cents = np.array([geometry.centroid(w) for w in walls]).reshape(-1, 2)
    all_cents = np.concatenate([cents, wall_cents])
    radius = np.array([np.max(np.linalg.norm(p - c, axis=1))
                       for p, c in zip(all_polys, all_cents, strict=True)])

    kind = np.array([ROCK] * n_rock + wall_kind, np.int32)
    free = np.array([not b.fixed for b in scene.blocks] + [False] * len(walls))
    kn_inv = np.zeros(N)
    ks_inv = np.zeros(N)
    f_ext = np.zeros((N, 3))
    for i, b in enumerate(scene.blocks):
        m = scene.materials[b.material]
        kn_i, ks_i = intact_stiffness(m.E, m.nu)
        kn_inv[i], ks_inv[i] = 1.0 / kn_i, 1.0 / ks_i
        f_ext[i, 1] = -m.unit_weight * areas[i]
    for bd in scene.boundaries:
        if bd.condition != "traction":
            continue
        p0, p1 = np.asarray(bd.start, float), np.asarray(bd.end, float)
        for i, p in enumerate(polys):
            for a, b in _faces_on_segment(p, p0, p1, tol_geo * 1e3):
                F = np.asarray(bd.traction, float) * np.linalg.norm(b - a)
                r = 0.5 * (a + b) - cents[i]
                f_ext[i] += [F[0], F[1], r[0] * F[1] - r[1] * F[0]]

    # Joint table; the default joint is repeated last (slots not on a discontinuity).
    names = list(scene.joints)
    joint_index = {name: k for k, name in enumerate(names)}
    table = [scene.joints[n] for n in names] + [scene.joints[scene.default_joint]] if names else []
    if not table:  # a single block: no contacts between rock blocks ever form
        table = [None]
    jk = lambda f, default: np.array([f(j) if j is not None else default for j in table])  # noqa: E731
    joint_kn = jk(lambda j: j.kn, 1.0)
    joint_ks = jk(lambda j: j.ks, 1.0)
    joint_c = jk(lambda j: j.cohesion, 0.0)
    joint_t = jk(lambda j: j.tensile_strength, 0.0)
    joint_tanphi = jk(lambda j: math.tan(math.radians(j.friction_deg)), 0.0)
    edge_joint = _edge_joints(all_polys, V, scene, joint_index, tol_geo * 1e3)
    edge_joint[n_rock:] = -1

    # Regularisation: a pseudo-mass proportional to a typical contact stiffness.
    k_block = float(np.median(kn_inv[:n_rock]))
    k_ref = L / (L * k_block + 1.0 / float(np.median(joint_kn)))
    rg2 = np.array([_polar_moment(p, c) for p, c in zip(all_polys, all_cents, strict=True)])
    pseudo_mass = s.regularization * k_ref * np.stack([np.ones(N), np.ones(N), rg2], axis=1)
    f_ref = float(np.max(np.linalg.norm(f_ext[free, :2], axis=1), initial=0.0))
    if f_ref <= 0:
        f_ref = k_ref * L * 1e-6

    big_r = 4.0 * float(np.median(radius[:n_rock]))
    big = np.nonzero((kind != ROCK) | (radius > big_r))[0].astype(np.int32)
    use_cells = N > _USE_CELLS_ABOVE
    margin = 2.0 * step_length
    if capacity is None:
        capacity = _initial_capacity(verts, nv, free, margin, use_cells)
    cell_capacity = _cell_capacity(verts, radius, big, margin) if use_cells else 1
    max_substeps = int(math.ceil(max_disp / step_length)) * 3 + 50

    model = Model(
        nv=jnp.asarray(nv), vmask=jnp.asarray(vmask), free=jnp.asarray(free),
        kind=jnp.asarray(kind), kn_inv=jnp.asarray(kn_inv, dtype),
        ks_inv=jnp.asarray(ks_inv, dtype),
        area=jnp.asarray(np.concatenate([areas, [geometry.signed_area(w) for w in walls]]), dtype),
        radius=jnp.asarray(radius, dtype), f_ext=jnp.asarray(f_ext, dtype),
        edge_joint=jnp.asarray(edge_joint), joint_kn=jnp.asarray(joint_kn, dtype),
        joint_ks=jnp.asarray(joint_ks, dtype), joint_c=jnp.asarray(joint_c, dtype),
        joint_t=jnp.asarray(joint_t, dtype), joint_tanphi=jnp.asarray(joint_tanphi, dtype),
        big=jnp.asarray(big), pseudo_mass=jnp.asarray(pseudo_mass, dtype),
        f_ref=jnp.asarray(f_ref, dtype),
        tol=jnp.asarray(max(s.tolerance, _tol_floor(dtype)), dtype),
        step_length=jnp.asarray(step_length, dtype), margin=jnp.asarray(margin, dtype),
        touch_tol=jnp.asarray(touch_tol, dtype), max_displacement=jnp.asarray(max_disp, dtype),
        cos_parallel=jnp.asarray(math.cos(math.radians(2.0)), dtype),
        corner_share=jnp.asarray(0.1, dtype),
        n_blocks=N, n_vertices=V, n_big=len(big), use_cells=use_cells,
        cell_capacity=cell_capacity, dense=n_rock <= _DENSE_UP_TO,
        max_iterations=jnp.asarray(s.max_iterations), max_substeps=jnp.asarray(max_substeps),
    )
    state = State(
        verts=jnp.asarray(verts, dtype), centroid=jnp.asarray(all_cents, dtype),
        u=jnp.zeros((N, 2), dtype), rot=jnp.zeros(N, dtype),
        capacity=capacity, **empty_history(N, capacity, V, dtype),
    )
    layout = Layout(
        n_rock=n_rock, polygons=polys, centroids=cents,
        walls=[w[:2].copy() for w in walls],
        monitors=_locate_monitors(scene, polys, cents, tol_geo * 1e3),
        length=L, dtype=dtype, load_steps=s.load_steps,
    )
    return model, state, layout


def _tol_floor(dtype) -> float:
    """Smallest relative residual the dtype can reach reliably."""
    return float(200 * np.finfo(dtype).eps)


def _polar_moment(poly, c):
    """Polar moment of area about the centroid divided by the area, r_g^2 (m2)."""
    p = poly - c
    x0, y0 = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    cross = x0 * y1 - x1 * y0
    ixx = np.sum(cross * (y0**2 + y0 * y1 + y1**2)) / 12.0
    iyy = np.sum(cross * (x0**2 + x0 * x1 + x1**2)) / 12.0
    area = np.sum(cross) / 2.0
    return (ixx + iyy) / area


def _boxes(verts, margin):
    lo = verts.min(1) - 0.5 * margin
    hi = verts.max(1) + 0.5 * margin
    return lo, hi


def _initial_capacity(verts, nv, free, margin, use_cells) -> int:
    """Pair capacity from the initial layout with head-room (sweep on x, NumPy).

    Large scenes start from 5 pairs per block; the solver grows it on overflow.
    """
    if use_cells:
        return 5 * len(nv) + 16
    lo, hi = _boxes(verts, margin)
    order = np.argsort(lo[:, 0])
    count = 0
    for k, i in enumerate(order):
        for j in order[k + 1:]:
            if lo[j, 0] > hi[i, 0]:
                break
            if lo[j, 1] <= hi[i, 1] and lo[i, 1] <= hi[j, 1] and (free[i] or free[j]):
                count += 1
    return int(count * 1.5) + 16


def _cell_capacity(verts, radius, big, margin) -> int:
    """Most blocks in one grid cell at the start, doubled."""
    small = np.ones(len(radius), bool)
    small[big] = False
    cell = 2 * radius[small].max() + 2 * margin
    lo, hi = _boxes(verts, margin)
    c = 0.5 * (lo + hi)[small]
    keys = np.floor((c - c.min(0)) / cell).astype(np.int64)
    _, counts = np.unique(keys[:, 0] * 2**20 + keys[:, 1], return_counts=True)
    return int(2 * counts.max()) + 2


def _locate_monitors(scene, polys, cents, tol) -> dict:
    """The rock block holding each monitored point, and the point's offset from its centroid."""
    out = {}
    for m in scene.monitors:
        pts = [m.point] if m.kind == "point" else [m.start, m.end]
        blocks, offsets = [], []
        for p in pts:
            p = np.asarray(p, float)
            k = next(i for i, poly in enumerate(polys) if geometry.point_in_polygon(p, poly, tol))
            blocks.append(k)
            offsets.append(p - cents[k])
        out[m.name] = dict(kind=m.kind, blocks=blocks, offsets=np.array(offsets),
                           points=np.array([np.asarray(p, float) for p in pts]))
    return out
