"""The public entry points: `simulate` (one trajectory) and `simulate_batch` (vmapped), and
`run`, the pure function under them that tuning, sweeps and the worst-case search compose.

A run is a `Setup` (every number traced) and a `RunSpec` (how it is simulated: the number of
steps, the save stride, the solver and the controller's sampling are static). Both entry points
are jitted once per static structure: changing a gain, dt or the metric window never
recompiles, nor does a host-side setting of the spec (`RunSpec.program`). A run that
diverges is run again refined (ETDRK4, smaller steps) before it counts as diverged; a diverged
trajectory's metrics are NaN, beside its status and time. Refinement is host-side: under a
trace (jit, grad, vmap) both entry points refuse a spec that would refine (pass refine=0, or
use the pure `dscjax.objective`); with refine=0 they compute the same function traced or not
(`simulate`'s throw becomes `eqx.error_if`).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import closed_loop, divergence, params, validation, xla
from dscjax import device as dscjax_device
from dscjax import metrics as m
from dscjax.closed_loop import Sampling, Setup
from dscjax.divergence import DivergenceError, counted_levels, divergence_report, level_spec
from dscjax.divergence import refine_rows as refine_rows  # callers import these from here
from dscjax.divergence import refinement_level as refinement_level
from dscjax.integrate import (
    DEFAULT_CHECKPOINT_EVERY,
    RK4,
    STATUS_OK,
    Status,
    TimeParallel,
    integrate,
    saved_steps,
)
from dscjax.rules import AtLeast
from dscjax.runspec import DEFAULT_REFINE, RunSpec


class Trajectory(eqx.Module):
    """A simulated closed loop at the saved steps 0, s, 2s, ... and N (leading axis T; under
    `simulate_batch` every field gains a leading batch axis).

    Attributes:
        t: (T,) save times (the last always t_final: `integrate.saved_steps`).
        x: (T, n) plant state. w: (T,) hysteresis output. h: the hysteresis model's state.
        u, u_dot: (T,) control input and its exact derivative.
        yr: (T,) reference as the controller uses it. S: (T, n) surfaces (S_1 = tracking error).
        ctrl: controller state with a leading T axis (for DSC: z, theta_hat, phi_hat, ...).
        metrics: scalars over EVERY step (`metrics.py`); NaN if diverged (`nan_if_diverged`).
        status: code (0 ok, 1 non-finite, 2 state bound) and first bad step.
        dt: the step of the run reported; for a run still diverged, the smallest one tried.
        refinements: the refinement level of the run reported (`refinement_level`; 0: none).
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
    def e(self):
        """Tracking error e = y - y_r."""
        return self.x[..., 0] - self.yr

    @property
    def diverged(self):
        return self.status.code != STATUS_OK

    @property
    def t_diverged(self):
        """Time at which the state first went bad, +inf if it never did."""
        return jnp.where(self.status.step >= 0, self.status.step * self.dt, jnp.inf)

    def __getattr__(self, name):
        # Controller states by name: traj.z, traj.theta_hat, traj.zeta_hat, ...
        ctrl = object.__getattribute__(self, "ctrl")
        if hasattr(ctrl, "_fields") and name in ctrl._fields:
            return getattr(ctrl, name)
        raise AttributeError(name)


