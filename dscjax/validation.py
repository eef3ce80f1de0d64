"""Host-side validation of setups and run settings, before anything is traced.

Every failure is a `ConfigError` naming the field by its config path, the allowed range and the
value received, e.g. ``hysteresis.lam must be > hysteresis.psi (got lam=0.1, psi=0.5)``. Arrays
with a leading batch axis are checked elementwise.
"""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import numpy as np

# RK4's stability interval on the negative real axis is about [-2.785, 0].
RK4_REAL_STABILITY = 2.785
# The integrator counts steps in an int32 (t_k = k dt): no run may have more.
MAX_STEPS = 2**31 - 1


class ConfigError(ValueError):
    """A setting out of its allowed range; the message names the field."""


def fmt(v) -> str:
    """A value for a message: a number, a short list, or the shape of a large array."""
    a = np.asarray(v)
    if a.ndim == 0:
        return f"{float(a):.6g}"
    if a.size <= 8:
        return "[" + ", ".join(f"{float(x):.6g}" for x in a.ravel()) + "]"
    return f"array of shape {a.shape}"


def floor_sig(x: float, digits: int = 3) -> str:
    """x rounded DOWN to `digits` significant digits (a safe upper bound to print)."""
    if x <= 0 or not np.isfinite(x):
        return f"{x:g}"
    scale = 10.0 ** (np.floor(np.log10(x)) - digits + 1)
    return f"{np.floor(x / scale) * scale:.{digits}g}"


def is_concrete(tree) -> bool:
    """False if any leaf is a tracer (then validation is the caller's job)."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(tree))


def positive(value, field: str) -> None:
    a = np.asarray(value, dtype=float)
    if not np.all(a > 0):
        raise ConfigError(f"{field} must be > 0 (got {fmt(value)})")


def nonnegative(value, field: str) -> None:
    a = np.asarray(value, dtype=float)
    if not np.all(a >= 0):
        raise ConfigError(f"{field} must be >= 0 (got {fmt(value)})")


def finite_positive(value, field: str) -> float:
    """`value` as a float if it is a finite number > 0; else ConfigError naming `field`."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if isinstance(value, bool) or not (math.isfinite(x) and x > 0):
        raise ConfigError(f"{field} must be a finite number > 0 (got {value!r})")
    return x


def finite(value, field: str) -> None:
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{field} must be finite (got {fmt(value)})")


def shape(value, field: str, expected: tuple[int, ...], why: str = "") -> None:
    got = tuple(np.shape(value))
    if got != tuple(expected):
        hint = f" {why}" if why else ""
        raise ConfigError(f"{field} must have shape {tuple(expected)}{hint} (got shape {got})")


def integer(value, field: str, low: int | None = None) -> int:
    """`value` if it is an int (not a bool, not a float) >= low; else ConfigError."""
    if (isinstance(value, bool) or not isinstance(value, int | np.integer)
            or (low is not None and value < low)):
        bound = "" if low is None else f" >= {low}"
        raise ConfigError(f"{field} must be an integer{bound} (got {value!r})")
    return int(value)


def number(value, field: str) -> float:
    """`value` as a float if it is a finite number (not a bool, not a string); else ConfigError."""
    if (isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating)
            or not np.isfinite(value)):
        raise ConfigError(f"{field} must be a number (got {value!r})")
    return float(value)


def string(value, field: str) -> str:
    """`value` if it is a string; else ConfigError."""
    if not isinstance(value, str):
        raise ConfigError(f"{field} must be a string (got {value!r})")
    return value


