"""Batches equal separate runs; gains and parameters never recompile; dtypes are kept."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compilations import lean

import dscjax
from dscjax import params, xla
from dscjax.simulate import _simulate, _simulate_batch

ALPHAS = jnp.array([0.7, 1.0, 1.3])
LAMS = jnp.array([1.2, 1.432, 1.7])


def test_batch_over_hysteresis_equals_separate_runs(paper_setup):
    batch = dscjax.simulate_batch(paper_setup, {"hysteresis.alpha": ALPHAS, "hysteresis.lam": LAMS},
                                  2.0, 1e-3, save_every=100)
    assert batch.x.shape == (3, 21, 2)
    for i in range(3):
        s = params.set_many(paper_setup, {"hysteresis.alpha": ALPHAS[i], "hysteresis.lam": LAMS[i]})
        one = dscjax.simulate(s, 2.0, 1e-3, save_every=100)
        np.testing.assert_allclose(np.asarray(batch.x[i]), np.asarray(one.x), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(batch.w[i]), np.asarray(one.w), rtol=0, atol=1e-11)
        for k in one.metrics:
            assert float(batch.metrics[k][i]) == pytest.approx(float(one.metrics[k]), rel=1e-10,
                                                                abs=1e-13)


def test_batch_over_initial_state_and_gains(paper_setup):
    x0 = jnp.array([[0.08, 0.1], [0.0, 0.0], [-0.1, 0.3]])
    k = jnp.array([[10.0, 0.45], [8.0, 0.6], [12.0, 0.3]])
    batch = dscjax.simulate_batch(paper_setup, {"plant.x0": x0, "controller.k": k}, 1.0, 1e-3)
    for i in range(3):
        s = params.set_many(paper_setup, {"plant.x0": x0[i], "controller.k": k[i]})
        one = dscjax.simulate(s, 1.0, 1e-3, save_every=1000)
        np.testing.assert_allclose(np.asarray(batch.x[i]), np.asarray(one.x), atol=1e-12)


def test_jax_vmap_of_simulate(paper_setup):
    def run(alpha):
        s = params.set(paper_setup, "hysteresis.alpha", alpha)
        return dscjax.simulate(s, 1.0, 1e-3, save_every=100, throw=False,
                               refine=0).metrics["l2_error"]

    got = jax.vmap(run)(ALPHAS)
    want = [float(run(a)) for a in ALPHAS]
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12)


def test_changing_numbers_does_not_recompile(paper_setup):
    # the step count t_final / dt is static: 500 and 250 steps are two programs, compiled here
    # (or by an earlier test of this process) before the count
    dscjax.simulate(paper_setup, 0.5, 1e-3)
    dscjax.simulate(paper_setup, 0.5, 2e-3)
    before = _simulate.top._cache_size()
    for gain in (8.0, 10.5, 12.0):
        s = params.set_many(paper_setup, {"controller.k": jnp.array([gain, 0.45]),
                                          "hysteresis.alpha": jnp.asarray(gain / 10),
                                          "reference.frequency": jnp.asarray(0.5)})
        dscjax.simulate(s, 0.5, 1e-3)
        # dt and t_final are traced numbers: another pair of the same step count reuses it
        dscjax.simulate(s, gain / 20, gain / 20 / 250)
    assert _simulate.top._cache_size() == before

    rows = xla.LEAN_ROWS + 1  # (a smaller batch runs _simulate's lean program)
    dscjax.simulate_batch(paper_setup, {"controller.k": jnp.ones((rows, 2))}, 0.5, 1e-3)
    b_before = _simulate_batch.top._cache_size()
    dscjax.simulate_batch(paper_setup, {"controller.k": 2 * jnp.ones((rows, 2))}, 0.5, 1e-3)
    assert _simulate_batch.top._cache_size() == b_before


def test_float32_setup_stays_float32(paper_setup):
    s32 = dscjax.cast(paper_setup, np.float32)
    tr = dscjax.simulate(s32, 0.5, 1e-3)
    for leaf in (tr.x, tr.u, tr.w, tr.t, tr.metrics["l2_error"]):
        assert leaf.dtype == jnp.float32
    ref = dscjax.simulate(paper_setup, 0.5, 1e-3)
    np.testing.assert_allclose(np.asarray(tr.x), np.asarray(ref.x), atol=1e-4)


def test_batch_divergence_is_per_trajectory(paper_setup):
    # alpha = 200 makes the hysteresis rate alpha |u'| far too stiff for RK4 at this dt
    batch = dscjax.simulate_batch(paper_setup, {"hysteresis.alpha": jnp.array([1.0, 200.0])},
                                  2.0, 2e-3, refine=0)
    diverged = np.asarray(batch.diverged)
    assert diverged.tolist() == [False, True]
    assert np.all(np.isfinite(np.asarray(batch.x)))
    report = dscjax.divergence_report(batch)
    assert len(report) == 1 and report[0].startswith("trajectory 1 diverged at t = ")


def test_diverged_trajectories_report_nan_metrics(paper_setup):
    # alpha 10 / lam 0.15 diverges within milliseconds at dt = 1e-3; the window [1, 2] s
    # starts after that, and used to read 0 ("perfect tracking"). Same shapes as the first
    # test of this file: nothing compiles again.
    alphas, lams = jnp.array([0.7, 10.0, 1.3]), jnp.array([1.2, 0.15, 1.7])
    batch = dscjax.simulate_batch(paper_setup, {"hysteresis.alpha": alphas,
                                                "hysteresis.lam": lams}, 2.0, 1e-3,
                                  save_every=100, refine=0)
    assert np.asarray(batch.diverged).tolist() == [False, True, False]
    assert float(batch.t_diverged[1]) < 0.1
    for k, v in batch.metrics.items():
        v = np.asarray(v)
        assert np.all(np.isfinite(v[[0, 2]])) and np.isnan(v[1]), k
    one = dscjax.simulate(params.set_many(paper_setup, {"hysteresis.alpha": alphas[1],
                                                        "hysteresis.lam": lams[1]}),
                          2.0, 1e-3, save_every=100, throw=False, refine=0)
    assert bool(one.diverged)
    assert all(np.isnan(float(v)) for v in one.metrics.values())


def test_forward_derivative_of_a_public_metric_stays_finite_when_the_run_diverges(paper_setup):
    @lean  # as a user compiles a gradient program (README)
    def l2_and_derivative(k, dk):
        def l2(k_):
            s = params.set(paper_setup, "controller.k", k_)
            return dscjax.simulate(s, 1.0, 1e-3, save_every=1000, throw=False,
                                   refine=0).metrics["l2_error"]

        return jax.jvp(l2, (k,), (dk,))

    dk = jnp.array([1.0, 1.0])
    value, slope = l2_and_derivative(jnp.array([1e4, 0.45]), dk)  # diverges
    assert np.isnan(float(value)) and float(slope) == 0.0  # the NaN is a constant branch
    value, slope = l2_and_derivative(jnp.array([10.0, 0.45]), dk)
    assert np.isfinite(float(value)) and np.isfinite(float(slope)) and float(slope) != 0.0
