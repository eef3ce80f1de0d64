"""The compiled programs of a worst-case search (`Programs`, a `dscjax.search` problem): the
metric of a (B, d + m) batch of normalised points and its gradient, the projection onto the
waveform's bound and random points of the box. Problems of one structure share them: the setup,
the box and the bound are traced.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import disturbance as dist_mod
from dscjax import search, xla
from dscjax.simulate import dtype_of, run
from dscjax.worst.problem import Problem, Static, box_overrides, box_setup, with_steps


def _problem_values(setup, z, lo, hi, bound, spec, extra=None, *, st: Static):
    traj = run(setup, spec, overrides=box_overrides(setup, st, z, lo, hi, bound), extra=extra)
    return traj.metrics[st.metric], traj.diverged


def _value_and_grad(single, z):
    """(values, diverged, d values / d z) of a batch, each start's own time-parallel gradient
    of `single` vmapped over the starts; a diverged member's gradient is 0."""
    def masked(z_):
        v, bad = single(z_)
        return jnp.sum(jnp.where(bad, 0.0, v)), (v, bad)

    (_, (v, bad)), g = jax.vmap(jax.value_and_grad(masked, has_aux=True))(z)
    return v, bad, g


_problem_values_jit = jax.jit(_problem_values, static_argnames=("st",))


# the gradients compile lean, as every gradient of dscjax does (dscjax.xla)
@functools.partial(xla.jit, lean=True, static_argnames=("st",))
def _problem_value_and_grad(setup, z, lo, hi, bound, spec, extra, *, st: Static):
    def single(z1):  # one point, as a setup of its own
        traj = run(box_setup(setup, st, z1, lo, hi, bound), spec, extra=extra)
        return traj.metrics[st.metric], traj.diverged

    return _value_and_grad(single, z)


@functools.partial(xla.jit, lean=True, static_argnames=("st",))
def _problem_coarse(setup, z, lo, hi, bound, spec, extra, spec_g, extra_g, *, st: Static):
    """Values of the loop of `spec`, gradients of the loop of `spec_g` (a coarser step; zero
    where that run diverged)."""
    v, bad = _problem_values(setup, z, lo, hi, bound, spec, extra, st=st)
    _, bad_g, g = _problem_value_and_grad(setup, z, lo, hi, bound, spec_g, extra_g, st=st)
    return v, bad, jnp.where(bad_g[:, None], 0.0, g)


@functools.partial(jax.jit, static_argnames=("d", "project_coef"))
def _project(z, basis, *, d, project_coef):
    u = jnp.clip(z[:, :d], 0.0, 1.0)
    if project_coef is None:
        return u
    c = z[:, d:]
    return jnp.concatenate([u, project_coef(c, 1.0, c @ basis.T)], axis=1)


@functools.partial(jax.jit, static_argnames=("d",))
def _rescale(z, basis, *, d):
    """Random points: the waveform scaled so that max |dbar| = D exactly."""
    if z.shape[1] == d:
        return z
    c = z[:, d:]
    peak = jnp.max(jnp.abs(c @ basis.T), axis=1, keepdims=True)
    c = jnp.where(peak > 0, c / jnp.where(peak > 0, peak, 1.0), c)
    return jnp.concatenate([z[:, :d], c], axis=1)


