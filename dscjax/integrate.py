"""Fixed-step RK4 over pytrees: the time loop is a `jax.lax.scan`, its derivative (for one
trajectory) a time-parallel linearisation.

Nothing here knows about DSC: `integrate` takes any f(t, y, args) -> (dy, obs), where obs is
an observation of the state at (t, y) read off for saving and for running reductions.

Step times are t_k = k dt exactly (an integer counter times dt, never a running sum), so
trajectories agree to round-off with any other implementation that uses the same grid.

How XLA:CPU runs a loop body decides the speed here (measured, see docs/architecture.md):
- a body whose buffers are all <= 512 bytes runs its kernels one after the other in the
  calling thread; one larger buffer anywhere in it (a stacked output, a (13, 9) tangent) makes
  the runtime schedule every kernel on a thread pool, which costs 5-10x for small kernels.
  Hence `SMALL`: states, parameters and stored blocks are kept in arrays of at most 64 floats;
- every kernel costs ~25 ns of dispatch, so one trajectory is bound by the number of kernels
  per step, not by arithmetic. A reverse-mode body has ~10x the kernels of the forward one.

Layouts. One trajectory carries its state as one flat vector (m,) and reads its parameters
from a few flat vectors of <= 64 floats. A batch is stored batch-LAST: the state is a tuple of m
rows of shape (B,), each a contiguous vector over the batch that XLA vectorises.

Gradients. Through one trajectory, `integrate` is a `jax.custom_jvp` whose rule is a
time-parallel linearisation (`_time_parallel_jvp`): the Jacobians of all N steps are computed
at once as one batched program over the stored states, then a small linear recurrence carries
the tangent through time. Reverse mode is JAX's transpose of that rule, so `jax.grad`,
`jax.jvp` and `jax.jacfwd` all get it, exactly (the derivative of the discrete RK4 map). A batch
is differentiated by JAX through the scan, in checkpointed segments (`checkpoint_every`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax._fusion import barriers

Pytree = Any

STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_BOUND = 2

SMALL = 64  # floats per buffer for XLA:CPU's sequential loop-body executor (512 bytes f64)

# Rows are written from an inner scan over this many steps when every step is saved: a single
# scan that both steps and writes rows ran ~3x slower on XLA:CPU (measured; 8+ is slow again).
_ROW_CHUNKS = (4, 2)
# Members per chunk of the time-parallel Jacobians (bounds their memory, not their result).
_PARALLEL_CHUNK = 8192


# -- RK4 ------------------------------------------------------------------------------------------


def _axpy(a, x, y):
    """y + a x over pytrees."""
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


def _hold(new, y, frozen):
    """`new` with the frozen components of the state taken from y unchanged.

    `frozen` (static) is None (nothing frozen) or a tree like y whose leaves are Python bools
    (one per row of a batch) or NumPy bool arrays (one per element of a packed chunk). In the
    batched rows layout a frozen row's increments are never formed (XLA drops them as dead
    code); in a packed chunk that mixes frozen and live elements they are computed with the
    chunk and discarded by the select."""
    if frozen is None:
        return new

    def pick(n, old, m):
        if not np.any(m):
            return n
        return old if np.all(m) else jnp.where(m, old, n)

    return jax.tree.map(pick, new, y, frozen)


def rk4_step(f: Callable, t, y: Pytree, dt, args) -> Pytree:
    """One classical RK4 step of y' = f(t, y, args) (f returns the derivative only).

    Example:
        >>> import jax.numpy as jnp
        >>> y1 = rk4_step(lambda t, y, a: -a * y, 0.0, jnp.array(1.0), 0.1, 2.0)
        >>> abs(float(y1) - float(jnp.exp(-0.2))) < 1e-5
        True
    """
    return _rk4(lambda tt, yy: (f(tt, yy, args), None), t, y, dt)[0]


def _rk4(f_obs, t, y, dt, h=None, frozen=None):
    """RK4 step for f_obs(t, y) -> (dy, obs); returns (y_next, obs at (t, y)).

    `h` (default dt) scales the increments only: h = 0 gives y_next = y exactly, with the
    stages still evaluated at finite points (how frozen steps are linearised safely).
    `frozen` (see `_hold`): components that every stage reads unchanged and that the step
    leaves as they are (a discrete state that only `integrate`'s `project` updates).
    """
    h = dt if h is None else h
    half = 0.5 * h
    k1, obs = f_obs(t, y)
    k2, _ = f_obs(t + 0.5 * dt, _hold(_axpy(half, k1, y), y, frozen))
    k3, _ = f_obs(t + 0.5 * dt, _hold(_axpy(half, k2, y), y, frozen))
    k4, _ = f_obs(t + dt, _hold(_axpy(h, k3, y), y, frozen))
    incr = jax.tree.map(lambda a, b, c, d: (a + 2.0 * (b + c) + d) * (h / 6.0), k1, k2, k3, k4)
    return _hold(jax.tree.map(jnp.add, y, incr), y, frozen), obs


def _taylor(poly, q, terms=20):
    """Taylor coefficients of [poly(z) + e^z q(z)] / z^3 (poly, q: {power: coefficient}),
    exactly in rationals, for the ETDRK4 weights near z = 0 where the formula cancels."""
    from fractions import Fraction
    from math import factorial

    num = [Fraction(0)] * (terms + 3)
    for p, c in poly.items():
        num[p] += c
    for p, c in q.items():
        for k in range(terms + 3 - p):
            num[k + p] += Fraction(c, factorial(k))
    return tuple(float(c) for c in num[3:])


# ETDRK4 weights f1, f2, f3 of Cox & Matthews (2002), and phi(z) = (e^z - 1)/z (as z^3 phi/z^2).
_F1 = _taylor({0: -4, 1: -1}, {0: 4, 1: -3, 2: 1})
_F2 = _taylor({0: 2, 1: 1}, {0: -2, 1: 1})
_F3 = _taylor({0: -4, 1: -3, 2: -1}, {0: 4, 1: -1})
_PHI = _taylor({0: 0, 2: -1}, {2: 1})


def _weight(z, coeffs, direct):
    """An ETDRK4 weight: its Taylor series for |z| < 1, the closed form beyond (double where,
    so that neither branch can put NaN into a derivative)."""
    small = jnp.abs(z) < 1.0
    zs = jnp.where(small, z, 0.0)
    series = functools.reduce(lambda acc, c: acc * zs + c, reversed(coeffs))
    zd = jnp.where(small, -2.0, z)
    return jnp.where(small, series, direct(zd))


def _etdrk4(f_obs, rates, t, y, dt, h=None, frozen=None):
    """One exponential RK4 step (ETDRK4, Cox & Matthews 2002) of y' = -lam y + N(t, y), with
    lam = rates(t_k, y_k, obs_k) >= 0 frozen over the step (a pytree like y).

    The rates are the stiff linear decays the model knows of (the hysteresis rate alpha |u'|,
    the filters 1/tau): they are integrated exactly, and the rest N = F + lam y with
    exponential weights, so the step stays stable however large lam h is; fourth order, and
    exactly classical RK4 where lam = 0. `frozen` as for `_rk4`. Returns (y_next, obs at
    (t, y)).
    """
    h = dt if h is None else h
    k1, obs = f_obs(t, y)
    lam = rates(t, y, obs)
    z = jax.tree.map(lambda r: -h * r, lam)

    def each(fn, *trees):
        return jax.tree.map(fn, *trees)

    e_full = each(jnp.exp, z)
    e_half = each(lambda zz: jnp.exp(0.5 * zz), z)
    # (e^(z/2) - 1)/(-lam) = (h/2) phi(z/2)
    p_half = each(lambda zz: 0.5 * h * _weight(0.5 * zz, _PHI, lambda x: jnp.expm1(x) / x), z)
    f1 = each(lambda zz: _weight(zz, _F1, lambda x: (-4 - x + jnp.exp(x) * (4 - 3 * x + x * x))
                                 / x**3), z)
    f2 = each(lambda zz: _weight(zz, _F2, lambda x: (2 + x + jnp.exp(x) * (x - 2)) / x**3), z)
    f3 = each(lambda zz: _weight(zz, _F3, lambda x: (-4 - 3 * x - x * x + jnp.exp(x) * (4 - x))
                                 / x**3), z)

    def rest(k, yy):  # N = F + lam y
        return each(lambda kk, r, v: kk + r * v, k, lam, yy)

    n_u = rest(k1, y)
    a = _hold(each(lambda eh, ph, v, n: eh * v + ph * n, e_half, p_half, y, n_u), y, frozen)
    n_a = rest(f_obs(t + 0.5 * dt, a)[0], a)
    b = _hold(each(lambda eh, ph, v, n: eh * v + ph * n, e_half, p_half, y, n_a), y, frozen)
    n_b = rest(f_obs(t + 0.5 * dt, b)[0], b)
    c = _hold(each(lambda eh, ph, v, nb, nu: eh * v + ph * (2.0 * nb - nu), e_half, p_half, a,
                   n_b, n_u), y, frozen)
    n_c = rest(f_obs(t + dt, c)[0], c)
    y_next = each(lambda ef, w1, w2, w3, v, nu, na, nb, nc:
                  ef * v + h * (w1 * nu + 2.0 * w2 * (na + nb) + w3 * nc),
                  e_full, f1, f2, f3, y, n_u, n_a, n_b, n_c)
    return _hold(y_next, y, frozen), obs


SOLVERS = ("rk4", "etdrk4")


def _rk4_scanned(f_obs, t, y, dt, h, frozen=None):
    """The same step as `_rk4`, its four stages a `lax.scan` over one copy of f_obs.

    Used where the step is differentiated in bulk (the time-parallel Jacobians): one copy of
    the vector field's derivative instead of four halves XLA's compile time. Equal to `_rk4`
    to round-off (the stage sums are formed in the same order).
    """
    c = jnp.asarray([0.0, 0.5, 0.5, 1.0], dt.dtype)
    w = jnp.asarray([1.0, 2.0, 2.0, 1.0], dt.dtype)

    def stage(carry, cw):
        k_prev, total = carry
        ci, wi = cw
        ki, obs = f_obs(t + ci * dt, _hold(_axpy(ci * h, k_prev, y), y, frozen))
        return (ki, _axpy(wi, ki, total)), obs

    zero = jax.tree.map(jnp.zeros_like, y)
    (_, total), obs = jax.lax.scan(stage, (zero, zero), (c, w))
    return _hold(_axpy(h / 6.0, total, y), y, frozen), jax.tree.map(lambda o: o[0], obs)


# -- public types ---------------------------------------------------------------------------------


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
    ys: Pytree  # states at the steps `saved_steps(N, s)`: 0, s, 2s, ..., N (then the batch)
    obs: Pytree  # observations at the same times
    acc: Pytree  # running reductions over every step k = 0..N (None without a reduction)
    status: Status


class Reduction(Protocol):
    """A running reduction folded over every step k = 0..N while the trajectory is healthy.

    A pytree (its numbers are traced leaves, differentiable like any parameter) with
        update(acc, k, t, y, obs) -> acc
    `acc` is a pytree of floating scalars; `integrate` takes its initial value as `acc0`.
    """

    def update(self, acc, k, t, y, obs): ...


# -- flat packing ---------------------------------------------------------------------------------


class _Packer:
    """A pytree <-> a tuple of flat float arrays of at most SMALL elements each.

    Leaves are packed whole, in order, greedily into arrays of <= SMALL floats (a leaf larger
    than that gets an array of its own); non-float leaves are kept aside as they are.
    """

    def __init__(self, proto):
        leaves, self.treedef = jax.tree.flatten(proto)
        self.fixed = []  # (index, value) of non-float leaves
        self.slots = []  # (index, chunk, offset, size, shape)
        sizes: list[int] = []
        for i, leaf in enumerate(leaves):
            dtype = jnp.result_type(leaf)
            if not jnp.issubdtype(dtype, jnp.floating):
                self.fixed.append((i, leaf))
                continue
            shape = np.shape(leaf)
            size = int(np.prod(shape, dtype=int))
            if not sizes or sizes[-1] + size > SMALL:
                sizes.append(0)
            self.slots.append((i, len(sizes) - 1, sizes[-1], size, shape))
            sizes[-1] += size
        self.sizes = tuple(sizes)
        self.n_leaves = len(leaves)

    @property
    def size(self) -> int:
        return sum(self.sizes)

    def pack(self, tree) -> tuple:
        leaves = jax.tree.leaves(tree)
        parts: list[list] = [[] for _ in self.sizes]
        for i, chunk, _, _, _ in self.slots:
            parts[chunk].append(jnp.ravel(leaves[i]))
        return tuple(p[0] if len(p) == 1 else jnp.concatenate(p) for p in parts)

    def unpack(self, chunks) -> Pytree:
        leaves: list = [None] * self.n_leaves
        for i, value in self.fixed:
            leaves[i] = value
        for i, chunk, off, size, shape in self.slots:
            c = chunks[chunk]
            leaves[i] = (c if size == c.shape[-1] and off == 0 else c[off:off + size]).reshape(
                shape)
        return jax.tree.unflatten(self.treedef, leaves)

    def zeros(self, dtype) -> tuple:
        return tuple(jnp.zeros((s,), dtype) for s in self.sizes)

    def pack_mask(self, mask) -> tuple:
        """A static tree of bool arrays like the packed tree -> one NumPy bool array per chunk."""
        leaves = jax.tree.leaves(mask)
        parts = [np.zeros((s,), bool) for s in self.sizes]
        for i, chunk, off, size, _ in self.slots:
            parts[chunk][off:off + size] = np.ravel(leaves[i])
        return tuple(parts)


def _first(tree):
    return jax.tree.map(lambda x: x[0], tree)


def _scalars(tree) -> tuple:
    """Every element of every leaf as a separate scalar (for the batched row layout)."""
    return tuple(e for leaf in jax.tree.leaves(tree) for e in jnp.ravel(leaf))


def _zeros(shape_tree):
    return jax.tree.map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shape_tree)


def _full_mask(frozen, y):
    """`frozen`, a tree of bools that is a prefix of y's, as NumPy bool arrays shaped like
    every leaf of y (None if nothing is frozen)."""
    if frozen is None:
        return None
    mask = jax.tree.map(lambda m, sub: jax.tree.map(lambda x: np.full(np.shape(x), bool(m)), sub),
                        frozen, y)
    return mask if any(np.any(m) for m in jax.tree.leaves(mask)) else None


def _all_finite_small(chunks, bound):
    ok_finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(c)) for c in chunks]))
    ok_small = jnp.all(jnp.stack([jnp.all(jnp.abs(c) <= bound) for c in chunks]))
    return ok_finite, ok_small


def _block_length(n: int, width: int) -> int:
    """The largest divisor L of n with L * width <= SMALL (at least 1): blocks of L steps
    whose per-step records fit XLA:CPU's cheap sequential executor."""
    cap = max(1, SMALL // max(width, 1))
    return max(d for d in range(1, min(cap, n) + 1) if n % d == 0)


def _blocked_scan(body, carry, xs, n: int, width: int, reverse: bool = False):
    """lax.scan over n steps with per-step inputs/outputs grouped in small blocks.

    An outer scan moves whole blocks in and out of the big (n, ...) arrays; the inner scan over
    the L steps of a block touches only <= 512-byte buffers, so XLA:CPU runs it sequentially.
    Same results as a plain scan.
    """
    L = _block_length(n, width)

    def split(a):
        return a.reshape(n // L, L, *a.shape[1:])

    def outer(c, block):
        return jax.lax.scan(body, c, block, reverse=reverse)

    if xs is None:
        def outer(c, _):  # noqa: F811 - the same, without inputs
            return jax.lax.scan(body, c, None, length=L, reverse=reverse)

        carry, ys = jax.lax.scan(outer, carry, None, length=n // L, reverse=reverse)
    else:
        carry, ys = jax.lax.scan(outer, carry, jax.tree.map(split, xs), reverse=reverse)
    return carry, jax.tree.map(lambda a: a.reshape(n, *a.shape[2:]), ys)


# -- one trajectory -------------------------------------------------------------------------------


class Carry(NamedTuple):
    """What the time loop carries from step k to k + 1 (one trajectory)."""

    k: jax.Array  # () int32: the step index
    y: tuple  # state y_k, packed
    acc: tuple  # running reductions over samples 0..k-1, packed
    code: jax.Array  # () int32 status code
    bad: jax.Array  # () int32: first bad step, -1 if none


class _Problem:
    """The static structure of a single-trajectory integration and its step functions."""

    def __init__(self, f, y0, args, reduction, acc0, n_steps, save_every, rates=None,
                 project=None, frozen=None):
        self.f, self.reduction_is_none = f, reduction is None
        self.rates = rates  # None: classical RK4; else ETDRK4 with these decay rates
        self.project = project  # None, or the map applied to the state after every step
        self.n, self.s = n_steps, save_every
        self.yp = _Packer(y0)
        mask = _full_mask(frozen, y0)  # components held inside a step, per packed chunk
        self.frozen = None if mask is None else self.yp.pack_mask(mask)
        self.ap = _Packer(args)
        self.accp = _Packer(acc0 if reduction is not None else ())
        dtype = jnp.result_type(*jax.tree.leaves(y0))
        obs_proto = jax.eval_shape(lambda: f(jnp.zeros((), dtype), y0, args)[1])
        self.op = _Packer(_zeros(obs_proto))
        self.dtype = dtype

    def field(self, t, y, a, packed=True):
        """(y', obs) at (t, y); `a` packed (chunks), or the args pytree itself."""
        dy, obs = self.f(t, self.yp.unpack(y), self.ap.unpack(a) if packed else a)
        return self.yp.pack(dy), self.op.pack(obs)

    def step(self, k, y, a, dt, h=None, scanned=False, packed=True):
        """(y_(k+1), obs_k) by RK4 (or ETDRK4) from y_k (unguarded)."""
        t = k.astype(dt.dtype) * dt
        h = dt if h is None else h

        def f_obs(tt, yy):
            return self.field(tt, yy, a, packed)

        args = self.ap.unpack(a) if packed else a
        if self.rates is not None:
            def rates(tt, yy, obs):
                return self.yp.pack(self.rates(tt, self.yp.unpack(yy), args,
                                               self.op.unpack(obs)))

            y_next, obs = _etdrk4(f_obs, rates, t, y, dt, h, self.frozen)
        else:
            y_next, obs = (_rk4_scanned if scanned else _rk4)(f_obs, t, y, dt, h, self.frozen)
        if self.project is not None:
            y_next = self.yp.pack(self.project(t + dt, self.yp.unpack(y_next), args))
        return y_next, obs

    def update(self, red, acc, k, t, y, obs):
        if self.reduction_is_none:
            return acc
        new = red.update(self.accp.unpack(acc), k, t, self.yp.unpack(y), self.op.unpack(obs))
        return self.accp.pack(new)

    def guarded(self, c: Carry, a, red, dt, bound):
        """One RK4 step with the divergence guard; returns (carry, obs_k)."""
        t = c.k.astype(dt.dtype) * dt
        y_next, obs = self.step(c.k, c.y, a, dt)
        ok_now = c.code == STATUS_OK
        acc = jax.tree.map(lambda old, new: jnp.where(ok_now, new, old), c.acc,
                           self.update(red, c.acc, c.k, t, c.y, obs))
        finite, small = _all_finite_small(y_next, bound)
        bad_now = ok_now & ~(finite & small)
        code = jnp.where(bad_now, jnp.where(finite, STATUS_BOUND, STATUS_NONFINITE), c.code)
        bad = jnp.where(bad_now, c.k + 1, c.bad)
        keep = code == STATUS_OK
        y = jax.tree.map(lambda new, old: jnp.where(keep, new, old), y_next, c.y)
        return Carry(c.k + 1, y, acc, code, bad), obs

    def init(self, y0, acc0):
        i32 = functools.partial(jnp.asarray, dtype=jnp.int32)
        return Carry(i32(0), y0, acc0, i32(STATUS_OK), i32(-1))

    def finish(self, c: Carry, a, red, dt):
        """Observation at t_N and the last sample folded into the reductions."""
        t = c.k.astype(dt.dtype) * dt
        _, obs = self.field(t, c.y, a)
        acc = jax.tree.map(lambda old, new: jnp.where(c.code == STATUS_OK, new, old), c.acc,
                           self.update(red, c.acc, c.k, t, c.y, obs))
        return acc, obs

    # -- the primal loop: saves every s-th state, never stores the others ----------------------
    def forward(self, y0, a, red, acc0, dt, bound):
        n, s = self.n, self.s
        c0 = self.init(y0, acc0)
        obs_zero = self.op.zeros(self.dtype)

        def step(c, _):
            c_new, obs = self.guarded(c, a, red, dt, bound)
            return c_new, (c.y, obs)

        if s == 1:
            chunk = next((q for q in _ROW_CHUNKS if n % q == 0), 1)

            def rows(c, _):
                return jax.lax.scan(step, c, None, length=chunk)

            c, (ys, obs) = jax.lax.scan(rows, c0, None, length=n // chunk)
            ys, obs = (jax.tree.map(lambda v: v.reshape(n, *v.shape[2:]), x) for x in (ys, obs))
        else:
            def block(c, length):
                def inner(cc, _):
                    cr, obs_first, first = cc
                    cr_new, obs = self.guarded(cr, a, red, dt, bound)
                    obs_first = jax.tree.map(lambda o, f_: jnp.where(first, o, f_), obs,
                                             obs_first)
                    return (cr_new, obs_first, jnp.zeros_like(first)), None

                (c_new, obs_first, _), _ = jax.lax.scan(inner, (c, obs_zero, jnp.array(True)),
                                                        None, length=length)
                return c_new, (c.y, obs_first)

            c, (ys, obs) = jax.lax.scan(lambda cc, _: block(cc, s), c0, None, length=n // s)
            if n % s:  # the last, shorter block: its first step is saved too
                c, last = block(c, n % s)
                ys, obs = (jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), x, x_last)
                           for x, x_last in zip((ys, obs), last, strict=True))
        acc, obs_end = self.finish(c, a, red, dt)
        ys = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), ys, c.y)
        obs = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), obs, obs_end)
        return ys, obs, acc, c.code, c.bad

    # -- the same loop, keeping every state, sample and observation (for the linearisation) --
    def forward_all(self, y0, a, red, acc0, dt, bound):
        n = self.n
        c0 = self.init(y0, acc0)

        def step(c, _):
            c_new, obs = self.guarded(c, a, red, dt, bound)
            return c_new, (c.y, c.acc, obs)

        width = max(self.yp.sizes + self.accp.sizes + self.op.sizes, default=1)
        c, (Y, A, O) = _blocked_scan(step, c0, None, n, width)
        acc, obs_end = self.finish(c, a, red, dt)
        return c, Y, A, O, acc, obs_end


