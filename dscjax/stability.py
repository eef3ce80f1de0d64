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


def _states_of(traj):
    from dscjax.closed_loop import State

    return State(x=traj.x, w=traj.w, ctrl=traj.ctrl)


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
