"""Exact gradients through the closed loop (issue 10): the time-parallel linearisation of one
trajectory (reverse and forward mode) and the checkpointed batch equal JAX's own
differentiation of the scan and central finite differences of the tuning objective.
(Finite gradients through a divergence: tests/test_tuning_gradients.py; the batch gradient's
memory against the horizon: experiments/bench_gradient.py.)"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from compilations import lean
from jax.flatten_util import ravel_pytree

import dscjax
import tuning
from dscjax.integrate import Checkpointed
from dscjax.runspec import RunSpec

T = 0.4  # short horizons: the tests check numbers, not speed


def _problem(batch: int = 0):
    """Every term of the objective at once: smooth L-inf, L2, the requirement envelope and the
    control-rate limit (the envelope and u_rate terms read u' and the windowed error), and the
    forward-Euler check loop's penalty. The loop tuned has its input delayed one sample (the
    delayed check loop's code, without a third loop to compile)."""
    cfg = tuning.TuningConfig(
        objective=tuning.ObjectiveSpec(window_start=0.1, linf=1.0, l2=1.0, u_max=None,
                                       delay_weight=0.0),
        requirements={"envelope": {"b0": 0.1, "b_inf": 0.005, "decay": 0.1},
                      "u_rate": {"max": 40.0}},
        robust=tuning.BatchSpec(batch=batch, seed=1), heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(),
                                RunSpec.make(t_final=T, sample_time=1e-3, delay=1), cfg)


def _with(objective, **changes):
    return dataclasses.replace(objective, sim=dataclasses.replace(objective.sim, **changes))


def _points(problem, n, seed=0):
    flat0, unravel = ravel_pytree(problem.z0)
    rng = np.random.default_rng(seed)
    return [unravel(flat0 + 0.15 * rng.standard_normal(flat0.shape)) for _ in range(n)], unravel


def _close(a, b):
    a, b = np.asarray(ravel_pytree(a)[0]), np.asarray(ravel_pytree(b)[0])
    np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.max(np.abs(b)))


def test_one_trajectory_gradient_equals_autodiff_and_finite_differences():
    obj = _problem().objective
    loss = lambda z: obj.evaluate(z)[0]  # noqa: E731
    ref_obj = _with(obj, gradient=Checkpointed(every=None))
    ref = lean(jax.jacfwd(lambda z: ref_obj.evaluate(z)[0]))  # JAX's forward mode of the scan
    grad, fwd, value = lean(jax.grad(loss)), lean(jax.jacfwd(loss)), lean(loss)
    points, unravel = _points(_problem(), 2)
    for z in points:
        g_ref = ref(z)
        _close(grad(z), g_ref)
        _close(fwd(z), g_ref)
        # central differences of the same discrete map, every coordinate
        flat = ravel_pytree(z)[0]
        h = 1e-6
        fd = np.array([(value(unravel(flat + h * e)) - value(unravel(flat - h * e))) / (2 * h)
                       for e in np.eye(flat.size)])
        g = np.asarray(ravel_pytree(grad(z))[0])
        assert np.max(np.abs(g - fd)) < 1e-4 * np.max(np.abs(fd)), (g, fd)


def test_batch_gradient_through_the_public_api_equals_single_plant_gradients():
    # jax.grad straight through dscjax.simulate_batch and dscjax.simulate (refine=0: no
    # host-side refinement under a trace): the batch (checkpointed scan) against each plant
    # alone (time-parallel rule)
    setup = dscjax.paper_example()
    alphas = jnp.array([0.8, 1.3])

    def batch_loss(k):
        s = dscjax.params.set(setup, "controller.k", k)
        return jnp.mean(dscjax.simulate_batch(s, {"hysteresis.alpha": alphas}, T, 1e-3,
                                              refine=0).metrics["l2_error"])

    @lean
    def single_grad(k, alpha):
        def loss(k):
            s = dscjax.params.set_many(setup, {"controller.k": k, "hysteresis.alpha": alpha})
            return dscjax.simulate(s, T, 1e-3, throw=False, refine=0).metrics["l2_error"]
        return jax.grad(loss)(k)

    k = jnp.asarray(setup.controller.k) * 1.1
    g = lean(jax.grad(batch_loss))(k)
    _close(g, np.mean([single_grad(k, a) for a in alphas], axis=0))
