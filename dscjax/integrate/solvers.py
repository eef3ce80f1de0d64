"""One-step methods over pytrees, as objects (diffrax's way): `RK4()` and `ETDRK4()` (exact on
the stiff linear decays the model reports). `Solver.step(f_obs, rates, t, y, dt, h, frozen)`
returns (y_next, obs at (t, y)); `h` scales the increments only and `frozen` components are
held inside a step. Adding a solver is a class here, listed in `SOLVERS`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

Pytree = Any


def _axpy(a, x, y):
    """y + a x over pytrees."""
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


def _hold(new, y, frozen):
    """`new` with the frozen components taken from y. `frozen` (static): None, or a tree like
    y of Python bools (batch rows: a frozen row's increments are dead code) or NumPy bool
    arrays (packed chunks: computed, then discarded by the select)."""
    if frozen is None:
        return new

    def pick(n, old, m):
        if not np.any(m):
            return n
        return old if np.all(m) else jnp.where(m, old, n)

    return jax.tree.map(pick, new, y, frozen)


def rk4_step(f: Callable, t, y: Pytree, dt, args) -> Pytree:
    """One classical RK4 step of y' = f(t, y, args) (f returns the derivative only).

    Example:
        >>> import jax.numpy as jnp
        >>> y1 = rk4_step(lambda t, y, a: -a * y, 0.0, jnp.array(1.0), 0.1, 2.0)
        >>> abs(float(y1) - float(jnp.exp(-0.2))) < 1e-5
        True
    """
    return _rk4(lambda tt, yy: (f(tt, yy, args), None), t, y, dt)[0]


def rk4_steps(f: Callable, t0, y: Pytree, dt, n: int, args, after=None) -> Pytree:
    """`n` classical RK4 steps of y' = f(t, y, args) from t0, one loop in the program (compiled
    once, whatever n; a Python loop would copy the step n times into every program and its
    derivatives). `after(t, y)`, if given, maps the state at the end of each step (t: its end).
    """
    def step(i, yy):
        t = t0 + i * dt
        y_next = rk4_step(f, t, yy, dt, args)
        return y_next if after is None else after(t + dt, y_next)

    return jax.lax.fori_loop(0, n, step, y)


def _rk4(f_obs, t, y, dt, h=None, frozen=None):
    """RK4 step for f_obs(t, y) -> (dy, obs); returns (y_next, obs at (t, y)). `h` (default
    dt) scales the increments only: h = 0 gives y_next = y with the stages at finite points
    (how frozen steps are linearised safely). `frozen`: see `_hold`."""
    h = dt if h is None else h
    half = 0.5 * h
    k1, obs = f_obs(t, y)
    k2, _ = f_obs(t + 0.5 * dt, _hold(_axpy(half, k1, y), y, frozen))
    k3, _ = f_obs(t + 0.5 * dt, _hold(_axpy(half, k2, y), y, frozen))
    k4, _ = f_obs(t + dt, _hold(_axpy(h, k3, y), y, frozen))
    incr = jax.tree.map(lambda a, b, c, d: (a + 2.0 * (b + c) + d) * (h / 6.0), k1, k2, k3, k4)
    return _hold(jax.tree.map(jnp.add, y, incr), y, frozen), obs


def _taylor(poly, q, terms=20):
    """Taylor coefficients of [poly(z) + e^z q(z)] / z^3 (poly, q: {power: coefficient}),
    exactly in rationals, for the ETDRK4 weights near z = 0 where the formula cancels."""
    from fractions import Fraction
    from math import factorial

    num = [Fraction(0)] * (terms + 3)
    for p, c in poly.items():
        num[p] += c
    for p, c in q.items():
        for k in range(terms + 3 - p):
            num[k + p] += Fraction(c, factorial(k))
    return tuple(float(c) for c in num[3:])


# ETDRK4 weights f1, f2, f3 of Cox & Matthews (2002), and phi(z) = (e^z - 1)/z (as z^3 phi/z^2).
_F1 = _taylor({0: -4, 1: -1}, {0: 4, 1: -3, 2: 1})
_F2 = _taylor({0: 2, 1: 1}, {0: -2, 1: 1})
_F3 = _taylor({0: -4, 1: -3, 2: -1}, {0: 4, 1: -1})
_PHI = _taylor({0: 0, 2: -1}, {2: 1})


def _weight(z, coeffs, direct):
    """An ETDRK4 weight: its Taylor series for |z| < 1, the closed form beyond (double where,
    so that neither branch can put NaN into a derivative)."""
    small = jnp.abs(z) < 1.0
    zs = jnp.where(small, z, 0.0)
    series = functools.reduce(lambda acc, c: acc * zs + c, reversed(coeffs))
    zd = jnp.where(small, -2.0, z)
    return jnp.where(small, series, direct(zd))


def _etdrk4(f_obs, rates, t, y, dt, h=None, frozen=None):
    """One ETDRK4 step (Cox & Matthews 2002) of y' = -lam y + N(t, y), lam = rates(t_k, y_k,
    obs_k) >= 0 (like y) frozen over the step: the stiff decays integrated exactly, so the step
    is stable however large lam h is; classical RK4 where lam = 0. As `_rk4` otherwise."""
    h = dt if h is None else h
    k1, obs = f_obs(t, y)
    lam = rates(t, y, obs)
    z = jax.tree.map(lambda r: -h * r, lam)

    each = jax.tree.map
    e_full = each(jnp.exp, z)
    e_half = each(lambda zz: jnp.exp(0.5 * zz), z)
    # (e^(z/2) - 1)/(-lam) = (h/2) phi(z/2)
    p_half = each(lambda zz: 0.5 * h * _weight(0.5 * zz, _PHI, lambda x: jnp.expm1(x) / x), z)
    f1 = each(lambda zz: _weight(zz, _F1, lambda x: (-4 - x + jnp.exp(x) * (4 - 3 * x + x * x))
                                 / x**3), z)
    f2 = each(lambda zz: _weight(zz, _F2, lambda x: (2 + x + jnp.exp(x) * (x - 2)) / x**3), z)
    f3 = each(lambda zz: _weight(zz, _F3, lambda x: (-4 - 3 * x - x * x + jnp.exp(x) * (4 - x))
                                 / x**3), z)

    def rest(k, yy):  # N = F + lam y
        return each(lambda kk, r, v: kk + r * v, k, lam, yy)

    n_u = rest(k1, y)
    a = _hold(each(lambda eh, ph, v, n: eh * v + ph * n, e_half, p_half, y, n_u), y, frozen)
    n_a = rest(f_obs(t + 0.5 * dt, a)[0], a)
    b = _hold(each(lambda eh, ph, v, n: eh * v + ph * n, e_half, p_half, y, n_a), y, frozen)
    n_b = rest(f_obs(t + 0.5 * dt, b)[0], b)
    c = _hold(each(lambda eh, ph, v, nb, nu: eh * v + ph * (2.0 * nb - nu), e_half, p_half, a,
                   n_b, n_u), y, frozen)
    n_c = rest(f_obs(t + dt, c)[0], c)
    y_next = each(lambda ef, w1, w2, w3, v, nu, na, nb, nc:
                  ef * v + h * (w1 * nu + 2.0 * w2 * (na + nb) + w3 * nc),
                  e_full, f1, f2, f3, y, n_u, n_a, n_b, n_c)
    return _hold(y_next, y, frozen), obs


def _rk4_scanned(f_obs, t, y, dt, h, frozen=None):
    """`_rk4` with its four stages a `lax.scan` over one copy of f_obs, for bulk
    differentiation (one copy of the field's derivative compiles faster). Equal to round-off."""
    c = jnp.asarray([0.0, 0.5, 0.5, 1.0], dt.dtype)
    w = jnp.asarray([1.0, 2.0, 2.0, 1.0], dt.dtype)

    def stage(carry, cw):
        k_prev, total = carry
        ci, wi = cw
        ki, obs = f_obs(t + ci * dt, _hold(_axpy(ci * h, k_prev, y), y, frozen))
        return (ki, _axpy(wi, ki, total)), obs

    zero = jax.tree.map(jnp.zeros_like, y)
    (_, total), obs = jax.lax.scan(stage, (zero, zero), (c, w))
    return _hold(_axpy(h / 6.0, total, y), y, frozen), jax.tree.map(lambda o: o[0], obs)


# -- the solvers as objects ----------------------------------------------------------------------


class Solver(eqx.Module):
    """A one-step method: `step(f_obs, rates, t, y, dt, h, frozen) -> (y_next, obs at (t, y))`.
    `rates(t, y, obs)` gives the stiff linear decays the model knows of (ETDRK4 uses them)."""

    name: ClassVar[str]

    def step_scanned(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        """The same step, written for bulk differentiation (the time-parallel Jacobians)."""
        return self.step(f_obs, rates, t, y, dt, h, frozen)


class RK4(Solver):
    """Classical fourth-order Runge-Kutta (the paper's method)."""

    name: ClassVar[str] = "rk4"

    def step(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        return _rk4(f_obs, t, y, dt, h, frozen)

    def step_scanned(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        return _rk4_scanned(f_obs, t, y, dt, dt if h is None else h, frozen)


class ETDRK4(Solver):
    """Exponential RK4 (Cox & Matthews 2002): the decays `rates` integrated exactly, the rest
    with exponential weights; stable however stiff those decays are, and RK4 where they are 0."""

    name: ClassVar[str] = "etdrk4"

    def step(self, f_obs, rates, t, y, dt, h=None, frozen=None):
        if rates is None:
            raise ValueError("ETDRK4 needs the model's decay rates (integrate(rates=...))")
        return _etdrk4(f_obs, rates, t, y, dt, h, frozen)


SOLVERS: dict[str, type[Solver]] = {c.name: c for c in (RK4, ETDRK4)}


def solver(spec: str | Solver) -> Solver:
    """A Solver from its name ("rk4", "etdrk4") or itself."""
    if isinstance(spec, Solver):
        return spec
    if spec not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)} (got {spec!r})")
    return SOLVERS[spec]()

