"""The optimisation loop: optax (Adam by default), a guard against bad steps, early stopping.

One iteration is ONE jitted call of `tune_step`: the objective, its exact gradient (forward
or reverse mode) and the optax update, with no host round trip in between. The state is a
NamedTuple of arrays (`TuneState`), so it checkpoints as plain arrays.

Guard. A step whose loss or gradient is not finite, or at which more plants diverge than at
the last accepted point, is rejected: the state goes back to the last accepted point, the
learning rate is multiplied by `shrink` (default 0.5), and a shorter step is taken from there
with the gradient of that point. Nothing non-finite ever enters the optimiser state, and the
best point is only ever replaced by a better finite one.

Best point. Points are ranked first by feasibility (no divergence, max|u| within the bound,
every requirement met, exactly, on all training plants), then by loss. So a run that has
found a feasible point never returns an infeasible one.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from dscjax import validation
from dscjax.validation import ConfigError
from tuning.objective import n_worst

# cma (CMA-ES), cma_path (CMA-ES + a line search from the incumbent along CMA-ES's evolution
# path, the default: ahead of CMA-ES at equal wall time on the nominal problem and of
# cma_line on both, not of CMA-ES on the robust problem; docs/tuning.md), cma_line (the
# same line along random directions) and cma_grad (along the exact gradient) run
# tuning/search.py; the others are optax rules with exact gradients.
OPTIMIZERS = ("cma_path", "cma_line", "cma", "cma_grad", "adam", "adamw", "sgd", "lion")
SEARCHES = ("cma", "cma_line", "cma_grad", "cma_path")
SCHEDULES = ("constant", "cosine", "exponential")
GRADIENTS = ("auto", "forward", "reverse", "plants")
# One trajectory: reverse mode (the time-parallel linearisation) costs a fixed ~8x the forward
# run whatever the number of tuned scalars, forward mode ~16x for 13 (experiments/
# bench_gradient.py). A batch of plants: reverse mode runs the transposed step over the batch,
# ~20x the step's flops, so forward mode wins up to this many scalars. A CVaR (or max) weighs
# only its worst plants: differentiating those alone ("plants") beat forward mode over the
# batch 1.8x for the default robust problem (2 of 8 plants, 13 scalars, 20 s: 0.84 s vs 1.54
# s, bench_gradient.py --only-tuning) and lost 3.5x when all 8 were weighed (a mean), so
# "auto" takes it up to B/4.
FORWARD_MAX_PARAMS = 64
# The optax methods' iterations when `steps` is not given: their schedule's length too.
OPTAX_STEPS = 300


@dataclasses.dataclass(frozen=True)
class OptimizerSpec:
    """The [tuning.optimizer] table.

    Attributes:
        name: "cma_path" (default: CMA-ES + line search along its evolution path),
            "cma_line" (the same along random directions), "cma" (CMA-ES alone),
            "cma_grad" (CMA-ES + line search along the exact gradient; all four: one batched
            simulation per generation, tuning/search.py), or an optax rule: "adam", "adamw",
            "sgd" (with momentum 0.9) or "lion". For the four searches an iteration is a
            generation; learning_rate, schedule and the rejection settings do not apply.
        learning_rate: initial step size, in the units of z (log-space: 0.05 = 5 % per step).
        schedule: "cosine" (decay to final_lr_fraction over decay_steps), "exponential"
            (same end point) or "constant".
        final_lr_fraction: learning rate at the end of the schedule, relative.
        decay_steps: length of the schedule in accepted steps; default: `steps` (or
            OPTAX_STEPS when `steps` is not given).
        clip_norm: gradient clipping by global norm (None: off).
        shrink: learning-rate factor applied at every rejected step.
        regrow: factor applied after every accepted step, up to the schedule's rate (so one
            bad step early on does not slow the whole run down).
        max_rejections: stop after this many consecutive rejected steps.
        patience, min_delta: stop when the best loss has not improved by more than min_delta
            (relative) for `patience` iterations (0: never).
        steps: maximum number of iterations (evaluations of loss and gradient; for the
            searches, generations). None (the default): OPTAX_STEPS = 300 for the optax
            rules (the schedule's length), no limit for the four searches, which stop at
            `time_limit`, by `patience` or by CMA-ES's own criteria after its `restarts`
            (`max_steps`).
        time_limit: stop after this many seconds of wall time in this invocation, compilation
            included (None: no limit).
        gradient: "forward" (jvp over a batch of tangents), "reverse", "plants" (only the
            plants the aggregate weighs, each differentiated alone) or "auto" (reverse for
            one plant; plants for a batch whose aggregate weighs at most a quarter of it, as
            CVaR at 0.25 does; else forward with at most 64 tuned scalars).
        checkpoint_every: segment length in steps of `jax.checkpoint` in reverse mode (100:
            near sqrt(N) for 20,000 steps, which minimises the O(N/L + L) states kept; it was
            both smaller and faster than 1000 for 256 plants over 20 s, measured).
        save_interval: write the checkpoint files every this many iterations.
        sigma0, popsize, seed: CMA-ES of "cma_grad" (step in z, population (0: cma's default
            4 + 3 ln n), seed of its random stream).
        grad_every: "cma_grad": the line search follows -C grad (exact gradient at the
            incumbent) every this many generations, a random direction otherwise; 0 switches
            the gradient off (the ablation: then cma_grad is cma_line, no gradient evaluated
            or compiled).
        line_points, line_min, line_max: "cma_line", "cma_path", "cma_grad": the line
            search's step sizes, sigma sqrt(n) x geomspace(line_min, line_max, line_points).
        line_backoff: "cma_line", "cma_path", "cma_grad": 0 takes the line in every
            generation; m > 0 skips it, after k consecutive generations whose line did not
            win, for min(2^(k-1), m) generations (CMA-ES's population alone, a second
            compiled batch width), until a line wins again.
        line_inject: the line methods inject a winning line point into CMA-ES's next
            generation (true); false leaves CMA-ES's own ask/tell sequence untouched (the same
            as "cma" with the same seed) and the line only moves the incumbent.
        line_generations: the line methods take the line in the first this many generations
            only (default 50), CMA-ES's population alone after them (a second batch width,
            compiled when first needed); 0: in every generation (the line methods before it).
            Generations of the whole run: a restart before N still takes the line until N.
        restarts: the CMA-ES methods: when CMA-ES's own termination criteria stop it
            (converged or stuck) before `steps` or `time_limit`, start a fresh CMA-ES from
            the start point (sigma0, a seed of its own; the incumbent is kept), at most this
            many times (0: stop).
        background_compile: "cma_grad": compile the gradient in a thread while the first
            generations run (their line points take random directions meanwhile).
    """

    name: str = "cma_path"
    learning_rate: float = 0.1
    schedule: str = "cosine"
    final_lr_fraction: float = 0.1
    decay_steps: int | None = None
    clip_norm: float | None = 1.0
    shrink: float = 0.5
    regrow: float = 1.1
    max_rejections: int = 20
    patience: int = 60
    min_delta: float = 1e-4
    steps: int | None = None
    time_limit: float | None = 100.0
    gradient: str = "auto"
    checkpoint_every: int = 100
    save_interval: int = 10
    sigma0: float = 0.3
    popsize: int = 0
    seed: int = 0
    grad_every: int = 1
    line_points: int = 6
    line_min: float = 0.02
    line_max: float = 1.0
    line_backoff: int = 0
    line_inject: bool = True
    line_generations: int = 50
    restarts: int = 9
    background_compile: bool = True

    def validate(self, field: str = "tuning.optimizer") -> None:
        validation.one_of(self.name, f"{field}.name", OPTIMIZERS)
        validation.one_of(self.schedule, f"{field}.schedule", SCHEDULES)
        validation.one_of(self.gradient, f"{field}.gradient", GRADIENTS)
        _positive(self.learning_rate, f"{field}.learning_rate")
        if not 0 < self.final_lr_fraction <= 1:
            raise ConfigError(f"{field}.final_lr_fraction must be in (0, 1] (got "
                              f"{self.final_lr_fraction!r})")
        if self.clip_norm is not None:
            _positive(self.clip_norm, f"{field}.clip_norm")
        if not 0 < self.shrink < 1:
            raise ConfigError(f"{field}.shrink must be in (0, 1) (got {self.shrink!r})")
        if not self.regrow >= 1:
            raise ConfigError(f"{field}.regrow must be >= 1 (got {self.regrow!r})")
        for name, low in (("max_rejections", 1), ("patience", 0),
                          ("checkpoint_every", 1), ("save_interval", 1), ("popsize", 0),
                          ("seed", 0), ("grad_every", 0), ("line_points", 0),
                          ("line_backoff", 0), ("line_generations", 0), ("restarts", 0)):
            validation.integer(getattr(self, name), f"{field}.{name}", low)
        for name in ("steps", "decay_steps"):
            if getattr(self, name) is not None:
                validation.integer(getattr(self, name), f"{field}.{name}", 1)
        if self.min_delta < 0:
            raise ConfigError(f"{field}.min_delta must be >= 0 (got {self.min_delta!r})")
        if self.time_limit is not None:
            _positive(self.time_limit, f"{field}.time_limit")
        for name in ("sigma0", "line_min", "line_max"):
            _positive(getattr(self, name), f"{field}.{name}")
        if self.line_min > self.line_max:
            raise ConfigError(f"{field}.line_min must be <= line_max (got {self.line_min!r} > "
                              f"{self.line_max!r})")

    @property
    def max_steps(self) -> int | None:
        """The iteration limit: `steps`, or by default OPTAX_STEPS for the optax rules and
        none (None) for the searches."""
        if self.steps is not None:
            return self.steps
        return None if self.name in SEARCHES else OPTAX_STEPS

    @property
    def schedule_steps(self) -> int:
        """The optax schedule's length: `decay_steps`, else `steps`, else OPTAX_STEPS."""
        return self.decay_steps or self.steps or OPTAX_STEPS

    def schedule_fn(self):
        lr, steps = self.learning_rate, self.schedule_steps
        if self.schedule == "cosine":
            return optax.cosine_decay_schedule(lr, steps, alpha=self.final_lr_fraction)
        if self.schedule == "exponential":
            return optax.exponential_decay(lr, steps, self.final_lr_fraction)
        return optax.constant_schedule(lr)

    def make(self) -> optax.GradientTransformation:
        lr = self.schedule_fn()
        core = {"adam": lambda: optax.adam(lr), "adamw": lambda: optax.adamw(lr),
                "sgd": lambda: optax.sgd(lr, momentum=0.9), "lion": lambda: optax.lion(lr)}
        parts = [optax.clip_by_global_norm(self.clip_norm)] if self.clip_norm else []
        return optax.chain(*parts, core[self.name]())


