"""What loads the blocks: the Loads of an increment, water pressure, in-situ stress, release.

Owns :func:`make_loads` (the :class:`jaxdem.core.state.Loads` pytree of one
increment), :func:`water_force` (pore pressure on the joint slots), the
in-situ preload :func:`in_situ_preload` (the contacts' starting forces from an
in-situ stress field, jitted) and :func:`release_forces` (the forces that blocks
being excavated exert on the rest).

Data flow: takes contact detection (:mod:`jaxdem.core._contact`), the slot
properties of :mod:`jaxdem.core.laws` and the rows of :mod:`jaxdem.core.kinematics`;
used by the sub-step (:mod:`jaxdem.core._substep`, water), the sensitivities, the
host driver (:mod:`jaxdem.solver`) and :mod:`jaxdem.batch`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.core._contact import Slots, broad_phase, narrow_phase
from jaxdem.core.compile_cache import on_disk
from jaxdem.core.kinematics import b_rows, point_row, scatter_pairs
from jaxdem.core.laws import SlotLaw, slot_properties
from jaxdem.core.state import OPEN, STICK, Loads, Model, Snapshot, State


def make_loads(model: Model, force, water_x=None, water_y=None, bolt_active=None,
               water_scale=1.0) -> Loads:
    """Loads for one increment: block forces (N, 3), optional water table and bolt switches."""
    # From host arrays (the driver's) the Loads are built in NumPy and sent
    # to the device in one transfer; from JAX arrays (under jit or vmap),
    # with jax.numpy.
    from_jax = any(isinstance(x, jax.Array)
                 for x in (force, water_x, water_y, bolt_active, water_scale))
    xp = jnp if from_jax else np
    dtype = model.radius.dtype
    no_water = xp.array([0.0, 1.0], dtype), xp.array([-1e30, -1e30], dtype)
    loads = Loads(
        force=xp.asarray(force, dtype),
        water_x=no_water[0] if water_x is None else xp.asarray(water_x, dtype),
        water_y=no_water[1] if water_y is None else xp.asarray(water_y, dtype),
        water_scale=xp.asarray(water_scale, dtype),
        bolt_active=(xp.ones(model.n_bolts, bool) if bolt_active is None
                     else xp.asarray(bolt_active, bool)))
    return loads if from_jax else jax.device_put(loads)


def water_force(model: Model, geo: Slots, prop: SlotLaw, water_x, water_y, scale=1.0):
    """Pore-pressure force on each joint slot, gamma_w (y_table(x) - y) x share (kN/m).

    Hydrostatic below the table, zero above it; none on intact bonds and walls.
    """
    p = geo.point
    head = jnp.interp(p[:, 0], water_x, water_y) - p[:, 1]
    on_joint = geo.active & ~prop.bonded & ~model.joint_intact[geo.joint]
    return jnp.where(on_joint, scale * model.gamma_w * jnp.maximum(head, 0.0) * geo.share, 0.0)


@on_disk("preload")
@functools.partial(jax.jit, static_argnames=("mode",))
def in_situ_preload(model: Model, state: State, loads: Loads, sigma, surface_y, gamma, k0,
                    mode: str):
    """Contacts at the start with the forces of the in-situ stress field (zero displacement).

    Each touching spring gets its part of the traction of the stress tensor
    (compression positive) on its face: the consistent (linear-element) nodal
    force of the traction t along the overlap, share x (2 t(here) + t(far end)) / 3,
    which gives the exact force and moment of a traction that varies linearly
    along the face (the gravity field does). fn0 is its normal part (minus the
    pore pressure: springs carry effective force) and fs minus its tangential
    part. ``mode`` "gravity": sigma_yy = gamma (surface_y - y), sigma_xx = k0
    sigma_yy; "uniform": ``sigma`` = (sxx, syy, sxy).
    """
    pairs, count, cell_full = broad_phase(model, state.verts, state.capacity, state.alive)
    geo, _ = narrow_phase(model, state.verts, state.centroid, pairs)
    prop = slot_properties(model, geo)
    p, n, t = geo.point, geo.normal, geo.tangent

    def traction(x):
        if mode == "gravity":
            syy = gamma * jnp.maximum(surface_y - x[:, 1], 0.0)
            sxx, sxy = k0 * syy, jnp.zeros_like(syy)
        else:
            sxx, syy, sxy = (jnp.broadcast_to(sigma[k], x[:, 0].shape) for k in range(3))
        return sxx * n[:, 0] + sxy * n[:, 1], sxy * n[:, 0] + syy * n[:, 1]

    (tx0, ty0), (tx1, ty1) = traction(p), traction(geo.far_point)
    tx, ty = (2.0 * tx0 + tx1) / 3.0, (2.0 * ty0 + ty1) / 3.0
    touching = geo.active & (geo.gap <= model.touch_tol)
    # Faces in contact carry the in-situ traction; a corner touching a face
    # (a cell corner on a boundary wall, a hanging node) is a point of a
    # tessellation and carries none, nor do nearly parallel faces that meet at
    # one end only (a sliver between them), else the state would not be in
    # equilibrium.
    loaded = touching & ~geo.corner & (geo.far_gap <= model.touch_tol)
    pw = water_force(model, geo, prop, loads.water_x, loads.water_y) if model.has_water else 0.0
    fn0 = jnp.where(loaded, (tx * n[:, 0] + ty * n[:, 1]) * geo.share - pw, 0.0)
    fs = jnp.where(loaded, -(tx * t[:, 0] + ty * t[:, 1]) * geo.share, 0.0)
    shape = state.fs.shape
    stress = state.stress
    if model.ndof == 6:
        # Each deformable block starts with the stress its contact forces and
        # boundary tractions imply, (1/A) sum r (x) F: exactly in equilibrium.
        every = jnp.ones(model.n_blocks, bool)
        rows = lambda v: b_rows(every, geo.a, geo.b, p, p, v, state.centroid, 6)  # noqa: E731
        f_row = rows(n) * (fn0 + pw)[:, None] - rows(t) * fs[:, None]
        virial = (scatter_pairs(model.n_blocks, geo.a, geo.b, f_row)[:, 3:]
                  + loads.force[:, 3:])
        stress = virial / model.area[:, None]
    new = dataclasses.replace(
        state, pairs=pairs, fn0=fn0.reshape(shape), fn=fn0.reshape(shape), fs=fs.reshape(shape),
        failed=(geo.gap > model.touch_tol).reshape(shape), edge=geo.edge.reshape(shape),
        cstate=jnp.where(touching, STICK, OPEN).astype(jnp.int32).reshape(shape),
        present=geo.active.reshape(shape), stress=stress)
    return new, (count > state.capacity) | cell_full


def release_forces(centroid, snap: Snapshot, removed, ndof):
    """Forces (N, D) that the blocks being removed exert on the others, from a contact snapshot.

    The force of each contact on a remaining block is (fn + pw) n - fs t at the
    contact point; :func:`jaxdem.core.kinematics.point_row` is linear in the force, so it gives the
    generalised force directly.
    """
    N = centroid.shape[0]
    act = snap.active
    a, b, p, n = snap.a, snap.b, snap.point, snap.normal
    t = jnp.stack([-n[:, 1], n[:, 0]], axis=1)
    F = (snap.fn + snap.pw)[:, None] * n - snap.fs[:, None] * t
    out = jnp.zeros((N, ndof), F.dtype)
    for on, by, sign in ((a, b, 1.0), (b, a, -1.0)):
        sel = act & removed[by] & ~removed[on]
        f = jnp.where(sel[:, None], sign * F, 0.0)
        out = out + jax.ops.segment_sum(point_row(p - centroid[on], f, ndof), on, N)
    return out


release_forces_jit = on_disk("release_forces")(jax.jit(release_forces, static_argnames="ndof"))
