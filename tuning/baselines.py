"""Gradient-free baselines on the same objective: random search and CMA-ES (the `cma` extra).

Both evaluate a whole population of candidate gains as ONE batched simulation (the candidates
enter as overrides of the tuned leaves, batch-last rows layout), which is what makes
gradient-free search competitive on a CPU: a batch of 16 costs about 5 forward runs, not 16.
Each method logs (wall time, loss) of every evaluation so that best-loss-against-time curves
can be compared at equal wall-clock budget (experiments/tune_compare.py).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax.cmaes import require_cma


@dataclasses.dataclass
class Trace:
    """Every evaluation of a search: when (s since the start, compilation included) and J."""

    method: str
    t: list[float] = dataclasses.field(default_factory=list)
    loss: list[float] = dataclasses.field(default_factory=list)
    best_z: Any = None
    best_loss: float = math.inf
    evaluations: int = 0
    info: dict = dataclasses.field(default_factory=dict)

    def add(self, t: float, losses: np.ndarray, zs: np.ndarray | None = None):
        for i, v in enumerate(np.asarray(losses, dtype=float)):
            self.t.append(t)
            self.loss.append(float(v))
            self.evaluations += 1
            if v < self.best_loss:
                self.best_loss = float(v)
                if zs is not None:
                    self.best_z = np.array(zs[i])

    def best_curve(self) -> tuple[np.ndarray, np.ndarray]:
        loss = np.asarray(self.loss, dtype=float)
        loss = np.where(np.isfinite(loss), loss, np.inf)
        return np.asarray(self.t), np.minimum.accumulate(loss) if loss.size else loss


def batch_loss_fn(problem):
    """(Jitted (B, n) flat z -> (B,) objective values, flat z0, unravel): each value the same
    loss the gradient method minimises (J of the nominal plant, or the aggregate over the
    training batch), from the search methods' batched program (`search.batch_fn`)."""
    from tuning.search import batch_fn

    run = batch_fn(problem)
    flat0, unravel = ravel_pytree(problem.z0)
    return (lambda pts: run(pts)["loss"]), np.asarray(flat0), unravel


def random_search(problem, budget_s: float, batch: int = 32, spread: float = math.log(10.0),
                  seed: int = 0) -> Trace:
    """Uniform samples in the box z0 +- spread (log-space: a factor of 10 either way), clipped
    to the bounds, evaluated `batch` at a time until the budget is spent."""
    t0 = time.perf_counter()
    run, flat0, _ = batch_loss_fn(problem)
    lo, hi = problem.selection.z_box(problem.z0)
    rng = np.random.default_rng(seed)
    trace = Trace("random search", info={"batch": batch, "spread": spread})
    first = True
    while True:
        zs = flat0 + rng.uniform(-spread, spread, (batch, flat0.size))
        if first:  # the start point is part of every method's history
            zs[0] = flat0
            first = False
        zs = np.clip(zs, lo, hi)
        losses = np.asarray(run(jnp.asarray(zs)))
        now = time.perf_counter() - t0
        trace.add(now, losses, zs)
        if now >= budget_s:
            return trace


def cma_es(problem, budget_s: float, sigma0: float = 0.3, popsize: int | None = None,
           seed: int = 0) -> Trace:
    """CMA-ES (`cma` package) in the tuner's coordinates z, started at the start gains with
    step sigma0 (log-space: about 30 %), one batched simulation per generation."""
    cma = require_cma()
    t0 = time.perf_counter()
    run, flat0, _ = batch_loss_fn(problem)
    lo, hi = problem.selection.z_box(problem.z0)
    opts = {"seed": seed + 1, "verbose": -9, "bounds": [
        [x if np.isfinite(x) else None for x in lo], [x if np.isfinite(x) else None for x in hi]]}
    if popsize:
        opts["popsize"] = popsize
    es = cma.CMAEvolutionStrategy(flat0, sigma0, opts)
    trace = Trace("CMA-ES", info={"sigma0": sigma0, "popsize": es.popsize})
    trace.add(time.perf_counter() - t0, np.asarray(run(jnp.asarray(flat0[None]))), flat0[None])
    while True:
        zs = np.asarray(es.ask())
        losses = np.asarray(run(jnp.asarray(zs)))
        es.tell(list(zs), list(np.where(np.isfinite(losses), losses, 1e30)))
        now = time.perf_counter() - t0
        trace.add(now, losses, zs)
        if now >= budget_s or es.stop():
            trace.info["generations"] = es.countiter
            return trace


def gradient(problem, budget_s: float, steps: int = 100000) -> Trace:
    """The gradient method (tuning.run) with a time limit, as a Trace."""
    from tuning.runner import run

    cfg = problem.cfg
    opt = dataclasses.replace(cfg.optimizer, time_limit=budget_s, steps=steps,
                              decay_steps=cfg.optimizer.schedule_steps,
                              patience=0)
    p = dataclasses.replace(problem, cfg=dataclasses.replace(cfg, optimizer=opt))
    result = run(p, None)
    trace = Trace("gradient (Adam, exact)", info={"iterations": int(result.state.iteration),
                                                  "compile_s": result.compile_s})
    for row in result.history:
        trace.add(row["wall_s"], np.array([row["loss"]]))
    trace.best_z = np.asarray(ravel_pytree(jax.device_get(result.state.best_z))[0])
    return trace
