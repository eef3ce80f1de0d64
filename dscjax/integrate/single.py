"""One trajectory: its state, arguments, observations and reductions packed into a few flat
arrays (`_Packer`: XLA:CPU then moves a couple of buffers per kernel, not dozens of scalars),
stepped by the solver under the divergence guard (`scan.advance`), and differentiated by its
gradient mode (`gradients`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax.integrate import scan
from dscjax.integrate.gradients import TimeParallel, time_parallel_jvp

Pytree = Any


class _Packer:
    """A pytree <-> a tuple of flat float arrays: leaves packed whole, in order, greedily into
    arrays of <= SMALL floats (a larger leaf gets its own); non-float leaves kept aside."""

    def __init__(self, proto):
        leaves, self.treedef = jax.tree.flatten(proto)
        self.fixed = {}  # index: value of the non-float leaves
        self.slots = []  # (index, chunk, offset, size, shape)
        sizes: list[int] = []
        for i, leaf in enumerate(leaves):
            if not jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
                self.fixed[i] = leaf
                continue
            shape = np.shape(leaf)
            size = int(np.prod(shape, dtype=int))
            if not sizes or sizes[-1] + size > scan.SMALL:
                sizes.append(0)
            self.slots.append((i, len(sizes) - 1, sizes[-1], size, shape))
            sizes[-1] += size
        self.sizes = tuple(sizes)

    def pack(self, tree, xp=jnp) -> tuple:
        """The float leaves in chunks; with xp=np a static tree (`frozen`'s NumPy bools)."""
        leaves = jax.tree.leaves(tree)
        parts: list[list] = [[] for _ in self.sizes]
        for i, chunk, _, _, _ in self.slots:
            parts[chunk].append(xp.ravel(leaves[i]))
        return tuple(p[0] if len(p) == 1 else xp.concatenate(p) for p in parts)

    def unpack(self, chunks) -> Pytree:
        leaves = [self.fixed.get(i) for i in range(self.treedef.num_leaves)]
        for i, chunk, off, size, shape in self.slots:
            c = chunks[chunk]
            leaves[i] = (c if size == c.shape[-1] and off == 0 else c[off:off + size]).reshape(
                shape)
        return jax.tree.unflatten(self.treedef, leaves)


class _Problem:
    """The static structure of a single-trajectory integration and its step functions."""

    def __init__(self, f, y0, args, reduction, acc0, n_steps, save_every, solver, rates,
                 project, frozen, skip_diverged, substeps):
        self.f, self.reduction_is_none = f, reduction is None
        self.skip_diverged, self.substeps = skip_diverged, substeps
        self.solver, self.rates, self.project = solver, rates, project
        self.n, self.s = n_steps, save_every
        self.yp, self.ap, self.accp = _Packer(y0), _Packer(args), _Packer(acc0)
        mask = scan.frozen_mask(frozen, y0)  # components held inside a step, per packed chunk
        self.frozen = None if mask is None else self.yp.pack(mask, np)
        self.dtype = jnp.result_type(*jax.tree.leaves(y0))
        # one trace of the field for every call with the same shapes (RK4's four stages, the
        # last observation, the linearisation, and the shapes of the observations here): an
        # inner jit, inlined by XLA
        self._unpacked_field = jax.jit(
            lambda t, y, a: f(t, self.yp.unpack(y), self.ap.unpack(a)))
        obs_proto = jax.eval_shape(self._unpacked_field, jnp.zeros((), self.dtype),
                                   self.yp.pack(y0), self.ap.pack(args))[1]
        self.op = _Packer(scan.zeros(obs_proto))

    def field(self, t, y, a, packed=True):
        """(y', obs) at (t, y); `a` packed (chunks), or the args pytree itself."""
        dy, obs = self._unpacked_field(t, y, a) if packed else self.f(t, self.yp.unpack(y), a)
        return self.yp.pack(dy), self.op.pack(obs)

    def step(self, k, y, a, dt, h=None, scanned=False, packed=True):
        """(y_(k+1), obs_k) by the solver from y_k (unguarded)."""
        t = k.astype(dt.dtype) * dt

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
        return self.accp.pack(red.update(self.accp.unpack(acc), k, t, self.yp.unpack(y),
                                         self.op.unpack(obs), dt))

    def guarded(self, c: scan.Carry, a, red, dt, bound):
        """One RK4 step with the divergence guard; returns (carry, obs_k)."""
        t = c.k.astype(dt.dtype) * dt
        y_next, obs = self.step(c.k, c.y, a, dt)
        acc = self.update(red, c.acc, c.k, t, c.y, obs, dt)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in y_next]))
        small = jnp.all(jnp.stack([jnp.all(jnp.abs(v) <= bound) for v in y_next]))
        return scan.advance(c, y_next, acc, finite, small), obs

    def observe(self, c: scan.Carry, a, dt):
        """The observation at the carry's step and state, without a step."""
        return self.field(c.k.astype(dt.dtype) * dt, c.y, a)[1]

    def finish(self, c: scan.Carry, a, red, dt):
        """Observation at t_N and the last sample folded into the reductions."""
        t = c.k.astype(dt.dtype) * dt
        obs = self.observe(c, a, dt)
        acc = scan.kept(c.code == scan.STATUS_OK, self.update(red, c.acc, c.k, t, c.y, obs, dt),
                        c.acc)
        return acc, obs

    # the primal loop: saves every s-th state, never stores the others
    def forward(self, y0, a, red, acc0, dt, bound):
        obs_zero = tuple(jnp.zeros((size,), self.dtype) for size in self.op.sizes)
        c, (ys, obs) = scan.saving_scan(
            lambda c: self.guarded(c, a, red, dt, bound), scan.start(y0, acc0), obs_zero,
            self.n, self.s, lambda c, obs: (c.y, obs),
            observe=(lambda c: self.observe(c, a, dt)) if self.skip_diverged else None,
            substeps=self.substeps)
        acc, obs_end = self.finish(c, a, red, dt)
        ys, obs = jax.tree.map(lambda v, e: jnp.concatenate([v, e[None]]), (ys, obs),
                               (c.y, obs_end))
        return ys, obs, acc, c.code, c.bad

    # the same loop, keeping every state, sample and observation (for the linearisation)
    def forward_all(self, y0, a, red, acc0, dt, bound):
        def step(c, _):
            c_new, obs = self.guarded(c, a, red, dt, bound)
            return c_new, (c.y, c.acc, obs)

        width = max(self.yp.sizes + self.accp.sizes + self.op.sizes, default=1)
        c, (Y, A, O) = scan.blocked_scan(step, scan.start(y0, acc0), self.n, width)
        acc, obs_end = self.finish(c, a, red, dt)
        return c, Y, A, O, acc, obs_end


def integrate_single(f, y0, args, reduction, acc0, dt, n_steps, save_every, state_bound,
                     solver, gradient, rates, project, frozen, skip_diverged, substeps):
    prob = _Problem(f, y0, args, reduction, acc0, n_steps, save_every, solver, rates, project,
                    frozen, skip_diverged, substeps)

    primal = prob.forward
    if isinstance(gradient, TimeParallel) and substeps is None:
        primal = jax.custom_jvp(primal)
        primal.defjvp(lambda p, t: time_parallel_jvp(prob, p, t))
    red = reduction if reduction is not None else ()
    ys, obs, acc, code, bad = primal(prob.yp.pack(y0), prob.ap.pack(args), red,
                                     prob.accp.pack(acc0), dt, state_bound)

    def unstack(packer, chunks):
        return jax.vmap(packer.unpack)(chunks) if packer.sizes else packer.unpack(())

    acc = prob.accp.unpack(acc) if reduction is not None else None
    return scan.Integration(unstack(prob.yp, ys), unstack(prob.op, obs), acc,
                            scan.Status(code, bad))
