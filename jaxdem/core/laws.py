"""Contact laws: equivalent spring stiffness (paper eqs. 3-7) and Mohr-Coulomb.

All functions act elementwise on flat slot arrays (shape (S,)) and are pure
jax.numpy, so they jit, vmap and differentiate.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxdem.core.state import OPEN, SLIP, STICK, WALL_ROLLER, Model


class SlotLaw(NamedTuple):
    """The spring and strength of each slot (S,) (:func:`slot_properties`): stiffnesses
    ``kn``, ``ks`` (kN/m per m of thickness: the stiffness per unit area of eqs. 5-7
    times the slot's share), ``cohesion`` and ``tension`` (kN/m: the strength, kPa,
    times the share), ``tanphi``, and ``bonded`` (a wall contact present from the
    start: elastic, no strength limit, no opening)."""

    kn: jax.Array
    ks: jax.Array
    cohesion: jax.Array
    tension: jax.Array
    tanphi: jax.Array
    bonded: jax.Array


def intact_stiffness(E, nu):
    """Intact-rock spring stiffnesses per unit area (kPa), Hamajima-Kawai (eqs. 3-4).

    Returns (kn_i, ks_i) = (E / (1 - nu^2), E / (1 + nu)).
    """
    return E / (1.0 - nu**2), E / (1.0 + nu)


def plane_strain_elasticity(E, nu, xp=jnp):
    """Plane-strain elasticity matrix D (kPa): (sx, sy, txy) = D (ex, ey, gxy); ``xp`` the
    array module (NumPy for the host's model, which then compiles no program for it)."""
    f = E / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return f * xp.array([[1.0 - nu, nu, 0.0], [nu, 1.0 - nu, 0.0], [0.0, 0.0, 0.5 - nu]])


def equivalent_stiffness(h1, h2, k1_inv, k2_inv, k0_inv):
    """Equivalent stiffness per unit contact length (kPa/m), eqs. 6-7.

    k = 1 / (h1 / k1 + h2 / k2 + 1 / k0), with h1, h2 (m) the distances from
    the contact line to the two centroids, k1, k2 the intact stiffnesses (kPa)
    and k0 the joint stiffness (kPa/m); pass k0_inv = 0 for no joint term.
    """
    return 1.0 / (h1 * k1_inv + h2 * k2_inv + k0_inv)


def slot_properties(model: Model, geo) -> SlotLaw:
    """Spring stiffness (kN/m per m) and strength of every slot of ``geo``, the
    detection's :class:`jaxdem.core._contact.Slots` (or any subset of them).

    A slot's spring is k * share (share = its part of the effective length Le).
    Contacts with a rigid wall have no joint term and are bonded (elastic, no
    strength limit, no opening) if they touch when first detected; a wall
    contact that forms later is unilateral and frictional (the joint's
    friction angle). Roller walls carry no shear.
    """
    a, b, j = geo.a, geo.b, geo.joint
    wall = (model.kind[a] != 0) | (model.kind[b] != 0)
    roller = (model.kind[a] == WALL_ROLLER) | (model.kind[b] == WALL_ROLLER)
    jkn_inv = jnp.where(wall, 0.0, 1.0 / model.joint_kn[j])
    jks_inv = jnp.where(wall, 0.0, 1.0 / model.joint_ks[j])
    kn = equivalent_stiffness(geo.h_a, geo.h_b, model.kn_inv[a], model.kn_inv[b], jkn_inv)
    ks = equivalent_stiffness(geo.h_a, geo.h_b, model.ks_inv[a], model.ks_inv[b], jks_inv)
    if model.ndof == 6:
        # Deformable blocks carry the rock's elasticity themselves: a joint is
        # its own springs, an intact bond or a wall a stiff penalty spring.
        bond = wall | model.joint_intact[j]
        safe = lambda x: jnp.where(bond, 1.0, x)  # noqa: E731
        no_joint = jnp.zeros_like(jkn_inv)
        kn_b = equivalent_stiffness(geo.h_a, geo.h_b, model.kn_inv[a], model.kn_inv[b],
                                    no_joint)
        ks_b = equivalent_stiffness(geo.h_a, geo.h_b, model.ks_inv[a], model.ks_inv[b],
                                    no_joint)
        kn = jnp.where(bond, model.bond_penalty * kn_b, 1.0 / safe(jkn_inv))
        ks = jnp.where(bond, model.bond_penalty * ks_b, 1.0 / safe(jks_inv))
    share = geo.share
    return SlotLaw(
        kn=kn * share,
        ks=jnp.where(roller, 0.0, ks * share),
        cohesion=model.joint_c[j] * share,
        tension=model.joint_t[j] * share,
        tanphi=model.joint_tanphi[j],
        bonded=wall,
    )


def mohr_coulomb(fn_trial, fs_trial, prop: SlotLaw, failed, active, prev=None, band=0.0):
    """Tension cut-off and Mohr-Coulomb slip of trial spring forces.

    Args:
      fn_trial: normal force, compression positive (kN/m).
      fs_trial: shear force (kN/m).
      prop: output of :func:`slot_properties`.
      failed: the slot has lost cohesion and tensile strength.
      active: the slot exists.
      prev: the slot's previous state, for the hysteresis band (optional).
      band: force (kN/m) by which the trial force must pass a threshold to
        change a slot's state: the opening threshold (open and closed), and
        the strength (a stuck slot slips only beyond limit + band; a slipping
        one sticks again below the limit). Within the band either state is
        within ``band`` of equilibrium, so a band below the residual
        tolerance never changes a converged answer; it stops slots at zero
        force from flipping at every iteration (a cohesionless joint without
        normal force has zero strength, and its round-off shear would make it
        slip).
    Returns:
      fn, fs, state (OPEN, STICK or SLIP). A contact opens when its tension
      exceeds its tensile strength (zero once failed); it slips when
      |Fs| > c * share + Fn tan(phi) (c zero once failed) and then carries
      that limit in the direction of the trial force.
    """
    # Wall contacts present from the start are bonded; one that forms later
    # (failed from its first detection) is an ordinary frictional contact.
    bonded = prop.bonded & ~failed
    t_cap = jnp.where(failed, 0.0, prop.tension)
    c = jnp.where(failed, 0.0, prop.cohesion)
    if prev is None:
        threshold = -t_cap
    else:
        threshold = jnp.where(prev == OPEN, -t_cap + band, -t_cap - band)
    opened = ~bonded & (fn_trial < threshold)
    fn = jnp.where(opened | ~active, 0.0, fn_trial)
    limit = jnp.maximum(c + fn * prop.tanphi, 0.0)
    slip_at = limit if prev is None else jnp.where(prev == SLIP, limit, limit + band)
    slip = ~bonded & ~opened & (jnp.abs(fs_trial) > slip_at)
    fs = jnp.where(opened | ~active, 0.0, jnp.where(slip, jnp.sign(fs_trial) * limit, fs_trial))
    state = jnp.where(~active | opened, OPEN, jnp.where(slip, SLIP, STICK)).astype(jnp.int32)
    return fn, fs, state


def has_strength(prop: SlotLaw):
    """(S,) the springs with strength to lose: cohesion or tensile strength (a clean
    joint and a frictional contact have none; whether it is lost yet is ``failed``)."""
    return (prop.cohesion > 0) | (prop.tension > 0)


def held_elastic(prop: SlotLaw) -> SlotLaw:
    """``prop`` with every spring that has strength to lose (cohesion or tensile
    strength) bonded: the law of a sub-step's Newton iteration where springs fail event
    by event (``solver.bond_failure = "events"``).

    Such a spring is elastic until it fails (``failed``, which :func:`mohr_coulomb` and
    :func:`forces_in_state` honour: a failed spring is frictional whatever ``bonded``
    says); whether it is loaded beyond its strength is decided when the sub-step is
    committed (:func:`excess_ratio`), and it then fails, losing its cohesion and
    tensile strength: it never slips or opens with them. A spring with nothing to lose
    (a clean joint) slips and opens within the iteration.
    """
    return prop._replace(bonded=prop.bonded | has_strength(prop))


def overload(fn, fs, prop: SlotLaw, failed):
    """(S,) kN/m: how far the forces (fn, fs) of each spring are beyond its strength,
    max(|fs| - max(c + fn tan(phi), 0), -fn - t) (c and t times the share, zero once
    failed; compression positive): positive beyond Mohr-Coulomb or the tension cut-off,
    whichever is passed further."""
    c = jnp.where(failed, 0.0, prop.cohesion)
    t_cap = jnp.where(failed, 0.0, prop.tension)
    limit = jnp.maximum(c + fn * prop.tanphi, 0.0)
    return jnp.maximum(jnp.abs(fs) - limit, -fn - t_cap)


def excess_ratio(fn, fs, prop: SlotLaw, failed, band=0.0):
    """How far a spring with strength to lose is loaded beyond it, relative to that
    strength: :func:`overload` / (c + t), both times the share (the hysteresis ``band``
    of :func:`mohr_coulomb` subtracted). Positive only beyond the strength; -1 for a
    spring with none to lose (failed, a clean joint, a wall bond).
    """
    strength = prop.cohesion + prop.tension
    brittle = ~prop.bonded & ~failed & has_strength(prop)
    over = overload(fn, fs, prop, failed) - band
    return jnp.where(brittle, over / jnp.where(brittle, strength, 1.0), -1.0)


def forces_in_state(fn_trial, fs_trial, prop: SlotLaw, failed, state, band=0.0):
    """Spring forces (kN/m) with a given state: a frozen slot's, and the held states' tangent.

    OPEN carries nothing; SLIP carries fn_trial and the Mohr-Coulomb limit
    |fs| = c * share + fn tan(phi) (c zero once failed) in the direction of
    the trial force; STICK carries the trial forces, but a stuck slot that is
    not bonded never carries more shear than that limit (plus ``band``, the
    hysteresis of :func:`mohr_coulomb`): there it carries the limit, as
    :func:`mohr_coulomb` would. Where the state is the one :func:`mohr_coulomb`
    gives with the same band, so are the forces and their derivatives. The
    normal force of a closed slot is fn_trial whatever its sign (a cap would
    break that agreement within the open/close hysteresis band): a slot held
    closed in tension beyond the cut-off is the caller's to refuse (the
    solver does not accept a sub-step whose blocks do not balance with the
    law's forces).
    """
    bonded = prop.bonded & ~failed
    c = jnp.where(failed, 0.0, prop.cohesion)
    fn = jnp.where(state == OPEN, 0.0, fn_trial)
    limit = jnp.maximum(c + fn * prop.tanphi, 0.0)
    capped = (state == SLIP) | (~bonded & (jnp.abs(fs_trial) > limit + band))
    fs = jnp.where(state == OPEN, 0.0, jnp.where(capped, jnp.sign(fs_trial) * limit, fs_trial))
    return fn, fs