def _loop(setup: Setup, spec: RunSpec):
    """(field, init, rates, project, frozen): what `integrate` needs for the continuous or the
    sampled loop, each function taking the setup and the sampling ((`Sampling`, dt) or None) as
    arguments, never closing over traced values: field(t, y, setup, samp) -> (dy, obs),
    init(setup, samp) -> y0, rates(t, y, setup, samp, obs) -> decay rates like y, project(k, t,
    y, setup, samp) -> y after a step (or None), and the static tree of held parts."""
    if not spec.sampled:
        return (lambda t, y, s, samp: closed_loop.vector_field(t, y, s),
                lambda s, samp: closed_loop.initial_state(s),
                lambda t, y, s, samp, obs: closed_loop.decay_rates(t, y, s, obs),
                (lambda k, t, y, s, samp: closed_loop.project(t, y, s))
                if type(setup.hysteresis).projects else None,
                closed_loop.frozen(setup))
    return (lambda t, y, s, samp: closed_loop.sampled_vector_field(t, y, s),
            lambda s, samp: closed_loop.sampled_initial_state(s, *samp),
            lambda t, y, s, samp, obs: jax.tree.map(jnp.zeros_like, y),
            lambda k, t, y, s, samp: closed_loop.sample_after_step(k, t, y, s, *samp),
            closed_loop.SAMPLED_FROZEN)


def run(setup: Setup, spec: RunSpec, *, overrides=None, extra=None) -> Trajectory:
    """The pure simulation under `simulate` and `simulate_batch`: not jitted, no host checks
    (the caller runs `check`); compose it with jit, vmap, grad and sharding. With `overrides`
    ({path: (B, ...)}) it runs that batch of setups; `extra` (an `integrate.Running`) adds the
    caller's running reductions to `metrics`."""
    dtype = dtype_of(setup)
    spec = spec.for_dtype(dtype)
    sub = spec.substeps  # (a refinement level's: steps of dt per step; None: one)
    red = m.Tracking(window_start=spec.window_start, n_steps=spec.n_steps, substeps=sub)
    if extra is not None:
        red = m.Combined((red, extra))
    samp = ((Sampling(every=spec.sample_every, delay=spec.delay, line=spec.line,
                      noise=spec.noise, seed=spec.noise_seed, scheme=spec.discretisation),
             spec.dt) if spec.sampled else None)
    loop_field, init, rates, project, frozen = _loop(setup, spec)
    if overrides is None:
        shared, batch = closed_loop.prepared(setup), None
        y0 = init(shared, samp)

        def member(args):  # (setup, sampling) from the args of the rates and the projection
            return args
    else:
        shared, batch, rebuild = _split_members(setup, overrides)
        y0 = jax.vmap(lambda b: init(rebuild(shared, b), samp))(batch)

        def member(args):
            (sh, sa), b = args
            return rebuild(sh, b), sa

    res = integrate(lambda t, y, args: loop_field(t, y, *member(args)), y0, spec.dt,
                    spec.n_steps, (shared, samp), batch=batch,
                    rates=lambda t, y, args, obs: rates(t, y, *member(args), obs),
                    project=None if project is None else
                    (lambda k, t, y, args: project(k, t, y, *member(args))),
                    save_every=spec.save_every, reduction=red, state_bound=spec.state_bound,
                    solver=spec.solver, gradient=spec.gradient, frozen=frozen,
                    skip_diverged=spec.skip_diverged, substeps=sub)
    k = jnp.asarray(saved_steps(spec.n_steps, spec.save_every), jnp.int32)
    t = (k if sub is None else k * sub).astype(dtype) * spec.dt
    t_final = jnp.asarray(spec.n_steps if sub is None else spec.n_steps * sub, dtype) * spec.dt
    finalize, dt = red.finalize, spec.dt
    if overrides is not None:
        finalize = jax.vmap(red.finalize, in_axes=(0, None))
        n_batch = jax.tree.leaves(overrides)[0].shape[0]
        t = jnp.broadcast_to(t, (n_batch, t.shape[0]))
        dt = jnp.broadcast_to(dt, (n_batch,))
    return Trajectory(t=t, x=res.ys.x, w=res.obs.w, h=res.ys.h, u=res.obs.u, u_dot=res.obs.u_dot,
                      yr=res.obs.yr, S=res.obs.S, ctrl=res.ys.ctrl,
                      metrics=finalize(res.acc, t_final), status=res.status, dt=dt,
                      refinements=jnp.zeros_like(res.status.code))


