"""The metrics of dscjax/metrics.py on saved arrays (t, e, u): a second implementation, the
tests' oracle for the running reductions (`metrics.Tracking`) that every run computes."""

import jax.numpy as jnp
import numpy as np


def _trapezoid_weights(t, mask):
    """Trapezoid weights over the samples selected by mask (a contiguous tail of t)."""
    dt = jnp.diff(t)
    left = jnp.concatenate([dt, jnp.zeros((1,), t.dtype)])  # interval to the right
    right = jnp.concatenate([jnp.zeros((1,), t.dtype), dt])  # interval to the left
    m = mask.astype(t.dtype)
    m_prev = jnp.concatenate([jnp.zeros((1,), t.dtype), m[:-1]])
    m_next = jnp.concatenate([m[1:], jnp.zeros((1,), t.dtype)])
    return 0.5 * m * (left * m_next + right * m_prev)


def linf(e, t=None, t0=None):
    """max |e| over the samples with t >= t0 (all samples if t0 is None)."""
    a = jnp.abs(e)
    if t0 is None:
        return jnp.max(a)
    return jnp.max(jnp.where(t >= t0, a, 0.0))


def l2(e, t, t0=None):
    """sqrt of the trapezoid integral of e^2 over [t0, T] (whole horizon if t0 is None)."""
    mask = jnp.ones_like(t, dtype=bool) if t0 is None else t >= t0
    return jnp.sqrt(jnp.sum(_trapezoid_weights(t, mask) * e * e))


def rms(e, t, t0=None):
    """L2 / sqrt(length of the window)."""
    mask = jnp.ones_like(t, dtype=bool) if t0 is None else t >= t0
    t_first = jnp.min(jnp.where(mask, t, jnp.inf))
    return l2(e, t, t0) / jnp.sqrt(t[-1] - t_first)


def total_variation(u, t=None, t0=None):
    """sum |u_(k+1) - u_k|, over the steps whose both ends lie in t >= t0 if t0 is given."""
    d = jnp.abs(jnp.diff(u))
    if t0 is None:
        return jnp.sum(d)
    return jnp.sum(jnp.where(t[:-1] >= t0, d, 0.0))


def chattering_numpy(t, u, t0, tau=0.02):
    """(TV(u), the chattering index) on t >= t0 from saved samples, in numpy: TV(u) over that
    of u low-passed (v_k = v_(k-1) + (1 - e^(-dt/tau)) (u_k - v_(k-1)), v_0 = u_0), tau = 20 ms
    as docs/numerics.md states it."""
    t, u = np.asarray(t), np.asarray(u)
    v = np.empty_like(u)
    v[0] = u[0]
    a = -np.expm1(-np.diff(t) / tau)
    for k in range(1, len(u)):
        v[k] = v[k - 1] + a[k - 1] * (u[k] - v[k - 1])
    steps = t[:-1] >= t0
    tv = np.abs(np.diff(u))[steps].sum()
    return tv, tv / np.abs(np.diff(v))[steps].sum()
