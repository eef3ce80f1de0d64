"""The closed loop as ONE vector field: plant (1), hysteresis (4), controller filters and
adaptive laws, integrated together.

    X = (x, h, controller state),   X' = F(t, X; setup)

h is the hysteresis model's state and w = P(u, h) its output (for the backlash-like model (4),
h = w). u is an algebraic function of (controller state, x, t); X' does not depend on w',
so u' = du/dX . X' + du/dt is one forward-mode derivative (jvp) of the control law along F:
exact, at every RK4 stage, with no algebraic loop (docs/numerics.md).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import xla
from dscjax.controllers.base import Controller
from dscjax.hysteresis import Hysteresis
from dscjax.plant import Plant
from dscjax.reference import Reference
from dscjax.rules import Number
from dscjax.validation import RK4_REAL_STABILITY, by_rule, floor_sig
from dscjax.xla import barrier


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Setup:
    """Everything a simulation needs, as one pytree: numbers are traced leaves, the model
    classes and static fields the structure (changing those recompiles).

    Attributes:
        plant: a `Plant` (its `x0` is the initial state x(0)).
        hysteresis: a `Hysteresis` model (its initial state, e.g. w0 or z0, is part of it).
        controller: a `Controller` (its initial estimates are part of it).
        reference: a `Reference` y_r(t).
    """

    plant: Plant
    hysteresis: Hysteresis
    controller: Controller
    reference: Reference

    @property
    def order(self) -> int:
        return self.plant.order

    def replace(self, **changes) -> Setup:
        return dataclasses.replace(self, **changes)


class State(NamedTuple):
    """State of the closed loop."""

    x: jax.Array  # (n,) plant state
    h: Any  # the hysteresis model's state (for the backlash-like model (4): its output w)
    ctrl: Any  # controller state (filters, estimates)


class Observation(NamedTuple):
    """Signals read off the loop at a state (not states themselves)."""

    u: jax.Array  # () control input
    u_dot: jax.Array  # () its exact time derivative
    yr: jax.Array  # () reference
    S: jax.Array  # (n,) surfaces; S_1 = x_1 - y_r is the tracking error
    w: jax.Array  # () hysteresis output w = P(u), the plant's input


def prepared(setup: Setup) -> Setup:
    """Apply the controller's initialisation rule (e.g. eqs. 67-68) to the setup."""
    controller, reference = setup.controller.prepare(setup.plant, setup.reference)
    return setup.replace(controller=controller, reference=reference)


def initial_state(setup: Setup) -> State:
    """X(0) for a prepared setup: x(0), the hysteresis state and the controller's state.

    The hysteresis state may depend on u(0) (a play's output z(0) = max(u0 - r, min(u0 + r,
    z0))), which is the control law at (x(0), controller state, t = 0)."""
    x0 = jnp.asarray(setup.plant.x0)
    c0 = setup.controller.init_state(setup.plant, setup.reference)
    u0, _ = setup.controller.law(c0, x0, jnp.zeros((), x0.dtype), setup.plant, setup.reference)
    h0 = jax.tree.map(lambda v: jnp.asarray(v, dtype=x0.dtype), setup.hysteresis.init_state(u0))
    return State(x=x0, h=h0, ctrl=c0)


def vector_field(t, X: State, setup: Setup) -> tuple[State, Observation]:
    """X' = F(t, X) of the whole closed loop, and the observation at (t, X).

    The setup must be `prepared`. Pure and elementwise in the batch sense: it composes with
    vmap, jvp, grad and checkpoint.
    """
    plant, ctrl, hyst, ref = setup.plant, setup.controller, setup.hysteresis, setup.reference

    def control(c_state, x, tt):
        return ctrl.law(c_state, x, tt, plant, ref)

    # The law is evaluated once; its linearisation gives u' = du/dX . X' + du/dt below.
    u, u_lin, info = jax.linearize(control, X.ctrl, X.x, t, has_aux=True)
    u, info = barrier((u, info))
    w = hyst.output(u, X.h)  # the actuator's output drives the plant
    dx = plant.rhs(X.x, w, t)
    dctrl = ctrl.state_rate(X.ctrl, X.x, t, info, plant, ref)
    dx, dctrl = barrier((dx, dctrl))
    du = barrier(u_lin(dctrl, dx, jnp.ones_like(t)))  # u' exactly, along the vector field
    dh = hyst.rate(u, du, X.h)
    return State(x=dx, h=dh, ctrl=dctrl), Observation(u=u, u_dot=du, yr=info.yr, S=info.S,
                                                       w=w)