def _split_members(setup, overrides):
    """The prepared setups of a batch as (shared, batched, rebuild): only the leaves that
    depend on the overrides (by a pass over the jaxpr) carry the batch axis, so XLA computes,
    e.g., the reference's sin(omega t) once per step, not once per member."""

    def member(values):
        return closed_loop.prepared(params.set_many(setup, values))

    one = jax.tree.map(lambda v: v[0], overrides)
    depends = depends_on_inputs(jax.make_jaxpr(member)(one).jaxpr)
    full = jax.vmap(member)(overrides)
    leaves, treedef = jax.tree.flatten(full)  # one leaf per output of the jaxpr
    shared = [None if d else leaf[0] for leaf, d in zip(leaves, depends, strict=True)]
    batched = [leaf if d else None for leaf, d in zip(leaves, depends, strict=True)]

    def rebuild(shared_, batched_):
        merged = [b if d else s_ for s_, b, d in zip(shared_, batched_, depends, strict=True)]
        return jax.tree.unflatten(treedef, merged)

    return shared, batched, rebuild


def depends_on_inputs(jaxpr) -> list[bool]:
    """For each output of a jaxpr: does it depend on any of its inputs (not only constants)?"""
    dep = set(jaxpr.invars)

    def is_dep(v):
        return not hasattr(v, "val") and v in dep

    for eqn in jaxpr.eqns:
        if any(is_dep(v) for v in eqn.invars):
            dep.update(eqn.outvars)
    return [is_dep(v) for v in jaxpr.outvars]


def nan_if_diverged(metrics: Mapping[str, Any], diverged) -> dict:
    """The metrics, NaN where `diverged` (elementwise): a diverged run's metrics cover only
    the time before it froze, not the horizon they name. Its gradient is 0, never NaN."""
    return {k: jnp.where(diverged, jnp.nan, v) for k, v in metrics.items()}


def run_reported(setup, spec, overrides=None, extra=None) -> Trajectory:
    """`run` with the metrics of diverged trajectories replaced by NaN (`nan_if_diverged`)."""
    traj = run(setup, spec, overrides=overrides, extra=extra)
    return dataclasses.replace(traj, metrics=nan_if_diverged(traj.metrics, traj.diverged))


# at the top level (dscjax.xla.jit): one trajectory and a small batch compile lean, a larger
# batch with 512-bit vectors on AVX-512 CPUs
_simulate = xla.jit(run_reported, lean=True)
_simulate_batch = xla.jit(run_reported)


