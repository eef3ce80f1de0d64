"""The tuner's strategies, each an object a config's name reads to (`tuning.config`): the
aggregate over the plants (`Mean`, `CVaR`, `Max`), the search method (`CMAES`, `Adam`), where
"start" effort bounds are measured (`Nominal`, `PerPlant`) and the AD mode of the exact gradient
(`Forward`, `Reverse`, `Plants`, or `Auto`: each `chosen` for a problem), each a `Strategy`;
and the loss as one pure function (`loss_function`)."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, dataclass_transform

import jax
import jax.numpy as jnp

from dscjax.search.methods import CMA, Gradient

FORWARD_MAX_PARAMS = 64  # "auto" over a batch: forward mode up to this many tuned scalars
# "auto" for one plant: forward mode up to this many tuned scalars, where its gradient costs no
# more than the time-parallel reverse mode's and compiles sooner (docs/benchmarks.md)
FORWARD_MAX_PARAMS_ONE_PLANT = 6


@dataclass_transform(frozen_default=True)
class Strategy:
    """What every strategy is: a frozen dataclass (each subclass is made one) whose `name`, the
    one a config gives it, is its class keyword: ``class Mean(CVaR, name="mean")`` (a subclass
    without one keeps its parent's)."""

    name: ClassVar[str]

    def __init_subclass__(cls, name: str | None = None, **kwargs):
        super().__init_subclass__(**kwargs)
        if name is not None:
            cls.name = name
        dataclasses.dataclass(frozen=True)(cls)


class CVaR(Strategy, name="cvar"):
    """The mean of the worst ceil(level B) of B plants."""

    level: float = 1.0
    leveled: ClassVar[bool] = True  # the share `level` is its own (Mean and Max have none)

    def weighs(self, n):
        """How many of n plants the aggregate weighs (n may be traced: the real plants of a
        padded batch)."""
        if isinstance(n, int):
            return max(1, int(math.ceil(self.level * n - 1e-9)))
        return jnp.maximum(1.0, jnp.ceil(self.level * n - 1e-9))

    def __call__(self, values, mask=None):
        """The aggregate over axis 0, of the plants where `mask` (None: every one)."""
        if values.ndim == 0:
            return values
        if mask is None:
            return jnp.mean(jax.lax.top_k(values, self.weighs(values.shape[0]))[0])
        idx, w = self.weights(values, mask)
        return jnp.sum(jnp.where(w > 0, values[idx], 0.0)) / self.weighs(jnp.sum(mask))

    def weights(self, values, mask=None):
        """(indices, weights) of a static count, the worst first: the aggregate is
        sum(weights values[indices]) where the values are finite."""
        n = values.shape[0]
        worst = jnp.where(mask, values, -jnp.inf) if mask is not None else values
        idx = jax.lax.top_k(worst, self.weighs(n))[1]
        k = self.weighs(n if mask is None else jnp.sum(mask))
        return idx, jnp.where(jnp.arange(idx.shape[0]) < k, 1.0 / k, 0.0)

    def at(self, level: float) -> CVaR:
        """This aggregate at the share `level` ([tuning.robust] cvar_level) if it has one."""
        return dataclasses.replace(self, level=level) if self.leveled else self

    def __str__(self) -> str:  # as the report says it
        return f"{self.name} at level {self.level:g}" if self.leveled else self.name


class Mean(CVaR, name="mean"):
    """The mean over the plants (CVaR at level 1, summed in the plants' order)."""

    leveled: ClassVar[bool] = False

    def weighs(self, n):
        return n

    def __call__(self, values, mask=None):
        if values.ndim == 0 or mask is not None:
            return super().__call__(values, mask)
        return jnp.mean(values)


class Max(CVaR, name="max"):
    """The worst plant (the mean of the worst one)."""

    leveled: ClassVar[bool] = False

    def weighs(self, n):
        return 1


class CMAES(Strategy, name="cma"):
    """CMA-ES with IPOP restarts: an iteration is a generation, one batched simulation."""

    generations: ClassVar[bool] = True

    def method(self, spec, plants: int, n: int) -> CMA:
        """The `dscjax.search` method of an `OptimizerSpec`."""
        return CMA(sigma0=spec.sigma0, popsize=spec.population(plants, n), restarts=spec.restarts,
                   growth=spec.growth, stall=spec.stall, stall_gain=spec.stall_gain)


class Adam(Strategy, name="adam"):
    """Projected descent on exact gradients (optax's Adam scaling): one point an iteration."""

    generations: ClassVar[bool] = False

    def method(self, spec, plants: int, n: int) -> Gradient:
        return Gradient(lr=spec.learning_rate)


class Nominal(Strategy, name="nominal"):
    """Effort bounds "start" measured on the nominal plant, for every plant."""

    per_plant: ClassVar[bool] = False


class PerPlant(Strategy, name="per_plant"):
    """Effort bounds "start" measured on each training plant, its own."""

    per_plant: ClassVar[bool] = True


class Forward(Strategy, name="forward"):
    """One jvp per tuned scalar, vmapped."""

    every: ClassVar[int | None] = None  # the reverse pass's checkpoint segment (none)

    def value_and_grad(self, objective, z):
        """((loss, aux), grads) of objective.evaluate at z, exactly."""
        def f(z_):
            loss, aux = objective.evaluate(z_)
            return loss, (loss, aux)

        grads, (loss, aux) = jax.jacfwd(f, has_aux=True)(z)
        return (loss, aux), grads

    def chosen(self, n_params: int, batch: int = 1, aggregate=None, every=None) -> Forward:
        """The mode run for n_params tuned scalars and `batch` plants weighed by `aggregate`,
        a reverse pass checkpointed in segments of `every` steps: this one."""
        return self


class Reverse(Forward, name="reverse"):
    """One vjp through the scan, `jax.checkpoint` segments of `every` steps (the loop's
    `TimeParallel` gradient carries it)."""

    every: int | None = None

    def value_and_grad(self, objective, z):
        return jax.value_and_grad(objective.evaluate, has_aux=True)(z)

    def chosen(self, n_params: int, batch: int = 1, aggregate=None, every=None) -> Forward:
        return Reverse(every)


class Plants(Forward, name="plants"):
    """The plants the aggregate weighs, one by one (`Objective.value_and_grad_plants`)."""

    def value_and_grad(self, objective, z):
        return objective.value_and_grad_plants(z)


class Auto(Strategy, name="auto"):
    """For one plant forward up to FORWARD_MAX_PARAMS_ONE_PLANT tuned scalars, else reverse
    (time-parallel); for a batch whose aggregate weighs at most a quarter of its plants (max,
    CVaR <= 0.25) the plants one by one; else forward up to FORWARD_MAX_PARAMS tuned scalars
    (docs/benchmarks.md)."""

    def chosen(self, n_params: int, batch: int = 1, aggregate=None, every=None) -> Forward:
        if batch > 1 and aggregate is not None and aggregate.weighs(batch) <= batch / 4:
            return Plants()
        most = FORWARD_MAX_PARAMS_ONE_PLANT if batch <= 1 else FORWARD_MAX_PARAMS
        return Forward() if n_params <= most else Reverse(every)


# the strategies by the names a config gives (`tuning.config`, `rules.Choice`)
AGGREGATES = {c.name: c() for c in (Mean, CVaR, Max)}
OPTIMIZERS = {c.name: c() for c in (CMAES, Adam)}
EFFORT_BOUNDS = {c.name: c() for c in (Nominal, PerPlant)}
GRADIENTS = {c.name: c() for c in (Auto, Forward, Reverse, Plants)}


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

    def loss(z):  # a function: a jitted method would hash its module, arrays and all
        return objective.evaluate(z)

    return loss, problem.z0