def decay_rates(t, X: State, setup: Setup, obs: Observation) -> State:
    """Rates >= 0 of the stiff linear decays in the loop, per state component, at (t, X):
    the hysteresis rate (alpha |u'| for eq. 4) and the controller's filters (1/tau). The
    exponential step (`integrate._etdrk4`) integrates -rate * X exactly over a step."""
    return State(x=jnp.zeros_like(X.x), h=setup.hysteresis.decay_rate(obs.u, obs.u_dot, X.h),
                 ctrl=setup.controller.decay_rates(X.ctrl))


def frozen(setup: Setup) -> State:
    """Which parts of X are held constant inside a step (static bools, a prefix of X's tree for
    `integrate(frozen=...)`): the hysteresis state of a model that `projects` (the plays),
    which only `project` changes."""
    return State(x=False, h=type(setup.hysteresis).projects, ctrl=False)


def project(t, X: State, setup: Setup) -> State:
    """The discrete update after every step, at its end (t, X): the hysteresis's `project`, the
    play operators' exact clamp at u(t) = the control law at X; the rest of X is an ODE state.
    The setup must be `prepared`."""
    u, _ = setup.controller.law(X.ctrl, X.x, t, setup.plant, setup.reference)
    return X._replace(h=setup.hysteresis.project(u, X.h))


# -- the loop's local spectrum: how stiff it is for RK4 --------------------------------------------
# Fixed-step RK4 is stable for a linear mode lambda while lambda dt lies in its stability region
# (about -2.785 on the negative real axis, +-2.83i on the imaginary one). The loop is nonlinear
# and non-smooth, so the spectral radius rho(t) of dF/dX along a run is a local guide, not a
# proof; 2.785 / max rho is a conservative step.


class SpectrumProfile(NamedTuple):
    t: np.ndarray  # (T,) times
    radius: np.ndarray  # (T,) spectral radius of dF/dX
    max_real: np.ndarray  # (T,) largest real part (positive: locally unstable)
    t_peak: float  # time of the largest radius
    suggested_dt: float  # 2.785 / max radius


def _flat_jacobian(setup, y, t):
    """dF/dX of the closed loop's flat field at (t, y)."""
    s = prepared(setup)
    _, unravel = ravel_pytree(initial_state(s))

    def field(yy, tt):
        return ravel_pytree(vector_field(tt, unravel(yy), s)[0])[0]

    return jax.jacfwd(field)(y, t)


# compiled once per structure (the setup an argument): a diagnosis does not recompile
_jacobians_along = xla.jit(jax.vmap(_flat_jacobian, in_axes=(None, 0, 0)), lean=True)


def _eigenvalues(setup: Setup, traj, at=slice(None), t=None) -> np.ndarray:
    """The eigenvalues of dF/dX at the saved closed-loop states `at` of a trajectory
    (`simulate.Trajectory`), each at its saved time or at the times `t`."""
    states = jax.tree.map(lambda a: a[at], State(x=traj.x, h=traj.h, ctrl=traj.ctrl))
    ys = jax.vmap(lambda s: ravel_pytree(s)[0])(states)
    ts = jnp.asarray(traj.t[at] if t is None else t, ys.dtype)
    return np.linalg.eigvals(np.asarray(_jacobians_along(setup, ys, ts)))


def spectrum_along(setup: Setup, traj) -> SpectrumProfile:
    """The local spectrum at every saved point of a single trajectory (`simulate.Trajectory`).

        traj = dscjax.simulate(setup, 20.0, 1e-3)
        prof = dscjax.closed_loop.spectrum_along(setup, traj)   # prof.suggested_dt
    """
    ev = _eigenvalues(setup, traj)
    radius = np.abs(ev).max(axis=1)
    i = int(np.argmax(radius))
    t = np.asarray(traj.t)
    return SpectrumProfile(t=t, radius=radius, max_real=ev.real.max(axis=1), t_peak=float(t[i]),
                           suggested_dt=float(RK4_REAL_STABILITY / radius[i]))


