"""Adaptive backstepping of order n: the baseline the paper compares the DSC with (Remark 6).

The paper's law (79) is garbled, so this is standard adaptive backstepping with the DSC's
parameterisation, robust terms and adaptive laws (docs/reproduction.md): the two controllers
differ in ONE thing, the exact derivative alpha_(i-1)' of the virtual control where the DSC has
its filter derivative z_i' (18), (24). With 0-based arrays and paper indices in the text:

    z_1 = x_1 - y_r,  z_i = x_i - alpha_(i-1) (no filter, no c_i),  alpha_0 = y_r
    alpha_i = -theta_hat_gi f_i - z_i rho_i^2 / (2 eps g_min) - k_i z_i + phi_hat_i alpha_(i-1)'
    u = zeta_hat ubar,  ubar = -k_n z_n - theta_hat_n f_n - z_n rho_n^2 / (2 eps) + alpha_(n-1)'
                               - sat(z_n / sat_width) d_hat

alpha_(i-1)' is taken by the chain rule along the NOMINAL closed loop (the adaptive laws,
y_r^(k+1), and x_j' = g_nom_j (x_(j+1) + theta_hat_gj f_j)), by n-1 nested forward-mode
derivatives (`jax.linearize`), never written out: the "explosion of complexity" the DSC avoids.
As in (79), no cross term -z_(i-1) in alpha_i and no damping of the nominal model's mismatch.
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dscjax.controllers.adaptive import AdaptiveLaws, RobustTerm
from dscjax.controllers.base import ControlInfo
from dscjax.model import option, positive


class BacksteppingState(NamedTuple):
    """Controller state: the adaptive estimates only (no filters)."""

    theta_hat: jax.Array  # (n,) estimates of theta_i/g_i (i<n) and theta_n
    phi_hat: jax.Array  # (n-1,) estimates of 1/g_i
    zeta_hat: jax.Array  # () estimate of 1/beta = 1/(lam g_n), eq. (27)
    d_hat: jax.Array  # () estimate of the bound d of d_n, eq. (12)


class BacksteppingExtra(NamedTuple):
    ubar: jax.Array  # () as eq. (30)
    f: jax.Array  # (n,) f_i(xbar_i)
    phi_signal: jax.Array  # (n-1,) signals multiplying phi_hat: alpha_0' = y_r', ..., alpha_(n-2)'
    alpha: jax.Array  # (n-1,) virtual controls alpha_1..alpha_(n-1)
    alpha_dot: jax.Array  # () alpha_(n-1)', the exact derivative used in ubar


class _Chain(NamedTuple):
    """Per-stage values at one point (lists of scalars, stage order)."""

    z: list  # z_1..z_m
    alpha: list  # alpha_1..alpha_m
    alpha_dot: list  # alpha_0'..alpha_(m-1)' (the signals multiplying phi_hat_1..phi_hat_m)
    f: jax.Array  # (n,)
    rho: jax.Array  # (n,)
    yr: jax.Array  # () y_r(t)


class Backstepping(AdaptiveLaws):
    """Adaptive backstepping of any order n with hysteresis compensation (module docstring).

    Traced: the DSC's gains and initial estimates but tau and c (`AdaptiveLaws`), and g_nom
    (n-1,), the nominal g_j of the chain rule.

    Static choices:
        robust_term: "sat" (sat(z_n/sat_width), as the paper's simulation), "sgn" or "smooth"
            (as `DSC.robust_term`).

    Example:
        >>> import dscjax
        >>> from dscjax.controllers.backstepping import with_backstepping
        >>> setup = with_backstepping(dscjax.paper_example())
        >>> setup.controller.kind
        'backstepping'
    """

    # The gains and initial estimates of `AdaptiveLaws` come first, then:
    g_nom: jax.Array = positive()
    sat_width: jax.Array = positive(default=0.01)
    smooth_delta: jax.Array = positive(default=0.1)
    robust_term: RobustTerm = option("sat")

    kind: ClassVar[str] = "backstepping"

    @classmethod
    def from_dsc(cls, dsc, **changes) -> Backstepping:
        """The backstepping controller with a DSC's gains and initial estimates.

        The filter constants tau and the surface constants c have no counterpart and are
        dropped; g_nom defaults to g_min for every stage.
        """
        m = np.shape(dsc.phi_hat0)[0]
        shared = {k: getattr(dsc, k) for k in dsc.law_shapes(m + 1)}  # AdaptiveLaws' fields
        return cls(**shared | dict(
            g_nom=np.full(m, np.asarray(dsc.g_min)).astype(np.asarray(dsc.k).dtype),
            robust_term=dsc.robust_term) | changes)

    def expected_shapes(self, n):
        return self.law_shapes(n) | dict(g_nom=(n - 1,))

    def init_state(self, plant, reference):
        return BacksteppingState(self.theta_hat0, self.phi_hat0, self.zeta_hat0, self.d_hat0)

    # The virtual controls (alpha_(i+1) = _virtual with v_i = alpha_i'), ubar and the adaptive
    # laws are the DSC's (`AdaptiveLaws`), with z_i in place of S_i.

    # -- the chain of virtual controls and their exact derivatives ----------------------------
    # Inside the nested derivatives every per-stage quantity is a scalar of a tuple (per-stage
    # code): alpha_m is differentiated with respect to the estimates of stages 1..m, x_1..x_m
    # and t only; the other estimates and states are closed over. (f and rho are still
    # evaluated for all n stages once, at the innermost level, through the plant's interface.)
    def _alpha(self, m, th, ph, xs, t, x_rest, plant, reference):
        """alpha_m and the chain below it (m >= 1), from per-stage scalars.

        th, ph, xs: the first m estimates theta_hat_g, phi_hat and states x; x_rest the states
        x_(m+1)..x_n (constants here: f_i and rho_i for i <= m do not depend on them).
        """
        if m == 1:
            x = jnp.stack(list(xs) + list(x_rest))
            f, rho = plant.f(x), plant.rho(x)
            yr, yr_dot = jax.jvp(reference.__call__, (t,), (jnp.ones_like(t),))
            chain = _Chain(z=[], alpha=[], alpha_dot=[yr_dot], f=f, rho=rho, yr=yr)
            prev = yr
        else:
            prev, prev_dot, chain = self._alpha_and_rate(
                m - 1, th[:-1], ph[:-1], xs[:-1], t, (xs[-1],) + tuple(x_rest), plant, reference)
            chain = chain._replace(alpha_dot=chain.alpha_dot + [prev_dot])
        z_m = xs[m - 1] - prev  # (13), and z_i = x_i - alpha_(i-1)
        a_m = self._virtual(m - 1, z_m, chain.f, chain.rho, th, ph, chain.alpha_dot[-1])
        return a_m, chain._replace(z=chain.z + [z_m], alpha=chain.alpha + [a_m])

    def _alpha_and_rate(self, m, th, ph, xs, t, x_rest, plant, reference):
        """(alpha_m, alpha_m', chain): alpha_m' exact along the nominal closed loop, by one
        `jax.linearize` of alpha_m (m nested derivatives in all); its primal pass yields the
        chain, from which the tangent (the nominal rates) is built."""

        def alpha_m(th_, ph_, xs_, t_):
            return self._alpha(m, th_, ph_, xs_, t_, x_rest, plant, reference)

        a_m, lin, chain = jax.linearize(alpha_m, th, ph, xs, t, has_aux=True)
        f, z, v = chain.f, chain.z, chain.alpha_dot
        th_dot = tuple(self._theta_rate(i, f[i], z[i], th[i]) for i in range(m))
        ph_dot = tuple(self._phi_rate(i, v[i], z[i], ph[i]) for i in range(m))
        x_next = tuple(xs[1:]) + (x_rest[0],)
        xs_dot = tuple(self.g_nom[j] * (x_next[j] + th[j] * f[j]) for j in range(m))
        return a_m, lin(th_dot, ph_dot, xs_dot, jnp.ones_like(t)), chain

    # -- the law ------------------------------------------------------------------------------
    def law(self, state, x, t, plant, reference):
        """(u, ControlInfo): u = zeta_hat ubar with alpha_(n-1)' exact, as eqs. (28), (30).

        The automatic law is an inner `jax.jit`: the loop traces the law at every RK4 stage,
        and JAX then traces the n-1 nested linearisations once; XLA inlines it (same results).
        """
        return _law_jit(self, state, x, t, plant, reference)

    def plain_law(self, state, x, t, plant, reference):
        """The automatic law without the inner jit (same values as `law`)."""
        m = x.shape[0] - 1
        th = tuple(state.theta_hat[i] for i in range(m))
        ph = tuple(state.phi_hat[i] for i in range(m))
        xs = tuple(x[i] for i in range(m + 1))
        a_prev, a_dot, chain = self._alpha_and_rate(m, th, ph, xs[:m], t, xs[m:], plant,
                                                    reference)
        return self._last_stage(state, x[m] - a_prev, a_dot, chain)  # z_n = x_n - alpha_(n-1)

    def _last_stage(self, state, z_n, a_dot, chain):
        f, rho = chain.f, chain.rho
        ubar = self._ubar(z_n, state.theta_hat, f, rho, a_dot, state.d_hat)  # as (30)
        u = state.zeta_hat * ubar  # (28)
        z = jnp.stack(chain.z + [z_n])
        extra = BacksteppingExtra(ubar=ubar, f=f, phi_signal=jnp.stack(chain.alpha_dot),
                                  alpha=jnp.stack(chain.alpha), alpha_dot=a_dot)
        return u, ControlInfo(yr=chain.yr, S=z, extra=extra)

    def state_rate(self, state, x, t, info, plant, reference):
        """Adaptive laws (17), (23), (29), (31), (32) with z_i for S_i, alpha_(i-1)' for z_i'."""
        return BacksteppingState(*self._rates(state, info))


def with_backstepping(setup, **changes):
    """The setup with its DSC replaced by backstepping with the same gains (`from_dsc`)."""
    return setup.replace(controller=Backstepping.from_dsc(setup.controller, **changes))


_law_jit = jax.jit(Backstepping.plain_law)
