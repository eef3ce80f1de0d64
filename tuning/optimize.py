"""The [tuning.optimizer] table (`OptimizerSpec`: the search method, its settings and limits),
the tuner's loss as one pure function (`loss_function`) and its exact gradient in each AD mode
(`value_and_grad`, `choose_gradient`)."""

from __future__ import annotations

import dataclasses

import jax

from dscjax import validation
from dscjax.validation import ConfigError
from tuning.objective import n_worst

OPTIMIZERS = ("cma_path", "cma", "adam")
SEARCHES = ("cma_path", "cma")
GRADIENTS = ("auto", "forward", "reverse", "plants")
FORWARD_MAX_PARAMS = 64  # "auto" over a batch: forward mode up to this many tuned scalars
OPTAX_STEPS = 300  # adam's iterations when `steps` is not given


@dataclasses.dataclass(frozen=True)
class OptimizerSpec:
    """The [tuning.optimizer] table (docs/tuning.md). An iteration of the CMA-ES methods is a
    generation: one batched simulation."""

    # cma_path (CMA-ES + a line search along its evolution path in its first generations),
    # cma (CMA-ES alone) or adam (projected gradient descent, exact gradients, Adam scaling)
    name: str = "cma_path"
    learning_rate: float = 0.1  # adam's initial step in z; x1.2 after a gain, /2 after a loss
    patience: int = 60  # stop after this many iterations without a min_delta (relative) gain
    min_delta: float = 1e-4
    steps: int | None = None  # at most this many iterations (None: `max_steps`)
    time_limit: float | None = 100.0  # seconds in this invocation, compilation included
    gradient: str = "auto"  # adam's AD mode (`choose_gradient`)
    checkpoint_every: int = 100  # reverse mode's `jax.checkpoint` segment in steps (~sqrt(N))
    save_interval: int = 10  # iterations between writes of history.csv, best.json, gains.json
    sigma0: float = 0.3  # CMA-ES's step in z
    popsize: int = 0  # CMA-ES's population (0: 4 + 3 ln n)
    seed: int = 0  # CMA-ES's (adam: a restarted start's random point)
    restarts: int = 9  # fresh CMA-ES runs from the start point after CMA-ES's own stop

    def validate(self, field: str = "tuning.optimizer") -> None:
        validation.one_of(self.name, f"{field}.name", OPTIMIZERS)
        validation.one_of(self.gradient, f"{field}.gradient", GRADIENTS)
        for name in ("learning_rate", "sigma0"):
            validation.finite_positive(getattr(self, name), f"{field}.{name}")
        for name, low in (("patience", 0), ("checkpoint_every", 1), ("save_interval", 1),
                          ("popsize", 0), ("seed", 0), ("restarts", 0)):
            validation.integer(getattr(self, name), f"{field}.{name}", low)
        if self.steps is not None:
            validation.integer(self.steps, f"{field}.steps", 1)
        if self.min_delta < 0:
            raise ConfigError(f"{field}.min_delta must be >= 0 (got {self.min_delta!r})")
        if self.time_limit is not None:
            validation.finite_positive(self.time_limit, f"{field}.time_limit")

    @property
    def max_steps(self) -> int | None:
        """The iteration limit: `steps`, or by default OPTAX_STEPS for adam and none (None)
        for the CMA-ES methods."""
        if self.steps is not None:
            return self.steps
        return None if self.name in SEARCHES else OPTAX_STEPS


def choose_gradient(mode: str, n_params: int, batch: int = 1, aggregate: str = "mean",
                    level: float = 1.0) -> str:
    """The AD mode for "auto": reverse (time-parallel) for one plant; for a batch whose
    aggregate weighs at most a quarter of its plants (max, CVaR <= 0.25) the plants one by
    one; else forward up to FORWARD_MAX_PARAMS tuned scalars (docs/benchmarks.md)."""
    if mode != "auto":
        return mode
    if batch <= 1:
        return "reverse"
    weighed = {"max": 1, "cvar": n_worst(level, batch)}.get(aggregate, batch)
    if weighed <= batch / 4:
        return "plants"
    return "forward" if n_params <= FORWARD_MAX_PARAMS else "reverse"


def value_and_grad(objective, z, mode: str, checkpoint_every: int | None = None):
    """((loss, aux), grads) of objective.evaluate at z, exactly: forward (one jvp per tuned
    scalar, vmapped), reverse (one vjp through the scan, `jax.checkpoint` segments of
    checkpoint_every steps) or plants (`Objective.value_and_grad_plants`)."""
    if mode == "forward":
        def f(z_):
            loss, aux = objective.evaluate(z_)
            return loss, (loss, aux)

        grads, (loss, aux) = jax.jacfwd(f, has_aux=True)(z)
        return (loss, aux), grads
    if mode == "plants":
        return objective.value_and_grad_plants(z)
    if mode == "reverse":
        return jax.value_and_grad(
            lambda z_: objective.evaluate(z_, checkpoint_every=checkpoint_every),
            has_aux=True)(z)
    raise ValueError(f"unknown gradient mode {mode!r}")


def loss_function(problem):
    """(loss, z0): the tuner's own loss as a pure function of the tuned coordinates.

    `loss(z) -> (J, aux)`: z as `z0` ({name: array}, log coordinates for positive numbers,
    `problem.selection`), J the objective the search minimises (normalised terms, constraint
    penalties, the batch aggregate; a diverged plant costs the finite divergence penalty) and
    aux its terms, exact metrics, `n_diverged` and `feasible`. No host-side step inside: the
    same value eagerly and under jit, differentiable (`jax.value_and_grad(loss,
    has_aux=True)`). The box of z: `problem.selection.z_box(z0)`.

    Example:
        >>> import jax, dscjax, tuning
        >>> problem = tuning.build_problem(dscjax.paper_example(), dscjax.RunSpec.make(0.5),
        ...                                tuning.TuningConfig())
        >>> loss, z0 = tuning.loss_function(problem)
        >>> (J, aux), g = jax.value_and_grad(loss, has_aux=True)(z0)
        >>> int(aux["n_diverged"]), sorted(g) == sorted(z0)
        (0, True)
    """
    objective = problem.objective

    def loss(z):
        return objective.evaluate(z)

    return loss, problem.z0