def _positive(v, field):
    if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{field} must be a number > 0 (got {v!r})")


class TuneState(NamedTuple):
    """Everything the loop carries (all arrays; z-pytrees are {name: value in z-space})."""

    iteration: jax.Array  # () int32: evaluations done so far (accepted + rejected)
    z: Any  # the point evaluated by the next step
    opt_state: Any  # optimiser state that produced z
    good_z: Any  # last accepted point ...
    good_opt_state: Any  # ... the optimiser state there ...
    good_grads: Any  # ... and its gradient (a rejected step retries from there)
    good_n_diverged: jax.Array  # () int32: diverged training plants at the last accepted point
    lr_scale: jax.Array  # () learning-rate multiplier, shrunk at every rejection
    n_rejected: jax.Array  # () int32: rejected steps so far
    streak: jax.Array  # () int32: consecutive rejections
    best_z: Any  # best point so far (feasible first, then lowest loss)
    best_loss: jax.Array  # () its loss (+inf before any accepted evaluation)
    best_feasible: jax.Array  # () bool
    best_iteration: jax.Array  # () int32, -1 before any
    stall: jax.Array  # () int32: iterations since the best improved by more than min_delta


def init_state(z0, optimizer: optax.GradientTransformation) -> TuneState:
    dtype = jnp.result_type(*jax.tree.leaves(z0))
    i32 = functools.partial(jnp.asarray, dtype=jnp.int32)
    opt_state = optimizer.init(z0)
    return TuneState(
        iteration=i32(0), z=z0, opt_state=opt_state, good_z=z0, good_opt_state=opt_state,
        good_grads=jax.tree.map(jnp.zeros_like, z0), good_n_diverged=i32(2**30),
        lr_scale=jnp.asarray(1.0, dtype), n_rejected=i32(0), streak=i32(0), best_z=z0,
        best_loss=jnp.asarray(jnp.inf, dtype), best_feasible=jnp.asarray(False),
        best_iteration=i32(-1), stall=i32(0))


