"""Backlash-like hysteresis, eq. (4)-(8) of the paper (Su et al. 2000).

    w' = alpha |u'| (lam u - w) + psi u',      lam > psi, alpha > 0.

In the closed loop w is a state; u' is supplied by the closed loop (a forward-mode derivative
of the control law along the vector field, see `closed_loop.py`). On a segment where u is
monotone the equation is linear in u and has the closed form (5)-(6), implemented in
`closed_form` as the test oracle.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation as v
from dscjax._smooth import smooth_abs
from dscjax.model import Model, option, positive


class Backlash(Model):
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

    def validate(self, prefix):
        super().validate(prefix)
        lam, psi = np.asarray(self.lam, float), np.asarray(self.psi, float)
        if not np.all(lam > psi):
            raise v.ConfigError(f"{prefix}.lam must be > {prefix}.psi (got lam={v.fmt(lam)}, "
                                f"psi={v.fmt(psi)})")

    def init_state(self):
        """The model's state at t = 0: for (4) the output itself, w(0) = w0."""
        return self.w0

    def output(self, u, w):
        """The output w = P(u): for (4) the state itself."""
        return w

    def rate(self, u, du, w):
        """w' of eq. (4) given u, u' and w."""
        abs_du = smooth_abs(du, self.smooth_delta) if self.smooth else jnp.abs(du)
        return self.alpha * abs_du * (self.lam * u - w) + self.psi * du

    def decay_rate(self, u, du, w):
        """The rate a >= 0 of the linear decay -a w in eq. (4): alpha |u'|. It makes the loop
        stiff where |u'| is large; the exponential step integrates it exactly."""
        return self.alpha * (smooth_abs(du, self.smooth_delta) if self.smooth else jnp.abs(du))

    def d1_limits(self):
        """Limits (7)-(8) of d_1: (lam-psi)/alpha as u -> -inf, -(lam-psi)/alpha as u -> +inf."""
        bound = (self.lam - self.psi) / self.alpha
        return bound, -bound


def closed_form(u, u0, w0, alpha, lam, psi, direction):
    """Solution (5)-(6) of eq. (4) on a monotone segment of u.

    With s = sgn(u') constant on the segment, (4) reads dw/du = alpha s (lam u - w) + psi, a linear
    ODE in u. Writing d_1 = w - lam u (eq. 5):

        d_1(u) = (w0 - lam u0) E + (psi - lam)/(alpha s) (1 - E),  E = e^{-alpha s (u - u0)},

    which is (6) with the paper's sgn(u) read as sgn(u') (docs/paper-readings.md).

    Args:
        u: input values on the segment (any shape).
        u0, w0: start of the segment.
        alpha, lam, psi: hysteresis parameters.
        direction: +1 on a rising segment, -1 on a falling one.

    Returns:
        w(u), same shape as u.
    """
    s = direction
    decay = jnp.exp(-alpha * s * (u - u0))
    d1 = (w0 - lam * u0) * decay + (psi - lam) / (alpha * s) * (1.0 - decay)
    return lam * u + d1
