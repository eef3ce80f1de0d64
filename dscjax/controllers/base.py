"""The small interface every controller of the closed loop implements.

A controller is a `dscjax.model.Model`: its gains are traced fields, its structural choices
(variant, robust term, initialisation) are static `Literal` fields. It owns a state (filters,
estimates) and gives:

    prepare(plant, reference)            -> (controller, reference)  initialisation rules
    init_state(plant, reference)         -> state at t = 0
    law(state, x, t, plant, reference)   -> (u, info)   u as a function of (state, x, t) only
    state_rate(state, x, t, info, plant, reference) -> d(state)/dt

`law` never sees w or the true plant parameters; as u is a function of (state, x, t) only, the
loop gets u' exactly by a jvp of `law` along the vector field (`closed_loop.py`).
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from dscjax.model import Model


class ControlInfo(NamedTuple):
    """What every control law reports besides u (all at the current time).

    Attributes:
        yr: () the reference y_r(t) the law used.
        S: (n,) the surface / tracking errors, S_1 = x_1 - y_r first.
        extra: controller-specific intermediates needed by `state_rate` (any pytree).
    """

    yr: jax.Array
    S: jax.Array
    extra: Any


class Controller(Model):
    """The interface every controller implements (module docstring)."""

    kind: ClassVar[str]

    def prepare(self, plant, reference):
        """Apply initialisation rules that depend on the plant's initial state; default: none."""
        return self, reference

    @abc.abstractmethod
    def init_state(self, plant, reference) -> Any: ...

    @abc.abstractmethod
    def law(self, state, x, t, plant, reference) -> tuple[jax.Array, ControlInfo]: ...

    @abc.abstractmethod
    def state_rate(self, state, x, t, info, plant, reference) -> Any: ...

    def decay_rates(self, state) -> Any:
        """Rates >= 0 of the linear decays -rate * state in `state_rate` that can make the loop
        stiff (a state-shaped pytree; the exponential step integrates them exactly).
        Default: none."""
        return jax.tree.map(jnp.zeros_like, state)

    @abc.abstractmethod
    def expected_shapes(self, n: int) -> dict[str, tuple[int, ...]]:
        """Shape of every array field for a plant of order n (used by validation)."""
