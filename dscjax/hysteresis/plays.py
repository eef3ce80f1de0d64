"""Play operators: Prandtl-Ishlinskii ("pi") and generalized Prandtl-Ishlinskii ("gpi").

A play operator is rate-independent and non-smooth, so it is not an ODE: its state z (the plays'
outputs at the step's start) is frozen inside a step, every RK4 stage reads the output through
the exact clamp max(lo(u), min(hi(u), z)), and `project` applies the clamp at the step's end with
u the control law at the new state: the exact recursion on the step grid. The ODE form
z' = u' [active branch] lets RK4's stages pick the branch from perturbed states and keeps an
error from every reversal.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation as v
from dscjax.hysteresis.base import Hysteresis
from dscjax.model import nonnegative


def play(z, lo, hi):
    """The play's clamp max(lo, min(hi, z)), exactly as defined (lo wins if lo > hi)."""
    return jnp.maximum(lo, jnp.minimum(hi, z))


def envelope(e, u):
    """gamma(u) = a tanh(b u + c) + d for e = [a, b, c, d] (last axis)."""
    return e[..., 0] * jnp.tanh(e[..., 1] * u + e[..., 2]) + e[..., 3]


def _pi_r():
    return np.arange(1, 11) / 5.0  # 0.2, 0.4, ..., 2.0, each the nearest float


class _Plays(Hysteresis):
    """w = p0 u + sum_j p_j z_j, each z_j a play between g_lo(u) - r_j and g_hi(u) + r_j
    (`envelopes(u)`, shaped like u): the fields P-I and generalized P-I share; a subclass adds
    its envelopes."""

    p0: jax.Array = nonnegative(default=0.432)
    r: jax.Array = eqx.field(default_factory=_pi_r)
    p: jax.Array = nonnegative(default_factory=lambda: 0.137 * np.exp(-0.3 * _pi_r()))
    z0: jax.Array = 0.0

    projects: ClassVar[bool] = True

    def expected_shapes(self, n):
        # r, p (N,) and z0 (() or (N,)) are checked against each other in `validate`
        return {k: s for k, s in super().expected_shapes(n).items() if k not in ("r", "p", "z0")}

    def validate(self, prefix):
        super().validate(prefix)
        r, p, z0 = (np.asarray(x, float) for x in (self.r, self.p, self.z0))
        # last axis: a batch of models (leading axes, `simulate_batch`) is checked elementwise
        if r.ndim == 0 or r.shape[-1] < 1:
            raise v.ConfigError(f"{prefix}.r must be a list of N >= 1 thresholds (got "
                                f"{v.fmt(r)})")
        n = r.shape[-1]
        if p.ndim == 0 or p.shape[-1] != n:
            raise v.ConfigError(f"{prefix}.p must have one weight per threshold of {prefix}.r: "
                                f"length {n} (got {'a scalar' if p.ndim == 0 else p.shape[-1]})")
        if z0.ndim > 0 and z0.shape[-1] != n:
            raise v.ConfigError(f"{prefix}.z0 must be one number or one per threshold of "
                                f"{prefix}.r: length {n} (got length {z0.shape[-1]})")
        v.every(r, f"{prefix}.r", lambda a: a >= 0, ">= 0: play thresholds")
        v.every(r, f"{prefix}.r", lambda a: np.diff(a, axis=-1) > 0, "strictly increasing")

    def init_state(self, u0):
        """z(0) = max(lo(u0), min(hi(u0), z0)): the plays' outputs at t = 0 (N,)."""
        u0 = jnp.asarray(u0)
        z0 = jnp.asarray(self.z0, jnp.result_type(u0, self.r))
        return self.plays(u0, jnp.broadcast_to(z0, jnp.shape(self.r)))

    def each_play(self, u, z):
        """The plays' outputs at input u from z (..., N) at the step's start, one array shaped
        like u per play: in a batch each play is then its own row (`integrate`'s rows layout),
        which XLA:CPU computes row by row instead of copying and transposing (B, N) arrays."""
        g_lo, g_hi = self.envelopes(jnp.asarray(u))
        r = jnp.asarray(self.r)
        return [play(z[..., j], g_lo - r[..., j], g_hi + r[..., j]) for j in range(z.shape[-1])]

    def plays(self, u, z):
        """The plays' outputs (N,) at input u, from their outputs z at the step's start."""
        return jnp.stack(self.each_play(u, z), axis=-1)

    def output(self, u, z):
        p = jnp.asarray(self.p)
        weighted = [p[..., j] * zj for j, zj in enumerate(self.each_play(u, z))]
        return self.p0 * u + functools.reduce(jnp.add, weighted)

    def rate(self, u, du, z):
        """0: z is held inside a step (`projects`; the stages read it through the clamp)."""
        return jnp.zeros_like(z)

    def project(self, u, z):
        """The exact clamp at the step's end: z <- max(lo(u), min(hi(u), z))."""
        return self.plays(u, z)

    def jump(self, u_from, u_to, z):
        """The plays after a step of u: the clamp at u_to (the envelopes are monotone, so the
        clamp at the end of a monotone segment is the play's output exactly)."""
        return self.plays(u_to, z)


