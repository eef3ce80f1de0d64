"""The time loop every layout shares: the divergence `Status` and its guard, the saving scan
(the save stride, checkpointed segments), the blocked scan of small buffers, the `Running`
protocol of running reductions and the `Integration` an integration returns.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

Pytree = Any

STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_BOUND = 2

SMALL = 64  # floats per buffer for XLA:CPU's sequential loop-body executor (512 bytes f64)

# `saving_scan` with `observe` tests whether every member has diverged once every this many
# steps (at most, in groups of whole save blocks; exactly, in parts of a longer block).
SKIP_STEPS = 256

# Rows are written from an inner scan over this many steps when every step is saved: one scan
# that both steps and writes rows is slower on XLA:CPU.
_ROW_CHUNKS = (4, 2)


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


def saved_steps(n_steps: int, save_every: int) -> np.ndarray:
    """The step indices k that `integrate` saves: 0, s, 2s, ... below N, and N itself (the
    stride need not divide N: the last interval is then shorter)."""
    return np.append(np.arange(0, n_steps, save_every), n_steps)


def zeros(shape_tree):
    """Zeros shaped like a tree of `jax.ShapeDtypeStruct`s."""
    return jax.tree.map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shape_tree)


def frozen_mask(frozen, y):
    """`frozen` (a prefix of y's tree) as NumPy bool arrays shaped like y's leaves, or None."""
    if frozen is None:
        return None
    mask = jax.tree.map(lambda m, sub: jax.tree.map(lambda x: np.full(np.shape(x), bool(m)), sub),
                        frozen, y)
    return mask if any(np.any(m) for m in jax.tree.leaves(mask)) else None


class Carry(NamedTuple):
    """What the time loop carries from step k to k + 1 (code and bad: one per batch member)."""

    k: jax.Array  # () int32: the step index
    y: tuple  # state y_k (packed chunks, or a batch's rows)
    acc: tuple  # running reductions over samples 0..k-1, likewise
    code: jax.Array  # int32 status code
    bad: jax.Array  # int32: first bad step, -1 if none


def start(y0, acc0, members=()) -> Carry:
    """The carry at step 0; `members`: the shape of the status, (B,) for a batch."""
    return Carry(jnp.zeros((), jnp.int32), y0, acc0, jnp.full(members, STATUS_OK, jnp.int32),
                 jnp.full(members, -1, jnp.int32))


def kept(ok, new, old):
    """`new` where ok, else `old` (pytrees alike)."""
    return jax.tree.map(lambda n, o: jnp.where(ok, n, o), new, old)


def advance(c: Carry, y_next, acc, finite, small) -> Carry:
    """The carry after step k: `acc` (sample k folded in) kept while the run is healthy, and
    y_next unless it left the bound or went non-finite: that freezes the run at its last
    good state."""
    ok_now = c.code == STATUS_OK
    bad_now = ok_now & ~(finite & small)
    code = jnp.where(bad_now, jnp.where(finite, STATUS_BOUND, STATUS_NONFINITE), c.code)
    return Carry(c.k + 1, kept(code == STATUS_OK, y_next, c.y), kept(ok_now, acc, c.acc), code,
                 jnp.where(bad_now, c.k + 1, c.bad))


def substepped(step, m, obs_zero):
    """`step` (c -> (c, obs)) taken m times (m traced) as one step, with the observation of
    the first; a step that starts with every member diverged takes one (a diverged run is
    frozen: only its k advances)."""
    def body(i, state):
        c, obs_first = state
        c, obs = step(c)
        return c, kept(i == 0, obs, obs_first)

    def steps(c):
        more = jnp.where(jnp.all(c.code != STATUS_OK), 1, m)
        c_new, obs = jax.lax.fori_loop(0, more, body, (c, obs_zero))
        return c_new._replace(k=c.k + m), obs

    return steps


def saving_scan(step, c0, obs_zero, n: int, s: int, record, every: int | None = None,
                observe=None, substeps=None):
    """n steps of `step(c) -> (c, obs)` from c0, keeping record(c, obs) of the steps 0, s, 2s,
    ... (c the carry before the step; a last, shorter block's first step too); a batch's
    steps are checkpointed in segments of `every` (None: not checkpointed).

    With `observe(c) -> obs` (the observation at c, without a step) the steps run in parts
    of up to `SKIP_STEPS` steps (groups of blocks, or parts of a long block), and a
    part that starts with every member diverged is not stepped: a diverged run is frozen, so
    it keeps c (k advanced) and records observe(c) for a block that starts there, which is
    what the steps would have given.

    With `substeps` m (traced), each of the n steps is m steps (`substepped`), k advancing by
    m: one program for every m."""
    stride = 1
    if substeps is not None:
        step, stride = substepped(step, substeps, obs_zero), substeps
    if s == 1 and observe is None:
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
            obs_f = kept(first, obs, obs_f)
            return (c, obs_f, jnp.zeros_like(first)), None

        return jax.lax.scan(inner, state, None, length=length)[0]

    def run(state, length):
        """`length` steps from state, checkpointed in segments of `every`."""
        seg = None if every is None else _largest_divisor(length, every)
        if seg is None or seg == length:
            def body(st):
                return steps(st, length)

            return (jax.checkpoint(body) if seg else body)(state)

        @jax.checkpoint
        def segment(st, _):
            return steps(st, seg), None

        return jax.lax.scan(segment, state, None, length=length // seg)[0]

    def diverged(c):
        return jnp.all(c.code != STATUS_OK)

    def block(c, length):
        state = (c, obs_zero, jnp.array(True))
        if observe is None or length <= SKIP_STEPS:
            state = run(state, length)
        else:  # a long block: its parts of SKIP_STEPS steps, each skipped once all diverged
            def skip(st):
                cc, obs_f, first = st
                return (cc._replace(k=cc.k + SKIP_STEPS * stride), kept(first, observe(cc), obs_f),
                        jnp.zeros_like(first))

            def part(st, _):
                return jax.lax.cond(diverged(st[0]), skip, lambda st: run(st, SKIP_STEPS),
                                    st), None

            state = jax.lax.scan(part, state, None, length=length // SKIP_STEPS)[0]
            if length % SKIP_STEPS:
                state = run(state, length % SKIP_STEPS)
        return state[0], record(c, state[1])

    def blocks(c, count):
        return jax.lax.scan(lambda cc, _: block(cc, s), c, None, length=count)

    count = n // s
    if observe is None or s > SKIP_STEPS:
        c, recs = blocks(c0, count)
    else:  # short blocks: in groups of up to SKIP_STEPS steps, each skipped once all diverged
        group = _largest_divisor(count, SKIP_STEPS // s)

        def skipped(c):
            return jax.lax.scan(lambda cc, _: (cc._replace(k=cc.k + s * stride),
                                               record(cc, observe(cc))), c, None, length=group)

        def part(c, _):
            return jax.lax.cond(diverged(c), skipped, lambda cc: blocks(cc, group), c)

        c, recs = jax.lax.scan(part, c0, None, length=count // group)
        recs = jax.tree.map(lambda v: v.reshape(count, *v.shape[2:]), recs)
    if n % s:
        c, last = block(c, n % s)
        recs = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), recs, last)
    return c, recs


def _largest_divisor(n: int, cap: int) -> int:
    """The largest divisor of n that is <= cap: a checkpoint segment inside a save block (cap
    the target), or a block of `blocked_scan` (cap SMALL // width, at least 1)."""
    return max(d for d in range(1, min(cap, n) + 1) if n % d == 0)


def blocked_scan(body, carry, n: int, width: int):
    """lax.scan of body(c, None) over n steps in blocks of L: the inner scan touches only small
    buffers (run sequentially by XLA:CPU), the outer one moves whole blocks. Same results as a
    plain scan."""
    L = _largest_divisor(n, max(1, SMALL // max(width, 1)))

    def outer(c, _):
        return jax.lax.scan(body, c, None, length=L)

    carry, ys = jax.lax.scan(outer, carry, None, length=n // L)
    return carry, jax.tree.map(lambda a: a.reshape(n, *a.shape[2:]), ys)
