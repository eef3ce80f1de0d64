"""Reference trajectories y_r(t) and their time derivatives.

A reference is one scalar function of t; every derivative a controller needs (y_r' for DSC, up
to y_r^(n) for backstepping) is taken from it by nested forward-mode autodiff, so a new
reference is one method.
"""

from __future__ import annotations

import abc
import functools
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from dscjax.model import Model, positive
from dscjax.xla import barrier


class Reference(Model):
    """Interface: `__call__(t)` gives y_r(t) for a scalar t. Every field is a scalar unless
    a subclass's `expected_shapes` says otherwise."""

    kind: ClassVar[str]

    @abc.abstractmethod
    def __call__(self, t): ...

    def derivatives(self, t, order: int):
        """(y_r, y_r', ..., y_r^(order)) at t, as a tuple of scalars, by nested jvp."""
        out = [self(t)]
        fn = self.__call__
        for _ in range(order):
            fn = functools.partial(_time_derivative, fn)
            out.append(fn(t))
        return time_signal(tuple(out))


def time_signal(tree):
    """Mark values that depend on time only as computed once per stage: in a batch XLA:CPU
    would otherwise fuse them into every per-trajectory kernel."""
    return barrier(tree)


def _time_derivative(fn, t):
    """fn'(t) by one forward-mode derivative."""
    return jax.jvp(fn, (t,), (jnp.ones_like(t),))[1]


class Sine(Reference):
    """y_r = amplitude sin(frequency t + phase) + offset. The paper uses sin t."""

    amplitude: jax.Array = 1.0
    frequency: jax.Array = 1.0
    phase: jax.Array = 0.0
    offset: jax.Array = 0.0

    kind: ClassVar[str] = "sine"

    def __call__(self, t):
        return self.amplitude * jnp.sin(self.frequency * t + self.phase) + self.offset


class SmoothStep(Reference):
    """A C-infinity step: y_r = initial + height (1 + tanh((t - t_step)/rise_time)) / 2."""

    height: jax.Array = 1.0
    t_step: jax.Array = 1.0
    rise_time: jax.Array = positive(default=0.5)
    initial: jax.Array = 0.0

    kind: ClassVar[str] = "smooth_step"

    def __call__(self, t):
        rise = jnp.tanh((t - self.t_step) / self.rise_time)
        return self.initial + 0.5 * self.height * (1.0 + rise)


class MultiSine(Reference):
    """y_r = sum_j amplitudes_j sin(frequencies_j t + phases_j) + offset; arrays of shape (m,)."""

    amplitudes: jax.Array
    frequencies: jax.Array
    phases: jax.Array
    offset: jax.Array = 0.0

    kind: ClassVar[str] = "multisine"

    def expected_shapes(self, n):
        m = np.shape(self.amplitudes)
        return dict(amplitudes=m, frequencies=m, phases=m, offset=())

    def __call__(self, t):
        return jnp.sum(self.amplitudes * jnp.sin(self.frequencies * t + self.phases)) + self.offset


@jax.custom_jvp
def _given(t, d):
    """y_r(t) from its given derivatives d = (y_r, y_r', ...): d[0]; its derivative in t is
    d[1], exactly (nested jvp shifts the tuple)."""
    return d[0]


@_given.defjvp
def _given_jvp(primals, tangents):
    t, d = primals
    return _given(t, d), _given(t, (*d[1:], jnp.zeros_like(d[0]))) * tangents[0]


class Given(Reference):
    """A reference whose value and derivatives at the current time are given, d = (y_r, y_r',
    ...): every law that differentiates the reference in t (DSC's y_r', backstepping's nested
    derivatives) reads them. How `dscjax.export` makes the reference an input of the C."""

    d: tuple

    kind: ClassVar[str] = "given"

    def __call__(self, t):
        return _given(t, self.d)


class InitialOffset(Reference):
    """base(t) + offset exp(-t / decay_time): a reference moved to start at a chosen y_r(0).

    For the L-infinity initialisation (68), which needs y_r(0) = x_1(0) (Assumption 3).
    """

    base: Reference
    offset: jax.Array
    decay_time: jax.Array = positive()

    kind: ClassVar[str] = "initial_offset"

    def expected_shapes(self, n):
        return dict(offset=(), decay_time=())

    def validate(self, prefix):
        self.base.validate(prefix)
        super().validate(prefix)

    def __call__(self, t):
        return self.base(t) + self.offset * jnp.exp(-t / self.decay_time)