class PrandtlIshlinskii(_Plays):
    """Prandtl-Ishlinskii hysteresis w = p0 u + sum_j p_j F_(r_j)[u], F_r the play
    z = max(u - r, min(u + r, z-)). Defaults: r_j = 0.2 j (j = 1..10), p_j = 0.137 exp(-0.3 r_j),
    p0 = 0.432 (slope 1.43 and offset 1.00, near the paper's lam and (lam - psi)/alpha).

    Attributes:
        p0: () weight of the linear term, >= 0.
        r: (N,) thresholds, >= 0 and strictly increasing.
        p: (N,) weights, >= 0.
        z0: () or (N,) the plays' outputs before t = 0: z(0) = max(u0 - r, min(u0 + r, z0)).
    """

    kind: ClassVar[str] = "pi"
    title: ClassVar[str] = "Prandtl-Ishlinskii"
    # the linear weight, the narrowest play (weight and threshold) and the widest play's weight
    default_sweep: ClassVar[tuple[str, ...]] = ("p0", "p[0]", "r[0]", "p[9]")

    def envelopes(self, u):
        return u, u

    def effective_slope(self):
        """lam = p0 + sum p_j: w = lam u + d_1 with d_1 = sum p_j (z_j - u), |z_j - u| <= r_j."""
        return self.p0 + jnp.sum(jnp.asarray(self.p), axis=-1)

    def d1_limits(self):
        """sum p_j r_j as u -> -inf (z_j = u + r_j), -sum p_j r_j as u -> +inf."""
        bound = jnp.sum(jnp.asarray(self.p) * jnp.asarray(self.r), axis=-1)
        return bound, -bound


class GeneralizedPI(_Plays):
    """Generalized Prandtl-Ishlinskii hysteresis w = p0 u + sum_j p_j G_(r_j)[u], each play
    clamped between gamma_l(u) - r_j and gamma_r(u) + r_j, gamma(u) = a tanh(b u + c) + d.
    Defaults: P-I's p0, r, p; envelopes 8 tanh(0.125 u -+ 0.02) (saturating at +-8).

    Attributes:
        envelope_left: (4,) [a, b, c, d] of gamma_l, which drags the plays while u rises;
            increasing (a b > 0).
        envelope_right: (4,) [a, b, c, d] of gamma_r (u falling); increasing.
        p0, r, p, z0: as for `PrandtlIshlinskii`.
    """

    envelope_left: jax.Array = eqx.field(default_factory=lambda: np.array([8.0, 0.125, -0.02, 0.0]))
    envelope_right: jax.Array = eqx.field(default_factory=lambda: np.array([8.0, 0.125, 0.02, 0.0]))

    kind: ClassVar[str] = "gpi"
    title: ClassVar[str] = "Generalized Prandtl-Ishlinskii"
    default_sweep: ClassVar[tuple[str, ...]] = ("p0", "envelope_left[0]", "envelope_right[0]",
                                                "p[0]")

    def expected_shapes(self, n):
        return {**super().expected_shapes(n), "envelope_left": (4,), "envelope_right": (4,)}

    def validate(self, prefix):
        super().validate(prefix)
        for side in ("left", "right"):
            e = np.asarray(getattr(self, f"envelope_{side}"), float)
            if e.ndim == 0 or e.shape[-1] != 4:
                raise v.ConfigError(f"{prefix}.envelope_{side} must be [a, b, c, d] (got "
                                    f"{v.fmt(e)})")
            if not np.all(e[..., 0] * e[..., 1] > 0):
                raise v.ConfigError(
                    f"{prefix}.envelope_{side} = [a, b, c, d] must be increasing: a*b > 0 (got "
                    f"a={v.fmt(e[..., 0])}, b={v.fmt(e[..., 1])})")

    def envelopes(self, u):
        return (envelope(jnp.asarray(self.envelope_left), u),
                envelope(jnp.asarray(self.envelope_right), u))

    def effective_slope(self):
        """p0: the envelopes saturate, so d_1 = sum p_j G_j is bounded for every u (near u = 0
        the loop is steeper: p0 + sum p_j gamma'(0))."""
        return jnp.asarray(self.p0)

    def d1_limits(self):
        """sum p_j (gamma_r(-inf) + r_j) as u -> -inf, sum p_j (gamma_l(+inf) - r_j) as
        u -> +inf, gamma(+-inf) = d +- a sgn(b)."""
        el, er = jnp.asarray(self.envelope_left), jnp.asarray(self.envelope_right)
        p, r = jnp.asarray(self.p), jnp.asarray(self.r)
        right_low = er[..., 3] - er[..., 0] * jnp.sign(er[..., 1])
        left_high = el[..., 3] + el[..., 0] * jnp.sign(el[..., 1])
        return (jnp.sum(p * (right_low[..., None] + r), axis=-1),
                jnp.sum(p * (left_high[..., None] - r), axis=-1))
