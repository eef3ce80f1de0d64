"""The metrics of dscjax/metrics.py on saved arrays (t, e, u): a second implementation, the
tests' oracle for the running reductions (`metrics.Tracking`) that every run computes."""

import jax.numpy as jnp


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
