"""Strict-feedback plants of order n >= 2, eq. (1):

    x_i' = g_i x_{i+1} + theta_i f_i(xbar_i) + Delta_i(x, t),        i = 1..n-1
    x_n' = g_n w     + theta_n f_n(x)      + Delta_n(x, t) + dbar(t),  y = x_1

with |Delta_i| <= rho_i(xbar_i), rho_i known to the designer (Assumption 2). A plant is a pytree:
its numbers are traced leaves (tunable, sweepable), its functional form is the class.

Every plant gives, for a state x of shape (n,):
    f(x)        (n,)  the known nonlinearities f_i(xbar_i)
    rho(x)      (n,)  the known bounds rho_i(xbar_i)
    delta(x, t) (n,)  the (unknown to the controller) perturbations Delta_i(x, t)
    dbar(t)     ()    the external disturbance on the last equation
f_i and rho_i must depend on x_1..x_i only (strict feedback); `check_strict_feedback` tests it.
"""

import abc
import dataclasses
import itertools
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation as v
from dscjax.disturbance import Disturbance
from dscjax.model import Model, nonnegative, positive
from dscjax.reference import time_signal
from dscjax.xla import barrier


class Plant(Model):
    """Interface of a strict-feedback plant. Subclasses declare at least the traced fields
    `g` (n,) (g_i > 0: Assumption 4, the signs of g_i are known), `theta` (n,) and `x0` (n,)
    (the initial state)."""

    g: eqx.AbstractVar[jax.Array]
    theta: eqx.AbstractVar[jax.Array]
    x0: eqx.AbstractVar[jax.Array]
    kind: ClassVar[str]

    @property
    def order(self) -> int:
        return int(np.shape(self.g)[-1])

    @abc.abstractmethod
    def f(self, x): ...

    @abc.abstractmethod
    def rho(self, x): ...

    @abc.abstractmethod
    def delta(self, x, t): ...

    @abc.abstractmethod
    def dbar(self, t): ...

    def expected_shapes(self, n):
        return dict(g=(n,), theta=(n,), x0=(n,))

    def rhs(self, x, w, t):
        """x' of eq. (1) given the state x (n,), the hysteresis output w and the time t."""
        n = x.shape[0]
        f, delta = barrier((self.f(x), self.delta(x, t)))
        dx = [self.g[i] * (x[i + 1] if i < n - 1 else w) + self.theta[i] * f[i] + delta[i]
              for i in range(n)]
        dx[-1] = dx[-1] + self.dbar(t)
        return jnp.stack(dx)


class _SineDbar(Plant):
    """The config plants' dbar(t) = dbar_amp sin(dbar_freq t) + dbar_bias, plus an optional
    waveform `disturbance` (`dscjax.disturbance`); without one the sinusoid is computed exactly
    as it always was."""

    def validate(self, prefix):
        super().validate(prefix)
        if self.disturbance is None:
            return
        if not isinstance(self.disturbance, Disturbance):
            raise v.ConfigError(f"{prefix}.disturbance must be a dscjax.disturbance waveform "
                                f"(got {type(self.disturbance).__name__})")
        self.disturbance.validate(f"{prefix}.disturbance")
        for name, expected in self.disturbance.expected_shapes(self.order).items():
            v.shape(getattr(self.disturbance, name), f"{prefix}.disturbance.{name}", expected)

    def dbar(self, t):
        d = self.dbar_amp * jnp.sin(self.dbar_freq * t) + self.dbar_bias
        if self.disturbance is not None:
            d = d + self.disturbance(t)
        return time_signal(d)


def _cumulative_sq(x):
    """[q_1, ..., q_n], q_i = sum_{j<=i} x_j^2, as per-stage scalars: whole-array ops (cumsum,
    concatenate) make vmap transpose the batch axis once per op."""
    return list(itertools.accumulate(x[i] * x[i] for i in range(x.shape[0])))


