"""Fixed-step integration over pytrees on t_k = k dt, a `jax.lax.scan`; knows nothing of DSC.

`integrate(f, y0, dt, n_steps, ...)` takes f(t, y, args) -> (dy, obs), obs read off for saving
and for the running reductions (`Running`). Strategies are objects, as in diffrax: the solver
(`RK4()`, `ETDRK4()`: exact on the stiff linear decays the model reports) and the gradient
(`TimeParallel()`: one trajectory's N step Jacobians at once, then a small recurrence;
`Checkpointed(every)`: JAX's own differentiation of the scan). A batch is differentiated
through its scan, checkpointed every `every` steps. Layouts suit XLA:CPU
(docs/architecture.md): one trajectory as flat vectors of at most `SMALL` floats, a batch
batch-last, one (B,) row per state component.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple, Protocol

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax.xla import barriers

Pytree = Any

STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_BOUND = 2

SMALL = 64  # floats per buffer for XLA:CPU's sequential loop-body executor (512 bytes f64)

# Rows are written from an inner scan over this many steps when every step is saved: one scan
# that both steps and writes rows is slower on XLA:CPU.
_ROW_CHUNKS = (4, 2)
# Members per chunk of the time-parallel Jacobians (bounds their memory, not their result).
_PARALLEL_CHUNK = 8192


# -- RK4 ------------------------------------------------------------------------------------------


def _axpy(a, x, y):
    """y + a x over pytrees."""
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


def _hold(new, y, frozen):
    """`new` with the frozen components taken from y. `frozen` (static): None, or a tree like
    y of Python bools (batch rows: a frozen row's increments are dead code) or NumPy bool
    arrays (packed chunks: computed, then discarded by the select)."""
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
    """RK4 step for f_obs(t, y) -> (dy, obs); returns (y_next, obs at (t, y)). `h` (default
    dt) scales the increments only: h = 0 gives y_next = y with the stages at finite points
    (how frozen steps are linearised safely). `frozen`: see `_hold`."""
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
    """One ETDRK4 step (Cox & Matthews 2002) of y' = -lam y + N(t, y), lam = rates(t_k, y_k,
    obs_k) >= 0 (like y) frozen over the step: the stiff decays integrated exactly, so the step
    is stable however large lam h is; classical RK4 where lam = 0. As `_rk4` otherwise."""
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


def _rk4_scanned(f_obs, t, y, dt, h, frozen=None):
    """`_rk4` with its four stages a `lax.scan` over one copy of f_obs, for bulk
    differentiation (one copy of the field's derivative compiles faster). Equal to round-off."""
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


class Running(Protocol):
    """A running reduction over every step k = 0..N while the run is healthy (metrics,
    tuning's terms and requirements, progress); a pytree whose numbers are traced leaves.

        init(dtype) -> acc                         a pytree of scalars
        update(acc, k, t, y, obs, dt) -> acc       at step k: time t_k, state y_k, obs_k
        finalize(acc, t_final) -> {name: value}
    """

    def init(self, dtype) -> Any: ...

    def update(self, acc, k, t, y, obs, dt) -> Any: ...

    def finalize(self, acc, t_final) -> dict[str, jax.Array]: ...


# -- strategies: solvers and gradients (adding one is a class here) -------------------------------


class Solver(eqx.Module):
    """A one-step method: `step(f_obs, rates, t, y, dt, h, frozen) -> (y_next, obs at (t, y))`.
    `rates(t, y, obs)` gives the stiff linear decays the model knows of (ETDRK4 uses them)."""

    name: ClassVar[str]

    def step(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        raise NotImplementedError

    def step_scanned(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        """The same step, written for bulk differentiation (the time-parallel Jacobians)."""
        return self.step(f_obs, rates, t, y, dt, h, frozen)


class RK4(Solver):
    """Classical fourth-order Runge-Kutta (the paper's method)."""

    name: ClassVar[str] = "rk4"

    def step(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        return _rk4(f_obs, t, y, dt, h, frozen)

    def step_scanned(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        return _rk4_scanned(f_obs, t, y, dt, dt if h is None else h, frozen)


class ETDRK4(Solver):
    """Exponential RK4 (Cox & Matthews 2002): the decays `rates` integrated exactly, the rest
    with exponential weights; stable however stiff those decays are, and RK4 where they are 0."""

    name: ClassVar[str] = "etdrk4"

    def step(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        if rates is None:
            raise ValueError("ETDRK4 needs the model's decay rates (integrate(rates=...))")
        return _etdrk4(f_obs, rates, t, y, dt, h, frozen)


SOLVERS: dict[str, type[Solver]] = {c.name: c for c in (RK4, ETDRK4)}


def solver(spec: str | Solver) -> Solver:
    """A Solver from its name ("rk4", "etdrk4") or itself."""
    if isinstance(spec, Solver):
        return spec
    if spec not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)} (got {spec!r})")
    return SOLVERS[spec]()


DEFAULT_CHECKPOINT_EVERY = 100


class Gradient(eqx.Module):
    """How an integration is differentiated. `every`: a batch's scan keeps its state every this
    many steps and recomputes the rest (None keeps every step's residuals)."""

    name: ClassVar[str]
    every: int | None = DEFAULT_CHECKPOINT_EVERY


class TimeParallel(Gradient):
    """One trajectory: all N step Jacobians in one batched program, then a small recurrence
    (the exact derivative of the discrete map; memory O(N m^2))."""

    name: ClassVar[str] = "time_parallel"


class Checkpointed(Gradient):
    """JAX's own differentiation of the scan (a reference for tests)."""

    name: ClassVar[str] = "checkpointed"


GRADIENTS: dict[str, type[Gradient]] = {c.name: c for c in (TimeParallel, Checkpointed)}


# -- flat packing ---------------------------------------------------------------------------------


class _Packer:
    """A pytree <-> a tuple of flat float arrays: leaves packed whole, in order, greedily into
    arrays of <= SMALL floats (a larger leaf gets its own); non-float leaves kept aside."""

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
    """`frozen` (a prefix of y's tree) as NumPy bool arrays shaped like y's leaves, or None."""
    if frozen is None:
        return None
    mask = jax.tree.map(lambda m, sub: jax.tree.map(lambda x: np.full(np.shape(x), bool(m)), sub),
                        frozen, y)
    return mask if any(np.any(m) for m in jax.tree.leaves(mask)) else None


def _all_finite_small(chunks, bound):
    ok_finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(c)) for c in chunks]))
    ok_small = jnp.all(jnp.stack([jnp.all(jnp.abs(c) <= bound) for c in chunks]))
    return ok_finite, ok_small


