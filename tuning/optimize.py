"""The tuner's loss as one pure function (`loss_function`) and its exact gradient in each AD
mode (`value_and_grad`, `choose_gradient`)."""

from __future__ import annotations

import jax

from tuning.objective import n_worst

FORWARD_MAX_PARAMS = 64  # "auto" over a batch: forward mode up to this many tuned scalars


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
