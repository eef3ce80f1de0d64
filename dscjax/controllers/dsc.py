"""Adaptive dynamic surface control of order n, Section 2 of the paper, eqs. (13)-(32).

Per stage i the law forms a surface S_i, a virtual control x_(i+1)d and passes it through a
first-order filter tau_(i+1) z_(i+1)' + z_(i+1) = x_(i+1)d (18), (24). The filter derivative
z_i' = (x_id - z_i)/tau_i replaces the derivative of the virtual control, so no derivative of a
virtual control is ever taken: this is what removes backstepping's explosion of complexity.

Index conventions (0-based arrays, paper indices in the comments):
    k (n,)          k_1..k_n
    tau (n-1,)      tau_2..tau_n
    c (n-1,)        c_2..c_n
    gamma_g, eta (n,)       gamma_g1..gamma_g(n-1), gamma_gn; eta_1..eta_n     (17), (23), (31)
    gamma_phi, sigma (n-1,) gamma_phi1..gamma_phi(n-1); sigma_1..sigma_(n-1) (17), (23)
    state.z (n-1,)  z_2..z_n
    state.theta_hat (n,)    theta_hat_g1..theta_hat_g(n-1), theta_hat_n
    state.phi_hat (n-1,)    phi_hat_1..phi_hat_(n-1)
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, Literal, NamedTuple, get_args

import jax
import jax.numpy as jnp

from dscjax.controllers.adaptive import AdaptiveLaws, RobustTerm
from dscjax.controllers.base import ControlInfo
from dscjax.model import option, positive
from dscjax.reference import InitialOffset
from dscjax.xla import barrier

Variant = Literal["full", "no_dhat", "no_dhat_no_zeta"]
VARIANTS: tuple[str, ...] = get_args(Variant)
InitMode = Literal["paper", "linf", "zero_surfaces"]


class DSCState(NamedTuple):
    """Controller state of the DSC (see the module docstring for the index conventions)."""

    z: jax.Array  # (n-1,) filter outputs z_2..z_n
    theta_hat: jax.Array  # (n,) estimates of theta_i/g_i (i<n) and theta_n
    phi_hat: jax.Array  # (n-1,) estimates of 1/g_i
    zeta_hat: jax.Array  # () estimate of 1/beta = 1/(lam g_n), eq. (27)
    d_hat: jax.Array  # () estimate of the bound d of d_n, eq. (12)


class DSCExtra(NamedTuple):
    ubar: jax.Array  # () eq. (30)
    f: jax.Array  # (n,) f_i(xbar_i)
    phi_signal: jax.Array  # (n-1,) the signal multiplying phi_hat: y_r' then z_2'..z_(n-1)'
    z_dot: jax.Array  # (n-1,) filter derivatives z_2'..z_n'


class DSC(AdaptiveLaws):
    """Adaptive DSC with hysteresis compensation, eqs. (13)-(32).

    Traced: `AdaptiveLaws`' gains and estimates, tau (n-1,), c (n-1,), sat_width (the boundary
    layer of sat(S_n/width)), smooth_delta (the smooth saturation's corner, relative to
    sat_width), linf_decay_time (fade of the L-infinity initialisation's reference offset).

    Static choices:
        variant: "full"; "no_dhat" = no hysteresis compensation, the robust term and d_hat are
            dropped (d_hat = 0); "no_dhat_no_zeta" = additionally zeta_hat = 1, so u = ubar.
        robust_term: "sat" (sat(S_n/sat_width), the paper's simulation), "sgn" (eq. 30 as
            printed), or "smooth" (C-infinity saturation and |S_n| in (32): clean gradients;
            bias <= smooth_delta/2 and <= smooth_delta * sat_width).
        init: "paper" (c and initial estimates as given), "linf" (eqs. 67-68: all estimates 0,
            c_i = x_i(0), y_r shifted so that y_r(0) = x_1(0) by an offset decaying in
            linf_decay_time; then S_i(0) = 0 for all i), or "zero_surfaces" (estimates as given,
            c_i chosen so that S_i(0) = 0 for i >= 2).
    """

    # The gains and initial estimates of `AdaptiveLaws` come first, then:
    tau: jax.Array = positive()
    c: jax.Array
    sat_width: jax.Array = positive(default=0.01)
    smooth_delta: jax.Array = positive(default=0.1)
    linf_decay_time: jax.Array = positive(default=0.5)
    variant: Variant = option("full")
    robust_term: RobustTerm = option("sat")
    init: InitMode = option("paper")

    kind: ClassVar[str] = "dsc"

    def expected_shapes(self, n):
        return self.law_shapes(n) | dict(tau=(n - 1,), c=(n - 1,), linf_decay_time=())

    # -- structural switches -------------------------------------------------------------
    @property
    def compensates(self) -> bool:
        return self.variant == "full"

    @property
    def adapts_zeta(self) -> bool:
        return self.variant != "no_dhat_no_zeta"

    # -- initialisation --------------------------------------------------------------------
    def prepare(self, plant, reference):
        x0 = jnp.asarray(plant.x0)
        if self.init == "linf":
            estimates = ("theta_hat0", "phi_hat0", "zeta_hat0", "d_hat0")
            ctrl = dataclasses.replace(
                self, c=x0[1:], **{k: jnp.zeros_like(getattr(self, k)) for k in estimates})
            return ctrl, InitialOffset(reference, x0[0] - reference(jnp.zeros_like(x0[0])),
                                       self.linf_decay_time)
        if self.init == "zero_surfaces":
            x_d0 = self._initial_filters(plant, reference, zero_surfaces=True)
            return dataclasses.replace(self, c=x0[1:] - x_d0), reference
        return self, reference

    def _initial_filters(self, plant, reference, zero_surfaces=False):
        """z(0) = x_d(0) of (18), (24), computed stage by stage.

        With z_i(0) = x_id(0) the filter derivatives are zero at t = 0, so x_(i+1)d(0) needs
        only S_i(0). With zero_surfaces, c_i is taken so that S_i(0) = 0 for i >= 2.
        """
        x = jnp.asarray(plant.x0)
        yr, yr_dot = reference.derivatives(jnp.zeros_like(x[0]), 1)
        f, rho = plant.f(x), plant.rho(x)
        th, ph = self.theta_hat0, self.phi_hat0
        x_d = [self._virtual(0, x[0] - yr, f, rho, th, ph, yr_dot)]
        for i in range(1, x.shape[0] - 1):
            s_i = jnp.zeros_like(x[0]) if zero_surfaces else x[i] - x_d[i - 1] - self.c[i - 1]
            x_d.append(self._virtual(i, s_i, f, rho, th, ph, jnp.zeros_like(s_i)))
        return jnp.stack(x_d)

    def init_state(self, plant, reference):
        """z(0) = x_d(0); the estimates as given, but zeta_hat = 1 and d_hat = 0 where the
        variant does not adapt them."""
        zeta0 = self.zeta_hat0 if self.adapts_zeta else jnp.ones_like(self.zeta_hat0)
        d0 = self.d_hat0 if self.compensates else jnp.zeros_like(self.d_hat0)
        return DSCState(self._initial_filters(plant, reference), self.theta_hat0, self.phi_hat0,
                        zeta0, d0)

    # -- the law -----------------------------------------------------------------------------
    def law(self, state, x, t, plant, reference):
        """u = zeta_hat ubar, eqs. (13)-(30). Returns (u, ControlInfo)."""
        n = x.shape[0]
        yr, yr_dot = reference.derivatives(t, 1)
        f, rho = barrier((plant.f(x), plant.rho(x)))
        theta_hat, phi_hat = state.theta_hat, state.phi_hat

        s = [x[0] - yr]  # (13)
        z_dot = []
        x_d = self._virtual(0, s[0], f, rho, theta_hat, phi_hat, yr_dot)  # (16)
        for i in range(1, n):
            z_dot.append((x_d - state.z[i - 1]) / self.tau[i - 1])  # (18), (24), (42)
            s.append(x[i] - state.z[i - 1] - self.c[i - 1])  # (19), (25)
            if i < n - 1:
                x_d = self._virtual(i, s[i], f, rho, theta_hat, phi_hat, z_dot[-1])  # (22)

        d_hat = state.d_hat if self.compensates else jnp.zeros_like(state.d_hat)
        ubar = self._ubar(s[-1], theta_hat, f, rho, z_dot[-1], d_hat)  # (30)
        u = state.zeta_hat * ubar  # (28)
        # phi_hat multiplies y_r' in (16), then z_2'..z_(n-1)' in (22)
        extra = DSCExtra(ubar=ubar, f=f, phi_signal=jnp.stack([yr_dot] + z_dot[:-1]),
                         z_dot=jnp.stack(z_dot))
        return u, ControlInfo(yr=yr, S=jnp.stack(s), extra=extra)

    def decay_rates(self, state):
        """The filters (18), (24) decay at 1/tau_i."""
        return super().decay_rates(state)._replace(z=jnp.ones_like(state.z) / self.tau)

    def state_rate(self, state, x, t, info, plant, reference):
        """Filters (18), (24) and adaptive laws (17), (23), (29), (31), (32)."""
        theta_dot, phi_dot, zeta_dot, d_dot = self._rates(state, info)
        return DSCState(z=info.extra.z_dot, theta_hat=theta_dot, phi_hat=phi_dot,
                        zeta_hat=zeta_dot if self.adapts_zeta else jnp.zeros_like(zeta_dot),
                        d_hat=d_dot if self.compensates else jnp.zeros_like(d_dot))
