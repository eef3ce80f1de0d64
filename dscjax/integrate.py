"""Fixed-step classical RK4 over pytrees, the time loop a `jax.lax.scan`.

Nothing here knows about DSC: `integrate` takes any f(t, y, args) -> (dy, obs) where obs is an
observation of the state at (t, y) (read off for saving and running reductions).

Step times are t_k = k dt exactly (an integer counter times dt, never a running sum), so
trajectories agree to round-off with any other implementation that uses the same grid.

Layout. The loop carries ONE flat state array and reads ONE flat parameter array, so that
XLA:CPU hands each fused kernel a couple of buffers instead of dozens of scalars (most of the
cost of a small loop body); the models still see their pytrees (unravelling is slicing, fused
into the consumers). A batch is stored batch-LAST, (state size, B): every state component is
a contiguous vector over the batch, which XLA vectorises; vmap's batch-first layout would make
every component a strided column (measured: 1.5-2x slower).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from dscjax._fusion import barriers

Pytree = Any

STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_BOUND = 2

# Rows are written from an inner scan over this many steps when every step is saved: a single
# scan that both steps and writes rows ran ~3x slower on XLA:CPU (measured; 8+ is slow again).
_ROW_CHUNKS = (4, 2)


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
    """Outcome of an integration (per trajectory in a batch: never raises in traced code).

    code: int32, STATUS_OK, STATUS_NONFINITE (a state became inf/NaN) or STATUS_BOUND (a state
        component exceeded the state bound in magnitude).
    step: int32, the first step index k whose state y_k was bad, -1 if none. From then on the
        state is frozen at its last good value, so outputs stay finite.
    """

    code: jax.Array
    step: jax.Array


class Integration(NamedTuple):
    ys: Pytree  # states at t_0, t_s, t_2s, ..., t_N (leading axis N/s + 1, then the batch)
    obs: Pytree  # observations at the same times
    acc: Pytree  # running reductions over every step k = 0..N
    status: Status


def _ravel_floats(tree):
    """ravel_pytree over the floating leaves only (other leaves are kept as they are)."""
    leaves, treedef = jax.tree.flatten(tree)
    is_float = [jnp.issubdtype(jnp.result_type(x), jnp.floating) for x in leaves]
    floats = [x for x, fl in zip(leaves, is_float, strict=True) if fl]
    flat, unravel_floats = ravel_pytree(floats)

    def unravel(v):
        it = iter(unravel_floats(v))
        return jax.tree.unflatten(treedef, [next(it) if fl else x
                                            for x, fl in zip(leaves, is_float, strict=True)])

    return flat, unravel


def _first(tree):
    return jax.tree.map(lambda x: x[0], tree)


def _scalars(tree) -> tuple:
    """Every element of every leaf as a separate scalar (for the batched row layout)."""
    return tuple(e for leaf in jax.tree.leaves(tree) for e in jnp.ravel(leaf))


class _Flat:
    """One trajectory: the state is ONE flat vector (m,)."""

    def __init__(self, proto):
        self.unravel = ravel_pytree(proto)[1]

    def pack(self, tree):
        return ravel_pytree(tree)[0]

    def unpack(self, y):
        return self.unravel(y)

    def all(self, pred):
        return jnp.all(pred)

    def stack(self, y):
        return y

    def unstack(self, ys):
        return jax.vmap(self.unravel)(ys)


class _Rows:
    """A batch: the state is a tuple of m rows of shape (B,), one per state component.

    Each derivative component stays its own output: packing computed components into one
    array (a concatenate, as ravel_pytree does) lets XLA fuse the whole vector field into the
    concatenate, whose emitter then recomputes the shared control law once per component
    (measured 5x slower). Rows are stacked only to save them.
    """

    def __init__(self, proto):
        self.unravel = ravel_pytree(proto)[1]

    def pack_one(self, tree):
        return _scalars(tree)

    def unpack_one(self, row_scalars):
        return self.unravel(jnp.stack(row_scalars))

    def all(self, pred_rows):
        out = pred_rows[0]
        for p in pred_rows[1:]:
            out = out & p
        return out

    def stack(self, y):
        return jnp.stack(y)  # (m, B)

    def unstack(self, ys):
        # ys: (T, m, B) -> pytree with leaves (B, T, ...)
        return jax.vmap(jax.vmap(self.unravel), in_axes=-1)(ys)


def integrate(
    f: Callable,
    y0: Pytree,
    dt,
    n_steps: int,
    args=(),
    *,
    batch: Pytree = None,
    save_every: int = 1,
    accumulate: Callable | None = None,
    acc0: Pytree = None,
    state_bound=jnp.inf,
    unroll: int = 1,
    checkpoint_every: int | None = None,
) -> Integration:
    """Integrate y' = f(t, y, args) by RK4 on t_k = k dt, k = 0..n_steps.

    Args:
        f: f(t, y, args) -> (dy, obs); obs is an observation at (t, y). With `batch`, f is called
            as f(t, y, args, b) for one batch member b (and does not see the batch axis).
        y0: initial state pytree (with `batch`: every leaf has a leading batch axis B).
        dt: step (traced).
        n_steps: number of steps N (static). Must be a multiple of save_every.
        args: shared arguments passed to f (traced leaves, one copy for the whole batch).
        batch: None, or a pytree whose leaves have a leading batch axis B: per-member arguments.
        save_every: keep every s-th state and observation (static); memory is O(N/s).
        accumulate: acc <- accumulate(acc, k, t_k, y_k, obs_k) for every k = 0..N while the
            trajectory is healthy (reductions over every step, e.g. running metrics).
        acc0: initial accumulator (with `batch`: leading batch axis).
        state_bound: a state with any |component| above it counts as diverged (traced).
        unroll: scan unroll factor of the inner loop when save_every > 1 (static).
        checkpoint_every: None, or a segment length L (a multiple of save_every dividing
            n_steps): the loop is split into segments of L steps, each under `jax.checkpoint`,
            so reverse-mode differentiation stores O(N/L + L) states instead of O(N) and
            recomputes each segment once on the way back. Results are identical.

    Returns:
        Integration(ys, obs, acc, status); with `batch` every leaf has a leading batch axis.
    """
    if n_steps % save_every:
        raise ValueError(f"n_steps={n_steps} must be a multiple of save_every={save_every}")
    if checkpoint_every is not None and (checkpoint_every % save_every
                                         or n_steps % checkpoint_every):
        raise ValueError(f"checkpoint_every={checkpoint_every} must be a multiple of "
                         f"save_every={save_every} and divide n_steps={n_steps}")
    n_blocks = n_steps // save_every
    dt = jnp.asarray(dt)
    batched = batch is not None
    args_flat, unravel_args = _ravel_floats(args)
    acc_proto = acc0 if accumulate is not None else ()

    if batched:
        y_one, b_one = _first(y0), _first(batch)
        acc_one = _first(acc_proto) if accumulate is not None else ()
        _, unravel_b = _ravel_floats(b_one)
        b_flat = jax.vmap(lambda b: _ravel_floats(b)[0], out_axes=-1)(batch)  # (p, B)
        obs_one = jax.eval_shape(lambda: f(dt, y_one, unravel_args(args_flat), b_one)[1])
        ys_c, obs_c, acc_c = _Rows(y_one), _Rows(_zeros(obs_one)), _Rows(acc_one)

        def member(t, y_row, b_col):
            dy, obs = f(t, ys_c.unpack_one(y_row), unravel_args(args_flat), unravel_b(b_col))
            return _scalars(dy), _scalars(obs)

        f_rows = jax.vmap(member, in_axes=(None, 0, -1), out_axes=0)

        def f_obs(t, y):
            return f_rows(t, y, b_flat)

        def acc_member(acc_row, k, t, y_row, obs_row):
            new = accumulate(acc_c.unpack_one(acc_row), k, t, ys_c.unpack_one(y_row),
                             obs_c.unpack_one(obs_row))
            return _scalars(new)

        acc_fn = jax.vmap(acc_member, in_axes=(0, None, None, 0, 0), out_axes=0)
        y_init = tuple(jnp.moveaxis(jax.vmap(lambda y: ravel_pytree(y)[0])(y0), 0, -1))
        acc_init = (tuple(jnp.moveaxis(jax.vmap(lambda a: ravel_pytree(a)[0])(acc0), 0, -1))
                    if accumulate is not None else ())
        batch_shape = (jax.tree.leaves(y0)[0].shape[0],)
    else:
        obs_one = jax.eval_shape(lambda: f(dt, y0, unravel_args(args_flat))[1])
        ys_c, obs_c, acc_c = _Flat(y0), _Flat(_zeros(obs_one)), _Flat(acc_proto)

        def f_obs(t, y):
            dy, obs = f(t, ys_c.unpack(y), unravel_args(args_flat))
            return ys_c.pack(dy), obs_c.pack(obs)

        def acc_fn(acc, k, t, y, obs):
            return acc_c.pack(accumulate(acc_c.unpack(acc), k, t, ys_c.unpack(y),
                                         obs_c.unpack(obs)))

        y_init = ys_c.pack(y0)
        acc_init = acc_c.pack(acc_proto)
        batch_shape = ()

    where = functools.partial(jax.tree.map, lambda a, b, c: jnp.where(a, b, c))

    def acc_update(acc, k, t, y, obs, ok):
        if accumulate is None:
            return acc
        new = acc_fn(acc, k, t, y, obs)
        return jax.tree.map(lambda a, b: jnp.where(ok, b, a), acc, new)

    def step(carry):
        """One guarded RK4 step; returns the new carry and the observation at t_k."""
        k, y, acc, code, bad_step = carry
        t = k.astype(dt.dtype) * dt
        y_next, obs = _rk4(f_obs, t, y, dt)
        ok_now = code == STATUS_OK
        acc = acc_update(acc, k, t, y, obs, ok_now)
        finite = ys_c.all(jax.tree.map(jnp.isfinite, y_next))
        small = ys_c.all(jax.tree.map(lambda v: jnp.abs(v) <= state_bound, y_next))
        if not batched:
            finite, small = jnp.all(finite), jnp.all(small)
        bad = ok_now & ~(finite & small)
        code = jnp.where(bad, jnp.where(finite, STATUS_BOUND, STATUS_NONFINITE), code)
        bad_step = jnp.where(bad, k + 1, bad_step)
        keep = code == STATUS_OK
        y_next = jax.tree.map(lambda a, b: jnp.where(keep, a, b), y_next, y)
        return (k + 1, y_next, acc, code, bad_step), obs

    def save_step(carry, _):
        y_start = carry[1]
        carry, obs = step(carry)
        return carry, (ys_c.stack(y_start), obs_c.stack(obs))

    def block(carry, _):
        # save_every steps; keep the state and observation at the first one.
        def inner(c, _):
            carry_, obs_first, first = c
            carry_, obs = step(carry_)
            return (carry_, where(jax.tree.map(lambda _: first, obs), obs, obs_first),
                    jnp.zeros_like(first)), None

        obs_zero = jax.tree.map(jnp.zeros_like, jax.eval_shape(lambda y: f_obs(dt, y)[1], y_init))
        obs_zero = jax.tree.map(lambda sd: jnp.zeros(sd.shape, sd.dtype), obs_zero)
        y_start = carry[1]
        (carry, obs_first, _), _ = jax.lax.scan(inner, (carry, obs_zero, jnp.array(True)), None,
                                                length=save_every,
                                                unroll=min(unroll, save_every))
        return carry, (ys_c.stack(y_start), obs_c.stack(obs_first))

    with barriers(batched):
        return _loop(step, save_step, block, f_obs, acc_update, ys_c, obs_c, acc_c, y_init,
                     acc_init, batch_shape, n_steps, save_every, n_blocks, checkpoint_every, dt,
                     batched, accumulate)


def _loop(step, save_step, block, f_obs, acc_update, ys_c, obs_c, acc_c, y_init, acc_init,
          batch_shape, n_steps, save_every, n_blocks, checkpoint_every, dt, batched, accumulate):
    """The time loop proper (traced inside the barrier context chosen by `integrate`)."""
    init = (jnp.zeros((), jnp.int32), y_init, acc_init,
            jnp.full(batch_shape, STATUS_OK, jnp.int32), jnp.full(batch_shape, -1, jnp.int32))
    chunk = next((c for c in _ROW_CHUNKS if n_steps % c == 0), 1)
    if checkpoint_every is not None:
        blocks_per_segment = checkpoint_every // save_every

        @jax.checkpoint
        def segment(carry, _):
            return jax.lax.scan(block, carry, None, length=blocks_per_segment)

        carry, (ys, obs) = jax.lax.scan(segment, init, None,
                                        length=n_steps // checkpoint_every)
        ys = ys.reshape(n_blocks, *ys.shape[2:])
        obs = obs.reshape(n_blocks, *obs.shape[2:])
    elif save_every == 1:
        def rows(carry, _):
            return jax.lax.scan(save_step, carry, None, length=chunk)

        carry, (ys, obs) = jax.lax.scan(rows, init, None, length=n_steps // chunk)
        ys = ys.reshape(n_steps, *ys.shape[2:])
        obs = obs.reshape(n_steps, *obs.shape[2:])
    else:
        carry, (ys, obs) = jax.lax.scan(block, init, None, length=n_blocks)
    k, y_end, acc, code, bad_step = carry
    t_end = k.astype(dt.dtype) * dt
    _, obs_end = f_obs(t_end, y_end)
    acc = acc_update(acc, k, t_end, y_end, obs_end, code == STATUS_OK)
    ys = ys_c.unstack(jnp.concatenate([ys, ys_c.stack(y_end)[None]]))
    obs = obs_c.unstack(jnp.concatenate([obs, obs_c.stack(obs_end)[None]]))
    if batched:
        acc = (jax.vmap(acc_c.unravel, in_axes=-1)(jnp.stack(acc))
               if accumulate is not None else None)
    else:
        acc = acc_c.unpack(acc) if accumulate is not None else None
    return Integration(ys=ys, obs=obs, acc=acc, status=Status(code=code, step=bad_step))


def _zeros(shape_tree):
    return jax.tree.map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shape_tree)
