"""An experiment as a pure function of numbers: the actuator (and the plant behind it) driven
by the measured input u(t), simulated on the record's own time stamps.

    exp = Experiment.make(record, plant=True, dt=1e-3, segments=4)
    x, w, ends = simulate(setup, exp, x_init)     # (N, n), (N,), (S - 1, n)

Between two samples u is held (`hold = "zoh"`: the actuator steps along its own curve at each
sample, `Hysteresis.jump`) or linear (`"linear"`: u' constant, the hysteresis rate integrated
with the plant). Each interval is integrated by `substeps` RK4 steps of at most dt
(`integrate.rk4_steps`). With segments (multiple shooting) the plant restarts at each
segment's first sample from a state of its own, `x_init[s]`; the actuator, driven by u alone,
runs through the whole record. A plain `lax.scan`: differentiable in both modes, so Jacobians
come by forward mode.
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax.closed_loop import Setup
from dscjax.integrate import rk4_steps

Hold = Literal["linear", "zoh"]
HOLDS: tuple[str, ...] = ("linear", "zoh")


class Experiment(eqx.Module):
    """The record's time stamps and input, and how it is simulated."""

    t: jax.Array  # (N,) increasing
    u: jax.Array  # (N,) the measured input
    starts: tuple[int, ...] = eqx.field(static=True)  # each segment's first sample (0 first)
    substeps: int = eqx.field(static=True, default=1)  # RK4 steps per interval
    hold: Hold = eqx.field(static=True, default="zoh")
    plant: bool = eqx.field(static=True, default=True)  # False: the actuator alone

    @classmethod
    def make(cls, t, u, *, plant: bool, dt: float, segments: int = 1,
             hold: Hold = "zoh") -> Experiment:
        t, u = np.asarray(t, np.float64), np.asarray(u, np.float64)
        starts = tuple(int(round(i * (t.size - 1) / segments)) for i in range(segments))
        substeps = max(1, math.ceil(float(np.max(np.diff(t))) / dt * (1 - 1e-12)))
        if not plant and hold == "zoh":
            substeps = 1  # the actuator alone steps along its curve: nothing to integrate
        return cls(jnp.asarray(t), jnp.asarray(u), starts, substeps, hold, plant)

    @property
    def segments(self) -> int:
        return len(self.starts)


def simulate(setup: Setup, exp: Experiment, x_init=None, h0=None, final: bool = False):
    """(x (N, n) or None, w (N,), ends (S - 1, n) or None): the plant's states and the
    actuator's output at every sample, and each segment's last state before the next one
    restarts from `x_init` (S, n) (the continuity that multiple shooting fits). The actuator
    starts from `h0` (default its state at rest, `init_state(u[0])`); `final`: return its
    state at the last sample instead (where a record's tail goes on)."""
    hyst, plant = setup.hysteresis, setup.plant
    t, u = exp.t, exp.u
    dtype = t.dtype
    h0 = hyst.init_state(u[0]) if h0 is None else h0
    h0 = jax.tree.map(lambda a: jnp.asarray(a, dtype), h0)
    restart = np.asarray(exp.starts[1:], int) - 1  # after interval k-1, sample k starts a segment
    which = np.zeros(t.size - 1, np.int32)  # > 0: the segment the interval's end sample starts
    which[restart] = np.arange(1, exp.segments)
    x_inits = x_init if exp.plant else jnp.zeros((1, 0), dtype)
    x0 = x_inits[0]

    def interval(carry, xs):
        x, h = carry
        t0, t1, u0, u1, again, s = xs
        step = (t1 - t0) / exp.substeps
        if exp.hold == "zoh":
            w = hyst.output(u0, h)
            if exp.plant:
                x = rk4_steps(lambda tt, xx, _: plant.rhs(xx, w, tt), t0, x, step, exp.substeps,
                              None)
            h = hyst.jump(u0, u1, h)
        else:
            slope = (u1 - u0) / (t1 - t0)

            def f(tt, y, _):
                xx, hh = y
                uu = u0 + slope * (tt - t0)
                dh = hyst.rate(uu, slope, hh)
                dx = plant.rhs(xx, hyst.output(uu, hh), tt) if exp.plant else jnp.zeros_like(xx)
                return dx, dh

            def project(tt, y):  # the plays' exact clamp at the step's end
                return y[0], hyst.project(u0 + slope * (tt - t0), y[1])

            x, h = rk4_steps(f, t0, (x, h), step, exp.substeps, None,
                             project if hyst.projects else None)
        end = x
        x = jnp.where(again, x_inits[s], x)
        return (x, h), (x, hyst.output(u1, h), end)

    xs = (t[:-1], t[1:], u[:-1], u[1:], jnp.asarray(which > 0), jnp.asarray(which))
    (_, h_last), (x, w, ends) = jax.lax.scan(interval, (x0, h0), xs)
    if final:
        return h_last
    w = jnp.concatenate([hyst.output(u[0], h0)[None], w])
    if not exp.plant:
        return None, w, None
    return jnp.concatenate([x0[None], x]), w, ends[restart]


__all__ = ["HOLDS", "Experiment", "Hold", "simulate"]
