"""Waveforms of the external disturbance dbar(t) on the last plant equation, eq. (1), added to
a plant's own term (`plant.disturbance`); what a worst-case search varies.

    Fourier(coefficients (2K+1,), period ()):
        dbar(t) = c_0 + sum_{j=1..K} a_j cos(j w t) + b_j sin(j w t),   w = 2 pi / period,
        coefficients = [c_0, a_1..a_K, b_1..b_K].
    Spline(knots (K,), horizon ()):
        the monotone cubic Hermite spline (PCHIP) through `knots` at K equally spaced times on
        [0, horizon] (constant after it); max_t |dbar| = max |knots| exactly.

The bound max_t |dbar(t)| <= D is enforced by `project_coefficients` (a worst-case search's
projection): a spline's knots are clipped to [-D, D]; a Fourier series is scaled by
min(1, D / max_k |dbar(t_k)|) on the half-step grid t_k = k dt/2 on which RK4 evaluates it.
Config: a table [plant.disturbance] with `kind` ("fourier" | "spline") and the fields above.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation as v
from dscjax.model import Model, positive


class Disturbance(Model):
    """Interface: `__call__(t)` gives dbar(t) for a scalar t; `coefficients_name` names the
    leaf a search varies; the static `project_coefficients(coef, bound, values_on_grid)` gives
    the coefficients (..., m) within the bound from the waveform's values on the half-step grid
    (..., G) (traceable, for the search)."""

    kind: ClassVar[str]
    coefficients_name: ClassVar[str]

    def coefficient_values(self):
        """The leaf a search varies (Fourier: coefficients; spline: knots)."""
        return getattr(self, self.coefficients_name)

    def expected_shapes(self, n):
        """The coefficients (m,) as they are, the time scale a scalar."""
        return super().expected_shapes(n) | {
            self.coefficients_name: np.shape(self.coefficient_values())}

    def max_abs(self) -> float:
        """An upper bound of max_t |dbar(t)| (exact for a spline)."""
        return float(np.sum(np.abs(np.asarray(self.coefficient_values()))))


def _harmonics(coef, period, t):
    """c_0 + sum a_j cos(j w t) + b_j sin(j w t) with cos/sin of the harmonics by the angle
    addition recurrence (two trig calls per evaluation whatever K)."""
    coef = jnp.asarray(coef)
    k = (coef.shape[-1] - 1) // 2
    w = 2.0 * jnp.pi / period
    c1, s1 = jnp.cos(w * t), jnp.sin(w * t)
    c, s = c1, s1
    out = coef[0]
    for j in range(1, k + 1):
        out = out + coef[j] * c + coef[k + j] * s
        c, s = c * c1 - s * s1, s * c1 + c * s1
    return out


class Fourier(Disturbance):
    """A Fourier series of K harmonics over `period` (see the module docstring).

    Fields: coefficients (2K+1,) = [c_0, a_1..a_K, b_1..b_K]; period () > 0 [s].
    """

    coefficients: jax.Array
    period: jax.Array = positive(default=20.0)

    kind: ClassVar[str] = "fourier"
    coefficients_name: ClassVar[str] = "coefficients"

    def validate(self, prefix):
        super().validate(prefix)
        m = np.shape(self.coefficients)
        if len(m) != 1 or m[0] % 2 != 1:
            raise v.ConfigError(f"{prefix}.coefficients must be a list of 2K+1 numbers "
                                f"[c_0, a_1..a_K, b_1..b_K] (got shape {m})")

    def __call__(self, t):
        return _harmonics(self.coefficients, self.period, t)

    @staticmethod
    def project_coefficients(coef, bound, values_on_grid):
        peak = jnp.max(jnp.abs(values_on_grid), axis=-1, keepdims=True)
        safe = jnp.where(peak > bound, peak, 1.0)
        return jnp.where(peak > bound, coef * (bound / safe), coef)


def _pchip_slopes(y, h):
    """Fritsch-Butland slopes on equally spaced knots: harmonic mean of the neighbouring
    secants where they agree in sign, else 0; one-sided secants at the ends. Monotone on
    every interval (slope/secant ratios in [0, 2]), so the spline stays within its knots."""
    d = (y[1:] - y[:-1]) / h
    a, b = d[:-1], d[1:]
    same = a * b > 0
    inner = jnp.where(same, 2.0 * a * b / jnp.where(same, a + b, 1.0), 0.0)
    return jnp.concatenate([d[:1], inner, d[-1:]])


def _pchip(y, horizon, t):
    y = jnp.asarray(y)
    k = y.shape[-1]
    if k == 1:
        return y[0] + 0.0 * t
    h = horizon / (k - 1)
    m = _pchip_slopes(y, h)
    s = jnp.clip(t / h, 0.0, k - 1.0)
    i = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, k - 2)
    u = s - i
    u2, u3 = u * u, u * u * u
    return ((2 * u3 - 3 * u2 + 1) * y[i] + (u3 - 2 * u2 + u) * h * m[i]
            + (-2 * u3 + 3 * u2) * y[i + 1] + (u3 - u2) * h * m[i + 1])


class Spline(Disturbance):
    """A monotone cubic spline on K equally spaced knots over [0, horizon] (module docstring).

    Fields: knots (K,) the values dbar(t_j); horizon () > 0 [s].
    """

    knots: jax.Array
    horizon: jax.Array = positive(default=20.0)

    kind: ClassVar[str] = "spline"
    coefficients_name: ClassVar[str] = "knots"

    def validate(self, prefix):
        super().validate(prefix)
        m = np.shape(self.knots)
        if len(m) != 1 or m[0] < 1:
            raise v.ConfigError(f"{prefix}.knots must be a list of K >= 1 numbers (got shape "
                                f"{m})")

    def __call__(self, t):
        return _pchip(self.knots, self.horizon, t)

    def max_abs(self) -> float:
        return float(np.max(np.abs(np.asarray(self.knots))))

    @staticmethod
    def project_coefficients(coef, bound, values_on_grid):
        return jnp.clip(coef, -bound, bound)


def half_step_grid(t_final: float, dt: float) -> np.ndarray:
    """t_k = k dt/2, k = 0..2N: every time at which RK4 evaluates a time signal."""
    return np.arange(2 * int(round(t_final / dt)) + 1) * (dt / 2)


@jax.jit
def sample(dist: Disturbance, t) -> jax.Array:
    """dbar on an array of times (the same code the simulation runs, vmapped; compiled once
    per waveform structure)."""
    return jax.vmap(dist)(t)


KINDS: dict[str, type[Disturbance]] = {Fourier.kind: Fourier, Spline.kind: Spline}

__all__ = ["KINDS", "Disturbance", "Fourier", "Spline", "half_step_grid", "sample"]
