"""The tuning objective as a `dscjax.search` problem over the flat z (`TuneProblem`: the
batched program `batch_fn`; the exact gradient `grad_fn` in the problem's AD mode), and the
method of an `OptimizerSpec` (`method_of`).

    sp = TuneProblem(problem)                  # problem: tuning.build_problem(...)
    method = method_of(problem.cfg.optimizer, problem.objective.batch_size, sp.x0.size)
    res = dscjax.search.run(sp, method, x0=sp.x0)

Its candidates never count as diverged: the loss itself penalises a plant that diverges.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import params, search, xla
from tuning.objective import aggregate, feasible_plants, loop_metrics, plant_loss
from tuning.optimize import value_and_grad

STATE_FILE = "search.npz"  # the run's search state (dscjax.search's format)
SPREAD = math.log(10.0)  # random points (a restarted adam start): z0 x/ 10, in the box


def batch_fn(problem):
    """Jitted (B, n) flat z -> per-candidate loss (`Objective.evaluate`'s), feasibility,
    figures and terms: every candidate x training plant in one batched simulation."""
    obj = problem.objective
    _, unravel = ravel_pytree(problem.z0)
    columns = obj.selection.columns(obj.setup)
    train = obj.overrides or {}
    n_train = obj.batch_size if train else 1
    sc = obj.scales

    # one top-level batched program: 512-bit vectors where the CPU has them (dscjax.xla)
    @functools.partial(jax.jit, compiler_options=xla.compiler_options())
    def run(flat_pts):
        table = jax.vmap(lambda p: obj.selection.row(unravel(p)))(flat_pts)
        b = flat_pts.shape[0]
        ov = params.overrides(obj.setup, columns, table)
        if train:
            ov = {p: jnp.repeat(v, n_train, axis=0) for p, v in ov.items()}
            ov |= {p: jnp.tile(jnp.asarray(v), (b,) + (1,) * (np.ndim(v) - 1))
                   for p, v in train.items()}
        m, div = loop_metrics(obj, obj.setup, ov)
        # the training plants' own bounds (per_plant), laid out as the plants are: tiled
        bounds = sc.bounds(train=bool(train), tile=b)
        loss, terms = plant_loss(m, div, obj.spec, sc, len(obj.requirements), bounds,
                                 obj.checks)
        feas = feasible_plants(m, div, bounds, len(obj.requirements), obj.checks)

        def per(v, how):
            v = v.reshape(b, n_train)
            return jax.vmap(lambda r: aggregate(r, how, obj.cvar_level))(v) if train \
                else v[:, 0]

        def worst(v):  # max over the plants that did not diverge (NaN: none)
            v = jnp.where(div, -jnp.inf, v).reshape(b, n_train).max(axis=1)
            return jnp.where(jnp.isfinite(v), v, jnp.nan)

        return {"loss": per(loss, obj.aggregate),
                "feasible": feas.reshape(b, n_train).all(axis=1),
                "n_diverged": div.reshape(b, n_train).sum(axis=1),
                "linf_window": worst(m["linf_error_window"]),
                "max_abs_u": worst(m["max_abs_u"]), "tv_u": worst(m["tv_u"]),
                "terms": {k: per(jnp.where(div, 0.0, v), obj.aggregate)
                          for k, v in terms.items()}}

    return run


def grad_fn(problem):
    """Jitted (M, n) flat z -> per-point loss, feasibility, figures and flat gradient, exact,
    in the problem's AD mode (the points one after the other)."""
    obj = problem.objective
    _, unravel = ravel_pytree(problem.z0)

    def one(flat):
        (loss, aux), g = value_and_grad(obj, unravel(flat), problem.mode,
                                        obj.sim.gradient.every)
        return {"loss": loss, "feasible": aux["feasible"], "n_diverged": aux["n_diverged"],
                "linf_window": aux["linf_window"], "max_abs_u": aux["max_abs_u"],
                "terms": aux["terms"], "grad": ravel_pytree(g)[0]}

    return jax.jit(lambda pts: jax.lax.map(one, pts))


class TuneProblem(search.Problem):
    """A `runner.Problem` as a search problem over the flat z (`ravel_pytree(problem.z0)`) in
    the box of its bounds; its programs are compiled once per objective (`compiled`)."""

    def __init__(self, problem):
        self.problem = problem
        flat0, self.unravel = ravel_pytree(problem.z0)
        self.x0 = np.asarray(flat0, dtype=np.float64)
        self.lower, self.upper = problem.selection.z_box(problem.z0)

    def _program(self, name: str, build) -> search.Batched:
        cache = self.problem.objective.compiled
        if name not in cache:
            cache[name] = search.Batched(build(self.problem))
        return cache[name]

    @property
    def compile_seconds(self) -> float:
        cache = self.problem.objective.compiled
        return sum(cache[k].seconds for k in ("batch", "gradient") if k in cache)

    @staticmethod
    def _evaluation(r) -> search.Evaluation:
        info = {k: r[k] for k in ("n_diverged", "linf_window", "max_abs_u")} | r["terms"]
        return search.Evaluation.of(r["loss"], r["feasible"], None, info)

    def evaluate(self, z) -> search.Evaluation:
        return self._evaluation(self._program("batch", batch_fn)(z))

    def value_and_grad(self, z) -> tuple[search.Evaluation, np.ndarray]:
        r = self._program("gradient", grad_fn)(z)
        return self._evaluation(r), np.asarray(r["grad"], dtype=np.float64)

    def sample(self, rng: np.random.Generator, b: int) -> np.ndarray:
        return np.clip(self.x0 + rng.uniform(-SPREAD, SPREAD, (b, self.x0.size)), self.lower,
                       self.upper)

    def flat(self, z: dict) -> np.ndarray:
        """The flat z of a {name: value} point."""
        return np.asarray(ravel_pytree({k: jnp.asarray(z[k]) for k in self.problem.z0})[0],
                          dtype=np.float64)

    def point(self, flat) -> dict:
        """The {name: value} point of a flat z."""
        return jax.tree.map(np.asarray, self.unravel(jnp.asarray(flat)))


def method_of(spec, plants: int = 1, n: int = 1) -> search.CMA | search.Gradient:
    """The search method of an `OptimizerSpec` for `plants` training plants and n tuned
    numbers."""
    if spec.name == "adam":
        return search.Gradient(lr=spec.learning_rate)
    return search.CMA(sigma0=spec.sigma0, popsize=spec.population(plants, n),
                      restarts=spec.restarts, growth=spec.growth,
                      stall=spec.stall, stall_gain=spec.stall_gain)
