"""Non-smooth scalar functions of the loop and their smooth surrogates.

The closed loop has two kinks: |u'| in the hysteresis model (4) and sat(.) in the robust term
of (30). Fixed-step RK4 loses its fourth order at every crossing of a kink, and gradients
through a kink are only one-sided. Each function here therefore comes in an exact form and a
smooth form with a documented, bounded bias; which one a model uses is a static switch.
"""

from __future__ import annotations

import jax.numpy as jnp


def smooth_abs(x, delta):
    """sqrt(x^2 + delta^2) - delta: a C-infinity |x|.

    Exact at x = 0 (so w' = 0 when u' = 0 is kept), and 0 <= |x| - smooth_abs(x) <= delta.
    """
    return jnp.sqrt(x * x + delta * delta) - delta


def sat(s):
    """Unit saturation sat(s) = clip(s, -1, 1)."""
    return jnp.clip(s, -1.0, 1.0)


def smooth_sat(s, delta):
    """(sqrt((s+1)^2 + delta^2) - sqrt((s-1)^2 + delta^2)) / 2: a C-infinity sat(s).

    Equal to (|s+1| - |s-1|)/2 = sat(s) when delta = 0; odd; |smooth_sat - sat| <= delta/2,
    the largest bias being at the corners s = +-1.
    """
    d2 = delta * delta
    return 0.5 * (jnp.sqrt((s + 1.0) ** 2 + d2) - jnp.sqrt((s - 1.0) ** 2 + d2))