def simulate(setup: Setup, t_final: float = 20.0, dt: float = 1e-3, *,
             spec: RunSpec | None = None, save_every: int = 1,
             window_start: float | None = None, state_bound: float = 1e6, solver: str = "rk4",
             refine: int = DEFAULT_REFINE, sample_time: float | None = None, throw: bool = True,
             progress: Callable[[float], None] | None = None, extra=None,
             device=None) -> Trajectory:
    """Simulate the closed loop on t_k = k dt, k = 0..t_final/dt.

    Args:
        setup: the plant, hysteresis, controller and reference (see `paper_example`).
        t_final, dt, save_every, window_start, state_bound, solver, refine, sample_time: the
            run (`RunSpec.make`'s arguments, checked), unless `spec` gives it whole. A diverged
            run is run again at the refinement levels 1..refine and the first that stays
            finite is reported. Under a trace (jit, grad, vmap) refine must be 0: refinement
            runs on the host (ValueError otherwise; `dscjax.objective` is the pure function).
            sample_time: a zero-order-hold controller.
        throw: raise DivergenceError if the run diverged (under a trace: `eqx.error_if`,
            an error when the compiled function runs).
        progress: called on the host with the fraction of steps done (every 1 %); pass the same
            callable to avoid recompiling.
        extra: the caller's running reductions, as `run`'s.
        device: "auto", "cpu", "gpu" or a jax Device (default: the spec's; `device.choose`).

    Returns:
        Trajectory (metrics NaN if the run diverged: `traj.diverged`, `traj.t_diverged`).

    Example:
        >>> import dscjax
        >>> traj = dscjax.simulate(dscjax.paper_example(), t_final=2.0, dt=1e-3, save_every=100)
        >>> traj.x.shape
        (21, 2)
    """
    if spec is None:
        spec = RunSpec.make(t_final, dt, save_every=save_every, window_start=window_start,
                            state_bound=state_bound, solver=solver, refine=refine,
                            sample_time=sample_time)
    setup = canonical(setup)
    check(setup, spec)
    if progress is not None:
        if extra is not None:
            raise ValueError("simulate: give progress or extra, not both")
        extra = _Progress(spec.n_steps, progress)
    divergence.refuse_traced_refinement(spec, "simulate", (setup, spec))
    with _placed(spec, device, 1, setup):
        traj = _simulate(setup, spec.program(), None, extra)
        # traced inside a user's jit even where the inputs are concrete
        concrete = validation.is_concrete(traj.status)
        divergence.refuse_traced_refinement(spec, "simulate", traj.status)
        t_first = traj.t_diverged
        for j in range(1, counted_levels(spec) + 1):  # none where traced (refused above)
            if not bool(traj.diverged):
                break
            finer = _simulate(setup, level_spec(spec, j).program(), None, extra)
            traj = dataclasses.replace(finer, refinements=jnp.asarray(j, jnp.int32))
    if throw and not concrete:
        return eqx.error_if(traj, traj.diverged, "simulate: the run diverged (throw=False "
                            "returns it with traj.status)")
    if throw and bool(traj.diverged):
        if int(traj.refinements) and divergence.sampled_unstable(spec, t_first, traj.t_diverged):
            raise DivergenceError(divergence.sampled_unstable_line(spec, traj.t_diverged), traj)
        why = "" if spec.sampled else closed_loop.diagnose(setup, traj)
        raise DivergenceError(divergence_report(traj, float(spec.state_bound))[0] + why, traj)
    return traj


class _Progress(eqx.Module):
    """An `integrate.Running` that reports progress to the host and reduces nothing."""

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


def dtype_of(setup: Setup):
    """The dtype of a setup's numbers: its plant.x0's."""
    return jnp.result_type(setup.plant.x0)


def canonical(setup: Setup) -> Setup:
    """Every floating leaf in `plant.x0`'s dtype, strongly typed (weak types are part of jit's
    cache key: a gain set from a Python float would recompile)."""
    return params.cast(setup, dtype_of(setup))


def check(setup: Setup, spec: RunSpec, overrides: Mapping[str, Any] | None = None,
          batched: bool = False) -> None:
    """Host-side checks of a setup against a run (ConfigError naming the field): the setup's
    models, with `overrides` ({path: (B, ...)}) every row's too and each path's shape, the
    measurement noise against the plant's order and, for a continuous loop integrated by RK4,
    the fastest filter against the step; with `batched`, not the filters (the rows may
    override them, and a batch reports a diverged row in its status)."""
    if validation.is_concrete(setup):
        validation.validate_setup(setup)
        if overrides is not None and validation.is_concrete(overrides):
            validation.validate_setup(params.set_many(setup, overrides), check_shapes=False)
            for p, val in overrides.items():
                validation.shape(val[0], p, np.shape(params.get(setup, p)))
    noise = np.shape(spec.noise)  # () for one number or None
    if noise and noise != (setup.order,):
        raise validation.ConfigError(f"simulation.noise must be one number or one per state "
                                     f"of the plant, {setup.order} numbers "
                                     f"(got {np.size(spec.noise)})")
    if not batched and not spec.sampled and isinstance(spec.solver, RK4):
        validation.check_filters(setup, float(spec.dt))


