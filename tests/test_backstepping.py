"""Adaptive backstepping (dscjax/controllers/backstepping.py) against independent references:
the hand-derived order-2 law, finite differences of the virtual controls along the nominal
closed loop, and closed-loop tracking at orders 3 and 4."""

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference_backstepping import HandBackstepping

import dscjax
from dscjax import config
from dscjax.closed_loop import initial_state, prepared, vector_field
from dscjax.controllers.backstepping import Backstepping, with_backstepping
from dscjax.reference import Sine

simulate_module = importlib.import_module("dscjax.simulate")


def _family2():
    """An order-2 plant whose f_1 and rho_1 have every term (so f_1', rho_1' are nontrivial)."""
    plant = dscjax.StrictFeedback.zeros(
        2, g=[1.3, 0.8], theta=[0.2, -0.1], x0=[0.1, -0.2], f_quad=[0.7, 0.3],
        f_sin=[0.4, 0.5], f_cross=[0.0, 0.6], rho_const=[0.2, 0.1], rho_quad=[0.3, 0.2],
        delta_sin=[0.1, 0.0], delta_quad=[0.0, 0.1])
    setup = dscjax.paper_example().replace(
        plant=plant, reference=Sine(amplitude=0.8, frequency=1.7, phase=0.3, offset=0.1))
    ctrl = Backstepping.from_dsc(
        setup.controller, g_nom=np.array([0.9]), k=np.array([3.0, 2.0]),
        gamma_g=np.array([2.0, 3.0]), eta=np.array([0.1, 0.2]), gamma_phi=np.array([1.5]),
        sigma=np.array([0.3]), eps=0.2, g_min=0.7)
    return dscjax.cast(setup.replace(controller=ctrl), jnp.float64)


def _random_point(rng, setup):
    n = setup.order
    st = setup.controller.init_state(setup.plant, setup.reference)
    st = st._replace(theta_hat=jnp.asarray(rng.normal(0, 0.5, n)),
                     phi_hat=jnp.asarray(rng.normal(1.0, 0.3, n - 1)),
                     zeta_hat=jnp.asarray(rng.uniform(0.3, 1.0)),
                     d_hat=jnp.asarray(rng.uniform(0.0, 1.0)))
    x = jnp.asarray(rng.normal(0, 0.6, n))
    t = jnp.asarray(rng.uniform(0, 10))
    return st, x, t


