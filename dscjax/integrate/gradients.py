"""How an integration is differentiated, as objects: `TimeParallel()` (one trajectory's N step
Jacobians in one batched program, then a small recurrence: `time_parallel_jvp`) and
`Checkpointed()` (JAX's own differentiation of the scan). A batch is differentiated through
its scan, checkpointed every `every` steps.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax.integrate.scan import kept

# Members per chunk of the time-parallel Jacobians (bounds their memory, not their result).
_PARALLEL_CHUNK = 4096
DEFAULT_CHECKPOINT_EVERY = 100


class Gradient(eqx.Module):
    """How an integration is differentiated. `every`: a batch's scan keeps its state every this
    many steps and recomputes the rest (None keeps every step's residuals)."""

    name: ClassVar[str]
    every: int | None = DEFAULT_CHECKPOINT_EVERY


class TimeParallel(Gradient):
    """One trajectory: all N step Jacobians in one batched program, then a small recurrence
    (the exact derivative of the discrete map; memory O(N (m^2 + r^2)) for m states and r
    floats of running reductions)."""

    name: ClassVar[str] = "time_parallel"


class Checkpointed(Gradient):
    """JAX's own differentiation of the scan (a reference for tests)."""

    name: ClassVar[str] = "checkpointed"


def _saved(all_k, end, s):
    """Every s-th row of a per-step record (k = 0..N-1) and the end value (k = N)."""
    return jax.tree.map(lambda v, e: jnp.concatenate([v[::s], e[None]]), all_k, end)


def time_parallel_jvp(prob, primals, tangents):
    """The jvp of `prob.forward` (`single._Problem`) as a time-parallel linearisation of y_(k+1) =
    Phi_k(y_k; a, dt), obs_k = O_k(y_k):

        dy_(k+1) = J_k dy_k + b_k,   dobs_k = G_k dy_k + g_k,   dacc_(k+1) = M_k dacc_k + r_k,

    J_k = dPhi/dy, G_k = dO/dy and M_k = dU/dacc (U: the reductions' update) by batched jacfwds
    over the stored steps; b_k, g_k along (da, d dt) and r_k along (dred, dy_k, dobs_k, d dt)
    by batched jvps; only the small matrix-vector recurrences run step by step. JAX
    transposes it for reverse mode. A frozen step (after a divergence) has its increments
    scaled by 0: exactly the identity with finite partials, so no NaN reaches the derivative.
    """
    y0, a, red, acc0, dt, bound = primals
    dy0, da, dred, dacc0, ddt, _ = tangents
    n, s = prob.n, prob.s
    c, Y, A, O, acc_end, obs_end = prob.forward_all(y0, a, red, acc0, dt, bound)
    ks = jnp.arange(n, dtype=jnp.int32)
    no_bad = c.bad < 0
    live_y = no_bad | (ks < c.bad - 1)  # step k maps y_k to y_(k+1) by RK4
    live_acc = no_bad | (ks < c.bad)  # sample k is folded into the reductions
    zero = jnp.zeros((), dt.dtype)
    H = jnp.where(live_y, dt, zero)  # increments of frozen steps scaled by 0

    # In the batched programs the parameters enter as the args pytree, not packed: packed
    # chunks would give every member a dense cotangent of the whole chunk in reverse mode.
    a_tree, da_tree = prob.ap.unpack(a), prob.ap.unpack(da)

    def member(k, y, a_, dt_, h_):
        return prob.step(k, y, a_, dt_, h_, scanned=True, packed=False)

    # Jacobians J_k, G_k of all steps, in parallel over k (chunked to bound memory).
    def jac(k, y, h):
        return jax.jacfwd(lambda yy: member(k, yy, a_tree, dt, h))(y)

    J, G = _parallel(jac, (ks, Y, H))

    # b_k, g_k along the parameters (da, d dt); a frozen step has h = 0 and d h = 0.
    def along(k, y, h, dh):
        return jax.jvp(lambda a_, dt_, h_: member(k, y, a_, dt_, h_), (a_tree, dt, h),
                       (da_tree, ddt, dh))[1]

    dH = jnp.where(live_y, ddt, zero)
    b, g = _parallel(jax.checkpoint(along), (ks, Y, H, dH))

    # dy_(k+1) = J_k dy_k + b_k: a small matrix-vector recurrence.
    def tangent_step(dy, inp):
        Jk, bk = inp
        return tuple(_matvec(rows, dy) + bb for rows, bb in zip(Jk, bk, strict=True)), dy

    dy_end, dY = jax.lax.scan(tangent_step, dy0, (J, b))
    dO = tuple(jax.vmap(_matvec)(rows, dY) + gg for rows, gg in zip(G, g, strict=True))

    # Reductions: dacc_(k+1) = M_k dacc_k + r_k along the stored samples, then the last one.
    t_end = c.k.astype(dt.dtype) * dt
    dt_end = c.k.astype(dt.dtype) * ddt
    dobs_end = jax.jvp(lambda y_, a_, t_: prob.field(t_, y_, a_)[1], (c.y, a, t_end),
                       (dy_end, da, dt_end))[1]
    if prob.reduction_is_none:
        dacc_end = dacc0
    else:
        def update_at(k, r, ac, y_, o_, h):  # t_k = k h: its tangent k dh
            return prob.update(r, ac, k, k.astype(dt.dtype) * h, y_, o_, h)

        def acc_jac(k, acc_k, y_k, o_k):
            return jax.jacfwd(lambda ac: update_at(k, red, ac, y_k, o_k, dt))(acc_k)

        def acc_along(k, acc_k, y_k, o_k, dy_k, do_k):
            return jax.jvp(lambda r, y_, o_, h: update_at(k, r, acc_k, y_, o_, h),
                           (red, y_k, o_k, dt), (dred, dy_k, do_k, ddt))[1]

        def acc_step(dacc, inp):
            Mk, rk, live = inp
            new = tuple(_matvec(rows, dacc) + rr for rows, rr in zip(Mk, rk, strict=True))
            return kept(live, new, dacc), None

        M = _parallel(acc_jac, (ks, A, Y, O))
        R = _parallel(jax.checkpoint(acc_along), (ks, A, Y, O, dY, dO))

        dacc_n, _ = jax.lax.scan(acc_step, dacc0, (M, R, live_acc))
        _, dacc_last = jax.jvp(lambda r, ac, y_, o_, h: update_at(c.k, r, ac, y_, o_, h),
                               (red, c.acc, c.y, obs_end, dt),
                               (dred, dacc_n, dy_end, dobs_end, ddt))
        dacc_end = kept(no_bad, dacc_last, dacc_n)

    out = (_saved(Y, c.y, s), _saved(O, obs_end, s), acc_end, c.code, c.bad)
    f0 = np.zeros((), dtype=jax.dtypes.float0)
    dout = (_saved(dY, dy_end, s), _saved(dO, dobs_end, s), dacc_end, f0, f0)
    return out, dout


def _parallel(fn, xs):
    """fn vmapped over the leading axis of xs in chunks of _PARALLEL_CHUNK (the last padded with
    the first member, its results dropped): bounded memory, compiled once."""
    n = jax.tree.leaves(xs)[0].shape[0]
    if n <= _PARALLEL_CHUNK:
        return jax.vmap(fn)(*xs)
    n_chunks = -(-n // _PARALLEL_CHUNK)
    size = -(-n // n_chunks)  # chunks of equal size: at most n_chunks - 1 padded members
    pad = n_chunks * size - n

    def chunks(a):
        a = jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad, *a.shape[1:]))]) if pad else a
        return a.reshape(n_chunks, size, *a.shape[1:])

    out = jax.lax.map(lambda c: jax.vmap(fn)(*c), jax.tree.map(chunks, xs))
    return jax.tree.map(lambda a: a.reshape(-1, *a.shape[2:])[:n], out)


def _matvec(rows, v):
    """One output chunk of J v, J stored as jacfwd gives it for chunked in- and outputs:
    `rows` is a tuple over the input chunks j of arrays (out_size, in_size_j)."""
    return sum(jnp.sum(r * vj[None, :], axis=1) for r, vj in zip(rows, v, strict=True))
