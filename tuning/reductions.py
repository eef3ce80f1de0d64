"""The running reductions the tuner adds to a simulation (`dscjax.metrics`' protocol,
`tuning_metrics`): the smooth windowed L-inf of the error and the smooth max|u|
(`dscjax.metrics.SmoothMax` of the `LogSumExp` form), the requirements' penalties, and the
error against the config's own reference where the controller tracks a shifted one
(`UserError`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from dscjax import metrics as dm
from dscjax.closed_loop import Setup, prepared
from dscjax.metrics import LogSumExp, SmoothMax

# the error figures `UserError` gives against the config's reference (as "user_" + name)
USER_METRICS = ("linf_error_window", "linf_error", "l2_error_window")


class UserError(dm.Tracking):
    """The error figures USER_METRICS of e = x_1 - y_r(t) against the config's reference y_r
    (`reference`), where the controller tracks a shifted one (`shifted_reference`), as
    `dscjax.metrics` defines them: results user_linf_error_window, ..."""

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


def tuning_metrics(window_start, e_sharpness, u_sharpness, requirements: tuple = (),
                   n_steps: int = 1, reference=None) -> dm.Combined:
    """The running reductions tuning adds to `dscjax.metrics` (the `extra` of `run`): Linf~
    of e on [t0, T] (smooth_linf_window, sharpness `e_sharpness` in 1/units of e) and max~|u|
    over every step (smooth_max_abs_u, `u_sharpness`), every requirement (req0_penalty,
    req0_met, ...) and, with a `reference`, `UserError` (user_linf_error_window, ...)."""
    parts = [SmoothMax(LogSumExp(e_sharpness), window_start, "smooth_linf_window", n_steps=n_steps),
             SmoothMax(LogSumExp(u_sharpness), name="smooth_max_abs_u", of_u=True)]
    parts += [dataclasses.replace(r, n_steps=n_steps) for r in requirements]
    parts += [] if reference is None else [UserError(window_start, n_steps, reference)]
    prefixes = ("", "") + tuple(f"req{i}_" for i in range(len(requirements))) + ("",)
    return dm.Combined(tuple(parts), prefixes[:len(parts)])
