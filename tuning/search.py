"""The tuning objective as a `dscjax.search` problem over the flat z (`TuneProblem`: the
batched program `batch_fn`; the exact gradient `grad_fn` in the problem's AD mode).

    sp = TuneProblem(problem)                  # problem: tuning.build_problem(...)
    method = problem.cfg.optimizer.method(problem.objective.batch_size, sp.x0.size)
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

from dscjax import search, xla
from tuning.objective import loop_metrics

STATE_FILE = "search.npz"  # the run's search state (dscjax.search's format)
SPREAD = math.log(10.0)  # random points (a restarted adam start): z0 x/ 10, in the box


def _unravel(obj):
    """The {name: array} point of a flat z (the structure of the selection's own z)."""
    return ravel_pytree(obj.selection.init(obj.setup))[1]


def _batch(obj, flat_pts):
    """(B, n) flat z -> per-candidate loss (`Objective.evaluate`'s), feasibility, figures and
    terms: every candidate x training plant in one batched simulation."""
    b, n = flat_pts.shape[0], obj.batch_size
    train = obj.overrides or {}
    zs = jax.tree.map(lambda v: jnp.repeat(v, n, axis=0), jax.vmap(_unravel(obj))(flat_pts))
    ov = {p: jnp.tile(v, (b,) + (1,) * (v.ndim - 1)) for p, v in train.items()}
    m, div = loop_metrics(obj, zs, ov, points=True)
    # the training plants' own bounds (per_plant), laid out as the plants are: tiled
    judged = obj.judged(m, div, obj.scales.bounds(train=bool(train), tile=b))
    rows = jax.tree.map(lambda v: v.reshape(b, n, *v.shape[1:]), (*judged, m, div))
    loss, aux = jax.vmap(lambda p, t, f, m_, d: obj.summary(p, t, m_, d, f, obj.mask))(*rows)
    return {"loss": loss, **aux}


# one top-level batched program: 512-bit vectors where the CPU has them, or lean for a search
# whose whole work is small (dscjax.xla.lean_work)
_BATCH = {lean: xla.jit(_batch, lean=lean).top for lean in (False, True)}


@functools.partial(xla.jit, lean=True, static_argnums=0)
def _gradient(mode, obj, flat_pts):
    """(M, n) flat z -> per-point loss, feasibility, figures and flat gradient, exact, in the
    AD `mode` (the points one after the other)."""
    def one(flat):
        (loss, aux), g = mode.value_and_grad(obj, _unravel(obj)(flat))
        return {"loss": loss, **aux, "grad": ravel_pytree(g)[0]}

    return jax.lax.map(one, flat_pts)


def batch_fn(problem):
    """The batched program (`search.Batched`) of the problem's objective: every candidate x
    training plant; lean where an iteration limit bounds the search's work (`search_work`)."""
    return search.Batched(_BATCH[xla.lean_work(search_work(problem))],
                          (problem.objective.program(),))


def search_work(problem) -> float | None:
    """The member-steps of the batched evaluations of a search with an iteration limit
    (`steps` generations of the first population, every training plant in the loop tuned and
    its check loops; None without one)."""
    spec, obj = problem.cfg.optimizer, problem.objective
    if spec.steps is None:
        return None
    plants, loops = obj.batch_size, 1 + len(obj.checks)
    return (spec.steps * spec.population(plants, problem.n_params) * plants * loops
            * obj.sim.n_steps)


def grad_fn(problem):
    """The exact gradient program (`search.Batched`) of the problem's objective in its AD
    mode."""
    return search.Batched(_gradient, (problem.mode, problem.objective.program()))


class TuneProblem(search.Problem):
    """A `runner.Problem` as a search problem over the flat z (`ravel_pytree(problem.z0)`) in
    the box of its bounds; its programs take the objective as an argument, so they compile
    once per structure of the objective (a new round's training plants reuse them)."""

    def __init__(self, problem):
        self.problem = problem
        flat0, self.unravel = ravel_pytree(problem.z0)
        self.x0 = np.asarray(flat0, dtype=np.float64)
        self.lower, self.upper = problem.selection.z_box(problem.z0)

    def _program(self, name: str, build) -> search.Batched:
        """The problem's program `name`, its widths and compilation timed (`search.Batched`),
        kept with the problem for this objective: every program compiles once per structure."""
        obj, cache = self.problem.objective, self.problem.programs
        if name not in cache or cache[name][0] is not obj:
            cache[name] = (obj, build(self.problem))
        return cache[name][1]

    @property
    def compile_seconds(self) -> float:
        return sum(program.seconds for _, program in self.problem.programs.values())

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
        return self.project(self.x0 + rng.uniform(-SPREAD, SPREAD, (b, self.x0.size)))

    def flat(self, z: dict) -> np.ndarray:
        """The flat z of a {name: value} point."""
        return np.asarray(ravel_pytree({k: jnp.asarray(z[k]) for k in self.problem.z0})[0],
                          dtype=np.float64)

    def point(self, flat) -> dict:
        """The {name: value} point of a flat z."""
        return jax.tree.map(np.asarray, self.unravel(jnp.asarray(flat)))