def diagnose(setup: Setup, traj) -> str:
    """One sentence on the local stiffness (the eigenvalues of dF/dX) at the last good state
    of a diverged single run ("" if it cannot be computed: a diagnosis never hides the
    divergence report itself)."""
    try:
        # after divergence the state is frozen at its last good value: the last saved point
        ev = _eigenvalues(setup, traj, slice(-1, None),
                          [float(traj.t_diverged) - float(traj.dt)])
    except Exception:
        return ""
    rho = float(np.abs(ev).max())
    dt = float(traj.dt)
    return (f" Just before, the closed loop's local Jacobian had spectral radius {rho:.3g}: "
            f"dt * radius = {dt * rho:.3g} (RK4 is stable up to about {RK4_REAL_STABILITY} on the "
            f"real axis); dt <= {floor_sig(RK4_REAL_STABILITY / rho, 2)} would resolve that mode.")


# -- the digital controller: sampled at Ts, its input held (zero-order hold) ---------------


class ExponentialEuler(eqx.Module):
    """c <- c + Ts phi(-lam Ts) c', phi(z) = (e^z - 1)/z, lam = `Controller.decay_rates`:
    exact for the filters' linear part."""

    name: ClassVar[str] = "exponential-euler"
    words: ClassVar[str] = "exponential Euler"

    def advance(self, ctrl, c, rate, ts):
        return jax.tree.map(lambda c_, r, l: c_ + ts * _phi(-l * ts) * r, c, rate,
                            ctrl.decay_rates(c))


class ForwardEuler(eqx.Module):
    """c <- c + Ts c' (what a hand-written controller often does)."""

    name: ClassVar[str] = "euler"
    words: ClassVar[str] = "forward Euler"

    def advance(self, ctrl, c, rate, ts):
        return jax.tree.map(lambda c_, r: c_ + ts * r, c, rate)


# How a sampled controller may advance its states over one sample, by the name a config gives
SCHEME = {s.name: s for s in (ExponentialEuler(), ForwardEuler())}


def check_delay(delay, line: int, owner: str) -> None:
    """A delay given as a number must be a whole number of samples within its line (indexing
    would clamp a longer one silently); ConfigError otherwise. Arrays and tracers are a
    compiled program's own (set from a checked spec)."""
    if not isinstance(delay, jax.Array | np.ndarray):
        by_rule(Number(ge=0, le=line, integer=True), delay, f"{owner}.delay")


class Sampling(eqx.Module):
    """A controller that runs at the sample times t_k = k Ts, Ts = `every` dt.

    At t_k it reads x(t_k) (plus seeded Gaussian noise of std `noise`), computes u_k and
    advances its states once by the `scheme` (`ExponentialEuler` or `ForwardEuler`). The
    actuator holds u_(k-delay) until t_(k+1) (the first input for the first `delay`
    samples); a change of the held input moves the hysteresis along its curve (`jump`). The
    delay line keeps the last `line` inputs: one program serves every delay up to `line`.
    """

    every: Any  # dt steps per sample, Ts = every dt (a number: one program serves every Ts)
    delay: Any = 0  # input delay in whole samples, at most `line` (a number, as `every`)
    line: int = eqx.field(static=True, default=0)  # the delay line's length
    noise: Any = None  # std of the measurement noise on x: () or (n,); None: no noise
    seed: Any = 0  # seed of the noise (a float holding an integer: no integer leaf is traced)
    scheme: ExponentialEuler | ForwardEuler = eqx.field(static=True, default=ExponentialEuler())

    def __check_init__(self):
        check_delay(self.delay, self.line, "Sampling")


class SampledState(NamedTuple):
    """State of the sampled loop: the continuous loop's, the held input and the delay line."""

    x: jax.Array  # (n,) plant state
    h: Any  # hysteresis state
    ctrl: Any  # controller state after the last sample
    u: jax.Array  # () the input the actuator holds
    past: jax.Array  # (line,) the last inputs computed, the newest first