def simulate_batch(setup: Setup, overrides: Mapping[str, Any], t_final: float = 20.0,
                   dt: float = 1e-3, *, spec: RunSpec | None = None,
                   save_every: int | None = None, window_start: float | None = None,
                   state_bound: float = 1e6,
                   checkpoint_every: int | None = DEFAULT_CHECKPOINT_EVERY,
                   refine: int = DEFAULT_REFINE, solver: str = "rk4",
                   sample_time: float | None = None, device=None) -> Trajectory:
    """Simulate `setup` with the parameters at the paths of `overrides` replaced by the rows
    of its arrays (leading axis B) in one jitted call; only those leaves are batched. Never
    raises on divergence (`traj.status`, `divergence_report`); diverged rows' metrics are NaN.

    Args:
        overrides: {"hysteresis.alpha": (B,), "plant.x0": (B, n), ...}.
        t_final, dt, window_start, state_bound, solver, refine, sample_time, device: as
            `simulate`'s (or `spec`); refinement re-runs only the diverged rows, on the host
            (under a trace refine must be 0, as for `simulate`).
        save_every: default t_final/dt: only the first and last points.
        checkpoint_every: reverse mode keeps the state every this many steps and recomputes
            the rest.

    Example:
        >>> import dscjax, jax.numpy as jnp
        >>> setup = dscjax.paper_example()
        >>> traj = dscjax.simulate_batch(setup, {"hysteresis.alpha": jnp.array([0.8, 1.0, 1.2])},
        ...                              t_final=1.0, dt=1e-3)
        >>> traj.metrics["linf_error"].shape
        (3,)
    """
    if spec is None:
        if checkpoint_every is not None:
            validation.by_rule(AtLeast(1), checkpoint_every, "checkpoint_every")
        n_total = validation.whole_steps(t_final, dt)
        spec = RunSpec.make(t_final, dt, save_every=n_total if save_every is None else save_every,
                            window_start=window_start, state_bound=state_bound, solver=solver,
                            refine=refine, sample_time=sample_time,
                            gradient=TimeParallel(every=checkpoint_every))
    setup = canonical(setup)
    overrides = {p: params.cast(v, dtype_of(setup)) for p, v in overrides.items()}
    sizes = {p: np.shape(v)[0] for p, v in overrides.items()}
    if len(set(sizes.values())) != 1:
        raise validation.ConfigError(f"overrides must share one batch size (got {sizes})")
    check(setup, spec, overrides, batched=True)

    def level(j, idx=None):  # the compiled batch for rows idx (default all: `xla.LEAN_ROWS`)
        ov = overrides if idx is None else {p: np.asarray(v)[idx] for p, v in overrides.items()}
        lean = np.shape(next(iter(ov.values())))[0] <= xla.LEAN_ROWS
        return (_simulate if lean else _simulate_batch)(setup, level_spec(spec, j).program(), ov)

    divergence.refuse_traced_refinement(spec, "simulate_batch", (setup, spec, overrides))
    with _placed(spec, device, next(iter(sizes.values())), (setup, overrides)):
        traj = level(0)
        divergence.refuse_traced_refinement(spec, "simulate_batch", traj.status)
        if counted_levels(spec):  # host-side: the diverged rows again, with the same save times
            traj, levels = refine_rows(traj, lambda tr: tr.diverged, level,
                                       counted_levels(spec))
            traj = jax.tree.map(jnp.asarray, dataclasses.replace(traj, refinements=levels))
    return traj


def _placed(spec: RunSpec, device, rows: int, inputs):
    """A context making the run's device (`device.choose` of `device`, else the spec's) JAX's
    default; nothing where `inputs` are traced."""
    choice = (dscjax_device.choose(spec.device, rows) if device is None else
              dscjax_device.choose(device, rows, field="device"))
    if not validation.is_concrete(inputs):
        return contextlib.nullcontext()
    return dscjax_device.placed(choice)


