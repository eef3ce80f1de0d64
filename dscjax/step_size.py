"""Which dt classical RK4 needs for a config, measured by running the loop (`dscjax stability`).

`stability_map` runs the loop over a grid of steps and filter constants and bisects the largest
stable step; the linear guide 2.785 / max rho(t) of `closed_loop.spectrum_along` is reported
beside it. Every run of a map is one compiled program (`map_steps`): N steps, each dt / step
steps of a step below dt (a traced count); a run may so take more steps than its horizon needs,
and is judged by its first bad step, which the later steps cannot change.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from dscjax.closed_loop import spectrum_along
from dscjax.runspec import RunSpec
from dscjax.simulate import simulate, simulate_batch


class StabilityMap(NamedTuple):
    """Where classical RK4 stays finite, measured by running the loop (see `stability_map`)."""

    dt: np.ndarray  # (D,) steps tried [s]
    tau_scale: np.ndarray  # (S,) factors applied to every filter constant tau_i
    tau: np.ndarray  # (S,) the smallest tau_i at each factor (nan without filters)
    stable: np.ndarray  # (S, D) bool: RK4 finite over the whole horizon
    t_diverged: np.ndarray  # (S, D) divergence time [s] (inf if stable)
    largest_stable_dt: float  # at the config's own tau: the largest stable dt (bisected)
    beyond_grid: bool  # no step tried diverged at the config's tau: a lower bound only
    linear_dt: float  # 2.785 / max spectral radius along the nominal run (the linear guide)
    t_peak: float  # where that radius peaks [s]
    requested_dt: float  # the config's dt


# The steps a stability map tries: dt * 2^k, k = -4..4.
DT_FACTORS = tuple(2.0 ** k for k in range(-4, 5))


def stability_map(setup, t_final: float, dt: float, tau_scales=(0.25, 0.5, 1.0, 2.0, 4.0),
                  factors=DT_FACTORS, bisections: int = 4,
                  log=lambda s: None) -> StabilityMap:
    """Which dt classical RK4 needs for this loop, against tau: the loop (no refinement) at
    every dt * factor, each one batch over tau * scale, then a bisection (in log dt) at the
    config's tau; beside it the linear guide 2.785 / max rho(t), rho the spectral radius of
    the loop's Jacobian along a finite (refined if need be) nominal run."""

    has_tau = hasattr(setup.controller, "tau")
    scales = np.asarray(tau_scales if has_tau else (1.0,), float)
    tau0 = np.asarray(setup.controller.tau, float) if has_tau else None
    dts = np.sort(np.asarray([dt * f for f in factors], float))

    n, subs = _plan(t_final, dt, dts)

    def runs(step, m):
        """(finite over t_final, divergence time) at each tau scale: n steps of m steps of
        `step`, each run judged by its first bad step against its own horizon's count."""
        ov = ({"controller.tau": jnp.asarray(tau0[None, :] * scales[:, None])} if has_tau
              else {"plant.x0": jnp.asarray(np.asarray(setup.plant.x0, float))[None]})
        spec = RunSpec.make(n * m * step, step, save_every=n * m, refine=0).grouped(m)
        b = simulate_batch(setup, ov, spec=spec)
        first = np.asarray(b.status.step)
        stable = (first < 0) | (first > _count(t_final, step))
        return stable, np.where(stable, np.inf, first * step)

    stable = np.zeros((scales.size, dts.size), bool)
    t_div = np.full((scales.size, dts.size), np.inf)
    for j, step in enumerate(dts):
        log(f"  dt = {step:.4g} s ...")
        stable[:, j], t_div[:, j] = runs(step, subs[j])
    own = int(np.argmin(np.abs(scales - 1.0)))
    ok = np.flatnonzero(stable[own])
    bad = np.flatnonzero(~stable[own])
    lo = dts[ok[-1]] if ok.size else None
    hi = next((dts[b] for b in bad if lo is None or dts[b] > lo), None)
    if lo is not None and hi is not None:
        m_lo = subs[ok[-1]]  # every step between lo and hi: as many as lo's, a longer horizon
        for _ in range(bisections):
            mid = math.sqrt(lo * hi)
            log(f"  bisecting: dt = {mid:.4g} s ...")
            if runs(mid, m_lo)[0][own]:
                lo = mid
            else:
                hi = mid
    largest = float(lo) if lo is not None else float("nan")
    nominal = simulate(setup, t_final, dt, save_every=max(int(round(t_final / dt)) // 2000, 1),
                       throw=False)
    prof = spectrum_along(setup, nominal) if not bool(nominal.diverged) else None
    return StabilityMap(
        dt=dts, tau_scale=scales,
        tau=scales * (tau0.min() if has_tau and tau0.size else np.nan), stable=stable,
        t_diverged=t_div, largest_stable_dt=largest, beyond_grid=hi is None and lo is not None,
        linear_dt=float(prof.suggested_dt) if prof is not None else float("nan"),
        t_peak=float(prof.t_peak) if prof is not None else float("nan"), requested_dt=dt)


def _count(t_final: float, step: float) -> int:
    """The steps of `step` that cover the horizon (at least one)."""
    return max(int(round(t_final / step)), 1)


def _plan(t_final: float, dt: float, dts) -> tuple[int, list[int]]:
    """(N, [m]): the map runs N steps of m steps of each of `dts`, m = dt / step below dt (a
    whole number for the map's steps dt * 2^k), 1 at dt and above, N the fewest that cover
    the horizon at every step (the runs at and above dt last longer than t_final)."""
    subs = [max(int(round(dt / step)), 1) for step in dts]
    return max(-(-_count(t_final, s) // m) for s, m in zip(dts, subs, strict=True)), subs


def map_steps(t_final: float, dt: float, dts) -> list[int]:
    """How many steps the map runs at each of `dts` (`_plan`'s N x m)."""
    n, subs = _plan(t_final, dt, dts)
    return [n * m for m in subs]


__all__ = ["DT_FACTORS", "StabilityMap", "map_steps", "stability_map"]
