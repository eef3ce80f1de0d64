"""Hysteresis actuators w = P[u] behind the DSC (docs/hysteresis.md): the backlash-like model
(4) of the paper ("backlash", the default), Prandtl-Ishlinskii ("pi"), generalized P-I ("gpi")
and Bouc-Wen ("bouc_wen").

Every model is a `Hysteresis` (numbers traced, class and options static) with one interface:

    init_state(u0) -> h(0)                 output(u, h) -> w, which drives the plant
    rate(u, du, h) -> h' given u' = du     decay_rate(u, du, h) -> rates >= 0 (like h) of the
                                           stiff linear decays in `rate` (ETDRK4's exact part)
    project(u, h) -> h after a step        jump(u_from, u_to, h) -> h after u steps (a held
                                           input of a sampled controller), along the model's curve
    effective_slope() -> lam of w = lam u + d_1(u), eq. (5); d1_limits() -> limits of d_1, (7)-(8)

A play operator is rate-independent and non-smooth, so it is not an ODE: its state z (the plays'
outputs at the step's start) is frozen inside a step, every RK4 stage reads the output through
the exact clamp max(lo(u), min(hi(u), z)), and `project` applies the clamp at the step's end with
u the control law at the new state: the exact recursion on the step grid. The ODE form
z' = u' [active branch] lets RK4's stages pick the branch from perturbed states and keeps an
error from every reversal.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation as v
from dscjax.integrate import Checkpointed, integrate
from dscjax.model import Model, nonnegative, option, positive, smooth_abs


class Hysteresis(Model):
    """The interface every hysteresis model provides (see the module docstring)."""

    kind: ClassVar[str]
    title: ClassVar[str]  # the model's name in figures
    # h is a discrete state (the plays): held inside a step, changed only by `project`
    projects: ClassVar[bool] = False
    # what `dscjax sweep` varies by default (each +-30 %): paths under [hysteresis]
    default_sweep: ClassVar[tuple[str, ...]] = ()

    def init_state(self, u0):
        raise NotImplementedError

    def output(self, u, h):
        raise NotImplementedError

    def rate(self, u, du, h):
        raise NotImplementedError

    def decay_rate(self, u, du, h):
        return jax.tree.map(jnp.zeros_like, h)

    def project(self, u, h):
        return h

    def jump(self, u_from, u_to, h):
        raise NotImplementedError

    def effective_slope(self):
        raise NotImplementedError

    def d1_limits(self):
        raise NotImplementedError

    def d1_bound(self):
        """A bound of |d_1| once it has settled: the larger limit (7)-(8) in magnitude."""
        lo, hi = self.d1_limits()
        return jnp.maximum(jnp.abs(lo), jnp.abs(hi))


# -- backlash-like hysteresis (4) -----------------------------------------------------------------


class Backlash(Hysteresis):
    """Backlash-like hysteresis w = P(u), eq. (4).

    Attributes:
        alpha: () rate at which w switches between its asymptotes, alpha > 0.
        lam: () slope lambda of the asymptotes, lam > psi.
        psi: () slope psi of the branches at reversal.
        w0: () initial output w(0); the paper does not give it, the default is 0.
        smooth_delta: () width of the smooth |u'| used when `smooth` is True (units of u').
        smooth: static; replace |u'| by sqrt(u'^2 + delta^2) - delta (bias <= delta in |u'|).
    """

    alpha: jax.Array = positive()
    lam: jax.Array = positive()
    psi: jax.Array
    w0: jax.Array = 0.0
    smooth_delta: jax.Array = positive(default=1e-2)
    smooth: bool = option(False)

    kind: ClassVar[str] = "backlash"
    title: ClassVar[str] = "Backlash-like hysteresis (4)"
    default_sweep: ClassVar[tuple[str, ...]] = ("alpha", "lam", "psi")

    def validate(self, prefix):
        super().validate(prefix)
        lam, psi = np.asarray(self.lam, float), np.asarray(self.psi, float)
        if not np.all(lam > psi):
            raise v.ConfigError(f"{prefix}.lam must be > {prefix}.psi (got lam={v.fmt(lam)}, "
                                f"psi={v.fmt(psi)})")

    def init_state(self, u0=None):
        """The model's state at t = 0: for (4) the output itself, w(0) = w0 (u0 unused)."""
        return self.w0

    def output(self, u, w):
        """The output w = P(u): for (4) the state itself."""
        return w

    def rate(self, u, du, w):
        """w' of eq. (4) given u, u' and w."""
        abs_du = smooth_abs(du, self.smooth_delta) if self.smooth else jnp.abs(du)
        return self.alpha * abs_du * (self.lam * u - w) + self.psi * du

    def decay_rate(self, u, du, w):
        """The rate a >= 0 of the linear decay -a w in eq. (4): alpha |u'|. It makes the loop
        stiff where |u'| is large; the exponential step integrates it exactly."""
        return self.alpha * (smooth_abs(du, self.smooth_delta) if self.smooth else jnp.abs(du))

    def jump(self, u_from, u_to, w):
        """w after u steps from u_from to u_to: the closed form (5)-(6) along the step (the
        exact |u'|, whatever `smooth` says: a step has no rate)."""
        direction = jnp.where(u_to >= u_from, 1.0, -1.0)
        return closed_form(u_to, u_from, w, self.alpha, self.lam, self.psi, direction)

    def effective_slope(self):
        """lam of (5): w = lam u + d_1(u)."""
        return jnp.asarray(self.lam)

    def d1_limits(self):
        """Limits (7)-(8) of d_1: (lam-psi)/alpha as u -> -inf, -(lam-psi)/alpha as u -> +inf."""
        bound = (self.lam - self.psi) / self.alpha
        return bound, -bound


def closed_form(u, u0, w0, alpha, lam, psi, direction):
    """w(u) (shaped like u) by the solution (5)-(6) of eq. (4) on a monotone segment of u from
    (u0, w0), direction +1 rising, -1 falling. With s = sgn(u'), d_1 = w - lam u is

        d_1(u) = (w0 - lam u0) E + (psi - lam)/(alpha s) (1 - E),  E = e^{-alpha s (u - u0)},

    (6) with the paper's sgn(u) read as sgn(u') (docs/paper-readings.md)."""
    s = direction
    decay = jnp.exp(-alpha * s * (u - u0))
    d1 = (w0 - lam * u0) * decay + (psi - lam) / (alpha * s) * (1.0 - decay)
    return lam * u + d1


# -- play operators --------------------------------------------------------------------------------


def play(z, lo, hi):
    """The play's clamp max(lo, min(hi, z)), exactly as defined (lo wins if lo > hi)."""
    return jnp.maximum(lo, jnp.minimum(hi, z))


def envelope(e, u):
    """gamma(u) = a tanh(b u + c) + d for e = [a, b, c, d] (last axis)."""
    return e[..., 0] * jnp.tanh(e[..., 1] * u + e[..., 2]) + e[..., 3]


def _pi_r():
    return np.arange(1, 11) / 5.0  # 0.2, 0.4, ..., 2.0, each the nearest float


def _pi_p():
    return 0.137 * np.exp(-0.3 * _pi_r())


class _Plays(Hysteresis):
    """w = p0 u + sum_j p_j z_j, each z_j a play between g_lo(u) - r_j and g_hi(u) + r_j
    (`envelopes`): the fields P-I and generalized P-I share; a subclass adds its envelopes."""

    p0: jax.Array = nonnegative(default=0.432)
    r: jax.Array = eqx.field(default_factory=_pi_r)
    p: jax.Array = nonnegative(default_factory=_pi_p)
    z0: jax.Array = 0.0

    projects: ClassVar[bool] = True

    def envelopes(self, u):
        """(g_lo, g_hi) at input u, shaped like u."""
        raise NotImplementedError

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
        if np.any(r < 0):
            raise v.ConfigError(f"{prefix}.r must be >= 0: play thresholds (got {v.fmt(r)})")
        if n > 1 and not np.all(np.diff(r, axis=-1) > 0):
            raise v.ConfigError(f"{prefix}.r must be strictly increasing (got {v.fmt(r)})")

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


_GPI_LEFT = (8.0, 0.125, -0.02, 0.0)
_GPI_RIGHT = (8.0, 0.125, 0.02, 0.0)


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

    envelope_left: jax.Array = eqx.field(default_factory=lambda: np.array(_GPI_LEFT))
    envelope_right: jax.Array = eqx.field(default_factory=lambda: np.array(_GPI_RIGHT))

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


# -- Bouc-Wen --------------------------------------------------------------------------------------


def _pow_abs(h, n):
    """|h|^n with finite derivatives at h = 0 (double where)."""
    zero = h == 0
    safe = jnp.where(zero, 1.0, jnp.abs(h))
    return jnp.where(zero, 0.0, safe ** n)


def _pow_abs_m1(h, n):
    """|h|^(n-1) for n >= 1, finite at h = 0 (1 there for n = 1, 0 for n > 1)."""
    zero = h == 0
    safe = jnp.where(zero, 1.0, jnp.abs(h))
    return jnp.where(zero, jnp.where(n == 1, 1.0, 0.0), safe ** (n - 1.0))


# RK4 substeps in u of a Bouc-Wen jump: a sampled controller's input moves by |u'| Ts per
# sample, a short segment of the curve
JUMP_SUBSTEPS = 16


class BoucWen(Hysteresis):
    """Bouc-Wen hysteresis: w = a u + b h, h' = A u' - beta |u'| |h|^(n-1) h - gamma u' |h|^n.

    For beta >= |gamma| and |h0| <= h_max = (A / (beta + gamma))^(1/n), |h| <= h_max, so
    |d_1| = |b h| <= |b| h_max. Defaults: the paper's slope 1.432 and nearly its offset.

    Attributes:
        a: () slope of the elastic part, > 0 (the effective slope).
        b: () weight of the hysteretic part.
        A: () > 0.
        beta, gamma: () with beta + gamma > 0.
        n: () exponent, >= 1 (below 1, |h|^(n-1) h is not Lipschitz at h = 0).
        h0: () h(0).
        smooth_delta, smooth: as for `Backlash`: |u'| -> sqrt(u'^2 + delta^2) - delta.
    """

    a: jax.Array = positive(default=1.432)
    b: jax.Array = 1.0
    A: jax.Array = positive(default=1.0)
    beta: jax.Array = 0.6
    gamma: jax.Array = 0.15
    n: jax.Array = 1.0
    h0: jax.Array = 0.0
    smooth_delta: jax.Array = positive(default=1e-2)
    smooth: bool = option(False)

    kind: ClassVar[str] = "bouc_wen"
    title: ClassVar[str] = "Bouc-Wen"
    default_sweep: ClassVar[tuple[str, ...]] = ("a", "b", "beta", "gamma")

    def validate(self, prefix):
        super().validate(prefix)
        beta, gamma = np.asarray(self.beta, float), np.asarray(self.gamma, float)
        if not np.all(beta + gamma > 0):
            raise v.ConfigError(f"{prefix}.beta + {prefix}.gamma must be > 0 (got "
                                f"beta={v.fmt(beta)}, gamma={v.fmt(gamma)})")
        if not np.all(np.asarray(self.n, float) >= 1):
            raise v.ConfigError(f"{prefix}.n must be >= 1 (got {v.fmt(self.n)}): below 1, "
                                f"|h|^(n-1) h is not Lipschitz at h = 0")

    def _abs_du(self, du):
        return smooth_abs(du, self.smooth_delta) if self.smooth else jnp.abs(du)

    def init_state(self, u0=None):
        return self.h0

    def output(self, u, h):
        return self.a * u + self.b * h

    def rate(self, u, du, h):
        hn = _pow_abs(h, self.n)
        return self.A * du - self.beta * self._abs_du(du) * jnp.sign(h) * hn \
            - self.gamma * du * hn

    def decay_rate(self, u, du, h):
        """(beta |u'| + gamma u' sgn h) |h|^(n-1) where >= 0: the decay -(...) h in `rate`."""
        k = (self.beta * self._abs_du(du) + self.gamma * du * jnp.sign(h)) \
            * _pow_abs_m1(h, self.n)
        return jnp.maximum(k, 0.0)

    def jump(self, u_from, u_to, h):
        """h after a step of u: dh/du = A - beta s |h|^(n-1) h - gamma |h|^n, s = sgn(u_to -
        u_from), integrated by RK4 in u over JUMP_SUBSTEPS substeps (the exact |u'|)."""
        s = jnp.where(u_to >= u_from, 1.0, -1.0)
        du = (u_to - u_from) / JUMP_SUBSTEPS

        def slope(hh):
            hn = _pow_abs(hh, self.n)
            return self.A - self.beta * s * jnp.sign(hh) * hn - self.gamma * hn

        for _ in range(JUMP_SUBSTEPS):
            k1 = slope(h)
            k2 = slope(h + 0.5 * du * k1)
            k3 = slope(h + 0.5 * du * k2)
            k4 = slope(h + du * k3)
            h = h + du / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)
        return h

    def h_max(self):
        """(A / (beta + gamma))^(1/n): the bound of |h| for beta >= |gamma|."""
        return (self.A / (self.beta + self.gamma)) ** (1.0 / self.n)

    def effective_slope(self):
        return jnp.asarray(self.a)

    def d1_limits(self):
        """-b h_max as u -> -inf and +b h_max as u -> +inf (h tends to -+h_max)."""
        bound = self.b * self.h_max()
        return -bound, bound