def one_of(value, field: str, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{field} must be one of {', '.join(map(repr, allowed))} (got {value!r})")


def validate_setup(setup, check_shapes: bool = True) -> None:
    """Check every model of a Setup; raise ConfigError on the first bad field.

    Range checks are elementwise, so a setup whose leaves carry a leading batch axis can be
    checked with check_shapes=False (its unbatched template checked with shapes).
    """
    n = setup.plant.order
    if n < 2:
        raise ConfigError(f"plant.g must have length n >= 2 (the order; got n={n})")
    if check_shapes:
        validate_shapes(setup)
    for f in dataclasses.fields(setup):  # first: inf or nan is named as such, not as a range
        finite_tree(getattr(setup, f.name), f.name)
    setup.plant.validate("plant")
    setup.hysteresis.validate("hysteresis")
    setup.controller.validate("controller")
    setup.reference.validate("reference")


def assumption_warnings(setup) -> list[str]:
    """The paper's assumptions a (valid) setup violates, one sentence each; [] if none.

    Not errors: a controller may be tried outside its design assumptions on purpose, but its
    guarantees (Theorem 1) then do not apply. Checked: Assumption 4, g_min <= |g_i| for every
    i (the controller's known lower bound of the plant's unknown gains).
    """
    g_min = getattr(setup.controller, "g_min", None)
    g = getattr(setup.plant, "g", None)
    if g_min is None or g is None or not is_concrete((g_min, g)):
        return []
    g_abs = np.abs(np.asarray(g, dtype=float))
    g_min = float(np.max(np.asarray(g_min, dtype=float)))
    below = np.flatnonzero(g_abs < g_min)
    if not below.size:
        return []
    which = ", ".join(f"|g_{i + 1}| = {g_abs[i]:.6g}" for i in below)
    return [f"Assumption 4 (g_min <= |g_i|) does not hold: controller.g_min = {g_min:.6g} but "
            f"plant.g has {which}; the design's guarantees (Theorem 1) do not apply"]


def validate_shapes(setup) -> None:
    """Every array field has the shape its model expects for the plant's order n."""
    n = setup.plant.order
    for section in ("plant", "hysteresis", "controller", "reference"):
        model = getattr(setup, section)
        why = f"for a plant of order n={n}" if section == "controller" else ""
        for name, expected in model.expected_shapes(n).items():
            shape(getattr(model, name), f"{section}.{name}", expected, why)


def finite_tree(obj, prefix: str) -> None:
    from dscjax import params

    for path in params.numeric_paths(obj):
        finite(params.get(obj, path), f"{prefix}.{path}")


def whole_steps(t_final, dt, t_field="simulation.t_final", dt_field="simulation.dt") -> int:
    """The number of steps N = t_final / dt: the one place a horizon becomes a step count.

    ConfigError naming the fields (config paths, or the command-line options the values came
    from) if either is not a finite number > 0, if N exceeds the integrator's step counter
    (MAX_STEPS, checked before any arithmetic that could overflow), or if the horizon is not
    a whole number of steps."""
    dt = finite_positive(dt, dt_field)
    t_final = finite_positive(t_final, t_field)
    ratio = t_final / dt
    if not ratio < MAX_STEPS + 0.5:
        raise ConfigError(
            f"{t_field} / {dt_field} = {ratio:.4g} steps, more than the {MAX_STEPS:,} the "
            f"integrator's step counter holds (got t_final={t_final:.6g}, dt={dt:.6g}); use a "
            f"shorter {t_field} or a larger {dt_field}")
    n_steps = int(round(ratio))
    if n_steps < 1 or abs(n_steps * dt - t_final) > 1e-9 * max(1.0, t_final):
        raise ConfigError(
            f"{t_field} must be a whole number of steps of {dt_field} "
            f"(got t_final={t_final:.6g}, dt={dt:.6g}, ratio {ratio:.6g})"
        )
    return n_steps


def validate_run(setup, t_final, dt, save_every: int, window_start) -> int:
    """Check the run settings against the setup; returns the number of steps N = t_final/dt.
    The save stride need not divide N (the last saved point is always t_final)."""
    n_steps = whole_steps(t_final, dt)
    integer(save_every, "simulation.save_every", 1)
    if window_start is not None and not (0 <= float(window_start) < float(t_final)):
        raise ConfigError(
            f"simulation.window_start must be in [0, t_final) = [0, {float(t_final):.6g}) "
            f"(got {float(window_start):.6g})"
        )
    tau = getattr(setup.controller, "tau", None)
    # a traced tau (e.g. differentiated by tuning) cannot be checked here: its caller does
    if tau is not None and np.size(tau) and is_concrete(tau):
        ratio = float(dt) / np.min(np.asarray(tau, dtype=float))
        if ratio > RK4_REAL_STABILITY:
            raise ConfigError(
                f"simulation.dt = {float(dt):.6g} is too large for RK4 on the fastest filter: "
                f"dt / min(controller.tau) must be <= {RK4_REAL_STABILITY} "
                f"(got min tau = {float(np.min(tau)):.6g}, ratio {ratio:.3g}); use dt <= "
                f"{floor_sig(RK4_REAL_STABILITY * float(np.min(tau)))}"
            )
    return n_steps
