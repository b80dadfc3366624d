"""Device data: the model (what does not change in a solve) and the state (what does),
the loads of an increment, and what a sub-step leaves for the host (its :class:`Balance`
and contact :class:`Snapshot`).

The first three are frozen dataclasses registered as JAX pytrees, the last two
NamedTuples. Array fields are leaves; sizes and switches that fix the compiled program
are static (``meta``) fields, so changing one of them recompiles, which is how
capacities grow.

Shapes use these letters:
  N  blocks, rock blocks first, then rigid boundary walls
  V  vertices per block (padded; ``nv`` holds the real count)
  P  capacity of the candidate pair list (grows on overflow)
  J  joints
  S = P * 2 * V  spring slots: for pair (a, b), a < b, slot (p, 0, v) is vertex v
     of a against an edge of b and slot (p, 1, v) is vertex v of b against an
     edge of a. A slot's identity (pair, side, vertex) is its stable key.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import numpy as np

# Contact spring states.
OPEN, STICK, SLIP = 0, 1, 2

# Block kinds: rock blocks carry material stiffness; walls are rigid boundaries.
ROCK, WALL_FIXED, WALL_ROLLER = 0, 1, 2


def _pytree(data: list[str], meta: list[str]):
    def wrap(cls):
        return jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)

    return wrap


@_pytree(
    data=[
        "nv", "vmask", "free", "kind", "kn_inv", "ks_inv", "area", "radius", "f_ext",
        "edge_joint", "joint_kn", "joint_ks", "joint_c", "joint_t", "joint_tanphi",
        "big", "pseudo_mass", "f_ref", "tol", "step_length", "margin", "touch_tol",
        "max_displacement", "travel_limit", "travel_range", "span_tol", "cos_parallel",
        "corner_share", "max_iterations", "max_substeps",
        "joint_intact", "gamma_w", "bolt_blocks", "bolt_offsets", "bolt_k", "bolt_cap",
        "bolt_comp", "bolt_pullout", "cell_D", "bond_penalty", "verts0", "centroid0",
    ],
    meta=["n_blocks", "n_vertices", "n_big", "use_cells", "cell_capacity", "narrow_vertices",
          "wide_capacity", "touch_capacity", "linear_solver", "events",
          "n_bolts", "has_water", "ndof", "lanes", "slots_per_pair"],
)
@dataclasses.dataclass(frozen=True)
class Model:
    """Constant data of a solve (host-built, device-resident).

    N, V and J are size classes (:func:`jaxdem.core.model.block_bucket`,
    :func:`jaxdem.core.model.bucket`), so that scenes of similar size share their
    compiled programs: the rock blocks come first, then the walls, then at least
    one dead block (a copy of block 0, never alive in the State, never free, in
    no contact); vertices past a block's own repeat its first; joint rows past
    the scene's are unused.

    Attributes:
      nv: (N,) int32 vertex count of each block.
      vmask: (N, V) bool, real vertices.
      free: (N,) bool, block has degrees of freedom (not fixed, not a wall).
      kind: (N,) int32, ROCK, WALL_FIXED or WALL_ROLLER.
      kn_inv, ks_inv: (N,) 1/kPa, inverse intact stiffness 1/kn_i = (1 - nu^2)/E and
        1/ks_i = (1 + nu)/E (paper eqs. 3-4); 0 for rigid walls.
      area: (N,) m2. radius: (N,) m, largest centroid-to-vertex distance.
      f_ext: (N, D) external load at load factor 1 (kN/m, kN/m, kN m/m about
        the centroid, then for deformable blocks the work-conjugates of the
        three strains, kN m/m): self-weight and boundary tractions.
      edge_joint: (N, V) int32, joint of the discontinuity each edge lies on, -1 if none.
      joint_kn, joint_ks: (J,) kPa/m. joint_c, joint_t: (J,) kPa.
      joint_tanphi: (J,) tan of the friction angle.
      big: (n_big,) int32, blocks paired with every block in the broad phase
        (walls and blocks much larger than the median); the rest go in cells.
        Filled up to its size class with the last (dead) block.
      pseudo_mass: (N, D) diagonal regularisation eps * k_ref * (1, 1, r_g^2, ...):
        changes the path of the iteration, never a converged equilibrium.
      f_ref: scalar kN/m, force scale of the convergence test.
      tol: relative residual tolerance. step_length: m, largest travel of a
        block in one geometry sub-step. margin: m, contact detection distance
        (open springs within it may close during a sub-step). touch_tol: m,
        gap under which faces are in contact. max_displacement: m, the scene's
        travel in one increment beyond which a block is moving (a mechanism).
        travel_limit: (N,) m, each block's own (max_displacement, or where the
        scene leaves it out the block's size, :mod:`jaxdem.core.model`). travel_range:
        (2,) m, the bounds of a limit ([max_displacement] twice where the scene gives it,
        else [TRAVEL_FLOOR L, L]), a group's too
        (:func:`jaxdem.core.kinematics.group_limits`). span_tol: m, how far past the end
        of a face a vertex still bears on it (0.01 L).
      cos_parallel: faces closer than this cosine to anti-parallel are an
        edge-to-edge contact. corner_share: effective length of a
        corner-to-edge point as a fraction of its shorter adjacent edge.
      max_iterations: Newton iterations per geometry sub-step.
      max_substeps: geometry sub-steps per increment.
      joint_intact: (J,) bool, the entry is an intact-rock bond (no water on it).
      gamma_w: scalar kN/m3, unit weight of water (0 when the scene has none).
      bolt_blocks: (B, 2) int32, blocks holding the two anchors of each bolt.
      bolt_offsets: (B, 2, 2) m, anchors relative to those centroids at rotation 0.
      bolt_k: (B,) kN/m per m, axial stiffness / spacing.
      bolt_cap: (B,) kN/m, min(yield force, anchor capacity) / spacing: the tension
        the bolt carries at most.
      bolt_comp: (B,) kN/m, compression / spacing: the compression it carries at
        most (0: none, a cable that goes slack).
      bolt_pullout: (B,) bool, the anchor capacity governs (pull-out, else yield).
      cell_D: (N, 3, 3) kPa, plane-strain elasticity of each deformable block
        (sigma = D (eps_x, eps_y, gamma_xy)); (0, 3, 3) when blocks are rigid.
      bond_penalty: scalar, stiffness of an intact-rock bond between deformable
        blocks as a multiple of the Hamajima-Kawai spring (eqs. 3-7).
      verts0: (N, V, 2) m, vertices at the start; centroid0: (N, 2) m, their
        centroids. A rigid block's position is this reference moved by its
        accumulated (u, rot), never a sum of many small moves: in float32 a
        load step's move can be below the resolution of a coordinate.
      n_blocks, n_vertices, n_big, n_bolts: static sizes.
      cell_capacity: the broad phase's neighbour places per block (its blocks in the
        nine grid cells around its own, on average); doubled, with a recompilation,
        when the blocks have more.
      narrow_vertices, wide_capacity: the narrow phase tests the pairs of blocks with at
        most ``narrow_vertices`` vertices with that many, and the others (at most
        ``wide_capacity`` pairs, doubled with ``cell_capacity``) with V
        (:func:`jaxdem.core.model._narrow_split`).
      touch_capacity: places for the touching pairs (a slot within the contact margin), the
        pairs that the Newton iteration works on (:func:`jaxdem.core._substep.pack_slots`);
        grown, with a recompilation, when a sub-step has more.
      slots_per_pair: the touching slots are packed into ``slots_per_pair`` x
        ``touch_capacity`` places, at most twice ``slots_per_pair`` of them for one pair;
        doubled, with a recompilation, when a sub-step has more (every slot, unpacked,
        where that is 2 V x P or more).
      ndof: degrees of freedom per block, D: 3 (rigid: ux, uy, rotation) or 6
        (deformable, constant strain: also eps_x, eps_y, gamma_xy).
      use_cells: grid broad phase (else all pairs).
      linear_solver: "dense" (LU), "sparse" (SciPy's sparse LU, on the
        host) or "cg" (matrix-free conjugate gradients); "auto" is resolved by
        :func:`jaxdem.core.model.linear_solver_for`.
      events: springs with cohesion or tensile strength fail event by event
        (``solver.bond_failure = "events"``: :func:`jaxdem.core._substep.breaking`).
      has_water: the scene has a water table (else no pore-pressure code is compiled).
      lanes: the name of the vmap axis when samples are solved side by side
        (:mod:`jaxdem.batch`), else None: a Newton iteration then skips its
        factorisation only when every member of the batch has converged.
    """

    nv: jax.Array
    vmask: jax.Array
    free: jax.Array
    kind: jax.Array
    kn_inv: jax.Array
    ks_inv: jax.Array
    area: jax.Array
    radius: jax.Array
    f_ext: jax.Array
    edge_joint: jax.Array
    joint_kn: jax.Array
    joint_ks: jax.Array
    joint_c: jax.Array
    joint_t: jax.Array
    joint_tanphi: jax.Array
    big: jax.Array
    pseudo_mass: jax.Array
    f_ref: jax.Array
    tol: jax.Array
    step_length: jax.Array
    margin: jax.Array
    touch_tol: jax.Array
    max_displacement: jax.Array
    travel_limit: jax.Array
    travel_range: jax.Array
    span_tol: jax.Array
    cos_parallel: jax.Array
    corner_share: jax.Array
    max_iterations: jax.Array
    max_substeps: jax.Array
    joint_intact: jax.Array
    gamma_w: jax.Array
    bolt_blocks: jax.Array
    bolt_offsets: jax.Array
    bolt_k: jax.Array
    bolt_cap: jax.Array
    bolt_comp: jax.Array
    bolt_pullout: jax.Array
    cell_D: jax.Array
    bond_penalty: jax.Array
    verts0: jax.Array
    centroid0: jax.Array
    n_blocks: int
    n_vertices: int
    n_big: int
    use_cells: bool
    cell_capacity: int
    narrow_vertices: int
    wide_capacity: int
    touch_capacity: int
    linear_solver: str
    events: bool = False
    n_bolts: int = 0
    has_water: bool = False
    ndof: int = 3
    lanes: str | None = None
    slots_per_pair: int = 3


@_pytree(
    data=["verts", "centroid", "u", "rot", "alive", "pairs", "fs", "fn", "fn0", "failed", "edge",
          "cstate", "present", "gap", "bolt_force", "bolt_state", "bolt_rest", "strain",
          "stress"],
    meta=["capacity"],
)
@dataclasses.dataclass(frozen=True)
class State:
    """What changes during a solve.

    Attributes:
      verts: (N, V, 2) m, current vertex positions (padding repeats vertex 0).
      centroid: (N, 2) m, current centroids.
      u: (N, 2) m, centroid displacement since the start.
      rot: (N,) rad, rotation since the start (counter-clockwise positive).
      alive: (N,) bool, the block has not been excavated.
      pairs: (P, 2) int32 candidate pairs (a < b); empty entries hold (N, N).
      fs: (P, 2, V) kN/m, shear spring force along the contacted edge's tangent.
      fn: (P, 2, V) kN/m, effective normal force (compression positive), for output.
      fn0: (P, 2, V) kN/m, initial (in-situ) normal force of the spring at zero gap.
      failed: (P, 2, V) bool, the contact lost its cohesion and tensile strength.
      edge: (P, 2, V) int32, contacted edge of the other block.
      cstate: (P, 2, V) int32, OPEN, STICK or SLIP.
      present: (P, 2, V) bool, the slot was within the detection margin.
      gap: (P, 2, V) m, the slot's gap at the end of the last sub-step (its detected gap
        plus the sub-step's normal motion): where the next detection finds the same
        gap to round-off, a float32 scene keeps this one (:func:`jaxdem.core._substep.
        slot_fields_of`).
      bolt_force: (B,) kN/m, axial bolt force (tension positive).
      bolt_state: (B,) int32, 0 elastic, 1 yielded, 2 pulled out, 3 slack (a bolt
        that carries no compression, shortened), 4 yielded in compression.
      bolt_rest: (B,) m, length at which the bolt carries no force: its length
        when installed, plus its plastic elongation (yield, pull-out) less its
        plastic shortening; 0 until installed.
      strain: (N, 3) strain of deformable blocks since the start (eps_x, eps_y,
        gamma_xy; extension positive); zero for rigid blocks.
      stress: (N, 3) kPa, stress of deformable blocks (sigma_x, sigma_y, tau_xy;
        tension positive inside the solver): in-situ stress + D strain.
      capacity: P, static.
    """

    verts: jax.Array
    centroid: jax.Array
    u: jax.Array
    rot: jax.Array
    alive: jax.Array
    pairs: jax.Array
    fs: jax.Array
    fn: jax.Array
    fn0: jax.Array
    failed: jax.Array
    edge: jax.Array
    cstate: jax.Array
    present: jax.Array
    gap: jax.Array
    bolt_force: jax.Array
    bolt_state: jax.Array
    bolt_rest: jax.Array
    strain: jax.Array
    stress: jax.Array
    capacity: int


class Snapshot(NamedTuple):
    """The contacts at the end of a sub-step, per slot (S,) (the forces at the sub-step's
    points: :func:`jaxdem.core._substep.commit_substep`): ``point`` and ``normal`` (S, 2),
    blocks ``a`` (the vertex's) and ``b`` (the face's), ``active``, forces ``fn``, ``fs``
    (kN/m, compression positive) and ``pw`` (the water's), ``state`` (OPEN, STICK, SLIP)
    and ``joint`` (a joint contact: not an intact bond, not a wall). Its derivatives
    (:data:`SNAPSHOT_FLOATS` alone, the rest None): :func:`float_part`."""

    point: jax.Array
    normal: jax.Array
    a: jax.Array
    b: jax.Array
    active: jax.Array
    fn: jax.Array
    fs: jax.Array
    pw: jax.Array
    state: jax.Array
    joint: jax.Array


#: The fields of a :class:`Snapshot` that have derivatives (the sensitivities carry them).
SNAPSHOT_FLOATS = ("point", "normal", "fn", "fs", "pw")


def float_part(snap: Snapshot) -> Snapshot:
    """``snap`` with its :data:`SNAPSHOT_FLOATS` alone, the other fields None."""
    return Snapshot(**{k: getattr(snap, k) if k in SNAPSHOT_FLOATS else None
                       for k in Snapshot._fields})


class Balance(NamedTuple):
    """The global balance of the free blocks at the end of a sub-step, and how far its
    answer is from admissible (:func:`jaxdem.core._substep.commit_substep`): ``overlap``
    (m, the deepest interpenetration), ``overlap_rel`` (the same relative to the smaller
    block's size), ``excess`` (the largest excess of a contact's forces over its
    strength, relative to its blocks' force scale), ``applied`` and ``reaction`` (3,)
    (Fx, Fy kN/m, M kN m/m about the origin: the loads, and the forces from blocks
    without degrees of freedom), ``scale`` (kN/m, the forces in play that the imbalance
    is relative to: :func:`jaxdem.core.status.global_imbalance`)."""

    overlap: jax.Array
    overlap_rel: jax.Array
    excess: jax.Array
    applied: jax.Array
    reaction: jax.Array
    scale: jax.Array


def empty_history(n_blocks: int, capacity: int, n_vertices: int, dtype) -> dict:
    """Contact history arrays of a given capacity, all slots empty."""
    shape = (capacity, 2, n_vertices)
    # Made in NumPy and sent in one transfer: jnp.zeros would compile a small program
    # for each shape and dtype at start-up.
    return jax.device_put(dict(
        pairs=np.full((capacity, 2), n_blocks, np.int32),
        fs=np.zeros(shape, dtype),
        fn=np.zeros(shape, dtype),
        fn0=np.zeros(shape, dtype),
        failed=np.zeros(shape, bool),
        edge=np.zeros(shape, np.int32),
        cstate=np.zeros(shape, np.int32),
        present=np.zeros(shape, bool),
        gap=np.zeros(shape, dtype),
    ))


def grow_capacity(state: State, capacity: int) -> State:
    """The same state with a larger pair capacity (history kept, new slots empty)."""
    old = state.capacity
    n_blocks = state.verts.shape[0]
    new = empty_history(n_blocks, capacity, state.verts.shape[1], state.fs.dtype)
    fields = {k: v.at[:old].set(getattr(state, k)) for k, v in new.items()}
    return dataclasses.replace(state, capacity=capacity, **fields)


@_pytree(data=["force", "water_x", "water_y", "water_scale", "bolt_active"], meta=[])
@dataclasses.dataclass(frozen=True)
class Loads:
    """What the host applies in one increment.

    Attributes:
      force: (N, D) external load on each block (kN/m, kN/m, kN m/m about its
        centroid; then the strain work-conjugates of deformable blocks):
        self-weight, tractions, support pressure, and the part of the
        excavated blocks' forces not yet released.
      water_x, water_y: (W,) water table polyline (m); unused without water.
      water_scale: scalar, fraction of the pore pressure applied (ramped with
        self-weight while a scene without in-situ stress is loaded).
      bolt_active: (B,) bool, the bolt is installed.
    """

    force: jax.Array
    water_x: jax.Array
    water_y: jax.Array
    water_scale: jax.Array
    bolt_active: jax.Array
