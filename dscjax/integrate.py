"""Fixed-step classical RK4 over pytrees, the time loop a `jax.lax.scan`.

Nothing here knows about DSC: `integrate` takes any f(t, y, args) -> (dy, obs) where obs is an
observation of the state at (t, y) (read off for saving and running reductions).

Step times are t_k = k dt exactly (an integer counter times dt, never a running sum), so
trajectories agree to round-off with any other implementation that uses the same grid.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

Pytree = Any

STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_BOUND = 2


def _axpy(a, x, y):
    """y + a x over pytrees."""
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


def rk4_step(f: Callable, t, y: Pytree, dt, args) -> Pytree:
    """One classical RK4 step of y' = f(t, y, args) (f returns the derivative only).

    Example:
        >>> import jax.numpy as jnp
        >>> y1 = rk4_step(lambda t, y, a: -a * y, 0.0, jnp.array(1.0), 0.1, 2.0)
        >>> abs(float(y1) - float(jnp.exp(-0.2))) < 1e-5
        True
    """
    return _rk4(lambda tt, yy: (f(tt, yy, args), None), t, y, dt)[0]


def _rk4(f_obs, t, y, dt):
    """RK4 step for f_obs(t, y) -> (dy, obs); returns (y_next, obs at (t, y))."""
    half = 0.5 * dt
    k1, obs = f_obs(t, y)
    k2, _ = f_obs(t + half, _axpy(half, k1, y))
    k3, _ = f_obs(t + half, _axpy(half, k2, y))
    k4, _ = f_obs(t + dt, _axpy(dt, k3, y))
    incr = jax.tree.map(lambda a, b, c, d: (a + 2.0 * (b + c) + d) * (dt / 6.0), k1, k2, k3, k4)
    return jax.tree.map(jnp.add, y, incr), obs


class Status(NamedTuple):
    """Outcome of an integration (per trajectory under vmap: never raises inside traced code).

    code: () int32, STATUS_OK, STATUS_NONFINITE (a state became inf/NaN) or STATUS_BOUND (a
        state component exceeded the state bound in magnitude).
    step: () int32, the first step index k at which the state at t_k was bad, -1 if none.
        After that step the state is frozen at its last good value, so outputs stay finite.
    """

    code: jax.Array
    step: jax.Array


class Integration(NamedTuple):
    ys: Pytree  # states at t_0, t_s, t_2s, ..., t_N (leading axis N/s + 1)
    obs: Pytree  # observations at the same times
    acc: Pytree  # running reductions over every step k = 0..N
    status: Status


def integrate(
    f: Callable,
    y0: Pytree,
    dt,
    n_steps: int,
    args,
    *,
    save_every: int = 1,
    accumulate: Callable | None = None,
    acc0: Pytree = None,
    state_bound=jnp.inf,
    unroll: int = 1,
) -> Integration:
    """Integrate y' = f(t, y, args) by RK4 on t_k = k dt, k = 0..n_steps.

    Args:
        f: f(t, y, args) -> (dy, obs); obs is an observation at (t, y).
        y0: initial state pytree.
        dt: step (traced).
        n_steps: number of steps N (static). Must be a multiple of save_every.
        args: passed to f.
        save_every: keep every s-th state and observation (static); memory is O(N/s).
        accumulate: acc <- accumulate(acc, k, t_k, y_k, obs_k) called for every k = 0..N while the
            trajectory is healthy (reductions over every step, e.g. running metrics).
        acc0: initial accumulator.
        state_bound: a state with any |component| above it counts as diverged (traced).
        unroll: scan unroll factor of the inner loop (static).

    Returns:
        Integration(ys, obs, acc, status).
    """
    if n_steps % save_every:
        raise ValueError(f"n_steps={n_steps} must be a multiple of save_every={save_every}")
    n_blocks = n_steps // save_every
    dt = jnp.asarray(dt)

    def f_obs(t, y):
        return f(t, y, args)

    def healthy(y):
        leaves = jax.tree.leaves(y)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in leaves]))
        small = jnp.all(jnp.stack([jnp.all(jnp.abs(leaf) <= state_bound) for leaf in leaves]))
        return finite, small

    def acc_update(acc, k, t, y, obs, ok):
        if accumulate is None:
            return acc
        new = accumulate(acc, k, t, y, obs)
        return jax.tree.map(lambda a, b: jnp.where(ok, b, a), acc, new)

    def step(carry, _):
        k, y, acc, code, bad_step, obs_first, first = carry
        t = k.astype(dt.dtype) * dt
        y_next, obs = _rk4(f_obs, t, y, dt)
        ok_now = code == STATUS_OK
        acc = acc_update(acc, k, t, y, obs, ok_now)
        finite, small = healthy(y_next)
        bad = ok_now & ~(finite & small)
        code = jnp.where(bad, jnp.where(finite, STATUS_BOUND, STATUS_NONFINITE), code)
        bad_step = jnp.where(bad, k + 1, bad_step)
        keep = code == STATUS_OK
        y_next = jax.tree.map(lambda a, b: jnp.where(keep, a, b), y_next, y)
        obs_first = jax.tree.map(lambda a, b: jnp.where(first, a, b), obs, obs_first)
        return (k + 1, y_next, acc, code, bad_step, obs_first, jnp.zeros_like(first)), None

    def block(carry, _):
        k, y, acc, code, bad_step = carry
        y_start = y
        _, obs_proto = jax.eval_shape(f_obs, dt, y)
        obs0 = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), obs_proto)
        inner = (k, y, acc, code, bad_step, obs0, jnp.array(True))
        (k, y, acc, code, bad_step, obs_first, _), _ = jax.lax.scan(
            step, inner, None, length=save_every, unroll=min(unroll, save_every))
        return (k, y, acc, code, bad_step), (y_start, obs_first)

    k0 = jnp.zeros((), jnp.int32)
    code0 = jnp.array(STATUS_OK, jnp.int32)
    bad0 = jnp.array(-1, jnp.int32)
    outer_unroll = max(1, unroll // save_every)
    carry, (ys, obs) = jax.lax.scan(block, (k0, y0, acc0, code0, bad0), None, length=n_blocks,
                                    unroll=min(outer_unroll, max(n_blocks, 1)))
    k, y_end, acc, code, bad_step = carry
    t_end = k.astype(dt.dtype) * dt
    _, obs_end = f_obs(t_end, y_end)
    acc = acc_update(acc, k, t_end, y_end, obs_end, code == STATUS_OK)
    ys = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), ys, y_end)
    obs = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), obs, obs_end)
    return Integration(ys=ys, obs=obs, acc=acc, status=Status(code=code, step=bad_step))
