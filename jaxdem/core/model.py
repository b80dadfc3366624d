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
- A scene with ``domain.mesh_size`` has deformable blocks (6 unknowns each: the
  rigid motion and a constant strain, with the material's plane-strain D); joints
  between them are their own springs and intact bonds and walls penalty springs
  (``BOND_PENALTY`` times eqs. 3-7). Other scenes have rigid blocks (3 unknowns).
- Scales: L = median size sqrt(area) of the free blocks. Detection margin 2 * step_length;
  step_length defaults to L / 20; touch tolerance 1e-6 L (1e-4 L in float32);
  max_displacement defaults to L (a block that moves its own size in one
  increment without finding equilibrium is falling or sliding away); where the
  scene leaves it out, each block's own limit is its size sqrt(area), between
  ``TRAVEL_FLOOR`` x L and L (a sliver at an opening that works loose is found when
  it has moved its own size, not L), and blocks that move together share the limit of
  their group, the size of their area together between the same bounds
  (:func:`jaxdem.core.kinematics.group_limits`).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math

import jax
import numpy as np

from jaxdem import geometry
from jaxdem.core.laws import intact_stiffness, plane_strain_elasticity
from jaxdem.core.state import ROCK, WALL_FIXED, WALL_ROLLER, Model, State, empty_history

_USE_CELLS_ABOVE = 400  # blocks; below this all-pairs boxes are cheaper
_DENSE_UP_TO = 600
"""Unknowns up to which "auto" takes the dense path for a batch on a CPU, and for a single
solve on a CPU where sparsax is not installed (above it: sparse direct)."""
_DENSE_UP_TO_ACCELERATOR = 32_000
"""Unknowns up to which "auto" takes the dense path on a GPU or TPU (LU, Cholesky where the
matrix is symmetric: :func:`jaxdem.core._linsolve.solve_dense`): its float64 matrix is
8 GB at 32,000 unknowns (a 10,000-block grid), a tenth of an 80 GB card. Above it "cg",
which has no slip coupling and stopped at the iteration limit on seed examples 2 and 4
and the 1,600- and 10,000-block grids (issue 30): on a GPU the dense path is the one that
converges wherever the CPU's does (the same Newton iterates, tests/test_scaling.py);
timed on an H100 (BENCHMARKS.md, "GPU")."""
# Unknowns up to which a single solve on a CPU above _DENSE_UP_TO would take "cg" (its
# program caches on disk). Not above _DENSE_UP_TO, i.e. no such band: the cg path
# has no slip coupling, and on seed example 4 (228 blocks) it ran into the iteration
# limit where "sparse" converges (issue 18's measurements in BENCHMARKS.md).
_CG_UP_TO = 0
BOND_PENALTY = 100.0
"""Intact bonds between deformable cells: this many times the Hamajima-Kawai spring.

The cells carry the rock's elasticity; the bond only keeps neighbours together,
and its compliance (about 1 / BOND_PENALTY of a cell's) is the error it adds."""
#: The least travel limit of a block, where the scene leaves ``solver.max_displacement``
#: out, as a share of the median block size L: a block's own limit is its size, but a
#: sliver is not a mechanism before it has moved a fifth of L (by then a piece that falls
#: into an opening is clear of the rock and is removed as a loose block; at a tenth, the
#: 0.004 m2 piece of tests/test_loose_blocks.py's tunnel was still sliding on its
#: neighbour, and its stage stopped in a mechanism).
TRAVEL_FLOOR = 0.2


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
      weight, traction: (N, 3) self-weight and boundary-traction loads.
      excavation: per rock block, the excavation it lies in (or None).
      supports: per support, its ``stage``, ``excavation`` and ``force`` (N, D)
        at full pressure on the faces of the excavation outline; also the
        tractions of boundaries that name a stage (``excavation`` None).
      bolt_stages, bolt_spacing: per solver bolt, its stage and out-of-plane spacing (m).
      bolt_of, bolt_share: per solver bolt, the scene bolt it is part of and its share
        of that bolt (1, or less where an anchor lies on a face shared by several
        blocks: see :func:`_bolts`).
      materials: per rock block, its material name.
    """

    n_rock: int
    polygons: list
    centroids: np.ndarray
    walls: list
    monitors: dict
    length: float
    dtype: type
    load_steps: int
    weight: np.ndarray
    traction: np.ndarray
    excavation: list
    supports: list
    bolt_stages: list
    bolt_spacing: np.ndarray
    materials: list
    bolt_of: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int32))
    bolt_share: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))


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


def _near_segment(boxes, p0, p1, tol) -> list[int]:
    """The boxes (N, 4) that reach within 2 tol (m) of the box of segment p0-p1: the only
    polygons that can have a face within tol of the segment."""
    lo, hi = np.minimum(p0, p1) - 2.0 * tol, np.maximum(p0, p1) + 2.0 * tol
    return np.nonzero((boxes[:, 0] <= hi[0]) & (boxes[:, 2] >= lo[0])
                      & (boxes[:, 1] <= hi[1]) & (boxes[:, 3] >= lo[1]))[0].tolist()


def _edge_joints(polys, V, scene, joint_index, tol):
    """(n, V) joint id of each face lying on a discontinuity, -1 elsewhere."""
    out = np.full((len(polys), V), -1, np.int32)
    boxes = geometry.bboxes(polys) if scene.discontinuities else None
    for disc in scene.discontinuities:
        p0, p1 = np.asarray(disc.start, float), np.asarray(disc.end, float)
        d = p1 - p0
        L = np.linalg.norm(d)
        t = d / L
        n = np.array([-t[1], t[0]])
        for i in _near_segment(boxes, p0, p1, tol):
            poly = polys[i]
            m = len(poly)
            a = poly
            b = np.roll(poly, -1, axis=0)
            on = (np.abs((a - p0) @ n) <= tol) & (np.abs((b - p0) @ n) <= tol)
            sa, sb = (a - p0) @ t, (b - p0) @ t
            on &= (np.minimum(sa, sb) >= -tol) & (np.maximum(sa, sb) <= L + tol)
            out[i, :m][on] = joint_index[disc.joint]
    return out


@dataclasses.dataclass
class _Piece:
    """A rock block before layout: explicit, or generated from the rock mass."""

    vertices: np.ndarray
    material: str
    fixed: bool
    excavation: str | None
    edge_labels: list | None  # generated pieces: per edge ("joint", name) / ("intact", None) / ...


def _pieces(scene, tol) -> list[_Piece]:
    """Explicit blocks (assigned to the excavation holding their centroid) and generated ones."""
    excavations = scene.excavations
    verts = [np.asarray(b.vertices, float) for b in scene.blocks]
    inside = geometry.points_in_polygons(geometry.centroids(verts).reshape(-1, 2),
                                         [np.asarray(e.vertices, float) for e in excavations], tol)
    names = [e.name for e in excavations] + [None]
    first = (np.where(inside.any(axis=1), np.argmax(inside, axis=1), len(excavations)).tolist()
             if excavations else [0] * len(verts))
    out = [_Piece(v, b.material, bool(b.fixed), names[k], None)
           for b, v, k in zip(scene.blocks, verts, first, strict=True)]
    if scene.domain is not None:
        from jaxdem import rockmass

        for pc in rockmass.generate(scene).pieces:
            out.append(_Piece(np.asarray(pc.vertices, float), pc.material, False, pc.excavation,
                              list(pc.edge_labels)))
    return out


def build(scene, capacity: int | None = None) -> tuple[Model, State, Layout]:
    """Lay a validated Scene out as device arrays.

    Returns the Model (constants), the initial State and the host Layout.
    """
    s = scene.solver
    dtype = np.float64 if s.dtype == "float64" else np.float32
    allv0 = np.concatenate([np.asarray(b.vertices, float) for b in scene.blocks]
                           + ([np.asarray(scene.domain.outline, float)]
                              if scene.domain is not None else []))
    size = float(np.linalg.norm(allv0.max(0) - allv0.min(0)))
    tol_geo = 1e-9 * size
    pieces = _pieces(scene, tol_geo * 1e3)
    polys = [p.vertices for p in pieces]
    n_rock = len(polys)
    areas = geometry.signed_areas(polys)
    cents = geometry.centroids(polys)
    free_rock = np.array([not p.fixed for p in pieces])
    kept = free_rock & np.array([p.excavation is None for p in pieces])
    sizes = np.sqrt(areas[kept] if kept.any() else areas)
    L = float(np.median(sizes))
    allv = np.concatenate(polys)
    lo, hi = allv.min(0), allv.max(0)

    step_length = s.step_length if s.step_length is not None else L / 20.0
    max_disp = s.max_displacement if s.max_displacement is not None else L
    # Each block's travel limit (a mechanism where one passes it): the scene's
    # max_displacement, else the block's own size, between TRAVEL_FLOOR x L and L.
    travel_range = ((TRAVEL_FLOOR * L, L) if s.max_displacement is None
                    else (max_disp, max_disp))
    travel_limit = np.clip(np.sqrt(areas), *travel_range)
    touch_tol = L * (1e-6 if dtype == np.float64 else 1e-4)

    # Rigid walls along fixed and roller boundaries.
    walls, wall_kind, wall_segments = [], [], []
    inside = 0.5 * (lo + hi)
    for bd in scene.boundaries:
        if bd.condition in ("fixed", "roller"):
            p0, p1 = np.asarray(bd.start, float), np.asarray(bd.end, float)
            thick = max(0.1 * np.linalg.norm(p1 - p0), 2 * L)
            walls.append(_wall_polygon(p0, p1, inside, thick))
            wall_segments.append(np.array([p0, p1]))
            wall_kind.append(WALL_FIXED if bd.condition == "fixed" else WALL_ROLLER)
    # Size classes: the block count (walls included), the vertices per block, the
    # joint table and the big blocks come in steps (block_bucket, bucket), so that
    # scenes of similar size share their compiled programs. The blocks past the
    # scene's own (at least one) are dead copies of its first block: never alive,
    # never free, in no contact.
    n_real = n_rock + len(walls)
    n_pad = block_bucket(n_real + 1) - n_real
    all_polys = polys + walls + [polys[0]] * n_pad
    N = len(all_polys)
    V = bucket(max(len(p) for p in all_polys))
    verts = np.zeros((N, V, 2))
    nv = np.zeros(N, np.int32)
    for n, idx, v in geometry.polygon_groups(all_polys):
        verts[idx, :n] = v
        verts[idx, n:] = v[:, :1]
        nv[idx] = n
    vmask = np.arange(V)[None, :] < nv[:, None]
    wall_cents = geometry.centroids(walls).reshape(-1, 2)
    all_cents = np.concatenate([cents, wall_cents, np.repeat(cents[:1], n_pad, axis=0)])
    # Padded vertices repeat the first: the largest distance is the polygon's own.
    radius = np.max(np.linalg.norm(verts - all_cents[:, None, :], axis=2), axis=1)

    kind = np.array([ROCK] * n_rock + wall_kind + [ROCK] * n_pad, np.int32)
    free = np.concatenate([free_rock, np.zeros(len(walls) + n_pad, bool)])
    # Intact-rock cells (mesh_size) are deformable constant-strain triangles.
    deformable = scene.domain is not None and scene.domain.mesh_size is not None
    D = 6 if deformable else 3
    kn_inv = np.zeros(N)
    ks_inv = np.zeros(N)
    weight = np.zeros((N, D))
    cell_D = np.zeros((N if deformable else 0, 3, 3))
    code = {name: k for k, name in enumerate(scene.materials)}
    material_of = np.array([code[pc.material] for pc in pieces], np.int64)
    for k, m in enumerate(scene.materials.values()):  # per material
        i = np.nonzero(material_of == k)[0]
        kn_i, ks_i = intact_stiffness(m.E, m.nu)
        kn_inv[i], ks_inv[i] = 1.0 / kn_i, 1.0 / ks_i
        weight[i, 1] = -m.unit_weight * areas[i]
        if deformable:
            cell_D[i] = plane_strain_elasticity(m.E, m.nu, np)
    traction = np.zeros((N, D))
    for bd in scene.boundaries:
        if bd.condition == "traction" and bd.stage is None:
            traction += _face_loads(polys, cents, N, [(bd.start, bd.end)],
                                    lambda n, tr=bd.traction: np.asarray(tr, float),
                                    tol_geo * 1e3, D)
    f_ext = weight + traction

    # Joint table: the scene's joints, an intact-rock bond per material, the
    # default joint last (slots on no labelled face).
    names = list(scene.joints)
    mats = list(scene.materials)
    joint_index = {name: k for k, name in enumerate(names)}
    intact_index = {name: len(names) + k for k, name in enumerate(mats)}
    default = scene.joints[scene.default_joint] if names else None
    rows = ([(j.kn, j.ks, j.cohesion, j.tensile_strength, j.friction_deg, False)
             for j in scene.joints.values()]
            + [(np.inf, np.inf, m.cohesion, m.tensile_strength, m.friction_deg, True)
               for m in scene.materials.values()]
            + [(default.kn, default.ks, default.cohesion, default.tensile_strength,
                default.friction_deg, False) if default else (1.0, 1.0, 0.0, 0.0, 0.0, False)])
    rows += [(1.0, 1.0, 0.0, 0.0, 0.0, False)] * (bucket(len(rows)) - len(rows))  # unused
    columns = (np.array(c) for c in zip(*rows, strict=True))
    joint_kn, joint_ks, joint_c, joint_t, phi, joint_intact = columns
    joint_tanphi = np.tan(np.radians(phi))
    edge_joint = _edge_joints(all_polys, V, scene, joint_index, tol_geo * 1e3)
    for i, pc in enumerate(pieces):
        for k, (label, name) in enumerate(pc.edge_labels or []):
            if label == "joint":
                edge_joint[i, k] = joint_index[name]
            elif label == "intact":
                edge_joint[i, k] = intact_index[pc.material]
    edge_joint[n_rock:] = -1
    # An explicit block's own joint ([[blocks]] joint) on its faces that lie on no line.
    for i, b in enumerate(scene.blocks):
        if getattr(b, "joint", None) is not None:
            faces = edge_joint[i, :len(polys[i])]
            faces[faces < 0] = joint_index[b.joint]

    # Regularisation: a pseudo-mass proportional to a typical contact stiffness.
    k_block = float(np.median(kn_inv[:n_rock]))
    finite_kn = joint_kn[np.isfinite(joint_kn)]
    k_ref = L / (L * k_block + (1.0 / float(np.median(finite_kn)) if finite_kn.size else 0.0))
    rg2 = geometry.polar_moments(all_polys, all_cents)
    pseudo_mass = s.regularization * k_ref * np.stack(
        [np.ones(N), np.ones(N)] + [rg2] * (D - 2), axis=1)
    f_ref = float(np.max(np.linalg.norm(f_ext[free, :2], axis=1), initial=0.0))
    if f_ref <= 0:
        f_ref = k_ref * L * 1e-6

    big_r = 4.0 * float(np.median(radius[:n_rock]))
    big = np.nonzero((kind != ROCK) | (radius > big_r))[0]
    big = big[big < n_real]
    # The last (dead) block fills the list of big blocks up to its size class: the
    # broad phase pairs a big block only while it is alive.
    big = np.concatenate([big, np.full(bucket(len(big)) - len(big), N - 1)]).astype(np.int32)
    use_cells = n_real > _USE_CELLS_ABOVE
    margin = 2.0 * step_length
    candidates = _candidate_pairs(verts[:n_real], free[:n_real], margin)
    if capacity is None:
        capacity = bucket(_initial_capacity(candidates))
    # At most the candidate pairs (more would never be used, and two scenes of one size
    # class would get two programs).
    touch_capacity = min(_touch_capacity(verts, nv, candidates, margin, max(0.01 * L, touch_tol)),
                         capacity)
    cell_capacity = (bucket(_cell_capacity(verts[:n_real], radius[:n_real], big[big < n_real],
                                           margin)) if use_cells else 1)
    narrow_vertices, wide_capacity = _narrow_split(nv[:n_real], candidates, capacity)
    min_step = min(step_length, 0.25 * float(np.min(radius[:n_rock][free_rock], initial=np.inf)))
    max_substeps = int(math.ceil(max_disp / min_step)) * 3 + 50
    bolts = _bolts(scene, polys, cents, pieces, tol_geo * 1e3)
    water = scene.water
    gamma_w = water.unit_weight if water is not None else 0.0

    model = Model(
        nv=_put(nv), vmask=_put(vmask), free=_put(free),
        kind=_put(kind), kn_inv=_put(kn_inv, dtype),
        ks_inv=_put(ks_inv, dtype),
        area=_put(np.concatenate([areas, geometry.signed_areas(walls),
                                  np.repeat(areas[:1], n_pad)]), dtype),
        radius=_put(radius, dtype), f_ext=_put(f_ext, dtype),
        edge_joint=_put(edge_joint), joint_kn=_put(joint_kn, dtype),
        joint_ks=_put(joint_ks, dtype), joint_c=_put(joint_c, dtype),
        joint_t=_put(joint_t, dtype), joint_tanphi=_put(joint_tanphi, dtype),
        big=_put(big), pseudo_mass=_put(pseudo_mass, dtype),
        f_ref=_put(f_ref, dtype),
        tol=_put(max(s.tolerance, _tol_floor(dtype)), dtype),
        step_length=_put(step_length, dtype), margin=_put(margin, dtype),
        touch_tol=_put(touch_tol, dtype), max_displacement=_put(max_disp, dtype),
        travel_limit=_put(np.concatenate([travel_limit, np.full(N - n_rock, max_disp)]), dtype),
        travel_range=_put(np.asarray(travel_range), dtype),
        span_tol=_put(max(0.01 * L, touch_tol), dtype),
        cos_parallel=_put(math.cos(math.radians(2.0)), dtype),
        corner_share=_put(0.1, dtype),
        max_iterations=jax.device_put(int(s.max_iterations)),
        max_substeps=jax.device_put(int(max_substeps)),
        joint_intact=_put(joint_intact.astype(bool)),
        gamma_w=_put(gamma_w, dtype),
        bolt_blocks=_put(bolts["blocks"]),
        bolt_offsets=_put(bolts["offsets"], dtype),
        bolt_k=_put(bolts["k"], dtype), bolt_cap=_put(bolts["cap"], dtype),
        bolt_comp=_put(bolts["comp"], dtype),
        bolt_pullout=_put(bolts["pullout"]),
        cell_D=_put(cell_D, dtype), bond_penalty=_put(BOND_PENALTY, dtype),
        verts0=_put(verts, dtype), centroid0=_put(all_cents, dtype),
        n_blocks=N, n_vertices=V, n_big=len(big), use_cells=use_cells,
        cell_capacity=cell_capacity, narrow_vertices=narrow_vertices,
        wide_capacity=wide_capacity, touch_capacity=touch_capacity,
        linear_solver=linear_solver_for(s.linear_solver, n_rock * D,
                                        float64=dtype == np.float64),
        events=s.bond_failure == "events", n_bolts=len(bolts["k"]), has_water=water is not None,
        ndof=D,
    )
    state = State(
        verts=_put(verts, dtype), centroid=_put(all_cents, dtype),
        u=_put(np.zeros((N, 2), dtype)), rot=_put(np.zeros(N, dtype)),
        alive=_put(np.arange(N) < n_real),
        bolt_force=_put(np.zeros(len(bolts["k"]), dtype)),
        bolt_state=_put(np.zeros(len(bolts["k"]), np.int32)),
        bolt_rest=_put(np.zeros(len(bolts["k"]), dtype)),
        strain=_put(np.zeros((N, 3), dtype)), stress=_put(np.zeros((N, 3), dtype)),
        capacity=capacity, **empty_history(N, capacity, V, dtype),
    )
    excavation = [pc.excavation for pc in pieces]
    supports = []
    for sp in scene.supports:
        exc = next(e for e in scene.excavations if e.name == sp.excavation)
        outline = np.asarray(exc.vertices, float)
        segs = list(zip(outline, np.roll(outline, -1, axis=0), strict=True))
        # The load of a unit pressure: the support's load is linear in its pressure.
        unit = _face_loads([polys[i] if excavation[i] != sp.excavation else None
                            for i in range(n_rock)], cents, N, segs, lambda n: -n,
                           tol_geo * 1e3, D)
        supports.append(dict(stage=sp.stage, excavation=sp.excavation, force=sp.pressure * unit,
                             unit=unit))
    for bd in scene.boundaries:
        if bd.condition == "traction" and bd.stage is not None:
            load = _face_loads(polys, cents, N, [(bd.start, bd.end)],
                               lambda n, tr=bd.traction: np.asarray(tr, float), tol_geo * 1e3, D)
            supports.append(dict(stage=bd.stage, excavation=None, force=load))
    layout = Layout(
        n_rock=n_rock, polygons=polys, centroids=cents,
        walls=wall_segments,
        monitors=_locate_monitors(scene, polys, cents, tol_geo * 1e3, excavation),
        length=L, dtype=dtype, load_steps=s.load_steps,
        weight=weight, traction=traction, excavation=excavation, supports=supports,
        bolt_stages=bolts["stages"], bolt_spacing=bolts["spacing"],
        bolt_of=bolts["bolt"], bolt_share=bolts["share"],
        materials=[pc.material for pc in pieces],
    )
    return model, state, layout


def _face_loads(polys, cents, n_blocks, segments, traction_of, tol, ndof=3):
    """Loads (N, ndof) of a traction on the block faces lying on the given segments.

    ``traction_of(n)`` gives the traction (kPa, global x, y) on a face whose
    outward normal is n; ``polys`` entries of None are skipped. For deformable
    blocks the last three columns are the work of the traction on the strains,
    integral of (t_x x, t_y y, (t_x y + t_y x) / 2) over the face (x, y from
    the centroid), exact for a uniform traction (the midpoint rule).
    """
    out = np.zeros((n_blocks, ndof))
    live = [i for i, p in enumerate(polys) if p is not None]
    boxes = geometry.bboxes([polys[i] for i in live])
    for p0, p1 in segments:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        for k in _near_segment(boxes, p0, p1, tol):
            i = live[k]
            p = polys[i]
            for a, b in _faces_on_segment(p, p0, p1, tol):
                d = b - a
                n = np.array([d[1], -d[0]]) / np.linalg.norm(d)
                if np.dot(0.5 * (a + b) - cents[i], n) < 0:
                    n = -n
                F = traction_of(n) * np.linalg.norm(d)
                r = 0.5 * (a + b) - cents[i]
                out[i, :3] += [F[0], F[1], r[0] * F[1] - r[1] * F[0]]
                if ndof == 6:
                    out[i, 3:] += [F[0] * r[0], F[1] * r[1], 0.5 * (F[0] * r[1] + F[1] * r[0])]
    return out


def _bolts(scene, polys, cents, pieces, tol) -> dict:
    """Bolt anchors: the rock blocks (not excavated) holding each end, and per-metre properties.

    The solver's bolts are springs between two blocks. An end on a face shared by
    several blocks (a bolt along a joint or an intact cut, as a crown bolt on the
    axis of a symmetric model often is) is held by all of them equally: the bolt is
    split into parallel sub-bolts, one per pair of holders, each with its share w
    of the stiffness and capacities. Taking one holder (the first in the block
    list) made the answer depend on how the blocks are numbered (a mirrored scene
    gave a bolt force 0.7% apart). ``bolt`` maps each sub-bolt to its scene bolt and
    ``share`` gives w.
    """
    rows = []
    ends = np.array([[b.start, b.end] for b in scene.bolts], float).reshape(-1, 2, 2)
    holds = geometry.points_in_polygons(ends.reshape(-1, 2), polys, tol).reshape(
        len(ends), 2, len(polys))
    holds &= np.array([pc.excavation is None for pc in pieces], bool)
    for i, b in enumerate(scene.bolts):
        holders = [[(k, p - cents[k]) for k in np.nonzero(h)[0].tolist()]
                   for p, h in zip(ends[i], holds[i], strict=True)]
        for k1, r1 in holders[0]:
            for k2, r2 in holders[1]:
                w = 1.0 / (len(holders[0]) * len(holders[1]))
                rows.append(dict(blocks=[k1, k2], offsets=[r1, r2], k=w * b.stiffness / b.spacing,
                                 cap=w * min(b.yield_force, b.anchor_capacity) / b.spacing,
                                 comp=w * b.compression / b.spacing,
                                 pullout=b.anchor_capacity < b.yield_force, stage=b.stage,
                                 spacing=b.spacing, bolt=i, share=w))
    return dict(
        blocks=np.array([r["blocks"] for r in rows], np.int32).reshape(-1, 2),
        offsets=np.array([r["offsets"] for r in rows], float).reshape(-1, 2, 2),
        k=np.array([r["k"] for r in rows], float),
        cap=np.array([r["cap"] for r in rows], float),
        comp=np.array([r["comp"] for r in rows], float),
        pullout=np.array([r["pullout"] for r in rows], bool),
        stages=[r["stage"] for r in rows],
        spacing=np.array([r["spacing"] for r in rows], float),
        bolt=np.array([r["bolt"] for r in rows], np.int32),
        share=np.array([r["share"] for r in rows], float),
    )


def linear_solver_for(choice: str, unknowns: int, *, platform: str | None = None,
                      batch: bool = False, native_sparse: bool | None = None,
                      float64: bool = True) -> str:
    """The linear solver of the Newton iteration: the scene's ``solver.linear_solver``.

    "auto" decides by size and where the solve runs (BENCHMARKS.md, "Scaling:
    solver paths"):

    - a single solve on a CPU in float64: "sparse" at every size where sparsax is
      installed (SuiteSparse inside the program). On the 80-block jointed tunnel of the
      back-analysis benchmark a plain solve took 0.057 s against the dense path's
      0.114, one with 6 parameters' sensitivities 0.128 against 0.214, and a small
      scene's warm run 0.07-0.17 s less: the dense path's LAPACK kernels import
      SciPy's BLAS and LAPACK, 90 modules (BENCHMARKS.md, "Forty-second session").
      Without sparsax (its wheels are Linux's), in float32 (whose dense LU is refined
      in float64, :func:`jaxdem.core._linsolve.refined_solve`: two blocks falling side
      by side land on a ledge in tests/test_hard_cases.py, where the sparse path's
      answer does not) and as a batch:
    - up to ``_DENSE_UP_TO`` (600) unknowns, 200 rigid blocks: "dense"
      (LU; the limits were measured with Cholesky, which the dense path used
      before it took the unsymmetric slip tangent); on a GPU or TPU up to
      ``_DENSE_UP_TO_ACCELERATOR`` (32,000: every bundled example and the grids up
      to 100 x 100 blocks).
      On a 2-core CPU SuperLU is already 1.3 times faster at 576 unknowns
      and 7 times at 1,788;
    - (``_CG_UP_TO``: a band above it where a single CPU solve would take "cg". It is
      empty: "cg" has no slip coupling, takes more Newton iterations where joints
      slip, and each is far slower on a CPU: seed example 2 600 s against 25 s.)
    - above that, on a CPU: "sparse" (SuiteSparse's CHOLMOD or KLU inside the program,
      through sparsax; SciPy's SuperLU through a host callback where sparsax is not
      installed), 4 to 7 times faster than the iterative path at 2,000 to 10,000
      blocks on a 2-core CPU (measured with SuperLU), if with 1.5 times its memory.
      A batch (``batch=True``, solved under ``vmap``, jaxdem.batch) takes it from
      ``_DENSE_UP_TO`` on: its members are factorised one after another (KLU, each
      with its own contacts' pattern: :func:`jaxdem.core._linsolve._lu_each_lane`); on
      the 492-block tunnel of bench_scaling.py a batch of 8 took 0.25 s a sample
      with SuperLU one member after another against 0.44 with "cg" and 0.60 with
      "dense" (0.31 for a loop of single solves);
    - above ``_DENSE_UP_TO_ACCELERATOR``, on a GPU or TPU: "cg", jittable, memory
      linear in the contacts, but without the slip coupling (more Newton iterations
      where slip governs: seed examples 2 and 4 converge to the direct answer in about
      1.5 times as many); sparsax's solvers run on the CPU only.

    Args:
      choice: "auto", "dense", "sparse" or "cg"; anything but "auto" is kept.
      unknowns: degrees of freedom of the rock blocks (3 or 6 per block).
      platform: JAX platform ("cpu", "gpu", "tpu"); default the default backend.
      batch: the solve is a vmapped batch (jaxdem.batch), not a single scene.
      native_sparse: whether sparsax is installed; default: looked up (not imported).
      float64: the scene solves in float64 (``solver.dtype``).

    Returns:
      "dense", "sparse" or "cg".

    Example:
      >>> linear_solver_for("auto", 30_000, platform="cpu")
      'sparse'
    """
    if choice != "auto":
        return choice
    platform = platform or jax.default_backend()
    accelerator = platform != "cpu"
    if native_sparse is None:
        native_sparse = importlib.util.find_spec("sparsax") is not None
    if not accelerator and not batch and float64 and native_sparse:
        return "sparse"
    if unknowns <= (_DENSE_UP_TO_ACCELERATOR if accelerator else _DENSE_UP_TO):
        return "dense"
    if accelerator or (not batch and unknowns <= max(_CG_UP_TO, _DENSE_UP_TO)
                       and _CG_UP_TO > _DENSE_UP_TO):
        return "cg"
    return "sparse"


def _tol_floor(dtype) -> float:
    """Smallest relative residual the dtype can reach reliably."""
    return float(200 * np.finfo(dtype).eps)


def _boxes(verts, margin):
    lo = verts.min(1) - 0.5 * margin
    hi = verts.max(1) + 0.5 * margin
    return lo, hi


def _put(x, dtype=None) -> jax.Array:
    """A host value on the device as it is (NumPy, then one transfer): ``jnp.asarray`` and
    ``jnp.zeros`` compile a small program for each new shape and dtype, some twenty of
    them for a scene's model, about 0.3 s of a cold start (and a cache read each, warm)."""
    return jax.device_put(np.asarray(x, dtype))


def block_bucket(n: int) -> int:
    """The size class of a block count: 8, or the least of 2^k, 1.25, 1.5 and 1.75 x 2^k
    at or above n.

    Finer than :func:`bucket`: at most 25% of dead blocks above 8 (a dense LU of
    the padded system costs at most twice the scene's own).
    """
    n = max(int(n), 1)
    if n <= 8:
        return 8
    k = (n - 1).bit_length() - 1
    return next(m * (1 << k) // 4 for m in (5, 6, 7, 8) if m * (1 << k) // 4 >= n)


def grown(model: Model, cell_full: bool, slots_full: bool, touching: int = 0) -> Model:
    """``model`` after an increment's capacity overflow: the broad phase's neighbour places
    and the narrow phase's wide pairs (:func:`_narrow_split`) doubled where the detection
    overflowed, the places of the touching slots
    (:func:`jaxdem.core._substep.pack_slots`) doubled where they were too few, those of
    the touching pairs grown where ``touching`` pairs did not fit. Each changes
    a static size, so the next call compiles again; nothing is truncated."""
    if cell_full:
        model = dataclasses.replace(model, cell_capacity=2 * model.cell_capacity,
                                    wide_capacity=2 * model.wide_capacity)
    if slots_full:
        model = dataclasses.replace(model, slots_per_pair=2 * model.slots_per_pair)
    if touching > model.touch_capacity:
        model = dataclasses.replace(model, touch_capacity=bucket(
            max(2 * model.touch_capacity, int(1.5 * touching) + 16)))
    return model


def bucket(n: int) -> int:
    """The capacity bucket of n: the least 2^k or 3 x 2^(k-1) at or above it.

    Capacities come in these steps (at most 50% head-room) so that a small
    change in the number of contacts, between the samples of a sweep or the
    iterations of a back-analysis, does not change an array shape and recompile.
    """
    n = max(int(n), 1)
    k = (n - 1).bit_length()
    return 3 << (k - 2) if k >= 2 and 3 << (k - 2) >= n else 1 << k


def _candidate_pairs(verts, free, margin):
    """The broad phase's pairs at the start, (i, j): boxes grown by the margin that overlap
    (:func:`jaxdem.geometry.near_box_pairs`), one of the two blocks free."""
    lo, hi = _boxes(verts, margin)
    i, j = geometry.near_box_pairs(np.concatenate([lo, hi], axis=1), 0.0)
    keep = free[i] | free[j]
    return i[keep], j[keep]


def _initial_capacity(pairs) -> int:
    """Pair capacity from the initial layout's candidate pairs (:func:`_candidate_pairs`),
    plus 16.

    The head-room is the capacity bucket's (:func:`bucket`: up to 50%): every
    padded pair costs its 2 V slots in detection and in each Newton iteration,
    and the solver grows the capacity (one recompilation) on overflow. The
    52-block benchmark tunnel has 230 candidate pairs: capacity 256, where a
    head-room of 1.5 times gave 384 and a sweep 25-40% slower (BENCHMARKS.md,
    "Throughput"). Large scenes were given 5 pairs per block: seed example 2 has 7.4,
    and every run of it overflowed in its first increment and loaded a second program.
    """
    return len(pairs[0]) + 16


def _touch_capacity(verts, nv, pairs, margin, span_tol) -> int:
    """Places for the touching pairs (:func:`jaxdem.core._substep.pack_slots`): the
    candidate pairs at the start that touch (:func:`_touching`), half as many again, plus
    16 (the size class)."""
    return bucket(int(1.5 * int(np.sum(_touching(verts, nv, pairs, margin, span_tol)))) + 16)


def _touching(verts, nv, pairs, margin, span_tol) -> np.ndarray:
    """Whether each candidate pair (i, j) of ``pairs`` touches at the start, (P,) bool.

    Touching much as the narrow phase sees it, in NumPy and without its finer choices: a
    vertex of one block within the margin of a face of the other (and of its nearest
    face), inside that face's span, or with one of its own faces anti-parallel to it and
    overlapping it or meeting it end to end. Faces that meet end to end at a node have no
    spring yet, but they are the pairs that come to touch as the blocks settle: the demo
    tunnel has 1,058 touching pairs at the start and 1,364 at the end, seed example 4
    487 and 735; counted with them, the estimate is 1,890 and 815. Seed example 2:
    2,529 of its 8,678 candidate pairs touch in its fourth increment.
    """
    V = verts.shape[1]
    k = np.arange(V)
    nxt = np.where(k + 1 < nv[:, None], k + 1, 0)
    prev = np.where(k > 0, k - 1, nv[:, None] - 1)
    d = np.take_along_axis(verts, nxt[..., None], axis=1) - verts
    length = np.hypot(d[..., 0], d[..., 1])
    edge = (k < nv[:, None]) & (length > 0)
    tangent = d / np.where(edge, length, 1.0)[..., None]
    normal = np.stack([tangent[..., 1], -tangent[..., 0]], -1)
    cos_parallel = math.cos(math.radians(2.0))

    def along(rx, ry, u):  # (p, V, E) offsets from y's vertices, along y's faces' u (p, E, 2)
        return rx * u[:, None, :, 0] + ry * u[:, None, :, 1]

    def touch(x, y):  # a vertex of x bears on a face of y
        # Coordinates apart, (p, V, E) each: no (p, V, E, 2) array and no contraction
        # over its last axis (seed example 3's 9,357 pairs: 330 -> 175 ms).
        p = np.arange(len(x))[:, None]
        vx, vy = verts[x], verts[y]
        rx = vx[:, :, None, 0] - vy[:, None, :, 0]
        ry = vx[:, :, None, 1] - vy[:, None, :, 1]
        dist = np.where(edge[y][:, None, :], along(rx, ry, normal[y]), -np.inf)
        # The faces it may bear on: within the margin, and within the margin of its
        # nearest one.
        near = ((dist <= margin) & (dist >= dist.max(axis=-1, keepdims=True) - margin)
                & (k < nv[x][:, None])[..., None])
        t, L = tangent[y], length[y][:, None, :]
        s = along(rx, ry, t)
        bears = (s > span_tol) & (s < L - span_tol)
        for own, other in ((tangent[x], nxt[x]), (tangent[x][p, prev[x]], prev[x])):
            ox = vx[p, other]
            s1 = along(ox[:, :, None, 0] - vy[:, None, :, 0], ox[:, :, None, 1] - vy[:, None, :, 1],
                       t)
            # Overlapping, or meeting end to end (above).
            meet = (np.minimum(s, s1) <= L + span_tol) & (np.maximum(s, s1) >= -span_tol)
            anti = along(own[:, :, None, 0], own[:, :, None, 1], t) < -cos_parallel
            bears |= anti & meet
        return np.any(near & bears, axis=(1, 2))

    i, j = pairs
    return np.concatenate([np.zeros(0, bool)]
                          + [touch(i[s:s + 10000], j[s:s + 10000])
                             | touch(j[s:s + 10000], i[s:s + 10000])
                             for s in range(0, len(i), 10000)])


def _cell_capacity(verts, radius, big, margin) -> int:
    """Neighbour places per block of the broad phase's grid (its blocks in the nine cells
    around its own, on average) at the start, and half as many again, plus 2: blocks
    move little before an overflow would double it (the size class :func:`bucket` adds
    up to a half more). Every place costs a few gathers in each detection."""
    small = np.ones(len(radius), bool)
    small[big] = False
    cell = 2 * radius[small].max() + 2 * margin
    lo, hi = _boxes(verts, margin)
    c = 0.5 * (lo + hi)[small]
    keys = np.floor((c - c.min(0)) / cell).astype(np.int64)
    cells, counts = np.unique(keys, axis=0, return_counts=True)
    held = dict(zip(map(tuple, cells.tolist()), counts.tolist(), strict=True))
    places = sum(n * held.get((x + dx, y + dy), 0) for (x, y), n in held.items()
                 for dx in (-1, 0, 1) for dy in (-1, 0, 1))
    return int(math.ceil(1.5 * places / len(radius))) + 2


#: The least number of vertex-face tests (per side of a pair) that :func:`_narrow_split`'s
#: split of the narrow phase must save: seed example 2, 12,288 pairs of 1,269 triangles
#: and two octagons, saves 620,000 (its detection 44 -> 13 ms); seed example 4, 1,024 pairs
#: with 9-gons, 94,000 (none to see).
SPLIT_SAVES = 300_000


def _narrow_split(nv, pairs, capacity) -> tuple[int, int]:
    """The narrow phase's vertex count for most pairs, and its capacity for the others.

    The narrow phase tests each vertex of a pair's blocks against each face of the other:
    V x V per side, V the most vertices of any block. Where a few blocks have many more
    vertices than the rest (seed example 2: 1,269 triangles and two octagons, V = 8), the
    pairs of blocks with at most v vertices are tested with v alone and the others
    ("wide", one of their blocks has more) with V, in a list of their own. v is the
    vertex count (of those the blocks have) that costs least, capacity x v^2 + wide
    capacity x V^2, with the wide capacity the size class of twice the candidate pairs
    at the start (``pairs``, :func:`_candidate_pairs`) with a wider block, plus 16. The
    second pass is a second copy of the narrow phase in the program (1.3 s more to
    compile seed example 4, whose detection it made no faster): a split is taken where
    it saves at least :data:`SPLIT_SAVES` vertex-face tests and half of them. Where none
    is, returns (V, 0): the narrow phase then tests every pair with V, which may be fewer
    than the model's (a size class).
    """
    V = int(nv.max())
    i, j = pairs
    whole = capacity * V * V
    best = (whole - max(SPLIT_SAVES, whole // 2), V, 0)
    for v in np.unique(nv)[:-1]:
        wide_capacity = bucket(2 * int(np.sum((nv[i] > v) | (nv[j] > v))) + 16)
        best = min(best, (capacity * int(v) ** 2 + wide_capacity * V * V, int(v), wide_capacity))
    return best[1], best[2]


def _locate_monitors(scene, polys, cents, tol, excavation) -> dict:
    """The rock blocks holding each monitored point, and the point's offsets from their centroids.

    A point on a face shared by several blocks (a joint or an intact cut) follows the
    mean of their material points there, with equal weights: taking one of them (the
    first in the block list) made a reading depend on how the blocks are numbered,
    and a mirrored scene read another block. Excavated blocks hold a point only when
    no rock block does. ``blocks`` and ``weights`` are (points, H) and ``offsets``
    (points, H, 2), H the largest number of holders of a point in the scene (unused
    entries have weight 0).
    """
    points = [[m.point] if m.kind == "point" else [m.start, m.end] for m in scene.monitors]
    flat = np.array([p for pts in points for p in pts], float).reshape(-1, 2)
    holds = iter(geometry.points_in_polygons(flat, polys, tol))
    found = []
    for m, pts in zip(scene.monitors, points, strict=True):
        rows = []
        for p in pts:
            inside = np.nonzero(next(holds))[0].tolist()
            rock = [i for i in inside if excavation[i] is None]
            rows.append((np.asarray(p, float), rock or inside[:1]))
        found.append((m, rows))
    H = max([len(h) for _, rows in found for _, h in rows], default=1)
    out = {}
    for m, rows in found:
        blocks = np.zeros((len(rows), H), np.int32)
        offsets = np.zeros((len(rows), H, 2))
        weights = np.zeros((len(rows), H))
        for j, (p, holders) in enumerate(rows):
            for h, k in enumerate(holders):
                blocks[j, h], offsets[j, h], weights[j, h] = k, p - cents[k], 1.0 / len(holders)
        out[m.name] = dict(kind=m.kind, blocks=blocks, offsets=offsets, weights=weights,
                           points=np.array([p for p, _ in rows]))
    return out
