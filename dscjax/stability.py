"""Which dt is stable for RK4: the closed loop's local spectrum along a trajectory.

Fixed-step RK4 is stable for a linear mode lambda when lambda dt lies in its stability region,
which reaches about -2.785 on the negative real axis and +-2.83i on the imaginary one. The closed
loop is nonlinear and non-smooth, so this is a local, linearised guide, not a proof: the spectral
radius rho(t) of dF/dX along a run says how stiff the loop is, and where. 2.785/max rho is a
conservative step (short bursts above it are often survived, since they last a few steps).

    traj = dscjax.simulate(setup, 20.0, 1e-3)
    prof = dscjax.stability.spectrum_along(setup, traj)
    prof.suggested_dt, prof.t_peak
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax.closed_loop import initial_state, prepared, vector_field
from dscjax.validation import RK4_REAL_STABILITY, floor_sig


class SpectrumProfile(NamedTuple):
    t: np.ndarray  # (T,) times
    radius: np.ndarray  # (T,) spectral radius of dF/dX
    max_real: np.ndarray  # (T,) largest real part (positive: locally unstable)
    t_peak: float  # time of the largest radius
    suggested_dt: float  # 2.785 / max radius


def _flat_field(setup):
    s = prepared(setup)
    _, unravel = ravel_pytree(initial_state(s))

    def field(y, t):
        return ravel_pytree(vector_field(t, unravel(y), s)[0])[0]

    return field


def local_eigenvalues(setup, t, state) -> np.ndarray:
    """Eigenvalues of the closed loop's Jacobian dF/dX at one time and state (a `State`)."""
    field = _flat_field(setup)
    y = ravel_pytree(state)[0]
    jac = jax.jit(jax.jacfwd(field))(y, jnp.asarray(t, y.dtype))
    return np.linalg.eigvals(np.asarray(jac))


def spectrum_along(setup, traj, every: int = 1) -> SpectrumProfile:
    """The local spectrum at every `every`-th saved point of a single trajectory."""
    field = _flat_field(setup)
    states = jax.tree.map(lambda a: a[::every], _states_of(traj))
    ys = jax.vmap(lambda s: ravel_pytree(s)[0])(states)
    ts = jnp.asarray(traj.t)[::every]
    jacs = jax.jit(jax.vmap(jax.jacfwd(field)))(ys, ts)
    ev = np.linalg.eigvals(np.asarray(jacs))
    radius = np.abs(ev).max(axis=1)
    max_real = ev.real.max(axis=1)
    i = int(np.argmax(radius))
    t = np.asarray(ts)
    return SpectrumProfile(t=t, radius=radius, max_real=max_real, t_peak=float(t[i]),
                           suggested_dt=float(RK4_REAL_STABILITY / radius[i]))


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
    """Which dt does classical RK4 need for this loop, and how does it depend on tau?

    Runs the loop (metrics only, no refinement) for every dt = dt * factor, each dt one batch
    over the filter constants tau * scale (the horizon rounded to a whole number of steps),
    then bisects (in log dt) between the largest stable and the smallest unstable step at the
    config's own tau. The linear guide 2.785 / max rho(t) along the nominal run is reported
    beside it: rho is the spectral radius of the closed loop's Jacobian, computed on a run
    that stays finite (refined if it had to be).
    """

    from dscjax.simulate import simulate, simulate_batch

    has_tau = hasattr(setup.controller, "tau")
    scales = np.asarray(tau_scales if has_tau else (1.0,), float)
    tau0 = np.asarray(setup.controller.tau, float) if has_tau else None
    dts = np.sort(np.asarray([dt * f for f in factors], float))

    def runs(step):
        n = max(int(round(t_final / step)), 1)
        if has_tau:
            ov = {"controller.tau": jnp.asarray(tau0[None, :] * scales[:, None])}
        else:
            ov = {"plant.x0": jnp.asarray(np.asarray(setup.plant.x0, float))[None]}
        b = simulate_batch(setup, ov, n * step, step, refine=0)
        return ~np.asarray(b.diverged), np.asarray(b.t_diverged)

    stable = np.zeros((scales.size, dts.size), bool)
    t_div = np.full((scales.size, dts.size), np.inf)
    for j, step in enumerate(dts):
        log(f"  dt = {step:.4g} s ...")
        stable[:, j], t_div[:, j] = runs(step)
    own = int(np.argmin(np.abs(scales - 1.0)))
    ok = np.flatnonzero(stable[own])
    bad = np.flatnonzero(~stable[own])
    lo = dts[ok[-1]] if ok.size else None
    hi = next((dts[b] for b in bad if lo is None or dts[b] > lo), None)
    if lo is not None and hi is not None:
        for _ in range(bisections):
            mid = math.sqrt(lo * hi)
            log(f"  bisecting: dt = {mid:.4g} s ...")
            if runs(mid)[0][own]:
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

def _states_of(traj):
    from dscjax.closed_loop import State

    return State(x=traj.x, h=traj.h, ctrl=traj.ctrl)

def diagnose(setup, traj) -> str:
    """One sentence on the local stiffness at the last good state of a diverged single run."""
    try:
        # after divergence the state is frozen at its last good value: the last saved point
        t_last = float(traj.t_diverged) - float(traj.dt)
        last = jax.tree.map(lambda a: a[-1], _states_of(traj))
        ev = local_eigenvalues(setup, t_last, last)
    except Exception:  # a diagnosis must never hide the divergence report itself
        return ""
    rho = float(np.abs(ev).max())
    dt = float(traj.dt)
    return (f" Just before, the closed loop's local Jacobian had spectral radius {rho:.3g}: "
            f"dt * radius = {dt * rho:.3g} (RK4 is stable up to about {RK4_REAL_STABILITY} on the "
            f"real axis); dt <= {floor_sig(RK4_REAL_STABILITY / rho, 2)} would resolve that mode.")