@pytest.mark.parametrize("which", ["paper", "family"])
def test_autodiff_law_equals_hand_derived_order2(which):
    setup = with_backstepping(dscjax.paper_example()) if which == "paper" else _family2()
    auto = setup.controller
    hand = HandBackstepping.of(auto)
    rng = np.random.default_rng(7)
    for _ in range(20):
        st, x, t = _random_point(rng, setup)
        u_a, info_a = auto.law(st, x, t, setup.plant, setup.reference)
        u_h, info_h = hand.law(st, x, t, setup.plant, setup.reference)
        # Tolerances: a few ulps of the terms summed (they are O(1)-O(100) here).
        assert abs(float(u_a) - float(u_h)) <= 1e-12 * (1.0 + abs(float(u_h)))
        np.testing.assert_allclose(info_a.extra.alpha_dot, info_h.extra.alpha_dot,
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(info_a.S, info_h.S, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(info_a.extra.ubar, info_h.extra.ubar, rtol=1e-12, atol=1e-12)


def test_closed_loop_derivative_equals_hand_derived_order2():
    """u' (the closed loop's linearisation of the law: one derivative more) agrees too."""
    setup = prepared(_family2())
    hand_setup = setup.replace(controller=HandBackstepping.of(setup.controller))
    field = jax.jit(vector_field)
    rng = np.random.default_rng(3)
    for _ in range(10):
        st, x, t = _random_point(rng, setup)
        X = initial_state(setup)._replace(x=x, ctrl=st, h=jnp.asarray(rng.normal()))
        dX_a, obs_a = field(t, X, setup)
        dX_h, obs_h = field(t, X, hand_setup)
        np.testing.assert_allclose(obs_a.u_dot, obs_h.u_dot, rtol=1e-12, atol=1e-11)
        for a, h in zip(jax.tree.leaves(dX_a), jax.tree.leaves(dX_h), strict=True):
            np.testing.assert_allclose(a, h, rtol=1e-12, atol=1e-12)


def _nominal_direction(setup, st, x, t):
    """(state', x', t' = 1) of the nominal closed loop, written independently of the module:
    the adaptive laws from `state_rate`, and x_j' = g_nom_j (x_(j+1) + theta_hat_gj f_j)."""
    ctrl, plant, ref = setup.controller, setup.plant, setup.reference
    _, info = ctrl.law(st, x, t, plant, ref)
    d_st = ctrl.state_rate(st, x, t, info, plant, ref)
    f = np.asarray(plant.f(x))
    xn, th, g = np.asarray(x), np.asarray(st.theta_hat), np.asarray(ctrl.g_nom)
    n = xn.shape[0]
    dx = np.array([g[j] * (xn[j + 1] + th[j] * f[j]) for j in range(n - 1)] + [0.0])
    return d_st, jnp.asarray(dx)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_virtual_control_derivatives_match_finite_differences(n):
    """alpha_m' from nested autodiff = 4th-order central difference of alpha_m along the
    nominal closed loop, for every stage m = 1..n-1."""
    setup = prepared(with_backstepping(dscjax.order_n_example(n)))
    ctrl, plant, ref = setup.controller, setup.plant, setup.reference
    rng = np.random.default_rng(11 + n)

    def alphas(st, x, t):
        return np.asarray(ctrl.law(st, x, t, plant, ref)[1].extra.alpha)

    for _ in range(3):
        st, x, t = _random_point(rng, setup)
        _, info = ctrl.law(st, x, t, plant, ref)
        auto = np.append(np.asarray(info.extra.phi_signal)[1:], float(info.extra.alpha_dot))
        d_st, dx = _nominal_direction(setup, st, x, t)
        h = 1e-3

        def at(s, st=st, d_st=d_st, x=x, dx=dx, t=t):
            moved = jax.tree.map(lambda a, b: a + s * b, st, d_st)
            return alphas(moved, x + s * dx, t + s)

        fd = (-at(2 * h) + 8 * at(h) - 8 * at(-h) + at(-2 * h)) / (12 * h)
        np.testing.assert_allclose(auto, fd, rtol=1e-7, atol=1e-7 * np.max(np.abs(fd)))


@pytest.mark.parametrize("n", [3, 4])
def test_backstepping_tracks_at_order_3_and_4(n):
    """Order 3 and 4 (the stable `order_n_example`): no divergence, error below 5 % of the
    reference amplitude after the first second, surfaces start at (about) zero."""
    setup = with_backstepping(dscjax.order_n_example(n))
    traj = dscjax.simulate(setup, t_final=3.0, dt=1e-3, save_every=500)
    assert not bool(traj.diverged)
    e_win = float(traj.metrics["linf_error_window"])
    assert e_win < 0.05, e_win
    assert float(traj.metrics["max_abs_u"]) < 20.0
    assert np.all(np.isfinite(np.asarray(traj.theta_hat)))


def test_changing_a_gain_does_not_recompile():
    setup = with_backstepping(dscjax.paper_example())
    dscjax.simulate(setup, t_final=0.01, dt=1e-3)
    size = simulate_module._simulate.top._cache_size()
    other = dscjax.params.set(setup, "controller.k", np.array([8.0, 0.5]))
    other = dscjax.params.set(other, "controller.g_nom", np.array([1.2]))
    dscjax.simulate(other, t_final=0.01, dt=1e-3)
    assert simulate_module._simulate.top._cache_size() == size


def test_config_round_trip_and_validation():
    setup = with_backstepping(dscjax.paper_example())
    d = config.to_dict(setup)
    assert d["controller"]["kind"] == "backstepping"
    back, _ = config.from_dict(d)
    assert isinstance(back.controller, Backstepping)
    for f in dataclasses.fields(Backstepping):
        np.testing.assert_array_equal(np.asarray(getattr(back.controller, f.name)),
                                      np.asarray(getattr(setup.controller, f.name)))
    bad = dict(d, controller=dict(d["controller"], g_nom=[-1.0]))
    with pytest.raises(dscjax.ConfigError, match=r"controller\.g_nom must be > 0"):
        dscjax.validate_setup(config.from_dict(bad)[0])
