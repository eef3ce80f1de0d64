"""A hysteresis model alone, driven by u(t) with the loop's RK4 and clamp: `open_loop` (any
u(t)) and `sine_loops` (u = A sin(omega t) for several A, one vmapped program).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import xla
from dscjax.hysteresis.base import Hysteresis
from dscjax.integrate import Checkpointed, integrate


def open_loop(hysteresis: Hysteresis, u_of_t: Callable, t_final: float, dt: float):
    """(t, u, w), NumPy arrays on t_k = k dt, of a model driven alone by u_of_t (a JAX function
    of t; u' by forward-mode AD) with the loop's RK4 and clamp, round(t_final / dt) steps.

        >>> import jax.numpy as jnp
        >>> from dscjax.hysteresis import PrandtlIshlinskii
        >>> t, u, w = open_loop(PrandtlIshlinskii(), lambda t: 3.5 * jnp.sin(2.3 * t), 1.0, 1e-3)
        >>> w.shape
        (1001,)
    """
    n_steps = max(int(round(t_final / dt)), 1)
    u, w = _open_loop_jit(_as_float(hysteresis), u_of_t, (), n_steps, _as_float(dt))
    return np.arange(n_steps + 1) * float(dt), np.asarray(u), np.asarray(w)


def _sine(t, amplitude, om):
    return amplitude * jnp.sin(om * t)


@functools.partial(xla.jit, lean=True, static_argnames=("n_steps",))
def _sine_loops(model, amps, om, dt, n_steps):
    return jax.vmap(lambda a: _open_loop(model, _sine, (a, om), n_steps, dt))(amps)


def sine_loops(hysteresis: Hysteresis, amplitudes, omega: float, t_final: float, dt: float):
    """(t (N+1,), u (K, N+1), w (K, N+1)): the model driven by u = A sin(omega t) for each of
    the K amplitudes (one vmapped program)."""
    n_steps = max(int(round(t_final / dt)), 1)
    u, w = _sine_loops(*_as_float((hysteresis, jnp.asarray(amplitudes), omega, dt)),
                       n_steps=n_steps)
    return np.arange(n_steps + 1) * float(dt), np.asarray(u), np.asarray(w)


def _as_float(tree):
    """Every number of `tree` (a model, an array, a number) in JAX's default float."""
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.result_type(float)), tree)


def _open_loop(model, u_of_t, args, n_steps, dt):
    """(u, w) on the step grid for u = u_of_t(t, *args), by `integrate` (and its clamp hook)."""
    def field(t, h, a):
        u, du = jax.jvp(lambda tt: u_of_t(tt, *a), (t,), (jnp.ones_like(t),))
        return model.rate(u, du, h), (u, model.output(u, h))

    def project(k, t, h, a):
        return model.project(u_of_t(t, *a), h)

    h0 = jax.tree.map(lambda x: jnp.asarray(x, dt.dtype),
                      model.init_state(u_of_t(jnp.zeros((), dt.dtype), *args)))
    return integrate(field, h0, dt, n_steps, args, gradient=Checkpointed(),
                     project=project if model.projects else None, frozen=model.projects).obs


_open_loop_jit = xla.jit(_open_loop, lean=True, static_argnums=(1, 3))
