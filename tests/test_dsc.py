"""DSC of any order: initialisations, variants, higher orders, strict-feedback checks."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscjax


@pytest.mark.parametrize("n", [2, 3])
def test_linf_initialisation_zeroes_every_surface(n):
    setup = dscjax.paper_example(init="linf") if n == 2 else dscjax.order_n_example(3)
    if n == 3:
        setup = setup.replace(controller=dataclasses.replace(setup.controller, init="linf"))
    tr = dscjax.simulate(setup, 0.2, 1e-3)
    np.testing.assert_allclose(np.asarray(tr.S[0]), np.zeros(n), atol=1e-14)
    # (67): all estimates start at 0; (68): y_r(0) = x_1(0), c_i = x_i(0)
    assert float(tr.theta_hat[0].sum() ** 2 + tr.phi_hat[0].sum() ** 2) == 0.0
    assert float(tr.zeta_hat[0]) == 0.0 and float(tr.d_hat[0]) == 0.0
    assert float(tr.yr[0]) == pytest.approx(float(setup.plant.x0[0]), abs=1e-15)
    assert float(tr.u[0]) == 0.0


def test_linf_reference_offset_fades():
    tr = dscjax.simulate(dscjax.paper_example(init="linf"), 5.0, 1e-3, save_every=100)
    t = np.asarray(tr.t)
    # y_r = sin t + 0.08 exp(-t / 0.5)
    np.testing.assert_allclose(np.asarray(tr.yr), np.sin(t) + 0.08 * np.exp(-t / 0.5),
                               atol=1e-14)


def test_zero_surfaces_initialisation():
    s = dscjax.paper_example(init="zero_surfaces")
    tr = dscjax.simulate(s, 0.1, 1e-3)
    assert float(tr.S[0, 1]) == pytest.approx(0.0, abs=1e-14)
    assert float(tr.S[0, 0]) == pytest.approx(0.08)  # S_1(0) = x_1(0) - y_r(0) unchanged


def test_paper_example_tracks(traj20):  # conftest's run over 20 s at dt = 1 ms
    m = {k: float(v) for k, v in traj20.metrics.items()}
    assert m["linf_error"] == pytest.approx(0.08)  # pinned by S_1(0) = 0.08
    assert m["linf_error_window"] < 0.03
    assert 1.0 < m["max_abs_u"] < 20.0


@pytest.mark.parametrize("n", [3, 4])
def test_higher_orders_run_bounded_and_track(n):
    tr = dscjax.simulate(dscjax.order_n_example(n), 20.0, 1e-3, save_every=50)
    assert not bool(tr.diverged)
    assert float(tr.metrics["linf_error_window"]) < 0.06
    assert np.abs(np.asarray(tr.x)).max() < 5.0
    late = np.asarray(tr.t) > 10.0
    assert np.abs(np.asarray(tr.e))[late].max() < 0.06


def test_variant_without_dhat_keeps_dhat_zero():
    tr = dscjax.simulate(dscjax.paper_example(variant="no_dhat"), 5.0, 1e-3, save_every=10)
    assert np.all(np.asarray(tr.d_hat) == 0.0)
    assert np.any(np.diff(np.asarray(tr.zeta_hat)) != 0.0)


def test_variant_without_dhat_and_zeta_gives_u_equal_ubar():
    setup = dscjax.paper_example(variant="no_dhat_no_zeta")
    tr = dscjax.simulate(setup, 2.0, 1e-3, save_every=10)
    assert np.all(np.asarray(tr.zeta_hat) == 1.0)
    assert np.all(np.asarray(tr.d_hat) == 0.0)
    # the law at every saved state: u = zeta_hat ubar with zeta_hat = 1 is ubar itself, and
    # it is the u the loop applied
    s = dscjax.prepared(setup)

    def law(ctrl_state, x, t):
        u, info = s.controller.law(ctrl_state, x, t, s.plant, s.reference)
        return u, info.extra.ubar

    u, ubar = jax.vmap(law)(tr.ctrl, tr.x, tr.t)
    np.testing.assert_array_equal(np.asarray(u), np.asarray(ubar))
    np.testing.assert_allclose(np.asarray(u), np.asarray(tr.u), rtol=0, atol=1e-12)
    assert np.ptp(np.asarray(ubar)) > 1.0  # a real control signal, not a constant


def test_check_strict_feedback_rejects_future_states():
    def f(x, p):
        return jnp.stack([x[0] * x[1], x[1]])  # f_1 depends on x_2: not strict feedback

    def zeros(x, *a):
        return jnp.zeros(2)

    plant = dscjax.CustomPlant(jnp.ones(2), jnp.zeros(2), jnp.zeros(2), {}, f, zeros, zeros,
                               lambda t, p: 0.0)
    with pytest.raises(ValueError, match="f_1 depends on x_2"):
        dscjax.check_strict_feedback(plant)


def test_custom_plant_reproduces_the_paper_plant(paper_setup):
    def f(x, p):
        return jnp.stack([x[0] ** 2, 0.0 * x[1]])

    def rho(x, p):
        return jnp.stack([0.2 + 0.0 * x[0], 0.1 * (x[0] ** 2 + x[1] ** 2)])

    def delta(x, t, p):
        return jnp.stack([p["a"] * jnp.sin(x[1]), 0.1 * (x[0] ** 2 + x[1] ** 2) * jnp.sin(t) ** 3])

    def dbar(t, p):
        return 0.0 * t

    plant = dscjax.CustomPlant(jnp.ones(2), jnp.array([0.1, 0.0]), jnp.array([0.08, 0.1]),
                               {"a": jnp.array(0.2)}, f, rho, delta, dbar)
    a = dscjax.simulate(paper_setup, 2.0, 1e-3, save_every=100)
    b = dscjax.simulate(paper_setup.replace(plant=plant), 2.0, 1e-3, save_every=100)
    np.testing.assert_allclose(np.asarray(a.x), np.asarray(b.x), atol=1e-12)
