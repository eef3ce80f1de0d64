"""One pure objective: a metric of one run as a function of chosen numbers of a setup.

    loss, z0 = dscjax.objective(setup, spec, ["controller.k", "controller.tau"], log=True)
    (value, status), grads = jax.value_and_grad(loss, has_aux=True)(z0)

`loss(z)` is pure: no host-side check, no refinement, no exception, so it is the same function
eagerly and under `jit`, `grad` and `vmap`, and equals `simulate(setup with z,
spec=spec).metrics[metric]` on any run that needs no refinement. A diverged run is a returned
status, never a silent switch: the value is NaN (its gradient 0) and `status.code` != 0
(`dscjax.selection.run_at`, the run the tuner and `dscjax.sensitivity` share). Refinement is
the host-side wrapper `simulate`; the checks run once, here.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import metrics as m
from dscjax.closed_loop import Setup
from dscjax.integrate import Status
from dscjax.runspec import RunSpec
from dscjax.selection import Linear, Log, Selection, run_at
from dscjax.simulate import canonical, check
from dscjax.validation import ConfigError, one_of


def objective(setup: Setup, spec: RunSpec | None = None,
              paths: Sequence[str] = ("controller.k",),
              metric: str | Callable[[Mapping[str, jax.Array]], jax.Array] = "l2_error_window",
              *, log: bool = False) -> tuple[Callable, dict[str, jax.Array]]:
    """(loss, z0): `loss(z) -> (value, status)`, a pure function of the numbers at `paths`.

    Args:
        setup: the loop; every number not at `paths` stays fixed.
        spec: how it runs (default `RunSpec.make()`); its `refine` is not used (refinement
            is `simulate`'s, on the host).
        paths: config paths of the numbers (`dscjax.params`: "controller.k", "plant.g[1]").
        metric: a name of `metric_names()` (every metric of `simulate`'s trajectories) or a
            function of the metrics dict returning a scalar.
        log: z holds the logarithms of the numbers (which must then be > 0), so that any
            step of an optimiser keeps them positive.

    Returns:
        loss: z ({path: array}, z0's structure) -> (value, `Status` of the run): value NaN
            and status.code != 0 if the run diverged.
        z0: the setup's own numbers at `paths` (their logs if `log`).

    Example:
        >>> import jax, dscjax
        >>> loss, z0 = dscjax.objective(dscjax.paper_example(), dscjax.RunSpec.make(0.1),
        ...                             ["controller.k"], "l2_error", log=True)
        >>> (value, status), g = jax.value_and_grad(loss, has_aux=True)(z0)
        >>> g["controller.k"].shape, int(status.code)
        ((2,), 0)
    """
    spec = RunSpec.make() if spec is None else spec
    if isinstance(metric, str):
        one_of(metric, "metric", metric_names())
    elif not callable(metric):
        raise ConfigError(f"metric must be a name or a function of the metrics (got "
                          f"{metric!r})")
    if isinstance(paths, str) or not paths:
        raise ConfigError(f"paths must be a non-empty list of config paths (got {paths!r})")
    setup = canonical(setup)
    check(setup, spec)
    selection = Selection.of(paths, Log() if log else Linear())
    for t in selection.items:
        value = np.asarray(t.param.check(setup, "paths"))
        if log and not np.all(value > 0):
            raise ConfigError(f"{t.name} must be > 0 with log=True (got {value.tolist()})")
    program = spec.program()
    pick = (lambda ms: ms[metric]) if isinstance(metric, str) else metric

    def loss(z: Mapping[str, Any]) -> tuple[jax.Array, Status]:
        traj = run_at(selection, setup, z, program)
        return pick(traj.metrics), traj.status

    return loss, selection.init(setup)


def metric_names() -> tuple[str, ...]:
    """The names of the metrics of every run (`dscjax.metrics.finalize`), without running."""
    acc = jax.eval_shape(lambda: m.running_init(jnp.float32))
    return tuple(jax.eval_shape(m.finalize, acc, 1.0))


__all__ = ["metric_names", "objective"]