def _phi(z):
    """(e^z - 1)/z, 1 at z = 0 (double where)."""
    small = jnp.abs(z) < 1e-8
    zs = jnp.where(small, 1.0, z)
    return jnp.where(small, 1.0 + 0.5 * z, jnp.expm1(zs) / zs)


def sample_update(k, t, X, setup: Setup, sampling: Sampling, dt):
    """The controller's step at sample index k (time t): read x, compute u, advance."""
    plant, ctrl, ref = setup.plant, setup.controller, setup.reference
    x = X.x
    if sampling.noise is not None:
        key = jax.random.fold_in(jax.random.PRNGKey(jnp.asarray(sampling.seed).astype(jnp.uint32)),
                                 k)
        x = x + jnp.asarray(sampling.noise, x.dtype) * jax.random.normal(key, x.shape, x.dtype)
    u_new, info = ctrl.law(X.ctrl, x, t, plant, ref)
    rate = ctrl.state_rate(X.ctrl, x, t, info, plant, ref)
    c_next = sampling.scheme.advance(ctrl, X.ctrl, rate, sampling.every * dt)
    applied, past = u_new, X.past
    if sampling.line:
        d = sampling.delay  # a Python int indexes statically (the exported law's C)
        newest = jnp.concatenate([u_new[None], X.past])
        applied = newest[d if isinstance(d, int) else jnp.round(d).astype(jnp.int32)]
        past = newest[:-1]
    h = setup.hysteresis.jump(X.u, applied, X.h)
    return SampledState(x=X.x, h=h, ctrl=c_next, u=applied, past=past)


def sampled_initial_state(setup: Setup, sampling: Sampling, dt) -> SampledState:
    """X(0) of the sampled loop (setup `prepared`): the first sample taken at t = 0."""
    X0 = initial_state(setup)
    dtype = X0.x.dtype
    u0, _ = setup.controller.law(X0.ctrl, X0.x, jnp.zeros((), dtype), setup.plant, setup.reference)
    u0 = jnp.asarray(u0, dtype)
    start = SampledState(*X0, u=u0, past=jnp.full((sampling.line,), u0, dtype))
    return sample_update(jnp.zeros((), jnp.int32), jnp.zeros((), dtype), start, setup, sampling,
                         jnp.asarray(dt, dtype))


def sampled_vector_field(t, X: SampledState, setup: Setup) -> tuple[SampledState, Observation]:
    """The plant alone between samples (the input held, the rest frozen), and the
    observation at (t, X): the held u, u' = 0, and y_r and the surfaces the law would see."""
    w = setup.hysteresis.output(X.u, X.h)
    dx = setup.plant.rhs(X.x, w, t)
    _, info = setup.controller.law(X.ctrl, X.x, t, setup.plant, setup.reference)
    zero = jax.tree.map(jnp.zeros_like, X)
    return zero._replace(x=dx), Observation(u=X.u, u_dot=jnp.zeros_like(X.u), yr=info.yr,
                                            S=info.S, w=w)


# Everything but the plant is held inside a step (a prefix of SampledState's tree)
SAMPLED_FROZEN = SampledState(x=False, h=True, ctrl=True, u=True, past=True)


def sample_after_step(k_next, t, X: SampledState, setup: Setup, sampling: Sampling, dt):
    """After the step that ends at t = t_(k_next): the controller's sample if k_next is a
    multiple of `every`, else X unchanged."""
    every = jnp.round(jnp.asarray(sampling.every)).astype(jnp.asarray(k_next).dtype)
    new = sample_update(k_next // every, t, X, setup, sampling, dt)
    due = k_next % every == 0
    return jax.tree.map(lambda a, b: jnp.where(due, a, b), new, X)


__all__ = ["SAMPLED_FROZEN", "SCHEME", "Controller", "ExponentialEuler", "ForwardEuler",
           "Observation", "SampledState", "Sampling", "Setup", "SpectrumProfile", "State",
           "check_delay", "decay_rates", "diagnose", "frozen", "initial_state", "prepared",
           "project", "sample_after_step", "sample_update", "sampled_initial_state",
           "sampled_vector_field", "spectrum_along", "vector_field"]
