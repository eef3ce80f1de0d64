"""A batch in the rows layout: the state a tuple of m rows of shape (B,), one per component
(batch-last), the field vmapped over the members, the shared arguments one flat vector.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax.integrate import scan
from dscjax.xla import barriers


def _scalars(tree) -> tuple:
    """Every element of every leaf as a separate scalar (for the batched row layout)."""
    return tuple(e for leaf in jax.tree.leaves(tree) for e in jnp.ravel(leaf))


class _Rows:
    """A batch: the state is a tuple of m rows of shape (B,), one per component. Packing
    computed components into one array lets XLA fuse the whole field into the concatenate,
    which then recomputes the control law once per component; rows are stacked only to save."""

    def __init__(self, proto):
        self.unravel = ravel_pytree(proto)[1]

    def unpack_one(self, row_scalars):
        return self.unravel(jnp.stack(row_scalars))

    def unstack(self, ys):
        # ys: (T, m, B) -> pytree with leaves (B, T, ...)
        return jax.vmap(jax.vmap(self.unravel), in_axes=-1)(ys)


def _ravel_floats(tree):
    """ravel_pytree over the floating leaves only (other leaves are kept as they are)."""
    floats, rest = eqx.partition(tree, lambda x: jnp.issubdtype(jnp.result_type(x), jnp.floating))
    flat, unravel = ravel_pytree(floats)
    return flat, lambda v: eqx.combine(unravel(v), rest)


def integrate_batch(f, y0, args, batch, reduction, acc0, dt, n_steps, save_every,
                    state_bound, solver, gradient, rates, project, frozen, skip_diverged, substeps):
    args_flat, unravel_args = _ravel_floats(args)
    y_one, b_one = jax.tree.map(lambda x: x[0], (y0, batch))
    mask = scan.frozen_mask(frozen, y_one)  # one Python bool per row: held inside a step
    frozen_rows = (None if mask is None else
                   tuple(bool(m) for leaf in jax.tree.leaves(mask) for m in np.ravel(leaf)))
    _, unravel_b = _ravel_floats(b_one)
    b_flat = jax.vmap(lambda b: _ravel_floats(b)[0], out_axes=-1)(batch)  # (p, B)
    obs_one = jax.eval_shape(lambda: f(dt, y_one, (unravel_args(args_flat), b_one))[1])
    ys_c, obs_c, acc_c = _Rows(y_one), _Rows(scan.zeros(obs_one)), _Rows(acc0)

    # one trace of the field for every call with the same shapes (RK4's four stages, the
    # last observation): an inner jit, inlined by XLA
    @jax.jit
    def f_rows(t, y, a_flat, b):
        def one(y_row, b_col):
            dy, obs = f(t, ys_c.unpack_one(y_row), (unravel_args(a_flat), unravel_b(b_col)))
            return _scalars(dy), _scalars(obs)
        return jax.vmap(one, in_axes=(0, -1), out_axes=0)(y, b)

    def f_obs(t, y):
        return f_rows(t, y, args_flat, b_flat)

    def member_args(b_col):  # (shared arguments, the member's), as rates and project take them
        return unravel_args(args_flat), unravel_b(b_col)

    def rates_member(t, y_row, obs_row, b_col):
        return _scalars(rates(t, ys_c.unpack_one(y_row), member_args(b_col),
                              obs_c.unpack_one(obs_row)))

    def rates_rows(t, y, obs):
        return jax.vmap(rates_member, in_axes=(None, 0, 0, -1), out_axes=0)(t, y, obs, b_flat)

    def project_member(k, t, y_row, b_col):
        return _scalars(project(k, t, ys_c.unpack_one(y_row), member_args(b_col)))

    def project_rows(k, t, y):
        return jax.vmap(project_member, in_axes=(None, None, 0, -1), out_axes=0)(k, t, y, b_flat)

    def acc_member(acc_row, k, t, y_row, obs_row):
        return _scalars(reduction.update(acc_c.unpack_one(acc_row), k, t, ys_c.unpack_one(y_row),
                                         obs_c.unpack_one(obs_row), dt))

    acc_fn = jax.vmap(acc_member, in_axes=(0, None, None, 0, 0), out_axes=0)
    y_init = tuple(jnp.moveaxis(jax.vmap(lambda y: ravel_pytree(y)[0])(y0), 0, -1))
    n_batch = jax.tree.leaves(y0)[0].shape[0]
    acc_init = tuple(jnp.broadcast_to(a, (n_batch,)) for a in ravel_pytree(acc0)[0])

    def acc_update(acc, k, t, y, obs):
        return acc if reduction is None else acc_fn(acc, k, t, y, obs)

    def step(c):
        t = c.k.astype(dt.dtype) * dt
        y_next, obs = solver.step(f_obs, rates_rows if rates is not None else None, t, c.y, dt,
                                  frozen=frozen_rows)
        if project is not None:
            y_next = project_rows(c.k + 1, t + dt, y_next)
        acc = acc_update(c.acc, c.k, t, c.y, obs)
        finite = functools.reduce(jnp.logical_and, [jnp.isfinite(v) for v in y_next])
        small = functools.reduce(jnp.logical_and, [jnp.abs(v) <= state_bound for v in y_next])
        return scan.advance(c, y_next, acc, finite, small), obs

    def observe(c):  # the observation at the carry's step and state, without a step
        return f_obs(c.k.astype(dt.dtype) * dt, c.y)[1]

    with barriers():  # (f_rows is traced once, here: with its barriers)
        obs_zero = scan.zeros(jax.eval_shape(lambda y: f_obs(dt, y)[1], y_init))
        carry, (ys, obs) = scan.saving_scan(
            step, scan.start(y_init, acc_init, (n_batch,)), obs_zero, n_steps, save_every,
            lambda c, o: (jnp.stack(c.y), jnp.stack(o)), gradient.every,
            observe if skip_diverged else None, substeps)
        k, y_end, acc, code, bad = carry
        t_end = k.astype(dt.dtype) * dt
        obs_end = observe(carry)
        acc = scan.kept(code == scan.STATUS_OK, acc_update(acc, k, t_end, y_end, obs_end), acc)
    ys = ys_c.unstack(jnp.concatenate([ys, jnp.stack(y_end)[None]]))  # rows (m, B) per step
    obs = obs_c.unstack(jnp.concatenate([obs, jnp.stack(obs_end)[None]]))
    acc = (jax.vmap(acc_c.unravel, in_axes=-1)(jnp.stack(acc)) if reduction is not None
           else None)
    return scan.Integration(ys=ys, obs=obs, acc=acc, status=scan.Status(code=code, step=bad))
