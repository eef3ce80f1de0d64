"""Fixed-step integration over pytrees on t_k = k dt, a `jax.lax.scan`; knows nothing of DSC.

`integrate(f, y0, dt, n_steps, ...)` takes f(t, y, args) -> (dy, obs), obs read off for saving
and for the running reductions (`Running`). Strategies are objects, as in diffrax: the solver
(`RK4()`, `ETDRK4()`: `solvers`) and the gradient (`TimeParallel()`, `Checkpointed(every)`:
`gradients`). Layouts suit XLA:CPU (docs/architecture.md): one trajectory as flat vectors of
at most `scan.SMALL` floats (`single`), a batch batch-last, one (B,) row per state component
(`batch`); the time loop, its save stride and divergence `Status` are `scan`'s.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from dscjax.integrate.batch import integrate_batch
from dscjax.integrate.gradients import (
    DEFAULT_CHECKPOINT_EVERY,
    Checkpointed,
    Gradient,
    TimeParallel,
)
from dscjax.integrate.scan import (
    STATUS_BOUND,
    STATUS_NONFINITE,
    STATUS_OK,
    Integration,
    Pytree,
    Running,
    Status,
    saved_steps,
)
from dscjax.integrate.single import integrate_single
from dscjax.integrate.solvers import ETDRK4, RK4, SOLVERS, Solver, rk4_step, rk4_steps, solver


def integrate(
    f: Callable,
    y0: Pytree,
    dt,
    n_steps: int,
    args=(),
    *,
    batch: Pytree = None,
    save_every: int = 1,
    reduction: Running | None = None,
    state_bound=jnp.inf,
    solver: Solver | None = None,
    gradient: Gradient | None = None,
    rates: Callable | None = None,
    project: Callable | None = None,
    frozen: Pytree = None,
    skip_diverged: bool = False,
    substeps=None,
) -> Integration:
    """Integrate y' = f(t, y, args) on t_k = k dt, k = 0..n_steps.

    Args:
        f: f(t, y, args) -> (dy, obs), obs an observation at (t, y); with `batch`, called as
            f(t, y, (args, b)) for one member b (without the batch axis), as `rates` and `project`.
        y0: initial state pytree (with `batch`: every leaf has a leading batch axis B).
        dt: step (traced). n_steps: N (static).
        args: shared arguments of f (traced, one copy for the whole batch).
        batch: None, or per-member arguments, leaves with a leading batch axis B.
        save_every: s (static): keep the steps 0, s, 2s, ... and always N (`saved_steps`).
        reduction: None, or a `Running` updated at every k = 0..N while the run is healthy;
            `Integration.acc` is its raw accumulator.
        state_bound: a state with any |component| above it counts as diverged (traced).
        solver: `RK4()` (default) or `ETDRK4()` (needs `rates`).
        gradient: `TimeParallel()` (default) or `Checkpointed()`; `every` is the checkpoint
            segment of a batch's scan.
        rates: rates(t, y, args, obs) -> decay rates >= 0 like y, integrated exactly by
            ETDRK4 (with `batch`, args is (args, b)).
        project: None, or project(k, t, y, args) -> y, applied after every step at its end
            (step k, time t): a discrete update (the plays' clamp, a sampled controller).
        frozen: None, or a static tree of Python bools, a prefix of y's (one member's):
            components held inside a step, changed only by `project`, still bound-checked.
        skip_diverged: step no more once every member has diverged
            (static): the same results, for one more observation in the program
            (`scan.saving_scan`); for runs likely to diverge, such as a refinement of a
            diverged run.
        substeps: None, or m (traced): each of the n_steps steps is m steps of dt, the
            reductions updated at each, saving every s-th of the n_steps (n_steps m steps of
            dt in all): one program for every m, as a refinement's levels need. Not for
            gradients (`TimeParallel` does not apply; a loop of traced length has no reverse
            mode).

    Returns:
        Integration(ys, obs, acc, status); with `batch` every leaf has a leading batch axis.
    """
    solver = RK4() if solver is None else solver
    gradient = TimeParallel() if gradient is None else gradient
    dt = jnp.asarray(dt)
    if not jnp.issubdtype(dt.dtype, jnp.floating):
        dt = dt.astype(jnp.result_type(*jax.tree.leaves(y0)))
    state_bound = jnp.asarray(state_bound, dt.dtype)
    acc0 = () if reduction is None else reduction.init(dt.dtype)  # one member's
    options = (reduction, acc0, dt, n_steps, save_every, state_bound, solver, gradient, rates,
               project, frozen, skip_diverged, substeps)  # both layouts take them alike
    if batch is None:
        return integrate_single(f, y0, args, *options)
    return integrate_batch(f, y0, args, batch, *options)


__all__ = ["DEFAULT_CHECKPOINT_EVERY", "ETDRK4", "RK4", "SOLVERS", "STATUS_BOUND",
           "STATUS_NONFINITE", "STATUS_OK", "Checkpointed", "Gradient", "Integration", "Running",
           "Solver", "Status", "TimeParallel", "integrate", "rk4_step", "rk4_steps", "saved_steps",
           "solver"]