def choose_gradient(mode: str, n_params: int, batch: int = 1, aggregate: str = "mean",
                    level: float = 1.0) -> str:
    """The AD mode for "auto": reverse for one plant; for a batch whose aggregate weighs at
    most a quarter of its plants (max, CVaR at level <= 0.25) the plants one by one; else
    forward with at most FORWARD_MAX_PARAMS tuned scalars (measured, see the comment above)."""
    if mode != "auto":
        return mode
    if batch <= 1:
        return "reverse"
    weighed = {"max": 1, "cvar": n_worst(level, batch)}.get(aggregate, batch)
    if weighed <= batch / 4:
        return "plants"
    return "forward" if n_params <= FORWARD_MAX_PARAMS else "reverse"


def value_and_grad(objective, z, mode: str, checkpoint_every: int | None = None):
    """((loss, aux), grads) of objective.evaluate at z, exactly, in the given AD mode.

    forward: one jvp per tuned scalar, all of them in one pass (jacfwd vmaps the tangents);
    reverse: one vjp through the scan, with `jax.checkpoint` segments of checkpoint_every
    steps (memory O(N/L + L) states instead of O(N));
    plants: one batched forward run, then each plant the aggregate weighs (CVaR: the worst
    ceil(level B)) differentiated alone by the time-parallel linearisation.
    """
    if mode == "forward":
        def f(z_):
            loss, aux = objective.evaluate(z_)
            return loss, (loss, aux)

        grads, (loss, aux) = jax.jacfwd(f, has_aux=True)(z)
        return (loss, aux), grads
    if mode == "plants":  # the plants the aggregate weighs, each alone (Objective's docstring)
        return objective.value_and_grad_plants(z)
    if mode == "reverse":
        return jax.value_and_grad(
            lambda z_: objective.evaluate(z_, checkpoint_every=checkpoint_every),
            has_aux=True)(z)
    raise ValueError(f"unknown gradient mode {mode!r}")


