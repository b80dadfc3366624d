"""The Newton matrix of the held states is the exact derivative of the residual.

Within a sub-step the geometry is fixed and the rows B linear, so with every slot's state
held the residual is a smooth function of the displacements and the slip tangent
(:func:`jaxdem.core._springs.stiffness_terms` with ``consistent``, plus
:func:`jaxdem.core._springs.slip_coupling`) must be its Jacobian: Newton then settles
slip in one or two iterations. The coupling d fs / d fn is taken with the hysteresis
band the forces are (:func:`jaxdem.core._springs.evaluate`): a slot stuck within the band
above its strength carries its trial force, and has no coupling.
"""

import jax.numpy as jnp
import numpy as np
from scenes import jointed_tunnel

from jaxdem.core import model as model_mod
from jaxdem.core._linsolve import _unsymmetric, assemble_dense
from jaxdem.core._springs import evaluate, slip_coupling, stiffness_terms
from jaxdem.core._substep import force_scales, prepare_substep
from jaxdem.core.loads import make_loads
from jaxdem.core.state import SLIP, STICK
from jaxdem.scene import parse_scene


def _moved_tunnel():
    """The jointed tunnel's first sub-step and a random move that makes joints slip: (mdl,
    sub, st0, du, the random generator after drawing du, the largest block radius)."""
    # Its cohesive joints slip in the iteration where they fail as they reach their
    # strength ("substep"); event by event (the default) they are elastic until then.
    scene = jointed_tunnel(water=False, bolts=False)
    scene.setdefault("solver", {})["bond_failure"] = "substep"
    model, state, _ = model_mod.build(parse_scene(scene))
    loads = make_loads(model, model.f_ext)
    mdl, sub, st0, _, _ = prepare_substep(model, state, loads)
    rng = np.random.default_rng(3)
    free = np.asarray(sub.free)[:, None]
    size = float(np.max(np.asarray(model.radius)))
    du = jnp.asarray(rng.normal(0.0, 2e-4 * size, (mdl.n_blocks, mdl.ndof)) * free)
    return mdl, sub, st0, du, rng, size


def test_slip_tangent_is_the_derivative_of_the_residual_in_held_states():
    """K v against the central difference of -R along v (relative 1e-6), on the jointed
    tunnel's first sub-step moved so that joints slip, every slot held in the law's
    state, with a hysteresis band wide enough that some stuck slots are beyond their
    strength within it (their force is their trial force: no coupling)."""
    mdl, sub, st0, du, rng, size = _moved_tunnel()
    none = jnp.zeros_like(st0, bool)
    # A band of about the median excess over the strength of the slots that slip
    # without one: about half of them stay stuck within it.
    law = evaluate(mdl, sub, du, none, none.astype(st0.dtype), st0, force_scales(mdl, sub)[1])
    limit = np.asarray(sub.prop.cohesion) + np.asarray(law.fn) * np.asarray(
        sub.prop.tanphi)
    excess = np.abs(np.asarray(law.fs_trial)) - limit
    over = np.unique(excess[np.asarray(law.state) == SLIP])  # the two sides of a contact alike
    k = over.size // 2
    band = float(0.5 * (over[k - 1] + over[k]))  # between two slots: none at its edge
    law = evaluate(mdl, sub, du, none, none.astype(st0.dtype), st0, band)
    limit = np.asarray(sub.prop.cohesion) + np.asarray(law.fn) * np.asarray(
        sub.prop.tanphi)  # the band moves the opening threshold too
    active = np.asarray(sub.geo.active)
    held = law.state
    st = np.asarray(held)
    assert (active & (st == SLIP)).sum() >= 4, "the move should make joints slip"
    fs, fs_trial = np.abs(np.asarray(law.fs)), np.abs(np.asarray(law.fs_trial))
    in_band = (active & (st == STICK) & (fs_trial > limit + 1e-3 * fs_trial.max())
               & ~np.asarray(sub.prop.bonded))
    assert in_band.sum() >= 2 and np.allclose(fs[in_band], fs_trial[in_band])
    frozen = jnp.asarray(active)
    Kv, fd = _tangent_and_difference(mdl, sub, du, frozen, held, band, rng, size)
    assert np.linalg.norm(Kv) > 0
    np.testing.assert_allclose(Kv, fd, rtol=0, atol=1e-6 * np.abs(Kv).max())


