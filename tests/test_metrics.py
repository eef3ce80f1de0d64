"""Running metrics (inside the scan) against the same definitions on saved arrays and numpy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compilations import lean
from reference_metrics import chattering_numpy, l2, linf, rms, total_variation
from scipy.integrate import trapezoid

import dscjax
from dscjax import metrics


@pytest.fixture(scope="module")
def full(paper_setup):
    return dscjax.simulate(paper_setup, 3.0, 1e-3, save_every=1, window_start=1.0)


def test_running_metrics_equal_array_metrics(full):
    t, e, u, w = (np.asarray(a) for a in (full.t, full.e, full.u, full.w))
    m = {k: float(v) for k, v in full.metrics.items()}
    win = t >= 1.0
    assert m["linf_error"] == pytest.approx(np.abs(e).max(), rel=1e-12)
    assert m["linf_error_window"] == pytest.approx(np.abs(e[win]).max(), rel=1e-12)
    assert m["l2_error"] == pytest.approx(np.sqrt(trapezoid(e * e, t)), rel=1e-10)
    assert m["l2_error_window"] == pytest.approx(np.sqrt(trapezoid(e[win] ** 2, t[win])), rel=1e-10)
    assert m["rms_error"] == pytest.approx(np.sqrt(trapezoid(e * e, t) / 3.0), rel=1e-10)
    assert m["rms_error_window"] == pytest.approx(
        np.sqrt(trapezoid(e[win] ** 2, t[win]) / (3.0 - t[win][0])), rel=1e-10)
    assert m["max_abs_u"] == pytest.approx(np.abs(u).max(), rel=1e-12)
    assert m["tv_u"] == pytest.approx(np.abs(np.diff(u)).sum(), rel=1e-10)
    assert m["l2_u"] == pytest.approx(np.sqrt(trapezoid(u * u, t)), rel=1e-10)
    assert m["max_abs_w"] == pytest.approx(np.abs(w).max(), rel=1e-12)
    # the array functions of tests/reference_metrics.py agree too
    assert float(l2(full.e, full.t, 1.0)) == pytest.approx(m["l2_error_window"], rel=1e-10)
    assert float(linf(full.e, full.t, 1.0)) == pytest.approx(m["linf_error_window"])
    assert float(rms(full.e, full.t)) == pytest.approx(m["rms_error"], rel=1e-10)
    assert float(total_variation(full.u)) == pytest.approx(m["tv_u"], rel=1e-10)


def test_metrics_use_every_step_not_only_saved_ones(paper_setup, full):
    strided = dscjax.simulate(paper_setup, 3.0, 1e-3, save_every=500, window_start=1.0)
    for k, v in full.metrics.items():
        assert float(strided.metrics[k]) == pytest.approx(float(v), rel=1e-12), k


def test_metric_gradients_are_finite(paper_setup):
    def loss(k):
        s = dscjax.params.set(paper_setup, "controller.k", k)
        m = dscjax.simulate(s, 1.0, 1e-3, save_every=100, throw=False, refine=0).metrics
        return m["linf_error_window"] + m["l2_error"] + m["tv_u"] * 1e-3 + m["rms_error_window"]

    g = lean(jax.grad(loss))(paper_setup.controller.k)  # one program, as a user's (README)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)


def test_window_effort_and_chattering_index_equal_numpy(full):
    t, u = np.asarray(full.t), np.asarray(full.u)
    m = {k: float(v) for k, v in full.metrics.items()}
    tv_win, index = chattering_numpy(t, u, 1.0)
    assert m["max_abs_u_window"] == pytest.approx(np.abs(u[t >= 1.0]).max(), rel=1e-12)
    assert m["tv_u_window"] == pytest.approx(tv_win, rel=1e-10)
    assert m["chattering_index"] == pytest.approx(index, rel=1e-9)
    assert 1.0 <= index < metrics.CHATTER_RATIO and not metrics.chatters(m["chattering_index"])


def _running_index(t, u, t0):
    """The chattering index of the running metrics every run folds, over the samples (t, u)."""
    dt, n = t[1] - t[0], len(t) - 1

    def step(acc, x):
        k, tk, uk = x
        return metrics.running_update(acc, k, tk, 0.0, uk, 0.0, dt, t0, n), None

    acc, _ = jax.lax.scan(step, metrics.running_init(jnp.float64),
                          (jnp.arange(n + 1), jnp.asarray(t), jnp.asarray(u)))
    return float(metrics.finalize(acc, t[-1])["chattering_index"])


def test_a_limit_cycle_chatters_and_a_smooth_signal_does_not():
    # u = sin t plus a +-a square wave at the sample rate of 1 kHz: TV grows by 2a per sample,
    # the low pass keeps about 1/(pi tau / Ts) of it
    t = np.arange(0, 5.0 + 5e-4, 1e-3)
    smooth = np.sin(t)
    cycle = smooth + 0.05 * (-1.0) ** np.arange(t.size)
    index = {}
    for name, u in (("smooth", smooth), ("cycle", cycle)):
        index[name] = _running_index(t, u, 1.0)  # the running index every run folds
        assert index[name] == pytest.approx(chattering_numpy(t, u, 1.0)[1], rel=1e-9)
    assert index["smooth"] == pytest.approx(1.0, abs=5e-3) and not metrics.chatters(index["smooth"])
    assert index["cycle"] > 10 and metrics.chatters(index["cycle"])