def saved_steps(n_steps: int, save_every: int) -> np.ndarray:
    """The step indices k that `integrate` saves: 0, s, 2s, ... below N, and N itself (the
    stride need not divide N: the last interval is then shorter)."""
    return np.append(np.arange(0, n_steps, save_every), n_steps)


def _saved(all_k, end, s):
    """Every s-th row of a per-step record (k = 0..N-1) and the end value (k = N)."""
    return jax.tree.map(lambda v, e: jnp.concatenate([v[::s], e[None]]), all_k, end)


def _time_parallel_jvp(prob: _Problem, primals, tangents):
    """The jvp of `_Problem.forward` as a time-parallel linearisation (see module docstring).

    With c_k the carry, the discrete map is y_(k+1) = Phi_k(y_k; a, dt) and obs_k = O_k(y_k).
    Its tangent is the linear recurrence

        dy_(k+1) = J_k dy_k + b_k,   dobs_k = G_k dy_k + g_k,
        dacc_(k+1) = jvp of the reduction update along (dacc_k, dy_k, dobs_k, dred, dt),

    with J_k = dPhi/dy, G_k = dO/dy (one batched jacfwd over all k: they need only the stored
    primal states) and b_k, g_k the derivatives along (da, d dt) (one batched jvp). Only the
    recurrences run step by step, and they are small. JAX transposes this for reverse mode.

    A frozen step (after a divergence) is linearised with its increments scaled by 0, which
    makes it exactly the identity with finite partials, so no NaN reaches the derivative.
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

    # Reductions: their own (cheap) tangent recurrence along the stored samples.
    t_end = c.k.astype(dt.dtype) * dt
    dt_end = c.k.astype(dt.dtype) * ddt
    dobs_end = jax.jvp(lambda y_, a_, t_: prob.field(t_, y_, a_)[1], (c.y, a, t_end),
                       (dy_end, da, dt_end))[1]
    if prob.reduction_is_none:
        dacc_end = dacc0
    else:
        def acc_step(dacc, inp):
            k, live, acc_k, y_k, o_k, dy_k, do_k = inp
            t_k, dt_k = k.astype(dt.dtype) * dt, k.astype(dt.dtype) * ddt
            _, d_new = jax.jvp(lambda r, ac, t_, y_, o_: prob.update(r, ac, k, t_, y_, o_),
                               (red, acc_k, t_k, y_k, o_k), (dred, dacc, dt_k, dy_k, do_k))
            return jax.tree.map(lambda new, old: jnp.where(live, new, old), d_new, dacc), None

        width = max(prob.yp.sizes + prob.accp.sizes + prob.op.sizes, default=1)
        dacc_n, _ = _blocked_scan(acc_step, dacc0, (ks, live_acc, A, Y, O, dY, dO), n, width)
        _, dacc_last = jax.jvp(lambda r, ac, t_, y_, o_: prob.update(r, ac, c.k, t_, y_, o_),
                               (red, c.acc, t_end, c.y, obs_end),
                               (dred, dacc_n, dt_end, dy_end, dobs_end))
        dacc_end = jax.tree.map(lambda new, old: jnp.where(no_bad, new, old), dacc_last, dacc_n)

    out = (_saved(Y, c.y, s), _saved(O, obs_end, s), acc_end, c.code, c.bad)
    f0 = np.zeros((), dtype=jax.dtypes.float0)
    dout = (_saved(dY, dy_end, s), _saved(dO, dobs_end, s), dacc_end, f0, f0)
    return out, dout


def _parallel(fn, xs):
    """fn vmapped over the leading axis of xs, in chunks of at most _PARALLEL_CHUNK members
    (the last chunk padded by repeating the first member, its results dropped): the memory
    of the batched program is bounded and it is compiled once."""
    n = jax.tree.leaves(xs)[0].shape[0]
    if n <= _PARALLEL_CHUNK:
        return jax.vmap(fn)(*xs)
    n_chunks = -(-n // _PARALLEL_CHUNK)
    pad = n_chunks * _PARALLEL_CHUNK - n

    def chunks(a):
        a = jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad, *a.shape[1:]))]) if pad else a
        return a.reshape(n_chunks, _PARALLEL_CHUNK, *a.shape[1:])

    out = jax.lax.map(lambda c: jax.vmap(fn)(*c), jax.tree.map(chunks, xs))
    return jax.tree.map(lambda a: a.reshape(-1, *a.shape[2:])[:n], out)


def _matvec(rows, v):
    """One output chunk of J v, J stored as jacfwd gives it for chunked in- and outputs:
    `rows` is a tuple over the input chunks j of arrays (out_size, in_size_j)."""
    return sum(jnp.sum(r * vj[None, :], axis=1) for r, vj in zip(rows, v, strict=True))


def _integrate_single(f, y0, args, reduction, acc0, dt, n_steps, save_every, state_bound,
                      time_parallel: bool, rates=None, project=None, frozen=None):
    prob = _Problem(f, y0, args, reduction, acc0, n_steps, save_every, rates, project, frozen)

    def primal(y0c, ac, red, acc0c, dtv, bound):
        return prob.forward(y0c, ac, red, acc0c, dtv, bound)

    if time_parallel:
        primal = jax.custom_jvp(primal)
        primal.defjvp(lambda p, t: _time_parallel_jvp(prob, p, t))
    red = reduction if reduction is not None else ()
    acc0c = prob.accp.pack(acc0 if reduction is not None else ())
    ys, obs, acc, code, bad = primal(prob.yp.pack(y0), prob.ap.pack(args), red, acc0c, dt,
                                     state_bound)
    def unstack(packer, chunks):
        return jax.vmap(packer.unpack)(chunks) if packer.sizes else packer.unpack(())

    return Integration(
        ys=unstack(prob.yp, ys),
        obs=unstack(prob.op, obs),
        acc=prob.accp.unpack(acc) if reduction is not None else None,
        status=Status(code=code, step=bad),
    )


# -- a batch (rows layout) ------------------------------------------------------------------------


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

    def stack(self, y):
        return jnp.stack(y)  # (m, B)

    def unstack(self, ys):
        # ys: (T, m, B) -> pytree with leaves (B, T, ...)
        return jax.vmap(jax.vmap(self.unravel), in_axes=-1)(ys)


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


def _segment_length(save_every: int, target: int | None) -> int | None:
    """Checkpoint segment inside a save block: the largest divisor of save_every <= target."""
    if target is None:
        return None
    if target >= save_every:
        return save_every
    return max(d for d in range(1, target + 1) if save_every % d == 0)


def _integrate_batch(f, y0, args, batch, reduction, acc0, dt, n_steps, save_every,
                     state_bound, checkpoint_every, rates=None, project=None, frozen=None):
    args_flat, unravel_args = _ravel_floats(args)
    y_one, b_one = _first(y0), _first(batch)
    mask = _full_mask(frozen, y_one)  # one Python bool per row: held inside a step
    frozen_rows = (None if mask is None else
                   tuple(bool(m) for leaf in jax.tree.leaves(mask) for m in np.ravel(leaf)))
    acc_one = _first(acc0) if reduction is not None else ()
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

    def rates_member(t, y_row, obs_row, b_col):
        return _scalars(rates(t, ys_c.unpack_one(y_row), (unravel_args(args_flat),
                                                          unravel_b(b_col)),
                              obs_c.unpack_one(obs_row)))

    def rates_rows(t, y, obs):
        return jax.vmap(rates_member, in_axes=(None, 0, 0, -1), out_axes=0)(t, y, obs, b_flat)

    def project_member(t, y_row, b_col):
        return _scalars(project(t, ys_c.unpack_one(y_row), (unravel_args(args_flat),
                                                            unravel_b(b_col))))

    def project_rows(t, y):
        return jax.vmap(project_member, in_axes=(None, 0, -1), out_axes=0)(t, y, b_flat)

    def acc_member(acc_row, k, t, y_row, obs_row):
        new = reduction.update(acc_c.unpack_one(acc_row), k, t, ys_c.unpack_one(y_row),
                               obs_c.unpack_one(obs_row))
        return _scalars(new)

    acc_fn = jax.vmap(acc_member, in_axes=(0, None, None, 0, 0), out_axes=0)
    y_init = tuple(jnp.moveaxis(jax.vmap(lambda y: ravel_pytree(y)[0])(y0), 0, -1))
    acc_init = (tuple(jnp.moveaxis(jax.vmap(lambda a: ravel_pytree(a)[0])(acc0), 0, -1))
                if reduction is not None else ())
    n_batch = jax.tree.leaves(y0)[0].shape[0]

    def acc_update(acc, k, t, y, obs, ok):
        if reduction is None:
            return acc
        new = acc_fn(acc, k, t, y, obs)
        return jax.tree.map(lambda a, b: jnp.where(ok, b, a), acc, new)

    def step(carry):
        k, y, acc, code, bad = carry
        t = k.astype(dt.dtype) * dt
        if rates is None:
            y_next, obs = _rk4(f_obs, t, y, dt, frozen=frozen_rows)
        else:
            y_next, obs = _etdrk4(f_obs, rates_rows, t, y, dt, frozen=frozen_rows)
        if project is not None:
            y_next = project_rows(t + dt, y_next)
        ok_now = code == STATUS_OK
        acc = acc_update(acc, k, t, y, obs, ok_now)
        finite = functools.reduce(jnp.logical_and, [jnp.isfinite(v) for v in y_next])
        small = functools.reduce(jnp.logical_and, [jnp.abs(v) <= state_bound for v in y_next])
        bad_now = ok_now & ~(finite & small)
        code = jnp.where(bad_now, jnp.where(finite, STATUS_BOUND, STATUS_NONFINITE), code)
        bad = jnp.where(bad_now, k + 1, bad)
        keep = code == STATUS_OK
        y_next = tuple(jnp.where(keep, a, b) for a, b in zip(y_next, y, strict=True))
        return (k + 1, y_next, acc, code, bad), obs

    obs_zero = _zeros(jax.eval_shape(lambda y: f_obs(dt, y)[1], y_init))

    def steps(carry, obs_first, first, length):
        def inner(c, _):
            carry_, obs_f, fst = c
            carry_, obs = step(carry_)
            obs_f = jax.tree.map(lambda o, of: jnp.where(fst, o, of), obs, obs_f)
            return (carry_, obs_f, jnp.zeros_like(fst)), None

        return jax.lax.scan(inner, (carry, obs_first, first), None, length=length)[0]

    def block(carry, length):
        # `length` steps (in checkpointed segments); keep the state and obs at the first one.
        y_start = carry[1]
        state = (carry, obs_zero, jnp.array(True))
        seg = _segment_length(length, checkpoint_every)
        if seg is None or seg == length:
            def body(st):
                return steps(*st, length)

            state = (jax.checkpoint(body) if seg else body)(state)
        else:
            @jax.checkpoint
            def segment(st, _):
                return steps(*st, seg), None

            state, _ = jax.lax.scan(segment, state, None, length=length // seg)
        carry, obs_first, _ = state
        return carry, (ys_c.stack(y_start), obs_c.stack(obs_first))

    init = (jnp.zeros((), jnp.int32), y_init, acc_init,
            jnp.full((n_batch,), STATUS_OK, jnp.int32), jnp.full((n_batch,), -1, jnp.int32))
    with barriers(True):
        if save_every == 1:
            chunk = next((c for c in _ROW_CHUNKS if n_steps % c == 0), 1)

            def save_step(carry, _):
                y_start = carry[1]
                carry, obs = step(carry)
                return carry, (ys_c.stack(y_start), obs_c.stack(obs))

            def rows(carry, _):
                return jax.lax.scan(save_step, carry, None, length=chunk)

            rows = jax.checkpoint(rows) if checkpoint_every else rows
            carry, (ys, obs) = jax.lax.scan(rows, init, None, length=n_steps // chunk)
            ys = ys.reshape(n_steps, *ys.shape[2:])
            obs = obs.reshape(n_steps, *obs.shape[2:])
        else:
            carry, (ys, obs) = jax.lax.scan(lambda c, _: block(c, save_every), init, None,
                                            length=n_steps // save_every)
            if n_steps % save_every:  # the last, shorter block: its first step is saved too
                carry, (y_last, obs_last) = block(carry, n_steps % save_every)
                ys = jnp.concatenate([ys, y_last[None]])
                obs = jnp.concatenate([obs, obs_last[None]])
        k, y_end, acc, code, bad = carry
        t_end = k.astype(dt.dtype) * dt
        _, obs_end = f_obs(t_end, y_end)
        acc = acc_update(acc, k, t_end, y_end, obs_end, code == STATUS_OK)
    ys = ys_c.unstack(jnp.concatenate([ys, ys_c.stack(y_end)[None]]))
    obs = obs_c.unstack(jnp.concatenate([obs, obs_c.stack(obs_end)[None]]))
    acc = (jax.vmap(acc_c.unravel, in_axes=-1)(jnp.stack(acc)) if reduction is not None
           else None)
    return Integration(ys=ys, obs=obs, acc=acc, status=Status(code=code, step=bad))


# -- the entry point ------------------------------------------------------------------------------

DEFAULT_CHECKPOINT_EVERY = 100


def integrate(
    f: Callable,
    y0: Pytree,
    dt,
    n_steps: int,
    args=(),
    *,
    batch: Pytree = None,
    save_every: int = 1,
    reduction: Reduction | None = None,
    acc0: Pytree = None,
    state_bound=jnp.inf,
    checkpoint_every: int | None = DEFAULT_CHECKPOINT_EVERY,
    time_parallel: bool = True,
    rates: Callable | None = None,
    project: Callable | None = None,
    frozen: Pytree = None,
) -> Integration:
    """Integrate y' = f(t, y, args) by RK4 on t_k = k dt, k = 0..n_steps.

    Args:
        f: f(t, y, args) -> (dy, obs); obs is an observation at (t, y). With `batch`, f is called
            as f(t, y, args, b) for one batch member b (and does not see the batch axis).
        y0: initial state pytree (with `batch`: every leaf has a leading batch axis B).
        dt: step (traced).
        n_steps: number of steps N (static).
        args: shared arguments passed to f (traced leaves, one copy for the whole batch).
        batch: None, or a pytree whose leaves have a leading batch axis B: per-member arguments.
        save_every: keep the states and observations at the steps 0, s, 2s, ... and always
            at N (`saved_steps`; s need not divide N) (static); memory is O(N/s).
        reduction: None, or a `Reduction` pytree: acc <- reduction.update(acc, k, t_k, y_k,
            obs_k) for every k = 0..N while the trajectory is healthy (running metrics).
        acc0: initial accumulator (with `batch`: leading batch axis).
        state_bound: a state with any |component| above it counts as diverged (traced).
        checkpoint_every: batches only: reverse-mode differentiation keeps the state every this
            many steps (a divisor of save_every is used) and recomputes the steps in between,
            so memory is O(N / L + L) states per member; None keeps every step's residuals.
            One trajectory is differentiated by the time-parallel linearisation instead.
        time_parallel: one trajectory only: differentiate by the time-parallel linearisation
            (default; exact, memory O(N m^2) for m state components). False: JAX's own
            differentiation of the scan (a reference for tests).
        rates: None for classical RK4 (the default). Else the exponential RK4 step
            (`_etdrk4`): rates(t, y, args, obs) gives a decay rate >= 0 for every state
            component (a pytree like y; with `batch`, args is (args, b)) whose linear part
            -rate * y is integrated exactly: stable for stiff linear decays.
        project: None, or project(t, y, args) -> y (with `batch`, args is (args, b)), applied
            to the state after every step, at the step's end time t: a discrete update that
            is no ODE, such as the play operators' clamp (`hysteresis.PrandtlIshlinskii`).
        frozen: None, or a tree of Python bools, a prefix of y's structure (static; for a
            batch, of one member's): True marks components held constant inside a step. Every
            stage reads them unchanged and the step leaves them as they are, whatever f gives
            for their rate (their increments are discarded; in the rows layout never formed);
            only `project` changes them.
            They are still checked against `state_bound` after the step.

    Returns:
        Integration(ys, obs, acc, status); with `batch` every leaf has a leading batch axis.
    """
    dt = jnp.asarray(dt)
    if not jnp.issubdtype(dt.dtype, jnp.floating):
        dt = dt.astype(jnp.result_type(*jax.tree.leaves(y0)))
    state_bound = jnp.asarray(state_bound, dt.dtype)
    if reduction is not None and acc0 is None:
        raise ValueError("a reduction needs its initial accumulator acc0")
    if batch is None:
        return _integrate_single(f, y0, args, reduction, acc0, dt, n_steps, save_every,
                                 state_bound, time_parallel, rates, project, frozen)
    return _integrate_batch(f, y0, args, batch, reduction, acc0, dt, n_steps, save_every,
                            state_bound, checkpoint_every, rates, project, frozen)


__all__ = ["STATUS_BOUND", "STATUS_NONFINITE", "STATUS_OK", "Carry", "Integration",
           "Reduction", "SMALL", "Status", "integrate", "rk4_step", "saved_steps"]
