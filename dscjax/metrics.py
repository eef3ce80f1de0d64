"""Tracking and control-effort metrics, all differentiable (max and |.| a.e.).

`Tracking` computes them as a running reduction (`integrate.Running`) over every step,
without storing the trajectory (tests/reference_metrics.py: the same on saved arrays). `Combined`
folds several reductions into one; `SmoothMax` is the one smooth maximum (the tuner's smooth
L-inf and max|u|, sensitivity's L_p error).

Definitions on the step grid t_k = k dt, k = 0..N, window W = {k : t_k >= t0}:
    L_inf  = max_{k in W} |e_k|
    L2     = sqrt( trapezoid_W(e^2) )           (trapezoid rule over the samples in W)
    RMS    = sqrt( trapezoid_W(e^2) / (T - t_first) ),  t_first the first sample time in W
    max|u| = max_k |u_k|, TV(u) = sum_k |u_(k+1) - u_k|, L2(u) = sqrt(trapezoid(u^2))
    (each also on W: max|u| and TV(u) over the steps k, k-1 in W)
where e = y - y_r = x_1 - y_r.

Chattering (the one definition; docs/numerics.md): u_lp is u through a first-order low pass
of time constant CHATTER_TIME_CONSTANT, and the chattering index is TV_W(u) / TV_W(u_lp). A
smooth u passes the filter unchanged (index near 1); a limit cycle near the sample or step rate
is filtered out (index >> 1). A run chatters when its index exceeds CHATTER_RATIO.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp


def trapezoid_weight(k, dt, n_steps):
    """Weight of sample k = 0..N in a trapezoid integral over the horizon: dt, dt/2 at ends."""
    return jnp.where((k == 0) | (k == n_steps), 0.5 * dt, dt)


def step_weights(k, t, dt, t0, n_steps):
    """Trapezoid weights of sample k: (over the horizon, over the window t >= t0, whether
    t_k is in the window, whether it is the window's first sample)."""
    in_win = t >= t0
    t_prev = (k - 1).astype(t.dtype) * dt  # the grid time before t_k, formed as t_k is
    first_win = in_win & (t_prev < t0)
    w_all = trapezoid_weight(k, dt, n_steps)
    w_win = jnp.where(in_win, jnp.where(first_win | (k == n_steps), 0.5 * dt, dt), 0.0)
    return w_all, w_win, in_win, first_win

CHATTER_TIME_CONSTANT = 0.02  # [s] of the low pass in the chattering index
CHATTER_RATIO = 1.5  # a run whose chattering index exceeds this chatters

DEFAULT_WINDOW_START = 1.0  # [s]; the paper's example's transient is over by then


def default_window(t_final):
    """The metric window's default start: 1 s (0 s if the horizon is 1 s or less).

    Every feature takes its default window from here (simulate, sweeps, tuning, reproduce).
    """
    return DEFAULT_WINDOW_START if t_final > DEFAULT_WINDOW_START else 0.0


# -- running, inside the scan -----------------------------------------------------------------


class RunningMetrics(NamedTuple):
    """Reductions accumulated at every step k = 0..N (all scalars)."""

    e_max: jax.Array  # max |e| over the horizon
    e_max_win: jax.Array  # max |e| over t >= t0
    e_sq: jax.Array  # trapezoid integral of e^2 over the horizon
    e_sq_win: jax.Array  # trapezoid integral of e^2 over t >= t0
    t_first_win: jax.Array  # first sample time in the window
    u_max: jax.Array  # max |u|
    u_sq: jax.Array  # trapezoid integral of u^2
    u_tv: jax.Array  # total variation of u
    u_prev: jax.Array  # u at the previous step
    w_max: jax.Array  # max |w|
    u_max_win: jax.Array  # max |u| over t >= t0
    u_tv_win: jax.Array  # total variation of u over t >= t0
    u_lp: jax.Array  # u through the chattering index's low pass
    u_lp_tv_win: jax.Array  # total variation of u_lp over t >= t0


def running_init(dtype) -> RunningMetrics:
    z = jnp.zeros((), dtype)
    return RunningMetrics(z, z, z, z, jnp.asarray(jnp.inf, dtype), z, z, z, z, z, z, z, z, z)


def running_update(acc: RunningMetrics, k, t, e, u, w, dt, t0, n_steps: int) -> RunningMetrics:
    """Fold the sample (t_k, e_k, u_k, w_k) into the running metrics."""
    w_all, w_win, in_win, first_win = step_weights(k, t, dt, t0, n_steps)
    ae, au = jnp.abs(e), jnp.abs(u)
    a = -jnp.expm1(-dt / CHATTER_TIME_CONSTANT)
    u_lp = jnp.where(k > 0, acc.u_lp + a * (u - acc.u_lp), u)
    step_win = in_win & ~first_win & (k > 0)  # the step k-1 -> k lies in the window
    return RunningMetrics(
        e_max=jnp.maximum(acc.e_max, ae),
        e_max_win=jnp.where(in_win, jnp.maximum(acc.e_max_win, ae), acc.e_max_win),
        e_sq=acc.e_sq + w_all * e * e,
        e_sq_win=acc.e_sq_win + w_win * e * e,
        t_first_win=jnp.where(first_win, t, acc.t_first_win),
        u_max=jnp.maximum(acc.u_max, au),
        u_sq=acc.u_sq + w_all * u * u,
        u_tv=acc.u_tv + jnp.where(k > 0, jnp.abs(u - acc.u_prev), 0.0),
        u_prev=u,
        w_max=jnp.maximum(acc.w_max, jnp.abs(w)),
        u_max_win=jnp.where(in_win, jnp.maximum(acc.u_max_win, au), acc.u_max_win),
        u_tv_win=acc.u_tv_win + jnp.where(step_win, jnp.abs(u - acc.u_prev), 0.0),
        u_lp=u_lp,
        u_lp_tv_win=acc.u_lp_tv_win + jnp.where(step_win, jnp.abs(u_lp - acc.u_lp), 0.0),
    )


def finalize(acc: RunningMetrics, t_final) -> dict[str, jax.Array]:
    """The named metrics from the running accumulator (differentiable)."""
    span_win = jnp.maximum(t_final - acc.t_first_win, jnp.finfo(acc.e_sq.dtype).tiny)
    return {
        "linf_error": acc.e_max,
        "linf_error_window": acc.e_max_win,
        "l2_error": _safe_sqrt(acc.e_sq),
        "l2_error_window": _safe_sqrt(acc.e_sq_win),
        "rms_error": _safe_sqrt(acc.e_sq / t_final),
        "rms_error_window": _safe_sqrt(acc.e_sq_win / span_win),
        "max_abs_u": acc.u_max,
        "l2_u": _safe_sqrt(acc.u_sq),
        "tv_u": acc.u_tv,
        "max_abs_w": acc.w_max,
        "max_abs_u_window": acc.u_max_win,
        "tv_u_window": acc.u_tv_win,
        "chattering_index": acc.u_tv_win / jnp.maximum(acc.u_lp_tv_win,
                                                      jnp.finfo(acc.u_tv.dtype).tiny),
    }


def chatters(chattering_index) -> bool:
    """Whether a run with this chattering index chatters (module docstring)."""
    return bool(chattering_index > CHATTER_RATIO)


class Tracking(eqx.Module):
    """The metrics of every run as a running reduction (`integrate.Running`): it reads
    e = x_1 - y_r, u and w off a closed-loop state y (`y.x`) and its observation; y_r is the
    reference the controller tracks, or `reference(t)` where given (tuning's `UserError`)."""

    window_start: jax.Array  # () t0 of the window [t0, T]
    n_steps: int = eqx.field(static=True, default=1)
    reference: Any = None
    substeps: Any = None  # a refinement level's steps per step (`RunSpec.substeps`): N m steps

    def init(self, dtype) -> RunningMetrics:
        return running_init(dtype)

    def update(self, acc, k, t, y, obs, dt):
        yr = obs.yr if self.reference is None else self.reference(t)
        n = self.n_steps if self.substeps is None else self.n_steps * self.substeps
        return running_update(acc, k, t, y.x[0] - yr, obs.u, obs.w, dt, self.window_start, n)

    def finalize(self, acc, t_final):
        return finalize(acc, t_final)


class Combined(eqx.Module):
    """Several running reductions as one; their results are merged, each name prefixed."""

    reductions: tuple  # the reductions (pytrees)
    prefixes: tuple[str, ...] = eqx.field(static=True, default=())  # one per reduction

    def init(self, dtype):
        return tuple(r.init(dtype) for r in self.reductions)

    def update(self, acc, k, t, y, obs, dt):
        return tuple(r.update(a, k, t, y, obs, dt)
                     for r, a in zip(self.reductions, acc, strict=True))

    def finalize(self, acc, t_final) -> dict[str, Any]:
        prefixes = self.prefixes or ("",) * len(self.reductions)
        return {prefix + k: v for prefix, r, a in zip(prefixes, self.reductions, acc, strict=True)
                for k, v in r.finalize(a, t_final).items()}


class LogSumExp(eqx.Module):
    """The form (1/s) log(mean exp(s a)) of a `SmoothMax`: s the sharpness (1/units of a); it
    tends to max a as s grows, and its gradient is the softmax-weighted one of the largest a."""

    sharpness: Any

    def fold(self, m, s, a, w, on):
        """(running max m of s a, sum s of w exp(s a - m)) with the sample a of weight w, where
        `on`; the exponent is masked where not, not just its weight: 0 x inf is NaN."""
        x = self.sharpness * a
        top = jnp.where(on, jnp.maximum(m, x), m)
        arg = jnp.where(on, x - top, 0.0)
        return top, s * jnp.exp(m - top) + jnp.where(on, w * jnp.exp(arg), 0.0)

    def value(self, m, mean):
        ok = mean > 0
        return (m + jnp.where(ok, jnp.log(jnp.where(ok, mean, 1.0)), -jnp.inf)) / self.sharpness


class Power(eqx.Module):
    """The form (mean a^p)^(1/p) of a `SmoothMax`, the L_p norm: p the order; between the mean
    and the max of a, tending to the max as p grows, smooth in a for p > 1. Summed relative
    to the running max of a, so a^p neither under- nor overflows."""

    order: Any

    def fold(self, m, s, a, w, on):
        a = jnp.where(on, a, 0.0)
        top = jnp.maximum(m, a)
        safe = jnp.where(top > 0, top, 1.0)  # top = 0: every term so far is 0
        return top, s * (m / safe) ** self.order + w * (a / safe) ** self.order

    def value(self, m, mean):
        pos = mean > 0
        return m * jnp.where(pos, jnp.where(pos, mean, 1.0) ** (1.0 / self.order), 0.0)


class SmoothMax(eqx.Module):
    """A smooth maximum of |e| (e = x_1 - y_r) or |u| as a running reduction, named `name`:
    the `form` (`LogSumExp` or `Power`) of the mean over the window [t0, T] (trapezoid
    weights) or, without a window (`window_start` None), of the sum over every step, which
    bounds the max from above."""

    form: LogSumExp | Power
    window_start: Any = None  # () t0; None: every step, summed
    name: str = eqx.field(static=True, default="smooth_max")
    of_u: bool = eqx.field(static=True, default=False)  # |u|, else |e|
    n_steps: int = eqx.field(static=True, default=1)

    def init(self, dtype):
        return dict.fromkeys(("m", "s", "w"), jnp.zeros((), dtype))

    def update(self, acc, k, t, y, obs, dt):
        a = jnp.abs(obs.u if self.of_u else y.x[0] - obs.yr)
        w, on = 1.0, True
        if self.window_start is not None:
            _, w, on, _ = step_weights(k, t, dt, self.window_start, self.n_steps)
        m, s = self.form.fold(acc["m"], acc["s"], a, w, on)
        return {"m": m, "s": s, "w": acc["w"] + w}

    def finalize(self, acc, t_final):
        s = acc["s"]
        if self.window_start is not None:
            s = s / jnp.maximum(acc["w"], jnp.finfo(acc["w"].dtype).tiny)
        return {self.name: self.form.value(acc["m"], s)}


def _safe_sqrt(x):
    """sqrt with a finite gradient at 0 (double-where trick)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)
