"""The hysteresis models whose state follows an ODE in u': the backlash-like model (4) of the
paper ("backlash", the default; its solution (5)-(6) in closed form) and Bouc-Wen
("bouc_wen"). Their |u'| may be smoothed (`smooth`), and their stiff decays are reported to
ETDRK4 (`decay_rate`).
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation as v
from dscjax.hysteresis.base import Hysteresis
from dscjax.integrate.solvers import rk4_steps
from dscjax.model import option, positive, smooth_abs


def _abs_du(model, du):
    """|u'|, or sqrt(u'^2 + delta^2) - delta when the model is `smooth`."""
    return smooth_abs(du, model.smooth_delta) if model.smooth else jnp.abs(du)


class Backlash(Hysteresis):
    """Backlash-like hysteresis w = P(u), eq. (4).

    Attributes:
        alpha: () rate at which w switches between its asymptotes, alpha > 0.
        lam: () slope lambda of the asymptotes, lam > psi.
        psi: () slope psi of the branches at reversal.
        w0: () initial output w(0); the paper does not give it, the default is 0.
        smooth_delta: () width of the smooth |u'| used when `smooth` is True (units of u').
        smooth: static; replace |u'| by sqrt(u'^2 + delta^2) - delta (bias <= delta in |u'|).
    """

    alpha: jax.Array = positive()
    lam: jax.Array = positive()
    psi: jax.Array
    w0: jax.Array = 0.0
    smooth_delta: jax.Array = positive(default=1e-2)
    smooth: bool = option(False)

    kind: ClassVar[str] = "backlash"
    title: ClassVar[str] = "Backlash-like hysteresis (4)"
    default_sweep: ClassVar[tuple[str, ...]] = ("alpha", "lam", "psi")

    def validate(self, prefix):
        super().validate(prefix)
        lam, psi = np.asarray(self.lam, float), np.asarray(self.psi, float)
        if not np.all(lam > psi):
            raise v.ConfigError(f"{prefix}.lam must be > {prefix}.psi (got lam={v.fmt(lam)}, "
                                f"psi={v.fmt(psi)})")

    def init_state(self, u0=None):
        """The model's state at t = 0: for (4) the output itself, w(0) = w0 (u0 unused)."""
        return self.w0

    def output(self, u, w):
        """The output w = P(u): for (4) the state itself."""
        return w

    def rate(self, u, du, w):
        """w' of eq. (4) given u, u' and w."""
        return self.alpha * _abs_du(self, du) * (self.lam * u - w) + self.psi * du

    def decay_rate(self, u, du, w):
        """The rate a >= 0 of the linear decay -a w in eq. (4): alpha |u'|. It makes the loop
        stiff where |u'| is large; the exponential step integrates it exactly."""
        return self.alpha * _abs_du(self, du)

    def jump(self, u_from, u_to, w):
        """w after u steps from u_from to u_to: the closed form (5)-(6) along the step (the
        exact |u'|, whatever `smooth` says: a step has no rate)."""
        direction = jnp.where(u_to >= u_from, 1.0, -1.0)
        return closed_form(u_to, u_from, w, self.alpha, self.lam, self.psi, direction)

    def effective_slope(self):
        """lam of (5): w = lam u + d_1(u)."""
        return jnp.asarray(self.lam)

    def d1_limits(self):
        """Limits (7)-(8) of d_1: (lam-psi)/alpha as u -> -inf, -(lam-psi)/alpha as u -> +inf."""
        bound = (self.lam - self.psi) / self.alpha
        return bound, -bound


def closed_form(u, u0, w0, alpha, lam, psi, direction):
    """w(u) (shaped like u) by the solution (5)-(6) of eq. (4) on a monotone segment of u from
    (u0, w0), direction +1 rising, -1 falling. With s = sgn(u'), d_1 = w - lam u is

        d_1(u) = (w0 - lam u0) E + (psi - lam)/(alpha s) (1 - E),  E = e^{-alpha s (u - u0)},

    (6) with the paper's sgn(u) read as sgn(u') (docs/paper-readings.md)."""
    s = direction
    decay = jnp.exp(-alpha * s * (u - u0))
    d1 = (w0 - lam * u0) * decay + (psi - lam) / (alpha * s) * (1.0 - decay)
    return lam * u + d1


def _pow_abs(h, n, at_zero=0.0):
    """|h|^n with finite derivatives at h = 0 (double where), `at_zero` there (0; for
    |h|^(n-1), n >= 1: 1 if n = 1)."""
    zero = h == 0
    safe = jnp.where(zero, 1.0, jnp.abs(h))
    return jnp.where(zero, at_zero, safe ** n)


# RK4 substeps in u of a Bouc-Wen jump: a sampled controller's input moves by |u'| Ts per
# sample, a short segment of the curve
JUMP_SUBSTEPS = 16


class BoucWen(Hysteresis):
    """Bouc-Wen hysteresis: w = a u + b h, h' = A u' - beta |u'| |h|^(n-1) h - gamma u' |h|^n.

    For beta >= |gamma| and |h0| <= h_max = (A / (beta + gamma))^(1/n), |h| <= h_max, so
    |d_1| = |b h| <= |b| h_max. Defaults: the paper's slope 1.432 and nearly its offset.

    Attributes:
        a: () slope of the elastic part, > 0 (the effective slope).
        b: () weight of the hysteretic part.
        A: () > 0.
        beta, gamma: () with beta + gamma > 0.
        n: () exponent, >= 1 (below 1, |h|^(n-1) h is not Lipschitz at h = 0).
        h0: () h(0).
        smooth_delta, smooth: as for `Backlash`: |u'| -> sqrt(u'^2 + delta^2) - delta.
    """

    a: jax.Array = positive(default=1.432)
    b: jax.Array = 1.0
    A: jax.Array = positive(default=1.0)
    beta: jax.Array = 0.6
    gamma: jax.Array = 0.15
    n: jax.Array = 1.0
    h0: jax.Array = 0.0
    smooth_delta: jax.Array = positive(default=1e-2)
    smooth: bool = option(False)

    kind: ClassVar[str] = "bouc_wen"
    title: ClassVar[str] = "Bouc-Wen"
    default_sweep: ClassVar[tuple[str, ...]] = ("a", "b", "beta", "gamma")

    def validate(self, prefix):
        super().validate(prefix)
        beta, gamma = np.asarray(self.beta, float), np.asarray(self.gamma, float)
        if not np.all(beta + gamma > 0):
            raise v.ConfigError(f"{prefix}.beta + {prefix}.gamma must be > 0 (got "
                                f"beta={v.fmt(beta)}, gamma={v.fmt(gamma)})")
        if not np.all(np.asarray(self.n, float) >= 1):
            raise v.ConfigError(f"{prefix}.n must be >= 1 (got {v.fmt(self.n)}): below 1, "
                                f"|h|^(n-1) h is not Lipschitz at h = 0")

    def init_state(self, u0=None):
        return self.h0

    def output(self, u, h):
        return self.a * u + self.b * h

    def rate(self, u, du, h):
        hn = _pow_abs(h, self.n)
        return self.A * du - self.beta * _abs_du(self, du) * jnp.sign(h) * hn \
            - self.gamma * du * hn

    def decay_rate(self, u, du, h):
        """(beta |u'| + gamma u' sgn h) |h|^(n-1) where >= 0: the decay -(...) h in `rate`."""
        k = (self.beta * _abs_du(self, du) + self.gamma * du * jnp.sign(h)) \
            * _pow_abs(h, self.n - 1.0, jnp.where(self.n == 1, 1.0, 0.0))
        return jnp.maximum(k, 0.0)

    def jump(self, u_from, u_to, h):
        """h after a step of u: dh/du = A - beta s |h|^(n-1) h - gamma |h|^n, s = sgn(u_to -
        u_from), integrated by RK4 in u over JUMP_SUBSTEPS substeps (the exact |u'|)."""
        s = jnp.where(u_to >= u_from, 1.0, -1.0)
        du = (u_to - u_from) / JUMP_SUBSTEPS

        def slope(_u, hh, _args):
            hn = _pow_abs(hh, self.n)
            return self.A - self.beta * s * jnp.sign(hh) * hn - self.gamma * hn

        return rk4_steps(slope, 0.0, h, du, JUMP_SUBSTEPS, None)

    def h_max(self):
        """(A / (beta + gamma))^(1/n): the bound of |h| for beta >= |gamma|."""
        return (self.A / (self.beta + self.gamma)) ** (1.0 / self.n)

    def effective_slope(self):
        return jnp.asarray(self.a)

    def d1_limits(self):
        """-b h_max as u -> -inf and +b h_max as u -> +inf (h tends to -+h_max)."""
        bound = self.b * self.h_max()
        return -bound, bound