class Programs(search.Problem):
    """The compiled programs of a search on (B, d + m) batches of normalised points, as the
    `dscjax.search` problem: minimise -metric over [0, 1]^d x [-1, 1]^m, projected onto the
    waveform's bound (waveform `c @ basis.T`, `project_coef`), from `x0` (the nominal point);
    a diverged candidate's loss is +inf. `values(z) -> (v, diverged)`. `for_problem` builds
    them for a `Problem` (shared by problems of one structure), `from_functions` for any
    objective (a search checked on a known answer)."""

    def __init__(self, d: int, m: int, basis, project_coef, values: search.Batched,
                 value_and_grad: search.Batched, nominal_u: np.ndarray | None = None):
        self.d, self.m = d, m
        self.basis = jnp.asarray(basis)
        self.values, self._value_and_grad = values, value_and_grad
        self.project = search.Batched(_project, after=(self.basis,), d=d,
                                      project_coef=project_coef if m else None)
        self.rescale = search.Batched(_rescale, after=(self.basis,), d=d)
        self.lower = np.concatenate([np.zeros(d), -np.ones(m)])
        self.upper = np.ones(d + m)
        self.x0 = np.concatenate([nominal_u if nominal_u is not None else np.full(d, 0.5),
                                  np.zeros(m)])

    @property
    def compile_seconds(self) -> float:
        return sum(p.seconds for p in (self.values, self._value_and_grad, self.project,
                                       self.rescale))

    @staticmethod
    def _evaluation(v, bad) -> search.Evaluation:
        v, bad = np.asarray(v, dtype=np.float64), np.asarray(bad, dtype=bool)
        return search.Evaluation.of(np.where(bad, np.inf, -v), ~bad, bad)

    def evaluate(self, z) -> search.Evaluation:
        return self._evaluation(*self.values(z))

    def value_and_grad(self, z) -> tuple[search.Evaluation, np.ndarray]:
        v, bad, g = self._value_and_grad(z)
        return self._evaluation(v, bad), -np.asarray(g, dtype=np.float64)

    def sample(self, rng: np.random.Generator, b: int) -> np.ndarray:
        """b uniform points of the box, coefficients uniform in [-1, 1]^m rescaled so that
        max |dbar| = D exactly."""
        return self.rescale(np.concatenate([rng.random((b, self.d)),
                                            rng.uniform(-1.0, 1.0, (b, self.m))], axis=1))

    @classmethod
    def from_functions(cls, d: int, m: int, basis, project_coef, values: Callable,
                       single: Callable, nominal_u=None) -> Programs:
        """From a batch objective `values(z) -> (v, diverged)` and its one-point version
        `single(z1)` (differentiated per start)."""
        vg = jax.jit(functools.partial(_value_and_grad, single))
        return cls(d, m, basis, project_coef, search.Batched(jax.jit(values)),
                   search.Batched(vg), nominal_u)

    @classmethod
    def for_problem(cls, problem: Problem, coarsening: int = 1) -> Programs:
        """The programs of `problem`; with `coarsening` F > 1 the gradients are the loop's at
        F dt (a search direction only), the values always at dt."""
        p = problem  # (checked by `worst_case`, coarsening included)
        basis, project_coef = np.zeros((1, 0)), None
        if p.m:
            grid = dist_mod.half_step_grid(p.spec.t_final, float(p.spec.dt))
            model = p.setup.plant.disturbance
            basis = np.stack([np.asarray(dist_mod.sample(
                dataclasses.replace(model, **{model.coefficients_name: e}), grid))
                for e in np.eye(p.m)], axis=1)  # (G, m): each unit coefficient on the grid
            project_coef = type(model).project_coefficients
        lo, hi, bound = p.box()
        spec = p.spec.for_dtype(dtype_of(p.setup)).program()  # (refinement is simulate's)
        args = (lo, hi, bound, spec, p.requirement)
        st = p.static()
        values = search.Batched(_problem_values_jit, (p.setup,), args, st=st)
        if coarsening == 1:
            vg = search.Batched(_problem_value_and_grad, (p.setup,), args, st=st)
        else:
            f = coarsening
            spec_g = dataclasses.replace(spec, dt=spec.dt * f, n_steps=spec.n_steps // f,
                                         save_every=spec.n_steps // f,
                                         sample_every=spec.sample_every // f)
            extra_g = with_steps(p.requirement, spec_g.n_steps)
            vg = search.Batched(_problem_coarse, (p.setup,), args + (spec_g, extra_g), st=st)
        nominal = np.array([r.param.nominal(p.setup) for r in p.ranges])  # (d,) float64 if d = 0
        return cls(p.d, p.m, basis, project_coef, values, vg,
                   np.clip((nominal - lo) / (hi - lo), 0.0, 1.0))