MODELS = (Backlash, PrandtlIshlinskii, GeneralizedPI, BoucWen)


# -- the model alone ------------------------------------------------------------------------------


def open_loop(hysteresis: Hysteresis, u_of_t: Callable, t_final: float, dt: float):
    """(t, u, w), NumPy arrays on t_k = k dt, of a model driven alone by u_of_t (a JAX function
    of t; u' by forward-mode AD) with the loop's RK4 and clamp, round(t_final / dt) steps.

        >>> import jax.numpy as jnp
        >>> t, u, w = open_loop(PrandtlIshlinskii(), lambda t: 3.5 * jnp.sin(2.3 * t), 1.0, 1e-3)
        >>> w.shape
        (1001,)
    """
    n_steps = max(int(round(t_final / dt)), 1)
    u, w = _open_loop_jit(_as_float(hysteresis), _OfT(u_of_t), (), n_steps,
                          jnp.asarray(dt, jnp.result_type(float)))
    return np.arange(n_steps + 1) * float(dt), np.asarray(u), np.asarray(w)


@dataclasses.dataclass(frozen=True)
class _OfT:
    """u_of_t as a (t, args) function, equal for the same u_of_t (its program is reused)."""

    u_of_t: Callable

    def __call__(self, t, _):
        return self.u_of_t(t)


