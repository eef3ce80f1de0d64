"""Exact gradients of the tuning objectives against central finite differences (float64).

Short horizon (2 s, window [1, 2] s). The gradients are taken in the tuner's coordinates z
(log of the gains) at several random points around the paper's gains. All finite-difference
evaluations run as one vmapped batch and the Jacobians of the three metrics come from one
forward-mode pass, so the module compiles few functions.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compilations import lean
from jax.flatten_util import ravel_pytree

import dscjax
import tuning
from dscjax.runspec import RunSpec
from dscjax.selection import run_at
from tuning.optimize import Auto, CVaR, Forward, Max, Mean, Plants

T_FINAL = 2.0
SPEC = RunSpec.make(t_final=T_FINAL, sample_time=1e-3)  # the loop tuned: sampled at 1 ms
PARAMS = ("controller.k", "controller.tau", "controller.gamma_zeta", "controller.eps")
KEYS = ("l2_error_window", "smooth_linf_window", "linf_error_window")


@pytest.fixture(scope="module")
def problem():
    cfg = tuning.TuningConfig(params=PARAMS,
                              objective=tuning.ObjectiveSpec(linf=1.0, l2=1.0, u_max=None))
    return tuning.build_problem(dscjax.paper_example(), SPEC, cfg)


def _metrics_fn(problem, extra=True, checkpoint_every=None):
    """flat z -> the metrics of KEYS (or the L2 error alone without the extra reductions)."""
    obj = problem.objective
    unravel = ravel_pytree(problem.z0)[1]
    sim = obj.sim if checkpoint_every is None else dataclasses.replace(
        obj.sim, gradient=dataclasses.replace(obj.sim.gradient, every=checkpoint_every))

    def f(flat):
        metrics = run_at(obj.selection, obj.setup, unravel(flat), sim,
                         extra=obj.extra() if extra else None).metrics
        if not extra:
            return metrics["l2_error_window"]
        return jnp.stack([metrics[k] for k in KEYS])

    return f


@pytest.fixture(scope="module")
def points(problem):
    rng = np.random.default_rng(0)
    flat = np.asarray(ravel_pytree(problem.z0)[0])
    return np.stack([flat + rng.uniform(-0.15, 0.15, flat.shape) for _ in range(3)])


@pytest.fixture(scope="module")
def jacobians(problem, points):
    """(points, metrics, params) by forward mode, all points in one call."""
    return np.asarray(lean(jax.vmap(jax.jacfwd(_metrics_fn(problem))))(points))


@pytest.fixture(scope="module")
def fd(problem, points):
    """Central differences (points, metrics, params) at step h: one vmapped call per h."""
    f = lean(jax.vmap(_metrics_fn(problem)))
    n = points.shape[1]

    def at(h):
        steps = np.eye(n) * h
        args = np.concatenate([(p + steps, p - steps) for p in points]).reshape(-1, n)
        vals = np.asarray(f(args)).reshape(len(points), 2, n, -1)
        return np.swapaxes((vals[:, 0] - vals[:, 1]) / (2 * h), 1, 2)

    return at


@pytest.mark.parametrize("i, key", list(enumerate(KEYS[:2])))
def test_l2_and_smooth_linf_gradients_match_central_differences(jacobians, fd, i, key):
    d = fd(1e-5)
    for p in range(jacobians.shape[0]):
        rel = np.max(np.abs(jacobians[p, i] - d[p, i])) / np.max(np.abs(d[p, i]))
        assert rel < 1e-4, (key, p, rel, jacobians[p, i], d[p, i])


def test_exact_linf_gradient_where_the_max_is_unique(problem, points, jacobians, fd):
    """The exact L-inf (a running max) has the gradient of |e| at its argmax step; finite
    differences see the same as long as the argmax does not move (a unique max)."""
    unravel = ravel_pytree(problem.z0)[1]
    d = fd(1e-7)
    checked = 0
    for p, z in enumerate(points):
        tr = dscjax.simulate(problem.selection.apply(problem.setup, unravel(z)), T_FINAL, 1e-3,
                             window_start=1.0)
        e = np.sort(np.abs(np.asarray(tr.e))[np.asarray(tr.t) >= 1.0])
        if e[-1] - e[-2] < 1e-6:  # not unique by a margin far above the FD perturbation
            continue
        rel = np.max(np.abs(jacobians[p, 2] - d[p, 2])) / np.max(np.abs(d[p, 2]))
        assert rel < 1e-4, (p, rel, jacobians[p, 2], d[p, 2])
        checked += 1
    assert checked >= 1


def test_checkpointed_and_plain_reverse_gradients_agree(problem, points, jacobians):
    z = points[2]
    plain = np.asarray(lean(jax.grad(_metrics_fn(problem, extra=False)))(z))
    ckpt = np.asarray(lean(jax.grad(_metrics_fn(problem, extra=False, checkpoint_every=100)))(
        z))
    scale = np.max(np.abs(plain))
    assert np.max(np.abs(ckpt - plain)) <= 1e-13 * scale  # same numbers, rounding only
    # and reverse mode agrees with forward mode (row 0 of the Jacobian: the same L2 error)
    assert np.max(np.abs(jacobians[2, 0] - plain)) <= 1e-10 * scale


def test_loss_and_gradient_stay_finite_through_a_diverging_trajectory(problem):
    # k_1 = 1e4 makes the loop diverge within a step or two: its metrics are NaN (the one
    # convention of `run_at`), the loss is the finite divergence penalty, and the NaN reaches
    # neither the loss nor tuning's default forward-mode gradient
    z = dict(problem.z0)
    z["controller.k"] = jnp.log(jnp.array([1e4, 0.45]))
    obj = problem.objective
    ((loss, aux), grads), per = lean(lambda z_: (Forward().value_and_grad(obj, z_),
                                                    obj.per_plant(z_)))(z)
    assert bool(per["diverged"]) and float(per["loss"]) == float(loss)
    assert np.isnan(float(per["linf_error_window"])) and np.isnan(float(per["sampled_tv_u"]))
    assert int(aux["n_diverged"]) == 1
    assert float(loss) == problem.cfg.objective.divergence_penalty
    for g in jax.tree.leaves(grads):
        assert np.all(np.isfinite(np.asarray(g)))
    assert np.isnan(float(aux["linf_window"]))  # reported only: no plant was measured


def test_plant_by_plant_gradient_of_a_cvar_equals_forward_mode_of_the_batch():
    # gradient = "plants": one batched forward run, then only the worst ceil(0.5 x 4) = 2
    # plants differentiated, each alone by the time-parallel linearisation; the reference is
    # JAX's forward mode through the batched simulation of all 4 (no time-parallel rule)
    # (the loop tuned only: the check loops' gradients are test_gradients')
    cfg = tuning.TuningConfig(params=PARAMS,
                              objective=tuning.ObjectiveSpec(u_max=None, sampled_weight=0.0,
                                                             delay_weight=0.0),
                              robust=tuning.BatchSpec(batch=4, seed=3, aggregate=tuning.CVaR(),
                                                      cvar_level=0.5),
                              optimizer=tuning.OptimizerSpec(gradient=Plants()))
    prob = tuning.build_problem(dscjax.paper_example(), SPEC, cfg)
    assert prob.mode == Plants()
    assert prob.describe()["mode"] == "plants"  # asked for by name
    # picked by "auto" (CVaR 0.25 of 4 plants: ceil(0.25 x 4) = 1 <= 4/4); the fingerprint
    # holds the mode the run uses
    auto = tuning.build_problem(dscjax.paper_example(), SPEC,
                                tuning.TuningConfig(
                                    params=PARAMS, objective=tuning.ObjectiveSpec(u_max=None),
                                    robust=tuning.BatchSpec(batch=4, seed=3, cvar_level=0.25,
                                                            aggregate=tuning.CVaR())))
    assert auto.mode == Plants() and auto.describe()["mode"] == "plants"
    rng = np.random.default_rng(5)
    z = jax.tree.map(lambda v: v + rng.uniform(-0.15, 0.15, np.shape(v)), prob.z0)
    obj = prob.objective

    def both(z_):
        return Plants().value_and_grad(obj, z_), Forward().value_and_grad(obj, z_)

    ((_, aux), g), ((_, aux_f), g_f) = lean(both)(z)
    g, g_f = ravel_pytree(g)[0], ravel_pytree(g_f)[0]
    assert np.max(np.abs(np.asarray(g - g_f))) <= 1e-10 * np.max(np.abs(np.asarray(g_f)))
    assert bool(aux["feasible"]) == bool(aux_f["feasible"])


@pytest.mark.parametrize("batch, aggregate, n_params, expected", [
    (1, Mean(), 13, "reverse"),       # one plant
    (1, Mean(), 7, "reverse"),        # more than FORWARD_MAX_PARAMS_ONE_PLANT = 6
    (1, Mean(), 6, "forward"),
    (8, CVaR(0.25), 13, "plants"),    # ceil(0.25 x 8) = 2 <= 8 / 4
    (8, CVaR(0.3), 13, "forward"),    # ceil(2.4) = 3 > 2
    (8, Max(), 13, "plants"),         # 1 plant
    (8, Mean(), 13, "forward"),       # all 8
    (8, Mean(), 65, "reverse"),       # more than FORWARD_MAX_PARAMS = 64
    (3, Max(), 13, "forward"),        # 1 > 3 / 4
])
def test_auto_gradient_mode(batch, aggregate, n_params, expected):
    mode = Auto().chosen(n_params, batch, aggregate, every=50)
    assert mode.name == expected and mode.every == (50 if expected == "reverse" else None)
