"""The public entry points: `simulate` (one trajectory) and `simulate_batch` (vmapped).

Both are jitted once per static structure (model classes and their static fields, the order n,
the number of steps, the save stride); every number in the Setup, dt, the
metric window and the state bound are traced, so changing a gain never recompiles.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import metrics as m
from dscjax import params, validation, xla
from dscjax.closed_loop import (
    Setup,
    State,
    decay_rates,
    frozen,
    initial_state,
    prepared,
    project,
    vector_field,
)
from dscjax.integrate import (
    DEFAULT_CHECKPOINT_EVERY,
    SOLVERS,
    STATUS_BOUND,
    STATUS_NONFINITE,
    STATUS_OK,
    Status,
    integrate,
    saved_steps,
)
from dscjax.metrics import DEFAULT_WINDOW_START, default_window  # noqa: F401 (public here too)


class Trajectory(eqx.Module):
    """A simulated closed loop, saved every `save_every` steps and at T (leading axis T).

    Attributes:
        t: (T,) save times k dt at the saved steps k = 0, s, 2s, ..., and N (the last point is
            always t_final, also where s does not divide N: `integrate.saved_steps`).
        x: (T, n) plant state; y = x[:, 0].
        w: (T,) hysteresis output w = P(u).
        h: the hysteresis model's state (for the backlash-like model (4): w itself).
        u: (T,) control input; u_dot (T,) its exact derivative.
        yr: (T,) reference (as used by the controller, e.g. shifted by the L-inf initialisation).
        S: (T, n) surfaces S_1..S_n (S_1 = tracking error).
        ctrl: controller state with a leading T axis (for DSC: z, theta_hat, phi_hat, zeta_hat,
            d_hat).
        metrics: dict of scalars over EVERY step (not only the saved ones), see `metrics.py`;
            all NaN if the trajectory diverged (from `simulate` and `simulate_batch`; see
            `nan_if_diverged`).
        status: integration status: code (0 ok, 1 non-finite, 2 state bound) and first bad step.
        dt: the step of the run reported (the requested one unless it was refined).
        refinements: int, the refinement level of this run (`refinement_level`): 0 = classical
            RK4 at the requested dt; j >= 1 = RK4 diverged there and this is the exponential
            step ETDRK4 at dt/2^(j-1) (`refine` in `simulate`). For a trajectory still
            diverged, dt is the smallest step tried: it diverged at every level.
    Under `simulate_batch` every field gains a leading batch axis.
    """

    t: jax.Array
    x: jax.Array
    w: jax.Array
    h: Any
    u: jax.Array
    u_dot: jax.Array
    yr: jax.Array
    S: jax.Array
    ctrl: Any
    metrics: dict
    status: Status
    dt: jax.Array
    refinements: jax.Array = 0

    @property
    def refined(self):
        """True where the run needed a smaller step than requested to stay finite."""
        return jnp.asarray(self.refinements) > 0

    @property
    def y(self):
        return self.x[..., 0]

    @property
    def e(self):
        """Tracking error e = y - y_r."""
        return self.x[..., 0] - self.yr

    @property
    def diverged(self):
        return self.status.code != STATUS_OK

    @property
    def t_diverged(self):
        """Time at which the state first went bad, +inf if it never did."""
        step = self.status.step
        return jnp.where(step >= 0, step * self.dt, jnp.inf)

    def __getattr__(self, name):
        # Controller states by name: traj.z, traj.theta_hat, traj.zeta_hat, ...
        ctrl = object.__getattribute__(self, "ctrl")
        if hasattr(ctrl, "_fields") and name in ctrl._fields:
            return getattr(ctrl, name)
        raise AttributeError(name)


class DivergenceError(RuntimeError):
    """A simulation left the state bound or went non-finite. `.trajectory` holds the run,
    frozen at its last good state."""

    def __init__(self, message: str, trajectory: Trajectory):
        super().__init__(message)
        self.trajectory = trajectory


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LoopMetrics:
    """The running reductions of a simulation (an `integrate.Reduction`): `metrics.py`'s, plus
    the caller's own `extra` ones (tuning's smooth L-inf and requirement penalties)."""

    dt: jax.Array
    window_start: jax.Array
    extra: Any = None
    n_steps: int = dataclasses.field(default=1, metadata=dict(static=True))

    def init(self, dtype):
        base = m.running_init(dtype)
        return base if self.extra is None else (base, self.extra.init(dtype))

    def update(self, acc, k, t, y: State, obs):
        base = acc if self.extra is None else acc[0]
        base = m.running_update(base, k, t, y.x[0] - obs.yr, obs.u, obs.w, self.dt,
                                self.window_start, self.n_steps)
        if self.extra is None:
            return base
        return base, self.extra.update(acc[1], k, t, y, obs, self.dt)

    def finalize(self, acc, t_final):
        if self.extra is None:
            return m.finalize(acc, t_final)
        return {**m.finalize(acc[0], t_final), **self.extra.finalize(acc[1], t_final)}


def run(setup: Setup, dt, window_start, state_bound, *, n_steps: int, save_every: int,
        overrides=None, checkpoint_every: int | None = DEFAULT_CHECKPOINT_EVERY,
        extra=None, solver: str = "rk4", gradient: str = "time_parallel") -> Trajectory:
    """The pure simulation behind `simulate` and `simulate_batch`: not jitted, no host checks.

    Compose it freely with jit, vmap, grad, checkpoint and sharding (tuning and sweeps do).
    The caller validates (`validation.validate_setup`, `validate_run`) and passes the number
    of steps. All arguments but the keyword-only ones may be traced.

    With `overrides` ({path: (B, ...)}), simulates the batch of setups with those leaves
    replaced, stored batch-last inside the loop (see integrate.py).

    `extra` adds running reductions of the caller's own (tuning uses it for its smooth L-inf
    surrogate and requirement penalties): a pytree (traced leaves) with methods
    `init(dtype) -> acc` (a pytree of scalars), `update(acc, k, t, y, obs, dt) -> acc` (called
    at every step k = 0..N, like `metrics.running_update`) and `finalize(acc, t_final) -> dict`,
    whose entries are added to `metrics`. None (the default) costs nothing.

    `solver`: "rk4" (classical RK4, the default) or "etdrk4" (the exponential RK4, ETDRK4, that
    integrates the stiff linear decays of `closed_loop.decay_rates` exactly).

    `gradient` (one trajectory only): how jax.grad / jvp / jacfwd differentiate the loop:
    "time_parallel" (the default: the Jacobians of all steps in one batched program, then a
    small recurrence; memory O(N m^2) for N steps and m states) or "autodiff" (JAX's own
    differentiation of the scan: the same numbers, several times slower in reverse mode; a
    reference). A batch is always differentiated through its checkpointed scan.
    """
    validation.one_of(solver, "solver", SOLVERS)
    validation.one_of(gradient, "gradient", GRADIENTS)
    dtype = jnp.result_type(setup.plant.x0)
    dt = jnp.asarray(dt, dtype)
    window_start = jnp.asarray(window_start, dtype)
    t_final = jnp.asarray(n_steps, dtype) * dt
    red = LoopMetrics(dt=dt, window_start=window_start, extra=extra, n_steps=n_steps)
    common = dict(save_every=save_every, reduction=red,
                  state_bound=jnp.asarray(state_bound, dtype), frozen=frozen(setup))
    exponential = solver == "etdrk4"
    if overrides is None:
        if exponential:
            common["rates"] = decay_rates
        if type(setup.hysteresis).projects:
            common["project"] = project
        setup = prepared(setup)
        y0 = initial_state(setup)
        res = integrate(vector_field, y0, dt, n_steps, setup, acc0=red.init(dtype),
                        time_parallel=gradient == "time_parallel", **common)
    else:
        shared, batched, rebuild = _split_members(setup, overrides)
        y0 = jax.vmap(lambda b: initial_state(rebuild(shared, b)))(batched)
        n_batch = jax.tree.leaves(overrides)[0].shape[0]
        acc0 = jax.tree.map(lambda a: jnp.broadcast_to(a, (n_batch,)), red.init(dtype))
        if exponential:
            common["rates"] = lambda t, y, args, obs: decay_rates(t, y, rebuild(*args), obs)
        if type(setup.hysteresis).projects:
            common["project"] = lambda t, y, args: project(t, y, rebuild(*args))
        res = integrate(lambda t, y, sh, b: vector_field(t, y, rebuild(sh, b)), y0, dt, n_steps,
                        shared, batch=batched, acc0=acc0, checkpoint_every=checkpoint_every,
                        **common)
    steps = saved_steps(n_steps, save_every)
    n_saved = steps.size
    t = jnp.asarray(steps, jnp.int32).astype(dtype) * dt
    finalize = red.finalize if overrides is None else jax.vmap(red.finalize, in_axes=(0, None))
    if overrides is not None:
        t = jnp.broadcast_to(t, (n_batch, n_saved))
        dt = jnp.broadcast_to(dt, (n_batch,))
    return Trajectory(
        t=t, x=res.ys.x, w=res.obs.w, h=res.ys.h, u=res.obs.u, u_dot=res.obs.u_dot, yr=res.obs.yr,
        S=res.obs.S, ctrl=res.ys.ctrl, metrics=finalize(res.acc, t_final), status=res.status,
        dt=dt, refinements=jnp.zeros_like(res.status.code),
    )


def _split_members(setup, overrides):
    """The prepared setups of a batch, split into shared leaves and per-member leaves.

    Only leaves that depend on the overrides (found by a dependency pass over the jaxpr of
    `prepared(set_many(setup, overrides))`) carry the batch axis; everything else stays one
    shared copy. Broadcasting every parameter would make XLA compute, e.g., sin(omega t) of the
    reference once per trajectory instead of once per step (measured 2.7x slower).
    """

    def member(values):
        return prepared(params.set_many(setup, values))

    one = jax.tree.map(lambda v: v[0], overrides)
    closed = jax.make_jaxpr(member)(one)
    depends = _depends_on_inputs(closed.jaxpr)
    full = jax.vmap(member)(overrides)
    leaves, treedef = jax.tree.flatten(full)
    if len(leaves) != len(depends):
        raise AssertionError("setup leaves and jaxpr outputs disagree")
    shared = [None if d else leaf[0] for leaf, d in zip(leaves, depends, strict=True)]
    batched = [leaf if d else None for leaf, d in zip(leaves, depends, strict=True)]

    def rebuild(shared_, batched_):
        merged = [b if d else s_ for s_, b, d in zip(shared_, batched_, depends, strict=True)]
        return jax.tree.unflatten(treedef, merged)

    return shared, batched, rebuild


def _depends_on_inputs(jaxpr) -> list[bool]:
    """For each output of a jaxpr: does it depend on any of its inputs (not only constants)?"""
    dep = set(jaxpr.invars)

    def is_dep(v):
        return not hasattr(v, "val") and v in dep

    for eqn in jaxpr.eqns:
        if any(is_dep(v) for v in eqn.invars):
            dep.update(eqn.outvars)
    return [is_dep(v) for v in jaxpr.outvars]


def nan_if_diverged(metrics: Mapping[str, Any], diverged) -> dict:
    """The metrics as the public entry points report them: NaN for a diverged trajectory.

    The integrator freezes a diverged trajectory at its last good state, so its running
    metrics cover only the time before the divergence; a windowed metric whose window starts
    later saw nothing at all and reads 0. Such numbers were not measured over the horizon they
    name, so every metric of a diverged trajectory becomes NaN (elementwise over a batch);
    `diverged` and `t_diverged` say what happened. Differentiable: the gradient of a diverged
    trajectory's metric is 0, never NaN. Tuning reads `run`'s raw metrics instead, with its own
    finite divergence penalty.
    """
    return {k: jnp.where(diverged, jnp.nan, v) for k, v in metrics.items()}


def _run_reported(setup, dt, window_start, state_bound, *, n_steps: int, save_every: int,
                  overrides=None, checkpoint_every: int | None = DEFAULT_CHECKPOINT_EVERY,
                  extra=None, solver: str = "rk4",
                  gradient: str = "time_parallel") -> Trajectory:
    """`run` with the metrics of diverged trajectories replaced by NaN (`nan_if_diverged`)."""
    traj = run(setup, dt, window_start, state_bound, n_steps=n_steps, save_every=save_every,
               overrides=overrides, checkpoint_every=checkpoint_every, extra=extra,
               solver=solver, gradient=gradient)
    return dataclasses.replace(traj, metrics=nan_if_diverged(traj.metrics, traj.diverged))


_simulate = jax.jit(_run_reported, static_argnames=("n_steps", "save_every", "checkpoint_every",
                                                   "solver", "gradient"))


def refinement_level(j: int, solver: str = "rk4") -> tuple[str, int]:
    """(solver, halvings of dt) of refinement level j: level 0 is the requested solver at the
    requested dt; then the exponential ETDRK4 step, which integrates the stiff decays
    (hysteresis rate alpha |u'|, filters 1/tau) exactly: at dt (after classical RK4), then
    at dt/2, dt/4, ..."""
    if j == 0:
        return solver, 0
    return "etdrk4", (j - 1 if solver == "rk4" else j)


GRADIENTS = ("time_parallel", "autodiff")
DEFAULT_REFINE = 6  # halvings of dt tried before a run counts as diverged: down to dt/64


def simulate(
    setup: Setup,
    t_final: float = 20.0,
    dt: float = 1e-3,
    *,
    save_every: int = 1,
    window_start: float | None = None,
    state_bound: float = 1e6,
    throw: bool = True,
    progress: Callable[[float], None] | None = None,
    refine: int = DEFAULT_REFINE,
    solver: str = "rk4",
    gradient: str = "time_parallel",
    extra=None,
) -> Trajectory:
    """Simulate the closed loop by fixed-step RK4 on t_k = k dt, k = 0..t_final/dt.

    Args:
        setup: the plant, hysteresis, controller and reference (see `paper_example`).
        t_final: horizon T in seconds; must be a whole number of steps.
        dt: RK4 step. Validated against the fastest filter (dt/tau <= 2.785).
        save_every: keep every s-th step in the returned arrays, and always the last one, at
            t_final (s need not divide the number of steps; the metrics use every step).
        window_start: t0 of the windowed metrics [t0, T]; default 1 s (0 if T <= 1 s).
        state_bound: a state component beyond it in magnitude counts as divergence.
        throw: raise DivergenceError if the run diverged (set False to inspect `status`).
            Under an outer jit/vmap no exception can be raised; `status` is always returned.
        refine: if classical RK4 diverges, run again with the exponential step ETDRK4 (which
            integrates the stiff decays, the hysteresis rate alpha |u'| and the filters 1/tau,
            exactly) at dt, then dt/2, ..., dt/2^(refine-1), on the same save times, and
            report the first run that stays finite; `traj.refinements` says which level it
            took (`refinement_level`), `traj.dt` the step. A run that diverges at every level
            is reported diverged, with `traj.dt` the smallest step tried. RK4 at a fixed dt can
            blow up where u moves fast although the loop itself does not; where RK4 stays
            finite its result is returned unchanged. 0 disables it. Needs concrete inputs
            (under an outer jit nothing is refined).
        progress: called on the host with the fraction of the steps done, 0.0, 0.01, ...,
            1.0, while the compiled loop runs (a `jax.debug.callback` every 1 % of the steps;
            about 2 % slower). It is part of the compiled program: pass the same callable to
            avoid recompiling. None (the default) costs nothing.
        extra: running reductions of the caller's own, as `run`'s (e.g. a requirement of
            `tuning.requirements`, whose margin `dscjax worst-case` maximises); their results
            are added to `metrics`. Not together with `progress`.

    Returns:
        Trajectory with arrays of length ceil(N / save_every) + 1 (N = t_final/dt) and the
        metrics (NaN if the run diverged: `traj.diverged`, `traj.t_diverged` say when).

    Example:
        >>> import dscjax
        >>> traj = dscjax.simulate(dscjax.paper_example(), t_final=2.0, dt=1e-3, save_every=100)
        >>> traj.x.shape
        (21, 2)
    """
    window_start = default_window(t_final, window_start)
    setup = canonical(setup)
    n_steps = _check(setup, t_final, dt, save_every, window_start)
    if progress is not None:
        if extra is not None:
            raise ValueError("simulate: give progress or extra, not both")
        extra = _Progress(n_steps, progress)
    _check_refine(refine)
    validation.one_of(solver, "solver", SOLVERS)
    validation.one_of(gradient, "gradient", GRADIENTS)
    refine = counted_levels(n_steps, refine, solver)
    traj = _simulate(setup, dt, window_start, state_bound, n_steps=n_steps,
                     save_every=save_every, extra=extra, solver=solver, gradient=gradient)
    concrete = validation.is_concrete(traj.status)
    for j in range(1, refine + 1):
        if not (concrete and bool(traj.diverged)):
            break
        level_solver, m = refinement_level(j, solver)
        finer = _simulate(setup, dt / 2**m, window_start, state_bound, n_steps=n_steps * 2**m,
                          save_every=save_every * 2**m, extra=extra, solver=level_solver,
                          gradient=gradient)
        traj = dataclasses.replace(finer, refinements=jnp.asarray(j, jnp.int32))
    if throw and concrete and bool(traj.diverged):
        from dscjax.stability import diagnose

        raise DivergenceError(divergence_report(traj, state_bound)[0] + diagnose(setup, traj),
                              traj)
    return traj


class _Progress(eqx.Module):
    """An `extra` reduction of `run` (a `metrics.Running`) that reports progress to the host
    and reduces nothing."""

    n_steps: int = eqx.field(static=True)
    report: Callable[[float], None] = eqx.field(static=True)

    def init(self, dtype):
        return jnp.zeros((), jnp.int32)

    def update(self, acc, k, t, y, obs, dt):
        every = max(self.n_steps // 100, 1)
        jax.lax.cond(k % every == 0, lambda: jax.debug.callback(self._call, k), lambda: None)
        return acc

    def _call(self, k):
        self.report(min(int(k) / self.n_steps, 1.0))

    def finalize(self, acc, t_final):
        return {}


def _dtype(setup):
    return jnp.result_type(setup.plant.x0)


def canonical(setup: Setup) -> Setup:
    """Every floating leaf in the setup's dtype (that of `plant.x0`), strongly typed.

    Python floats and `jnp.asarray(0.5)` are weakly typed, and weak types are part of jit's
    cache key: without this, setting a gain from a Python float would recompile.
    """
    return params.cast(setup, _dtype(setup))


def _check_refine(refine):
    validation.integer(refine, "refine", 0)


def counted_levels(n_steps: int, refine: int, solver: str = "rk4") -> int:
    """The refinement levels up to `refine` whose step count (N 2^halvings) the integrator's
    int32 step counter holds (`validation.MAX_STEPS`): finer ones are not tried."""
    while refine and n_steps * 2 ** refinement_level(refine, solver)[1] > validation.MAX_STEPS:
        refine -= 1
    return refine


def _check_checkpoint(checkpoint_every):
    if checkpoint_every is not None:
        validation.integer(checkpoint_every, "checkpoint_every", 1)


def _check(setup, t_final, dt, save_every, window_start, batched=False) -> int:
    if validation.is_concrete(setup) and not batched:
        validation.validate_setup(setup)
    return validation.validate_run(setup, t_final, dt, save_every, window_start)


def simulate_batch(
    setup: Setup,
    overrides: Mapping[str, Any],
    t_final: float = 20.0,
    dt: float = 1e-3,
    *,
    save_every: int | None = None,
    window_start: float | None = None,
    state_bound: float = 1e6,
    checkpoint_every: int | None = DEFAULT_CHECKPOINT_EVERY,
    refine: int = DEFAULT_REFINE,
    solver: str = "rk4",
) -> Trajectory:
    """Simulate a batch: `setup` with the parameters at the paths in `overrides` replaced by
    the rows of the given arrays (leading axis B), all in one vmapped, jitted call.

    Only the overridden leaves are batched; the rest of the setup is shared, not copied. Never
    raises on divergence: inspect `traj.status` (per trajectory) or `divergence_report(traj)`.
    The metrics of a diverged trajectory are NaN.

    Args:
        overrides: {"hysteresis.alpha": (B,), "plant.x0": (B, n), ...}.
        save_every: default t_final/dt, i.e. only the first and last points plus the metrics.
        checkpoint_every: reverse-mode differentiation keeps the batch's state every this many
            steps and recomputes the steps between (memory O(N/L + L) states per member).
        refine: as for `simulate`, per trajectory: only the diverged ones are run again, as a
            batch of their own, at dt/2, dt/4, ... (`traj.refinements` per trajectory).

    Example:
        >>> import dscjax, jax.numpy as jnp
        >>> setup = dscjax.paper_example()
        >>> traj = dscjax.simulate_batch(setup, {"hysteresis.alpha": jnp.array([0.8, 1.0, 1.2])},
        ...                              t_final=1.0, dt=1e-3)
        >>> traj.metrics["linf_error"].shape
        (3,)
    """
    setup = canonical(setup)
    dtype = _dtype(setup)
    overrides = {p: params.cast(v, dtype) for p, v in overrides.items()}
    sizes = {p: np.shape(v)[0] for p, v in overrides.items()}
    if len(set(sizes.values())) != 1:
        raise validation.ConfigError(f"overrides must share one batch size (got {sizes})")
    window_start = default_window(t_final, window_start)
    n_total = validation.whole_steps(t_final, dt)  # before any arithmetic that can overflow
    save_every = n_total if save_every is None else save_every
    if validation.is_concrete(setup):
        validation.validate_setup(setup)
        if validation.is_concrete(overrides):
            validation.validate_setup(params.set_many(setup, dict(overrides)), check_shapes=False)
            for p, val in overrides.items():
                validation.shape(val[0], p, np.shape(params.get(setup, p)))
    n_steps = _check(setup, t_final, dt, save_every, window_start, batched=True)
    _check_checkpoint(checkpoint_every)
    _check_refine(refine)
    validation.one_of(solver, "solver", SOLVERS)
    refine = counted_levels(n_steps, refine, solver)
    overrides = dict(overrides)

    def level(j, ov):
        level_solver, m = refinement_level(j, solver)
        return _simulate_batch(setup, ov, dt / 2**m, window_start, state_bound,
                               n_steps=n_steps * 2**m, save_every=save_every * 2**m,
                               checkpoint_every=checkpoint_every, solver=level_solver)

    traj = level(0, overrides)
    if refine and validation.is_concrete((traj, overrides)):  # refinement is host-side
        traj = refine_diverged(traj, overrides, level, refine)
    return traj


def refine_rows(rows, failed: Callable[[Any], np.ndarray], level: Callable, refine: int):
    """Re-run the failed rows of a batch at the refinement levels 1..refine, host-side.

    `rows`: a pytree of arrays whose leading axis is the batch; `failed(tree)`: its rows that
    diverged (bool); `level(j, idx)`: the rows `idx` re-run at level j (`refinement_level`), the
    same pytree. Each level runs only the rows still diverged, as a batch of their own padded to
    a power of two (sub-batches of similar sizes share one compiled program), and its rows
    replace theirs. Returns (rows as NumPy arrays, the level of each row's run: 0 = unrefined).
    Used by `simulate_batch` and by sweeps.
    """
    out = jax.tree.map(np.array, rows)
    todo = np.flatnonzero(failed(out))
    levels = np.zeros(len(failed(out)), np.int32)
    for j in range(1, refine + 1):
        if todo.size == 0:
            break
        size = 1 << int(np.ceil(np.log2(todo.size)))
        idx = np.concatenate([todo, np.full(size - todo.size, todo[0])])
        sub = jax.tree.map(lambda a, n=todo.size: np.asarray(a)[:n], level(j, idx))

        def put(dst, src, todo=todo):
            dst[todo] = src
            return dst

        out = jax.tree.map(put, out, sub)
        levels[todo] = j
        todo = todo[failed(sub)]
    return out, levels


def refine_diverged(traj: Trajectory, overrides: Mapping[str, Any], level: Callable,
                    refine: int) -> Trajectory:
    """`refine_rows` for a batch Trajectory: `level(j, overrides_subset)` simulates a
    sub-batch at level j with the same save times; `refinements` says each member's level."""
    def rows(j, idx):
        sub = level(j, {p: np.asarray(v)[idx] for p, v in overrides.items()})
        return dataclasses.replace(sub, refinements=None)

    out, levels = refine_rows(dataclasses.replace(traj, refinements=None),
                              lambda t: np.asarray(t.status.code) != STATUS_OK, rows, refine)
    return jax.tree.map(jnp.asarray, dataclasses.replace(out, refinements=levels))


def _simulate_batch_body(setup, overrides, dt, window_start, state_bound, *, n_steps,
                         save_every, checkpoint_every=DEFAULT_CHECKPOINT_EVERY, solver="rk4"):
    return _run_reported(setup, dt, window_start, state_bound, n_steps=n_steps,
                         save_every=save_every, overrides=overrides,
                         checkpoint_every=checkpoint_every, solver=solver)


# 512-bit vectors on AVX-512 CPUs when called at the top level (dscjax.xla.jit)
_simulate_batch = xla.jit(_simulate_batch_body,
                          static_argnames=("n_steps", "save_every", "checkpoint_every", "solver"))


def divergence_report(traj: Trajectory, state_bound: float | None = None) -> list[str]:
    """One line per diverged trajectory: which one (batch index), when, and how."""
    code = np.atleast_1d(np.asarray(traj.status.code))
    t_bad = np.atleast_1d(np.asarray(traj.t_diverged))
    lines = []
    batched = np.ndim(traj.status.code) > 0
    for i in np.flatnonzero(code != STATUS_OK):
        who = f"trajectory {i}" if batched else "the trajectory"
        how = {STATUS_NONFINITE: "a state became non-finite (inf/NaN)",
               STATUS_BOUND: "a state exceeded the state bound"
               + (f" {state_bound:g}" if state_bound is not None else "")}[int(code[i])]
        lines.append(
            f"{who} diverged at t = {t_bad[i]:.6g} s: {how}; outputs after that time hold the "
            f"last good state. Reduce dt (RK4 stability) or revise the gains."
        )
    return lines