def _sine(t, amp_omega):
    amplitude, om = amp_omega
    return amplitude * jnp.sin(om * t)


@functools.partial(jax.jit, static_argnames=("n_steps",))
def _sine_loops(model, amps, om, dt, n_steps):
    return jax.vmap(lambda a: _open_loop(model, _sine, (a, om), n_steps, dt))(amps)


def sine_loops(hysteresis: Hysteresis, amplitudes, omega: float, t_final: float, dt: float):
    """(t (N+1,), u (K, N+1), w (K, N+1)): the model driven by u = A sin(omega t) for each of
    the K amplitudes (one vmapped program)."""
    n_steps = max(int(round(t_final / dt)), 1)
    dtype = jnp.result_type(float)
    u, w = _sine_loops(_as_float(hysteresis), jnp.asarray(amplitudes, dtype),
                       jnp.asarray(omega, dtype), jnp.asarray(dt, dtype), n_steps=n_steps)
    return np.arange(n_steps + 1) * float(dt), np.asarray(u), np.asarray(w)


def _as_float(model):
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.result_type(float)), model)


def _open_loop(model, u_of_t, args, n_steps, dt):
    """(u, w) on the step grid for u = u_of_t(t, args), by `integrate` (and its clamp hook)."""
    def field(t, h, a):
        u, du = jax.jvp(lambda tt: u_of_t(tt, a), (t,), (jnp.ones_like(t),))
        return model.rate(u, du, h), (u, model.output(u, h))

    def project(k, t, h, a):
        return model.project(u_of_t(t, a), h)

    h0 = jax.tree.map(lambda x: jnp.asarray(x, dt.dtype),
                      model.init_state(u_of_t(jnp.zeros((), dt.dtype), args)))
    res = integrate(field, h0, dt, n_steps, args, gradient=Checkpointed(),
                    project=project if model.projects else None, frozen=model.projects)
    return res.obs


_open_loop_jit = jax.jit(_open_loop, static_argnums=(1, 3))

__all__ = ["Backlash", "BoucWen", "GeneralizedPI", "Hysteresis", "MODELS",
           "PrandtlIshlinskii", "closed_form", "envelope", "open_loop", "play", "sine_loops"]
