"""The parameterisation and adaptive laws the DSC and the backstepping baseline share.

Both controllers derive from `AdaptiveLaws` (the same gains, estimates and robust term) and
differ only in their surfaces (S_i, or z_i = x_i - alpha_(i-1): `s` below) and in the signal
v_i that multiplies phi_hat_i (a filter derivative, or alpha_i').
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp

from dscjax.controllers.base import Controller
from dscjax.model import nonnegative, positive, sat, smooth_abs, smooth_sat

ALL = slice(None)  # stage index selecting every stage at once (the vectorised laws)
# The switching function of the robust term: sgn(s_n) as printed in (30), sat(s_n/width) as
# in the paper's simulation, or a smooth saturation (C-infinity, for RK4's order and gradients).
RobustTerm = Literal["sat", "sgn", "smooth"]


class AdaptiveLaws(Controller):
    """Formulas (16), (22), (30) and the adaptive laws (17), (23), (29), (31), (32), with the
    gains and initial estimates they read (shapes for order n; paper indices).

    Attributes:
        k: (n,) gains k_1..k_n of (16), (22), (30).
        gamma_g, eta: (n,) rates and leakages of theta_hat, (17), (23), (31).
        gamma_phi, sigma: (n-1,) rates and leakages of phi_hat, (17), (23).
        gamma_zeta, eta_zeta: () rate and leakage of zeta_hat, (29).
        gamma_d, eta_d: () rate and leakage of d_hat, (32).
        eps: () the epsilon of the rho^2/(2 eps) terms; g_min: () Assumption 4's bound.
        theta_hat0 (n,), phi_hat0 (n-1,), zeta_hat0 (), d_hat0 (): initial estimates.
    Each controller also declares (with defaults, so after its own fields) the robust term's
    `sat_width`, `smooth_delta` and the static choice `robust_term`.
    """

    k: jax.Array = positive()
    gamma_g: jax.Array = positive()
    eta: jax.Array = nonnegative()
    gamma_phi: jax.Array = positive()
    sigma: jax.Array = nonnegative()
    gamma_zeta: jax.Array = positive()
    eta_zeta: jax.Array = nonnegative()
    gamma_d: jax.Array = positive()
    eta_d: jax.Array = nonnegative()
    eps: jax.Array = positive()
    g_min: jax.Array = positive()
    theta_hat0: jax.Array
    phi_hat0: jax.Array
    zeta_hat0: jax.Array
    d_hat0: jax.Array
    sat_width: eqx.AbstractVar[jax.Array]
    smooth_delta: eqx.AbstractVar[jax.Array]
    robust_term: eqx.AbstractVar[RobustTerm]

    def law_shapes(self, n: int) -> dict[str, tuple[int, ...]]:
        """Shapes of the shared fields for order n (`expected_shapes` adds the others)."""
        m = n - 1
        return dict(k=(n,), gamma_g=(n,), eta=(n,), gamma_phi=(m,), sigma=(m,), gamma_zeta=(),
                    eta_zeta=(), gamma_d=(), eta_d=(), eps=(), g_min=(), theta_hat0=(n,),
                    phi_hat0=(m,), zeta_hat0=(), d_hat0=(), sat_width=(), smooth_delta=())

    def _robust(self, s_n):
        """The robust term's switching function: sgn(s_n) or its saturated replacement."""
        if self.robust_term == "sgn":
            return jnp.sign(s_n)
        if self.robust_term == "smooth":
            return smooth_sat(s_n / self.sat_width, self.smooth_delta)
        return sat(s_n / self.sat_width)

    def _abs_surface(self, s_n):
        """|s_n| in the d_hat law (32), smoothed along with the robust term."""
        if self.robust_term == "smooth":
            return smooth_abs(s_n, self.smooth_delta * self.sat_width)
        return jnp.abs(s_n)

    def _virtual(self, i, s_i, f, rho, theta_hat, phi_hat, v_i):
        """Virtual control of (0-based) stage i, eqs. (16) and (22)."""
        robust = s_i * rho[i] ** 2 / (2.0 * self.eps * self.g_min)
        return -theta_hat[i] * f[i] - robust - self.k[i] * s_i + phi_hat[i] * v_i

    def _ubar(self, s_n, theta_hat, f, rho, v_n, d_hat):
        """ubar of eq. (30), with no 1/g_min in the rho_n term (as printed)."""
        n = f.shape[0]
        return (-self.k[n - 1] * s_n - theta_hat[n - 1] * f[n - 1]
                - s_n * rho[n - 1] ** 2 / (2.0 * self.eps) + v_n
                - self._robust(s_n) * d_hat)

    def _theta_rate(self, i, f_i, s_i, theta_hat_i):
        """theta_hat_i' of (17), (23), (31); i = ALL gives every stage."""
        return self.gamma_g[i] * (f_i * s_i - self.eta[i] * theta_hat_i)

    def _phi_rate(self, i, v_i, s_i, phi_hat_i):
        """phi_hat_i' of (17), (23); i = ALL gives every stage."""
        return -self.gamma_phi[i] * (v_i * s_i + self.sigma[i] * phi_hat_i)

    def _rates(self, state, info):
        """(theta_hat', phi_hat', zeta_hat', d_hat') of every stage, from the law's `info`."""
        s, e = info.S, info.extra
        s_n = s[-1]
        return (self._theta_rate(ALL, e.f, s, state.theta_hat),
                self._phi_rate(ALL, e.phi_signal, s[:-1], state.phi_hat),
                -self.gamma_zeta * (e.ubar * s_n + self.eta_zeta * state.zeta_hat),  # (29)
                self.gamma_d * (self._abs_surface(s_n) - self.eta_d * state.d_hat))  # (32)
