"""The [tuning.optimizer] table (`OptimizerSpec`: which search method, its settings and its
limits) and the exact gradient of the tuning objective in each AD mode (`value_and_grad`,
`choose_gradient`). The methods run on `dscjax.search` (tuning/search.py, tuning/runner.py).
"""

from __future__ import annotations

import dataclasses
import math

import jax

from dscjax import validation
from dscjax.validation import ConfigError
from tuning.objective import n_worst

# cma_path: CMA-ES + a line search from the incumbent along CMA-ES's evolution path in its
# first generations (the default); cma: CMA-ES alone, its baseline; adam: projected gradient
# descent with exact gradients (optax's Adam scaling). docs/tuning.md compares them.
OPTIMIZERS = ("cma_path", "cma", "adam")
SEARCHES = ("cma_path", "cma")
GRADIENTS = ("auto", "forward", "reverse", "plants")
# "auto": reverse mode (time-parallel) for one plant, whose cost does not grow with the tuned
# scalars; over a batch of plants forward mode up to this many scalars (reverse mode runs the
# transposed step over the batch); a CVaR or max that weighs at most a quarter of the batch:
# its worst plants one by one ("plants"). Measured by experiments/bench_gradient.py.
FORWARD_MAX_PARAMS = 64
# adam's iterations when `steps` is not given (the CMA-ES methods have no count limit)
OPTAX_STEPS = 300


@dataclasses.dataclass(frozen=True)
class OptimizerSpec:
    """The [tuning.optimizer] table.

    Attributes:
        name: "cma_path" (default: CMA-ES with a line search from the incumbent along its
            evolution path in its first generations), "cma" (CMA-ES alone) or "adam"
            (projected gradient descent on exact gradients with optax's Adam scaling). An
            iteration of the CMA-ES methods is a generation: one batched simulation.
        learning_rate: adam's initial step, in the units of z (log-space: 0.05 = 5 %); it
            grows x1.2 after an improvement and halves after a worse point.
        patience, min_delta: stop when the best loss has not improved by more than min_delta
            (relative) for `patience` iterations (0: never).
        steps: maximum number of iterations. None (the default): OPTAX_STEPS = 300 for adam,
            no limit for the CMA-ES methods, which stop at `time_limit`, by `patience` or by
            CMA-ES's own criteria after its `restarts` (`max_steps`).
        time_limit: stop after this many seconds of wall time in this invocation, compilation
            included (None: no limit).
        gradient: adam's AD mode: "forward" (jvp over a batch of tangents), "reverse",
            "plants" (only the plants the aggregate weighs, each differentiated alone) or
            "auto" (reverse for one plant; plants for a batch whose aggregate weighs at most
            a quarter of it, as CVaR at 0.25 does; else forward with at most 64 tuned scalars).
        checkpoint_every: segment length in steps of `jax.checkpoint` in reverse mode (100:
            near sqrt(N) for 20,000 steps, which minimises the O(N/L + L) states kept; it was
            both smaller and faster than 1000 for 256 plants over 20 s, measured).
        save_interval: write history.csv, best.json and gains.json every this many
            iterations (the search's own state is saved after every one).
        sigma0, popsize, seed: CMA-ES's step in z, population (0: cma's default 4 + 3 ln n)
            and seed (adam: the seed of a restarted start's random point).
        restarts: the CMA-ES methods: when CMA-ES's own termination criteria stop it
            (converged or stuck) before `steps` or `time_limit`, start a fresh CMA-ES from
            the start point (sigma0, a seed of its own; the incumbent is kept), at most this
            many times (0: stop).
    """

    name: str = "cma_path"
    learning_rate: float = 0.1
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
    restarts: int = 9

    def validate(self, field: str = "tuning.optimizer") -> None:
        validation.one_of(self.name, f"{field}.name", OPTIMIZERS)
        validation.one_of(self.gradient, f"{field}.gradient", GRADIENTS)
        for name in ("learning_rate", "sigma0"):
            _positive(getattr(self, name), f"{field}.{name}")
        for name, low in (("patience", 0), ("checkpoint_every", 1), ("save_interval", 1),
                          ("popsize", 0), ("seed", 0), ("restarts", 0)):
            validation.integer(getattr(self, name), f"{field}.{name}", low)
        if self.steps is not None:
            validation.integer(self.steps, f"{field}.steps", 1)
        if self.min_delta < 0:
            raise ConfigError(f"{field}.min_delta must be >= 0 (got {self.min_delta!r})")
        if self.time_limit is not None:
            _positive(self.time_limit, f"{field}.time_limit")

    @property
    def max_steps(self) -> int | None:
        """The iteration limit: `steps`, or by default OPTAX_STEPS for adam and none (None)
        for the CMA-ES methods."""
        if self.steps is not None:
            return self.steps
        return None if self.name in SEARCHES else OPTAX_STEPS


def _positive(v, field):
    if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{field} must be a number > 0 (got {v!r})")


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