def test_exact_tangent_of_slots_held_stuck_beyond_their_strength():
    """Slots held (frozen) STICK where the law has them slip carry the limit
    (:func:`jaxdem.core.laws.forces_in_state`): with ``exact`` their shear spring goes and
    K v is the central difference of -R (relative 1e-6); without it (the stiffness the
    Newton iteration uses until a tried step fails) it is not."""
    mdl, sub, st0, du, rng, size = _moved_tunnel()
    none = jnp.zeros_like(st0, bool)
    law = evaluate(mdl, sub, du, none, none.astype(st0.dtype), st0, 0.0)
    active = np.asarray(sub.geo.active)
    slipping = active & (np.asarray(law.state) == SLIP)
    assert slipping.sum() >= 4, "the move should make joints slip"
    held = jnp.where(jnp.asarray(slipping), STICK, law.state)
    frozen = jnp.asarray(active)
    ev = evaluate(mdl, sub, du, frozen, held, held, 0.0)
    # Held stuck, they carry the limit, as the law does.
    np.testing.assert_allclose(np.asarray(ev.fs)[slipping], np.asarray(law.fs)[slipping],
                               rtol=1e-12)
    Kv, fd = _tangent_and_difference(mdl, sub, du, frozen, held, 0.0, rng, size, exact=True)
    np.testing.assert_allclose(Kv, fd, rtol=0, atol=1e-6 * np.abs(Kv).max())
    rng = np.random.default_rng(3)
    Kv, fd = _tangent_and_difference(mdl, sub, du, frozen, held, 0.0, rng, size, exact=False)
    assert np.abs(Kv - fd).max() > 1e-3 * np.abs(Kv).max()


def _tangent_and_difference(mdl, sub, du, frozen, held, band, rng, size, exact=False):
    """K v of the slip tangent with its coupling (states ``held``) and the central
    difference of -R along a random v."""
    def at(x):
        return evaluate(mdl, sub, x, frozen, held, held, band)

    ev = at(du)
    terms = stiffness_terms(mdl, sub, ev, jnp.asarray(True), exact=jnp.asarray(exact))
    coupling = slip_coupling(sub, ev, jnp.asarray(True))
    zero = jnp.zeros(mdl.n_blocks * mdl.ndof)
    K = np.asarray(assemble_dense(mdl, sub, *_unsymmetric(sub, terms, coupling), zero))
    free = np.asarray(sub.free)[:, None]
    v = rng.normal(0.0, 1.0, du.shape) * free
    h = 1e-7 * size
    R_plus = np.asarray(at(du + h * jnp.asarray(v)).R).reshape(-1)
    R_minus = np.asarray(at(du - h * jnp.asarray(v)).R).reshape(-1)
    return K @ v.reshape(-1), -(R_plus - R_minus) / (2 * h)


def test_bolt_length_derivatives_are_those_of_the_exact_motion():
    """The bolts' closed-form length, gradient and Hessian
    (:func:`jaxdem.core.kinematics.bolt_length_derivatives`; the Hessian made of its rank-one
    terms, :func:`jaxdem.core.kinematics.bolt_hessian`) against automatic derivatives
    of the exact motion of the two anchors, rigid and strained (1e-12 relative): an
    anchor at r from its centroid goes to u + R(theta) (r + E(eps) r), as
    :func:`jaxdem.core.kinematics.move_blocks` moves it."""
    import jax

    from jaxdem.core.kinematics import bolt_hessian, bolt_length_derivatives

    def turned(v, angle):
        c, s = jnp.cos(angle), jnp.sin(angle)
        return jnp.stack([c * v[0] - s * v[1], s * v[0] + c * v[1]])

    def length(ndof, d0, ra, rb, x):
        def moved(u, r):
            if ndof == 6:
                r = r + jnp.stack([u[3] * r[0] + 0.5 * u[5] * r[1],
                                   0.5 * u[5] * r[0] + u[4] * r[1]])
            return u[:2] + turned(r, u[2])

        d = d0 + moved(x[:ndof], ra) - ra - moved(x[ndof:], rb) + rb
        return jnp.sqrt(jnp.sum(d * d))

    rng = np.random.default_rng(7)
    for ndof in (3, 6):
        n = 5
        d0, ra, rb = (jnp.asarray(rng.normal(0.0, 2.0, (n, 2))) for _ in range(3))
        scale = np.r_[0.05, 0.05, 0.3, 0.01, 0.01, 0.01][:ndof]
        x = jnp.asarray(rng.normal(0.0, 1.0, (n, 2 * ndof)) * np.tile(scale, 2))
        L, g, v, c = bolt_length_derivatives(ndof, d0, ra, rb, x)
        H = bolt_hessian(v, c)
        assert v.shape[1] == (3 if ndof == 3 else 7)  # within the tangent's 2 D places
        f = lambda *a, ndof=ndof: length(ndof, *a)  # noqa: E731
        L_ref, g_ref = jax.vmap(jax.value_and_grad(f, argnums=3))(d0, ra, rb, x)
        H_ref = jax.vmap(jax.hessian(f, argnums=3))(d0, ra, rb, x)
        np.testing.assert_allclose(L, L_ref, rtol=1e-12)
        for got, ref in ((g, g_ref), (H, H_ref)):
            np.testing.assert_allclose(got, ref, rtol=1e-12,
                                       atol=1e-12 * float(jnp.max(jnp.abs(ref))))
