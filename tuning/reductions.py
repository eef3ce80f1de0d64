"""The running reductions the tuner adds to a simulation (`dscjax.metrics`' protocol): the
smooth windowed L-inf of the error and max|u| (log-sum-exps, stable by a running max), the error
against the config's own reference where the controller tracks a shifted one, and the
requirements' penalties (`TuningMetrics`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from dscjax import metrics as dm
from dscjax.closed_loop import Setup, prepared
from dscjax.metrics import step_weights


class SmoothLinf(eqx.Module):
    """Linf~ of the tracking error on [t0, T] (module docstring), a `Running` reduction: a
    log-sum-exp with a running max m, s = sum w exp(x - m)."""

    window_start: jax.Array  # () t0
    sharpness: jax.Array  # () s (1/units of e)
    n_steps: int = eqx.field(static=True)

    def init(self, dtype):
        z = jnp.zeros((), dtype)
        return {"m": z, "s": z, "w": z}

    def update(self, acc, k, t, y, obs, dt):
        e = y.x[0] - obs.yr
        _, w_win, in_win, _ = step_weights(k, t, dt, self.window_start, self.n_steps)
        x = self.sharpness * jnp.abs(e)
        m = jnp.where(in_win, jnp.maximum(acc["m"], x), acc["m"])
        # the exponent masked before t0, not just its weight: 0 * inf is NaN (double where)
        arg = jnp.where(in_win, x - m, 0.0)
        s = acc["s"] * jnp.exp(acc["m"] - m) + jnp.where(in_win, w_win * jnp.exp(arg), 0.0)
        return {"m": m, "s": s, "w": acc["w"] + w_win}

    def finalize(self, acc, t_final):
        return {"smooth_linf_window": (acc["m"] + _safe_log(acc["s"] / _pos(acc["w"])))
                / self.sharpness}


class SmoothMaxU(eqx.Module):
    """max~|u| (module docstring), as a `dscjax.metrics.Running` reduction."""

    sharpness: jax.Array  # () r (1/units of u)

    def init(self, dtype):
        z = jnp.zeros((), dtype)
        return {"m": z, "s": z}

    def update(self, acc, k, t, y, obs, dt):
        x = self.sharpness * jnp.abs(obs.u)
        m = jnp.maximum(acc["m"], x)
        return {"m": m, "s": acc["s"] * jnp.exp(acc["m"] - m) + jnp.exp(x - m)}

    def finalize(self, acc, t_final):
        return {"smooth_max_abs_u": (acc["m"] + _safe_log(acc["s"])) / self.sharpness}


# the error figures `UserError` gives against the config's reference (as "user_" + name)
USER_METRICS = ("linf_error_window", "linf_error", "l2_error_window")


class UserError(eqx.Module):
    """The error figures USER_METRICS of e = x_1 - y_r(t) against the config's reference y_r,
    where the controller tracks a shifted one (`shifted_reference`), as `dscjax.metrics`
    defines them: results user_linf_error_window, ... A `Running` reduction."""

    reference: Any  # the config's `Reference`
    window_start: jax.Array  # () t0
    n_steps: int = eqx.field(static=True, default=1)

    def init(self, dtype):
        return dm.running_init(dtype)

    def update(self, acc, k, t, y, obs, dt):
        return dm.running_update(acc, k, t, y.x[0] - self.reference(t), obs.u, obs.w, dt,
                                 self.window_start, self.n_steps)

    def finalize(self, acc, t_final):
        m = dm.finalize(acc, t_final)
        return {f"user_{k}": m[k] for k in USER_METRICS}


def shifted_reference(setup: Setup, overrides: Mapping[str, Any] | None = None):
    """The config's reference where the controller's initialisation tracks another one (the
    DSC's init = "linf"), else None; None too where `overrides` vary the reference (its
    figures would be the nominal one's)."""
    if overrides and any(p.startswith("reference.") for p in overrides):
        return None
    return None if prepared(setup).reference is setup.reference else setup.reference


class TuningMetrics(eqx.Module):
    """The `Running` reductions tuning adds to `dscjax.metrics` (the `extra` of `run`):
    `SmoothLinf`, `SmoothMaxU`, every requirement (results req0_penalty, req0_met, ...) and,
    with a `reference`, `UserError` (results user_linf_error_window, ...)."""

    window_start: jax.Array  # () t0
    e_sharpness: jax.Array  # () s of the smooth L-inf (1/units of e)
    u_sharpness: jax.Array  # () r of the smooth max|u| (1/units of u)
    requirements: tuple = ()  # `Requirement`s (their number and kinds are static)
    n_steps: int = eqx.field(static=True, default=1)  # N, for the trapezoid end weights
    reference: Any = None  # the config's reference, where the controller tracks another

    def parts(self) -> tuple[tuple[str, Any], ...]:
        """(prefix of the result names, reduction) of every part."""
        reqs = tuple((f"req{i}_", dataclasses.replace(r, n_steps=self.n_steps))
                     for i, r in enumerate(self.requirements))
        user = (() if self.reference is None else
                (("", UserError(self.reference, self.window_start, self.n_steps)),))
        return (("", SmoothLinf(self.window_start, self.e_sharpness, self.n_steps)),
                ("", SmoothMaxU(self.u_sharpness))) + reqs + user

    def init(self, dtype):
        return tuple(p.init(dtype) for _, p in self.parts())

    def update(self, acc, k, t, y, obs, dt):
        return tuple(p.update(a, k, t, y, obs, dt)
                     for (_, p), a in zip(self.parts(), acc, strict=True))

    def finalize(self, acc, t_final):
        out = {}
        for (prefix, p), a in zip(self.parts(), acc, strict=True):
            out |= {prefix + k: v for k, v in p.finalize(a, t_final).items()}
        return out


def _pos(x):
    return jnp.maximum(x, jnp.finfo(jnp.result_type(x)).tiny)


def _safe_log(x):
    ok = x > 0
    return jnp.where(ok, jnp.log(jnp.where(ok, x, 1.0)), -jnp.inf)
