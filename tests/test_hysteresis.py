"""Backlash-like hysteresis (4) against its closed form (5)-(6) and its limits (7)-(8)."""

import jax.numpy as jnp
import numpy as np
import pytest

from dscjax.hysteresis import Backlash, closed_form
from dscjax.integrate import integrate
from dscjax.model import sat, smooth_abs, smooth_sat

ALPHA, LAM, PSI = 1.0, 1.432, 0.105


def _drive(k, t_final=6.0, dt=2e-4):
    """Integrate (4) alone, driven by u = k sin(2.3 t) with u' = 2.3 k cos(2.3 t)."""
    hyst = Backlash(alpha=ALPHA, lam=LAM, psi=PSI)

    def f(t, w, _):
        u, du = k * jnp.sin(2.3 * t), 2.3 * k * jnp.cos(2.3 * t)
        return hyst.rate(u, du, w), u

    n = int(round(t_final / dt))
    res = integrate(f, jnp.array(0.0), dt, n, ())
    t = np.arange(n + 1) * dt
    return t, np.asarray(res.obs), np.asarray(res.ys)


@pytest.mark.parametrize("k", [3.5, 6.5])
def test_ode_matches_closed_form_on_monotone_segments(k):
    t, u, w = _drive(k)
    # extrema of u = k sin(2.3 t) at 2.3 t = pi/2 + j pi: the segments between them are monotone
    edges = [0.0] + [(np.pi / 2 + j * np.pi) / 2.3 for j in range(5)]
    checked = 0
    for a, b in zip(edges[:-1], edges[1:], strict=False):
        seg = (t >= a) & (t <= b)
        if seg.sum() < 10:
            continue
        i0 = np.flatnonzero(seg)[0]
        direction = np.sign(u[np.flatnonzero(seg)[-1]] - u[i0])
        w_cf = np.asarray(closed_form(u[seg], u[i0], w[i0], ALPHA, LAM, PSI, direction))
        np.testing.assert_allclose(w[seg], w_cf, atol=1e-9)
        checked += 1
    assert checked >= 4


def test_limits_7_8():
    # d_1 = w - lam u -> +(lam - psi)/alpha as u -> -inf, -(lam - psi)/alpha as u -> +inf
    bound = (LAM - PSI) / ALPHA
    hi = closed_form(jnp.array(60.0), 0.0, 0.0, ALPHA, LAM, PSI, +1) - LAM * 60.0
    lo = closed_form(jnp.array(-60.0), 0.0, 0.0, ALPHA, LAM, PSI, -1) + LAM * 60.0
    assert float(hi) == pytest.approx(-bound, abs=1e-12)
    assert float(lo) == pytest.approx(bound, abs=1e-12)
    up, down = Backlash(alpha=ALPHA, lam=LAM, psi=PSI).d1_limits()
    assert float(up) == pytest.approx(bound) and float(down) == pytest.approx(-bound)


def test_ode_limit_under_a_long_ramp():
    hyst = Backlash(alpha=2.0, lam=LAM, psi=PSI)

    def f(t, w, _):
        return hyst.rate(3.0 * t, 3.0, w), None

    res = integrate(f, jnp.array(0.0), 1e-3, 4000, ())
    d1 = float(res.ys[-1]) - LAM * 12.0
    assert d1 == pytest.approx(-(LAM - PSI) / 2.0, abs=1e-8)


def test_smooth_surrogates_have_the_documented_bias():
    x = jnp.linspace(-3, 3, 2001)
    d = 0.05
    bias_abs = jnp.abs(x) - smooth_abs(x, d)
    assert float(bias_abs.min()) >= 0.0 and float(bias_abs.max()) <= d + 1e-15
    assert float(smooth_abs(jnp.array(0.0), d)) == 0.0
    bias_sat = jnp.abs(smooth_sat(x, d) - sat(x))
    assert float(bias_sat.max()) <= d / 2 + 1e-12
    assert float(bias_sat.max()) > d / 4  # attained near the corners