class StrictFeedback(_SineDbar):
    """A family of strict-feedback plants of any order whose coefficients a config file can set.

    With x_0 = 0, x_{n+1} = x_n and q_i = sum_{j<=i} x_j^2:
        f_i(xbar_i)  = f_quad_i x_i^2 + f_sin_i sin(x_i) + f_cross_i x_{i-1} x_i
        rho_i(xbar_i) = rho_const_i + rho_quad_i q_i
        Delta_i(x,t) = delta_sin_i sin(x_{i+1}) + delta_quad_i q_i sin^3(delta_freq t)
        dbar(t)      = dbar_amp sin(dbar_freq t) + dbar_bias (+ disturbance(t), if given)
    |Delta_i| <= rho_i holds when |delta_sin_i| <= rho_const_i and |delta_quad_i| <=
    rho_quad_i; not enforced, so a wrong bound can be studied. All fields traced, (n,) but the
    scalars delta_freq, dbar_*; x0 = x(0); `disturbance`: an optional waveform added to dbar.
    """

    g: jax.Array = positive()
    theta: jax.Array
    x0: jax.Array
    f_quad: jax.Array
    f_sin: jax.Array
    f_cross: jax.Array
    rho_const: jax.Array = nonnegative()
    rho_quad: jax.Array = nonnegative()
    delta_sin: jax.Array
    delta_quad: jax.Array
    delta_freq: jax.Array = 1.0
    dbar_amp: jax.Array = 0.0
    dbar_freq: jax.Array = 1.0
    dbar_bias: jax.Array = 0.0
    disturbance: Disturbance | None = None

    kind: ClassVar[str] = "strict_feedback"
    vector_fields: ClassVar[tuple[str, ...]] = (
        "g", "theta", "x0", "f_quad", "f_sin", "f_cross", "rho_const", "rho_quad", "delta_sin",
        "delta_quad",
    )

    def expected_shapes(self, n):
        shapes = {name: (n,) for name in self.vector_fields}
        return shapes | dict(delta_freq=(), dbar_amp=(), dbar_freq=(), dbar_bias=())

    def f(self, x):
        return jnp.stack([
            self.f_quad[i] * x[i] * x[i] + self.f_sin[i] * jnp.sin(x[i])
            + (self.f_cross[i] * x[i - 1] * x[i] if i > 0 else 0.0 * x[i])
            for i in range(x.shape[0])])

    def rho(self, x):
        q = _cumulative_sq(x)
        return jnp.stack([self.rho_const[i] + self.rho_quad[i] * q[i] for i in range(x.shape[0])])

    def delta(self, x, t):
        n = x.shape[0]
        q = _cumulative_sq(x)
        s = jnp.sin(self.delta_freq * t)
        s3 = time_signal(s * s * s)
        return jnp.stack([
            self.delta_sin[i] * jnp.sin(x[min(i + 1, n - 1)]) + self.delta_quad[i] * q[i] * s3
            for i in range(n)])

    @classmethod
    def zeros(cls, n: int, **values: Any) -> "StrictFeedback":
        """A plant of order n with g = 1 and every other coefficient 0, then `values` applied."""
        base = {name: np.zeros(n) for name in cls.vector_fields} | {"g": np.ones(n)}
        return cls(**base | {k: np.asarray(v, dtype=float) for k, v in values.items()})