def _guard(ok_now, finite, small, k, code, bad):
    """(code, first bad step, keep) after step k: a state that left the bound or went
    non-finite freezes the run at its last good state."""
    bad_now = ok_now & ~(finite & small)
    code = jnp.where(bad_now, jnp.where(finite, STATUS_BOUND, STATUS_NONFINITE), code)
    return code, jnp.where(bad_now, k + 1, bad), code == STATUS_OK


def _saving_scan(step, c0, obs_zero, n: int, s: int, record, every: int | None = None):
    """n steps of `step(c) -> (c, obs)` from c0, keeping record(c, obs) of the steps 0, s, 2s,
    ... (c the carry before the step; a last, shorter block's first step too); a batch's
    steps are checkpointed in segments of `every` (None: not checkpointed)."""
    if s == 1:
        chunk = next((q for q in _ROW_CHUNKS if n % q == 0), 1)

        def save_step(c, _):
            c_new, obs = step(c)
            return c_new, record(c, obs)

        def rows(c, _):
            return jax.lax.scan(save_step, c, None, length=chunk)

        c, recs = jax.lax.scan(jax.checkpoint(rows) if every else rows, c0, None,
                               length=n // chunk)
        return c, jax.tree.map(lambda v: v.reshape(n, *v.shape[2:]), recs)

    def steps(state, length):
        def inner(st, _):
            c, obs_f, first = st
            c, obs = step(c)
            obs_f = jax.tree.map(lambda o, of: jnp.where(first, o, of), obs, obs_f)
            return (c, obs_f, jnp.zeros_like(first)), None

        return jax.lax.scan(inner, state, None, length=length)[0]

    def block(c, length):
        state = (c, obs_zero, jnp.array(True))
        seg = _segment_length(length, every)
        if seg is None or seg == length:
            def body(st):
                return steps(st, length)

            state = (jax.checkpoint(body) if seg else body)(state)
        else:
            @jax.checkpoint
            def segment(st, _):
                return steps(st, seg), None

            state, _ = jax.lax.scan(segment, state, None, length=length // seg)
        return state[0], record(c, state[1])

    c, recs = jax.lax.scan(lambda cc, _: block(cc, s), c0, None, length=n // s)
    if n % s:
        c, last = block(c, n % s)
        recs = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), recs, last)
    return c, recs


def _block_length(n: int, width: int) -> int:
    """The largest divisor L of n with L * width <= SMALL (at least 1)."""
    cap = max(1, SMALL // max(width, 1))
    return max(d for d in range(1, min(cap, n) + 1) if n % d == 0)


def _blocked_scan(body, carry, xs, n: int, width: int, reverse: bool = False):
    """lax.scan over n steps in blocks of L: the inner scan touches only small buffers (run
    sequentially by XLA:CPU), the outer one moves whole blocks. Same results as a plain scan."""
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

    def __init__(self, f, y0, args, reduction, acc0, n_steps, save_every, solver, rates=None,
                 project=None, frozen=None):
        self.f, self.reduction_is_none = f, reduction is None
        self.solver, self.rates, self.project = solver, rates, project
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
        """(y_(k+1), obs_k) by the solver from y_k (unguarded)."""
        t = k.astype(dt.dtype) * dt
        h = dt if h is None else h

        def f_obs(tt, yy):
            return self.field(tt, yy, a, packed)

        args = self.ap.unpack(a) if packed else a
        rates = None
        if self.rates is not None:
            def rates(tt, yy, obs):
                return self.yp.pack(self.rates(tt, self.yp.unpack(yy), args,
                                               self.op.unpack(obs)))

        method = self.solver.step_scanned if scanned else self.solver.step
        y_next, obs = method(f_obs, rates, t, y, dt, h, self.frozen)
        if self.project is not None:
            y_next = self.yp.pack(self.project(k + 1, t + dt, self.yp.unpack(y_next), args))
        return y_next, obs

    def update(self, red, acc, k, t, y, obs, dt):
        if self.reduction_is_none:
            return acc
        new = red.update(self.accp.unpack(acc), k, t, self.yp.unpack(y), self.op.unpack(obs),
                         dt)
        return self.accp.pack(new)

    def guarded(self, c: Carry, a, red, dt, bound):
        """One RK4 step with the divergence guard; returns (carry, obs_k)."""
        t = c.k.astype(dt.dtype) * dt
        y_next, obs = self.step(c.k, c.y, a, dt)
        ok_now = c.code == STATUS_OK
        acc = jax.tree.map(lambda old, new: jnp.where(ok_now, new, old), c.acc,
                           self.update(red, c.acc, c.k, t, c.y, obs, dt))
        finite, small = _all_finite_small(y_next, bound)
        code, bad, keep = _guard(ok_now, finite, small, c.k, c.code, c.bad)
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
                           self.update(red, c.acc, c.k, t, c.y, obs, dt))
        return acc, obs

    # the primal loop: saves every s-th state, never stores the others
    def forward(self, y0, a, red, acc0, dt, bound):
        c, (ys, obs) = _saving_scan(lambda c: self.guarded(c, a, red, dt, bound),
                                    self.init(y0, acc0), self.op.zeros(self.dtype), self.n,
                                    self.s, lambda c, obs: (c.y, obs))
        acc, obs_end = self.finish(c, a, red, dt)
        ys = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), ys, c.y)
        obs = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), obs, obs_end)
        return ys, obs, acc, c.code, c.bad

    # the same loop, keeping every state, sample and observation (for the linearisation)
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
    """The jvp of `_Problem.forward` as a time-parallel linearisation of y_(k+1) =
    Phi_k(y_k; a, dt), obs_k = O_k(y_k):

        dy_(k+1) = J_k dy_k + b_k,   dobs_k = G_k dy_k + g_k,
        dacc_(k+1) = jvp of the reduction update along (dacc_k, dy_k, dobs_k, dred, dt),

    J_k = dPhi/dy, G_k = dO/dy by one batched jacfwd over the stored states, b_k, g_k along
    (da, d dt) by one batched jvp; only the small recurrences run step by step. JAX transposes
    it for reverse mode. A frozen step (after a divergence) has its increments scaled by 0:
    exactly the identity with finite partials, so no NaN reaches the derivative.
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
            _, d_new = jax.jvp(
                lambda r, ac, t_, y_, o_, h_: prob.update(r, ac, k, t_, y_, o_, h_),
                (red, acc_k, t_k, y_k, o_k, dt), (dred, dacc, dt_k, dy_k, do_k, ddt))
            return jax.tree.map(lambda new, old: jnp.where(live, new, old), d_new, dacc), None

        width = max(prob.yp.sizes + prob.accp.sizes + prob.op.sizes, default=1)
        dacc_n, _ = _blocked_scan(acc_step, dacc0, (ks, live_acc, A, Y, O, dY, dO), n, width)
        _, dacc_last = jax.jvp(
            lambda r, ac, t_, y_, o_, h_: prob.update(r, ac, c.k, t_, y_, o_, h_),
            (red, c.acc, t_end, c.y, obs_end, dt), (dred, dacc_n, dt_end, dy_end, dobs_end, ddt))
        dacc_end = jax.tree.map(lambda new, old: jnp.where(no_bad, new, old), dacc_last, dacc_n)

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
                      solver, gradient, rates=None, project=None, frozen=None):
    prob = _Problem(f, y0, args, reduction, acc0, n_steps, save_every, solver, rates, project,
                    frozen)

    def primal(y0c, ac, red, acc0c, dtv, bound):
        return prob.forward(y0c, ac, red, acc0c, dtv, bound)

    if isinstance(gradient, TimeParallel):
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
    """A batch: the state is a tuple of m rows of shape (B,), one per component. Packing
    computed components into one array lets XLA fuse the whole field into the concatenate,
    which then recomputes the control law once per component; rows are stacked only to save."""

    def __init__(self, proto):
        self.unravel = ravel_pytree(proto)[1]

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
                     state_bound, solver, gradient, rates=None, project=None, frozen=None):
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

    def project_member(k, t, y_row, b_col):
        return _scalars(project(k, t, ys_c.unpack_one(y_row), (unravel_args(args_flat),
                                                               unravel_b(b_col))))

    def project_rows(k, t, y):
        return jax.vmap(project_member, in_axes=(None, None, 0, -1), out_axes=0)(k, t, y, b_flat)

    def acc_member(acc_row, k, t, y_row, obs_row):
        new = reduction.update(acc_c.unpack_one(acc_row), k, t, ys_c.unpack_one(y_row),
                               obs_c.unpack_one(obs_row), dt)
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
        y_next, obs = solver.step(f_obs, rates_rows if rates is not None else None, t, y, dt,
                                  frozen=frozen_rows)
        if project is not None:
            y_next = project_rows(k + 1, t + dt, y_next)
        ok_now = code == STATUS_OK
        acc = acc_update(acc, k, t, y, obs, ok_now)
        finite = functools.reduce(jnp.logical_and, [jnp.isfinite(v) for v in y_next])
        small = functools.reduce(jnp.logical_and, [jnp.abs(v) <= state_bound for v in y_next])
        code, bad, keep = _guard(ok_now, finite, small, k, code, bad)
        y_next = tuple(jnp.where(keep, a, b) for a, b in zip(y_next, y, strict=True))
        return (k + 1, y_next, acc, code, bad), obs

    obs_zero = _zeros(jax.eval_shape(lambda y: f_obs(dt, y)[1], y_init))
    init = (jnp.zeros((), jnp.int32), y_init, acc_init,
            jnp.full((n_batch,), STATUS_OK, jnp.int32), jnp.full((n_batch,), -1, jnp.int32))
    with barriers(True):
        carry, (ys, obs) = _saving_scan(
            step, init, obs_zero, n_steps, save_every,
            lambda c, o: (ys_c.stack(c[1]), obs_c.stack(o)), gradient.every)
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


def integrate(
    f: Callable,
    y0: Pytree,
    dt,
    n_steps: int,
    args=(),
    *,
    batch: Pytree = None,
    save_every: int = 1,
    reduction: Running | None = None,
    state_bound=jnp.inf,
    solver: Solver | None = None,
    gradient: Gradient | None = None,
    rates: Callable | None = None,
    project: Callable | None = None,
    frozen: Pytree = None,
) -> Integration:
    """Integrate y' = f(t, y, args) on t_k = k dt, k = 0..n_steps.

    Args:
        f: f(t, y, args) -> (dy, obs), obs an observation at (t, y); with `batch`, called as
            f(t, y, args, b) for one member b (without the batch axis).
        y0: initial state pytree (with `batch`: every leaf has a leading batch axis B).
        dt: step (traced). n_steps: N (static).
        args: shared arguments of f (traced, one copy for the whole batch).
        batch: None, or per-member arguments, leaves with a leading batch axis B.
        save_every: s (static): keep the steps 0, s, 2s, ... and always N (`saved_steps`).
        reduction: None, or a `Running` updated at every k = 0..N while the run is healthy;
            `Integration.acc` is its raw accumulator.
        state_bound: a state with any |component| above it counts as diverged (traced).
        solver: `RK4()` (default) or `ETDRK4()` (needs `rates`).
        gradient: `TimeParallel()` (default) or `Checkpointed()`; `every` is the checkpoint
            segment of a batch's scan.
        rates: rates(t, y, args, obs) -> decay rates >= 0 like y, integrated exactly by
            ETDRK4 (with `batch`, args is (args, b)).
        project: None, or project(k, t, y, args) -> y, applied after every step at its end
            (step k, time t): a discrete update (the plays' clamp, a sampled controller).
        frozen: None, or a static tree of Python bools, a prefix of y's (one member's):
            components held inside a step, changed only by `project`, still bound-checked.

    Returns:
        Integration(ys, obs, acc, status); with `batch` every leaf has a leading batch axis.
    """
    solver = RK4() if solver is None else solver
    gradient = TimeParallel() if gradient is None else gradient
    dt = jnp.asarray(dt)
    if not jnp.issubdtype(dt.dtype, jnp.floating):
        dt = dt.astype(jnp.result_type(*jax.tree.leaves(y0)))
    state_bound = jnp.asarray(state_bound, dt.dtype)
    acc0 = None
    if reduction is not None:
        acc0 = reduction.init(dt.dtype)
        if batch is not None:
            n_batch = jax.tree.leaves(y0)[0].shape[0]
            acc0 = jax.tree.map(lambda a: jnp.broadcast_to(a, (n_batch, *jnp.shape(a))), acc0)
    if batch is None:
        return _integrate_single(f, y0, args, reduction, acc0, dt, n_steps, save_every,
                                 state_bound, solver, gradient, rates, project, frozen)
    return _integrate_batch(f, y0, args, batch, reduction, acc0, dt, n_steps, save_every,
                            state_bound, solver, gradient, rates, project, frozen)


__all__ = ["DEFAULT_CHECKPOINT_EVERY", "ETDRK4", "GRADIENTS", "RK4", "SOLVERS", "STATUS_BOUND",
           "STATUS_NONFINITE", "STATUS_OK", "Carry", "Checkpointed", "Gradient", "Integration",
           "Running", "SMALL", "Solver", "Status", "TimeParallel", "integrate", "rk4_step",
           "saved_steps", "solver"]
