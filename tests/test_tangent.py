"""The Newton matrix of the held states is the exact derivative of the residual.

Within a sub-step the geometry is fixed and the rows B linear, so with every slot's state
held the residual is a smooth function of the displacements and the slip tangent
(:func:`jaxdem.core._springs.stiffness_terms` with ``consistent``, plus
:func:`jaxdem.core._springs.slip_coupling`) must be its Jacobian: Newton then settles
slip in one or two iterations. A slot held in STICK beyond its strength carries the
Mohr-Coulomb limit, as a slipping one does (:func:`jaxdem.core.laws.forces_in_state`),
so its shear spring is not in that Jacobian either; with it, seed example 4's tried
tangent steps raised the residual threefold with every state held.
"""

import jax.numpy as jnp
import numpy as np
from scenes import jointed_tunnel

from jaxdem.core import model as model_mod
from jaxdem.core._linsolve import _unsymmetric, assemble_dense
from jaxdem.core._springs import evaluate, slip_coupling, stiffness_terms
from jaxdem.core._substep import force_scales, prepare_substep
from jaxdem.core.loads import make_loads
from jaxdem.core.state import OPEN, SLIP, STICK
from jaxdem.scene import parse_scene


def test_slip_tangent_is_the_derivative_of_the_residual_in_held_states():
    """K v against the central difference of -R along v (relative 1e-6), on the jointed
    tunnel's first sub-step moved so that joints slip, with half of the slipping slots
    held in STICK (beyond their strength: capped) and every other slot held in its
    state."""
    model, state, _ = model_mod.build(parse_scene(jointed_tunnel(water=False, bolts=False)))
    loads = make_loads(model, model.f_ext)
    mdl, sub, st0, _, _ = prepare_substep(model, state, loads)
    _, band = force_scales(mdl, sub)
    rng = np.random.default_rng(3)
    free = np.asarray(sub.free)[:, None]
    size = float(np.max(np.asarray(model.radius)))
    du = jnp.asarray(rng.normal(0.0, 2e-4 * size, (mdl.n_blocks, mdl.ndof)) * free)
    none = jnp.zeros_like(st0, bool)
    law = evaluate(mdl, sub, du, none, none.astype(st0.dtype), st0, band)
    active = np.asarray(sub.geo["active"])
    st = np.asarray(law["state"])
    slipping = np.flatnonzero(active & (st == SLIP))
    assert slipping.size >= 4, "the move should make joints slip"
    held = st.copy()
    held[slipping[::2]] = STICK
    frozen, held = jnp.asarray(active), jnp.asarray(held)

    def at(x):
        return evaluate(mdl, sub, x, frozen, held, held, band)

    ev = at(du)
    capped = active & (np.asarray(held) == STICK) & (
        np.abs(np.asarray(ev["fs"])) < np.abs(np.asarray(ev["fs_trial"])))
    assert capped.sum() >= 2 and (active & (np.asarray(held) == SLIP)).sum() >= 2
    assert (active & (np.asarray(held) != OPEN)).sum() > capped.sum()
    terms = stiffness_terms(mdl, sub, ev, jnp.asarray(True))
    coupling = slip_coupling(sub, ev, jnp.asarray(True))
    zero = jnp.zeros(mdl.n_blocks * mdl.ndof)
    K = np.asarray(assemble_dense(mdl, sub, *_unsymmetric(sub, terms, coupling), zero))
    v = rng.normal(0.0, 1.0, du.shape) * free
    h = 1e-7 * size
    R_plus = np.asarray(at(du + h * jnp.asarray(v))["R"]).reshape(-1)
    R_minus = np.asarray(at(du - h * jnp.asarray(v))["R"]).reshape(-1)
    fd = -(R_plus - R_minus) / (2 * h)
    Kv = K @ v.reshape(-1)
    assert np.linalg.norm(Kv) > 0
    np.testing.assert_allclose(Kv, fd, rtol=0, atol=1e-6 * np.abs(Kv).max())