class PaperPlant(_SineDbar):
    """The second-order plant of the paper's simulation, eq. (73), with exactly its terms:

        f_1 = x_1^2, f_2 = 0, rho_1 = rho1, rho_2 = rho2 (x_1^2 + x_2^2),
        Delta_1 = delta1 sin(x_2), Delta_2 = delta2 (x_1^2 + x_2^2) sin^3(delta_freq t),
        dbar = dbar_amp sin(dbar_freq t) + dbar_bias (+ disturbance(t), if given).

    The same plant is `StrictFeedback` with `paper_family_plant()`'s coefficients; this class
    computes only the terms (73) has (fewer sines per step in a batch).
    """

    g: jax.Array = positive()
    theta: jax.Array
    x0: jax.Array
    rho1: jax.Array = nonnegative(default=0.2)
    rho2: jax.Array = nonnegative(default=0.1)
    delta1: jax.Array = 0.2
    delta2: jax.Array = 0.1
    delta_freq: jax.Array = 1.0
    dbar_amp: jax.Array = 0.0
    dbar_freq: jax.Array = 1.0
    dbar_bias: jax.Array = 0.0
    disturbance: Disturbance | None = None

    kind: ClassVar[str] = "paper"

    def expected_shapes(self, n):
        shapes = {f.name: () for f in dataclasses.fields(self) if f.name != "disturbance"}
        return shapes | dict(g=(2,), theta=(2,), x0=(2,))

    def f(self, x):
        return jnp.stack([x[0] * x[0], 0.0 * x[1]])

    def rho(self, x):
        return jnp.stack([self.rho1 + 0.0 * x[0], self.rho2 * (x[0] * x[0] + x[1] * x[1])])

    def delta(self, x, t):
        s = jnp.sin(self.delta_freq * t)
        s3 = time_signal(s * s * s)
        return jnp.stack([self.delta1 * jnp.sin(x[1]),
                          self.delta2 * (x[0] * x[0] + x[1] * x[1]) * s3])


class CustomPlant(Plant):
    """A plant given by JAX-traceable Python functions (Python API only, never from config).

    Args:
        g, theta, x0: (n,) traced; x0 is the initial state.
        params: any pytree of traced numbers handed to the functions (tunable, sweepable).
        f_fn(x, params) -> (n,), rho_fn(x, params) -> (n,), delta_fn(x, t, params) -> (n,),
        dbar_fn(t, params) -> (): static callables. Use module-level functions (not lambdas made
        anew per call) so that equal plants hash equal and do not recompile.

    Example:
        >>> import jax.numpy as jnp
        >>> def f(x, p): return jnp.stack([x[0] ** 2, p["a"] * jnp.sin(x[1])])
        >>> def rho(x, p): return jnp.stack([0.2, 0.1 * (x[0] ** 2 + x[1] ** 2)])
        >>> def delta(x, t, p): return jnp.zeros(2)
        >>> def dbar(t, p): return 0.0
        >>> plant = CustomPlant(jnp.ones(2), jnp.array([0.1, 0.0]), jnp.array([0.08, 0.1]),
        ...                     {"a": 1.0}, f, rho, delta, dbar)
    """

    g: jax.Array = positive()
    theta: jax.Array
    x0: jax.Array
    params: Any
    f_fn: Callable = eqx.field(static=True)
    rho_fn: Callable = eqx.field(static=True)
    delta_fn: Callable = eqx.field(static=True)
    dbar_fn: Callable = eqx.field(static=True)

    kind: ClassVar[str] = "custom"

    def validate(self, prefix):
        super().validate(prefix)
        check_strict_feedback(self)  # a ConfigError naming plant.f or plant.rho

    def f(self, x):
        return jnp.asarray(self.f_fn(x, self.params))

    def rho(self, x):
        return jnp.asarray(self.rho_fn(x, self.params))

    def delta(self, x, t):
        return jnp.asarray(self.delta_fn(x, t, self.params))

    def dbar(self, t):
        return jnp.asarray(self.dbar_fn(t, self.params))


def check_strict_feedback(plant: Plant) -> None:
    """ConfigError (a ValueError) if f_i or rho_i depend on x_j, j > i (Jacobians not lower
    triangular) at a random-looking probe state."""
    n = plant.order
    x = jnp.asarray(np.linspace(0.3, 1.1, n) * np.array([1.0, -1.0] * n)[:n])
    for name in ("f", "rho"):
        jac = np.asarray(jax.jacfwd(getattr(plant, name))(x))
        upper = np.argwhere(np.abs(np.triu(jac, k=1)) > 0)
        if upper.size:
            i, j = upper[0]
            raise v.ConfigError(f"plant.{name}: {name}_{i + 1} depends on x_{j + 1}, but a "
                                f"strict-feedback plant's {name}_i may only depend on x_1..x_i")
