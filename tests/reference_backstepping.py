"""The order-2 adaptive backstepping law written out by hand, the tests' oracle for the
nested-autodiff law of dscjax/controllers/backstepping.py (tests/test_backstepping.py).

`HandBackstepping` is `Backstepping` with this law, so that a whole closed loop can run on it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from dscjax.controllers.backstepping import Backstepping, _Chain


def law_order2_by_hand(ctrl: Backstepping, state, x, t, plant, reference):
    """The order-2 backstepping law with alpha_1' written out by the chain rule.

    alpha_1 = -theta_hat_g1 f_1 - z_1 rho_1^2 / (2 eps g_min) - k_1 z_1 + phi_hat_1 y_r',
    z_1 = x_1 - y_r. Its derivative along the nominal closed loop is

        alpha_1' = dalpha_1/dx_1 * g_nom_1 (x_2 + theta_hat_g1 f_1)     (nominal x_1')
                 - f_1 * theta_hat_g1' + y_r' * phi_hat_1'              (adaptive laws)
                 + (k_1 + rho_1^2 / (2 eps g_min)) y_r' + phi_hat_1 y_r''  (reference)
        dalpha_1/dx_1 = -theta_hat_g1 f_1' - (rho_1^2 + 2 z_1 rho_1 rho_1') / (2 eps g_min) - k_1
        theta_hat_g1' = gamma_g1 (f_1 z_1 - eta_1 theta_hat_g1)               (17)
        phi_hat_1' = -gamma_phi1 (y_r' z_1 + sigma_1 phi_hat_1)               (17)

    with f_1', rho_1' (d/dx_1) by `jax.grad` of the plant's functions.
    """
    if x.shape[0] != 2:
        raise ValueError(f"law_order2_by_hand is for order n = 2 (got n={x.shape[0]})")
    eps_g = ctrl.eps * ctrl.g_min
    yr, yr_dot, yr_ddot = reference.derivatives(t, 2)
    f, rho = plant.f(x), plant.rho(x)
    f1, rho1 = f[0], rho[0]

    def stage1(name):
        return lambda x1: getattr(plant, name)(jnp.stack([x1, x[1]]))[0]

    df1 = jax.grad(stage1("f"))(x[0])
    drho1 = jax.grad(stage1("rho"))(x[0])
    th1, ph1 = state.theta_hat[0], state.phi_hat[0]
    k1 = ctrl.k[0]

    z1 = x[0] - yr
    alpha1 = -th1 * f1 - z1 * rho1**2 / (2.0 * eps_g) - k1 * z1 + ph1 * yr_dot
    dalpha_dx1 = -th1 * df1 - (rho1**2 + 2.0 * z1 * rho1 * drho1) / (2.0 * eps_g) - k1
    x1_dot_nominal = ctrl.g_nom[0] * (x[1] + th1 * f1)
    th1_dot = ctrl.gamma_g[0] * (f1 * z1 - ctrl.eta[0] * th1)
    ph1_dot = -ctrl.gamma_phi[0] * (yr_dot * z1 + ctrl.sigma[0] * ph1)
    alpha1_dot = (dalpha_dx1 * x1_dot_nominal - f1 * th1_dot + yr_dot * ph1_dot
                  + (k1 + rho1**2 / (2.0 * eps_g)) * yr_dot + ph1 * yr_ddot)
    z2 = x[1] - alpha1
    chain = _Chain(z=[z1], alpha=[alpha1], alpha_dot=[yr_dot], f=f, rho=rho, yr=yr)
    return ctrl._last_stage(state, z2, alpha1_dot, chain)


class HandBackstepping(Backstepping):
    """`Backstepping` whose law is `law_order2_by_hand` (order n = 2 only)."""

    def law(self, state, x, t, plant, reference):
        return law_order2_by_hand(self, state, x, t, plant, reference)

    @classmethod
    def of(cls, ctrl: Backstepping) -> HandBackstepping:
        """The same controller (every field) with the hand-written law."""
        return cls(**{f.name: getattr(ctrl, f.name) for f in dataclasses.fields(ctrl)})