def _finite_tree(tree):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


def _where(c, a, b):
    return jax.tree.map(lambda x, y: jnp.where(c, x, y), a, b)


def tune_step(state: TuneState, objective, optimizer: optax.GradientTransformation,
              project, mode: str, checkpoint_every: int | None, shrink, min_delta,
              regrow=1.0):
    """One iteration (pure; jit it whole, see `make_step`). Returns (state, report)."""
    (loss, aux), grads = value_and_grad(objective, state.z, mode, checkpoint_every)
    return guarded_update(state, loss, aux, grads, optimizer, project, shrink, min_delta,
                          regrow)


def guarded_update(state: TuneState, loss, aux, grads, optimizer, project, shrink, min_delta,
                   regrow=1.0):
    """The guard, best-point bookkeeping and optax update for an evaluation (loss, grads) at
    state.z (split from `tune_step` so that it can be tested on forced bad values)."""
    n_div = jnp.asarray(aux["n_diverged"], jnp.int32)
    ok = jnp.isfinite(loss) & _finite_tree(grads) & (n_div <= state.good_n_diverged)
    # Accepted: step from z with its gradient. Rejected: from the last accepted point with
    # its gradient and state, at a smaller learning rate.
    lr_used = jnp.where(ok, state.lr_scale, state.lr_scale * shrink)
    z_in = _where(ok, state.z, state.good_z)
    g_in = _where(ok, grads, state.good_grads)
    o_in = _where(ok, state.opt_state, state.good_opt_state)
    updates, opt_new = optimizer.update(g_in, o_in, z_in)
    z_new = project(jax.tree.map(lambda z, u: z + lr_used * u, z_in, updates))

    feasible = ok & aux["feasible"]
    better = ok & ((feasible & ~state.best_feasible)
                   | ((feasible == state.best_feasible) & (loss < state.best_loss)))
    margin = jnp.where(jnp.isfinite(state.best_loss), min_delta * jnp.abs(state.best_loss), 0.0)
    improved = better & ((feasible & ~state.best_feasible) | (loss < state.best_loss - margin))
    new = TuneState(
        iteration=state.iteration + 1,
        z=z_new,
        opt_state=opt_new,
        good_z=_where(ok, state.z, state.good_z),
        good_opt_state=_where(ok, state.opt_state, state.good_opt_state),
        good_grads=_where(ok, grads, state.good_grads),
        good_n_diverged=jnp.where(ok, n_div, state.good_n_diverged),
        lr_scale=jnp.where(ok, jnp.minimum(1.0, lr_used * regrow), lr_used),
        n_rejected=state.n_rejected + (~ok).astype(jnp.int32),
        streak=jnp.where(ok, 0, state.streak + 1),
        best_z=_where(better, state.z, state.best_z),
        best_loss=jnp.where(better, loss, state.best_loss),
        best_feasible=jnp.where(better, feasible, state.best_feasible),
        best_iteration=jnp.where(better, state.iteration, state.best_iteration),
        stall=jnp.where(improved, 0, state.stall + 1),
    )
    finite_grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, 0.0), grads)
    report = {"loss": loss, "accepted": ok, "feasible": feasible, "lr_scale": lr_used,
              "grad_norm": optax.tree.norm(finite_grads), **aux}
    return new, report


def make_step(objective, optimizer, selection, mode: str, checkpoint_every: int | None):
    """The jitted iteration state -> (state, report): loss, gradient and update in one call."""

    @jax.jit
    def step(state, shrink, min_delta, regrow):
        return tune_step(state, objective, optimizer, selection.project, mode,
                         checkpoint_every, shrink, min_delta, regrow)

    return step
