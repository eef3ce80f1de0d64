"""The start gains' figures on the nominal plant (`start_scales`): the normalisation of the
objective's terms and its effort bounds, "start" bounds being the start's own figures over the
whole horizon [0, T] (the transient included), on the nominal plant for every plant or on
each training plant its own; `Scales` holds them."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import xla
from dscjax.closed_loop import Setup
from dscjax.divergence import DivergenceError, diverged_lines
from dscjax.runspec import RunSpec, loop_words
from dscjax.simulate import run
from dscjax.validation import ConfigError
from tuning.config import TERMS, ObjectiveSpec
from tuning.reductions import UserError, shifted_reference


class Scales(eqx.Module):
    """The start gains' figures on the nominal plant (the terms' normalisation) and the bounds,
    with per-plant bounds also per training plant (u_max_train, tv_max_train); a pytree, so
    that a compiled objective takes them as numbers."""

    linf: Any
    l2: Any
    l2_u: Any
    max_u: Any
    u_max: Any  # the bound on max|u| (None: no bound)
    tv_u: Any = 1.0
    tv_max: Any = None  # the bound on TV(u) (None: no bound)
    # (B,) float64 per training plant (None: the nominal bound); other batches get the nominal
    u_max_train: Any = None
    tv_max_train: Any = None
    # training plants on which the start gains diverge: they keep the nominal bounds
    n_train_fallback: Any = 0
    # every figure of the start gains on the nominal plant (the loop tuned): the effort on the
    # window beside the bounds' [0, T], the error against the config's reference
    start: dict = eqx.field(default_factory=dict)

    @property
    def per_plant(self) -> bool:
        return self.u_max_train is not None or self.tv_max_train is not None

    def bounds(self, train: bool, tile: int = 1) -> tuple:
        """(bound on max|u|, bound on TV(u)) of a batch (None: no bound): the training batch's
        own if `train` (tiled `tile` times: candidates x training plants), else the nominal."""
        return tuple(jnp.tile(jnp.asarray(per), tile) if train and per is not None else nominal
                     for nominal, per in ((self.u_max, self.u_max_train),
                                          (self.tv_max, self.tv_max_train)))


def _start_run(setup: Setup, sim: RunSpec, extra=None, overrides=None):
    """(metrics, `Status`) of the start gains: the status says when a diverged run did."""
    traj = run(setup, sim, overrides=dict(overrides) if overrides else None, extra=extra)
    return traj.metrics, traj.status


# one compilation per setup and run structure (adversarial tuning builds a problem a round)
_start_metrics = xla.jit(_start_run, lean=True)


def start_scales(setup: Setup, sim: RunSpec, spec: ObjectiveSpec,
                 train: Mapping[str, Any] | None = None) -> Scales:
    """The start gains' `Scales` (DivergenceError, which run and when, if they diverge on the
    nominal plant). With effort_bounds = "per_plant" and a batch `train`, each training plant's
    "start" bounds are its own figures (a plant on which the start gains diverge, or show no
    effort at all, keeps the nominal ones); else the nominal ones hold for every plant."""
    reference = shifted_reference(setup)
    user = None if reference is None else UserError(  # reported beside, not tuned
        jnp.asarray(sim.window_start, jnp.result_type(setup.plant.x0)), sim.n_steps, reference)
    metrics, status = _start_metrics(setup, sim.program(), user)
    if int(status.code) != 0:
        raise start_divergence(sim, status)
    m = {k: float(v) for k, v in metrics.items()}
    for name, (_, key, _, _) in TERMS.items():
        if getattr(spec, name) and not m[key] > 0:
            raise ConfigError(f"tuning.objective.{name}: the start gains give {key} = "
                              f"{m[key]:g}, which cannot normalise the term")
    # each bound: a number, None (none) or "start" (factor x the start gains' figure)
    efforts = (("max_abs_u", "u_max", 1.0), ("tv_u", "tv_max", spec.tv_max_factor))
    given = {name: getattr(spec, name) for _, name, _ in efforts}
    bounds = {name: factor * m[key] if given[name] == "start"
              else None if given[name] is None else float(given[name])
              for key, name, factor in efforts}
    if spec.effort_bounds.per_plant and train and "start" in given.values():
        mb, status = jax.device_get(_start_metrics(setup, sim.program(), overrides=dict(train)))
        div = np.asarray(status.code) != 0
        bounds["n_train_fallback"] = int(div.sum())
        for key, name, factor in efforts:
            if given[name] == "start":
                v = factor * np.asarray(mb[key], np.float64)
                bounds[f"{name}_train"] = np.where(div | ~(v > 0), bounds[name], v)
    return Scales(**{scale: max(m[key], 1e-300) for _, key, scale, _ in TERMS.values()},
                  start=m, **bounds)


def start_divergence(sim: RunSpec, status) -> DivergenceError:
    """The error of start gains that diverge on the nominal plant (their run's `Status`):
    which run, when and how (`divergence.diverged_lines`)."""
    # a run that diverged has the first bad step's index (`Status`)
    how = diverged_lines(status, int(status.step) * float(sim.dt), float(sim.state_bound))[0]
    return DivergenceError(f"the start gains diverge on the nominal plant in the loop tuned "
                           f"({loop_words(sim)}): the run {how.removeprefix('the trajectory ')}; "
                           f"tuning needs a stable start (revise the gains, dt or tau)", None)
