"""Contact laws: equivalent stiffness (eqs. 3-7) and Mohr-Coulomb with tension cut-off."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdem.core.laws import (
    SlotLaw,
    equivalent_stiffness,
    excess_ratio,
    forces_in_state,
    held_elastic,
    intact_stiffness,
    mohr_coulomb,
)
from jaxdem.core.state import OPEN, SLIP, STICK


def test_intact_stiffness_eqs_3_4():
    kn, ks = intact_stiffness(1e7, 0.25)
    assert kn == pytest.approx(1e7 / (1 - 0.0625))
    assert ks == pytest.approx(1e7 / 1.25)


def test_equivalent_stiffness_is_springs_in_series_eq_7():
    # h1/k1 + h2/k2 + 1/k0 = 0.5/1e7 + 0.5/1e7 + 1/1e6 = 1.1e-6
    assert equivalent_stiffness(0.5, 0.5, 1e-7, 1e-7, 1e-6) == pytest.approx(1 / 1.1e-6)
    # Without a joint term only the blocks' halves remain.
    assert equivalent_stiffness(0.5, 0.5, 1e-7, 1e-7, 0.0) == pytest.approx(1e7)


def _prop(c=0.0, t=0.0, phi=30.0):
    one = jnp.ones(5)
    return SlotLaw(kn=one, ks=one, cohesion=c * one, tension=t * one,
                   tanphi=np.tan(np.radians(phi)) * one, bonded=jnp.zeros(5, bool))


def test_mohr_coulomb_states():
    fn_tr = jnp.array([10.0, 10.0, -1.0, -1.0, 10.0])
    fs_tr = jnp.array([1.0, 8.0, 0.0, 0.0, -8.0])
    failed = jnp.array([False, False, False, True, False])
    active = jnp.ones(5, bool)
    fn, fs, st = mohr_coulomb(fn_tr, fs_tr, _prop(c=0.0, t=2.0), failed, active)
    lim = 10.0 * np.tan(np.radians(30.0))
    # stick, slip (+), tension within T, tension after failure (T lost), slip (-)
    np.testing.assert_array_equal(np.asarray(st), [STICK, SLIP, STICK, OPEN, SLIP])
    np.testing.assert_allclose(np.asarray(fs), [1.0, lim, 0.0, 0.0, -lim])
    np.testing.assert_allclose(np.asarray(fn), [10.0, 10.0, -1.0, 0.0, 10.0])


def test_cohesion_lost_on_failure():
    fn_tr = jnp.full(5, 10.0)
    fs_tr = jnp.full(5, 8.0)
    active = jnp.ones(5, bool)
    lim = 10.0 * np.tan(np.radians(30.0))
    _, fs, st = mohr_coulomb(fn_tr, fs_tr, _prop(c=3.0), jnp.zeros(5, bool), active)
    assert (np.asarray(st) == STICK).all()  # 8 < 3 + 5.77
    _, fs, st = mohr_coulomb(fn_tr, fs_tr, _prop(c=3.0), jnp.ones(5, bool), active)
    assert (np.asarray(st) == SLIP).all()
    np.testing.assert_allclose(np.asarray(fs), lim)


def test_laws_vmap_and_grad():
    prop = _prop(c=1.0)
    f = lambda fn, fs: mohr_coulomb(fn, fs, prop, jnp.zeros(5, bool), jnp.ones(5, bool))[1]  # noqa: E731
    fn = jnp.full(5, 10.0)
    fs = jnp.linspace(0.0, 9.0, 5)
    batched = jax.vmap(f)(jnp.stack([fn, 2 * fn]), jnp.stack([fs, fs]))
    np.testing.assert_allclose(np.asarray(batched[0]), np.asarray(f(fn, fs)))
    # Slipping: d fs / d fn = tan(phi); sticking: d fs / d fs_trial = 1.
    g = jax.grad(lambda x: f(jnp.full(5, x), fs).sum())(10.0)
    slipping = int((jnp.abs(fs) > 1.0 + 10.0 * np.tan(np.radians(30.0))).sum())
    assert float(g) == pytest.approx(slipping * np.tan(np.radians(30.0)))


def test_forces_in_the_law_state_are_the_law_forces_and_their_derivatives():
    """forces_in_state with the state that mohr_coulomb gives returns its forces and
    derivatives (the exact tangent of the held states), and a slot held stuck never
    carries more shear than c + fn tan(phi) (a bonded wall contact has no limit)."""
    prop = _prop(c=1.0, t=2.0)
    failed, active = jnp.zeros(5, bool), jnp.ones(5, bool)
    fn_tr = jnp.array([10.0, 10.0, -1.0, -3.0, 10.0])
    fs_tr = jnp.array([1.0, 8.0, 0.2, 0.0, -8.0])
    fn, fs, st = mohr_coulomb(fn_tr, fs_tr, prop, failed, active)
    np.testing.assert_array_equal(np.asarray(st), [STICK, SLIP, STICK, OPEN, SLIP])
    held = lambda a, b: forces_in_state(a, b, prop, failed, st)  # noqa: E731
    law = lambda a, b: mohr_coulomb(a, b, prop, failed, active)[:2]  # noqa: E731
    np.testing.assert_allclose(np.asarray(held(fn_tr, fs_tr)), np.asarray((fn, fs)))
    for tangent in [(jnp.ones(5), jnp.zeros(5)), (jnp.zeros(5), jnp.ones(5))]:
        _, d_held = jax.jvp(held, (fn_tr, fs_tr), tangent)
        _, d_law = jax.jvp(law, (fn_tr, fs_tr), tangent)
        np.testing.assert_allclose(np.asarray(d_held), np.asarray(d_law))
    # Held stuck beyond the limit: the limit, in the direction of the trial force.
    stick = jnp.full(5, STICK)
    _, fs_stuck = forces_in_state(fn_tr, fs_tr, prop, failed, stick)
    limit = np.maximum(1.0 + np.asarray(fn_tr) * np.tan(np.radians(30.0)), 0.0)
    assert (np.abs(np.asarray(fs_stuck)) <= limit + 1e-12).all()
    np.testing.assert_allclose(np.asarray(fs_stuck)[[1, 4]], [limit[1], -limit[4]])
    bonded = prop._replace(bonded=jnp.ones(5, bool))
    _, fs_bonded = forces_in_state(fn_tr, fs_tr, bonded, failed, stick)
    np.testing.assert_allclose(np.asarray(fs_bonded), np.asarray(fs_tr))


def test_a_spring_with_strength_to_lose_is_elastic_in_the_iteration_until_it_fails():
    """SPEC's law: a contact that fails loses its cohesion and tensile strength. The
    Newton iteration holds a spring that has them elastic (held_elastic), and the
    sub-step's commit decides on its excess (excess_ratio) whether it fails: it never
    slips or opens while it keeps them. Once failed it is frictional, held or not; a
    clean joint (nothing to lose) slips within the iteration."""
    fn_tr = jnp.array([10.0, -4.0, 10.0, 10.0, 10.0])
    fs_tr = jnp.array([9.0, 0.0, 9.0, 9.0, 9.0])
    active = jnp.ones(5, bool)
    prop = _prop(c=3.0, t=2.0)
    prop = prop._replace(cohesion=prop.cohesion.at[4].set(0.0), tension=prop.tension.at[4].set(0.0))
    failed = jnp.array([False, False, True, False, False])
    lim = 10.0 * np.tan(np.radians(30.0))          # 5.77 without cohesion, 8.77 with
    fn, fs, st = mohr_coulomb(fn_tr, fs_tr, held_elastic(prop), failed, active)
    # beyond c + fn tan(phi) and beyond t: held; failed: slips on friction alone;
    # slot 3 as slot 0; a clean joint slips
    np.testing.assert_array_equal(np.asarray(st), [STICK, STICK, SLIP, STICK, SLIP])
    np.testing.assert_allclose(np.asarray(fs), [9.0, 0.0, lim, 9.0, lim])
    np.testing.assert_allclose(np.asarray(fn), fn_tr)
    # The law itself (what a sub-step commits): at its strength, or open in tension.
    fn, fs, st = mohr_coulomb(fn_tr, fs_tr, prop, failed, active)
    np.testing.assert_array_equal(np.asarray(st), [SLIP, OPEN, SLIP, SLIP, SLIP])
    np.testing.assert_allclose(np.asarray(fs), [3.0 + lim, 0.0, lim, 3.0 + lim, lim])


def test_excess_ratio_by_hand():
    """max(|fs| - max(c + fn tan(phi), 0), -fn - t) / (c + t), worked by hand with c = 10,
    t = 5, tan(phi) = 0.5."""
    one = jnp.ones(5)
    prop = SlotLaw(kn=one, ks=one, cohesion=10.0 * one, tension=5.0 * one, tanphi=0.5 * one,
                   bonded=jnp.array([False, False, False, False, True]))
    fn = jnp.array([20.0, -8.0, 20.0, 20.0, 20.0])
    fs = jnp.array([25.0, 0.0, 15.0, 25.0, 25.0])
    failed = jnp.array([False, False, False, True, False])
    r = np.asarray(excess_ratio(fn, fs, prop, failed))
    # shear: 25 - (10 + 10) = 5 over 15; tension: 8 - 5 = 3 over 15 (the shear limit
    # max(10 - 4, 0) = 6 not reached); within strength: 15 - 20 = -5 over 15; failed and
    # wall bonds have nothing to lose.
    np.testing.assert_allclose(r, [5.0 / 15.0, 3.0 / 15.0, -5.0 / 15.0, -1.0, -1.0])
    # The hysteresis band comes off the excess.
    np.testing.assert_allclose(np.asarray(excess_ratio(fn, fs, prop, failed, band=1.5))[:2],
                               [3.5 / 15.0, 1.5 / 15.0])
