"""Running metrics (inside the scan) against the same definitions on saved arrays and numpy."""

import numpy as np
import pytest
from compilations import lean
from reference_metrics import l2, linf, rms, total_variation
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
    import jax

    def loss(k):
        s = dscjax.params.set(paper_setup, "controller.k", k)
        m = dscjax.simulate(s, 1.0, 1e-3, save_every=100, throw=False, refine=0).metrics
        return m["linf_error_window"] + m["l2_error"] + m["tv_u"] * 1e-3 + m["rms_error_window"]

    g = lean(jax.grad(loss))(paper_setup.controller.k)  # one program, as a user's (README)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)


def _np_low_pass(u, t, tc):
    v = np.empty_like(u)
    v[0] = u[0]
    for k in range(1, len(u)):
        v[k] = v[k - 1] + (1 - np.exp(-(t[k] - t[k - 1]) / tc)) * (u[k] - v[k - 1])
    return v


def test_window_effort_and_chattering_index_equal_numpy(full):
    t, u = np.asarray(full.t), np.asarray(full.u)
    m = {k: float(v) for k, v in full.metrics.items()}
    win = t >= 1.0
    steps = win[:-1]  # the steps k -> k+1 that start (and so end) in the window
    tv_win = np.abs(np.diff(u))[steps].sum()
    lp = _np_low_pass(u, t, metrics.CHATTER_TIME_CONSTANT)
    assert m["max_abs_u_window"] == pytest.approx(np.abs(u[win]).max(), rel=1e-12)
    assert m["tv_u_window"] == pytest.approx(tv_win, rel=1e-10)
    index = tv_win / np.abs(np.diff(lp))[steps].sum()
    assert m["chattering_index"] == pytest.approx(index, rel=1e-9)
    assert 1.0 <= index < metrics.CHATTER_RATIO and not metrics.chatters(m["chattering_index"])


def test_a_limit_cycle_chatters_and_a_smooth_signal_does_not():
    # u = sin t plus a +-a square wave at the sample rate of 1 kHz: TV grows by 2a per sample,
    # the low pass keeps about 1/(pi tau / Ts) of it
    t = np.arange(0, 5.0 + 5e-4, 1e-3)
    steps = t[:-1] >= 1.0

    def index(u):
        lp = _np_low_pass(u, t, metrics.CHATTER_TIME_CONSTANT)
        return np.abs(np.diff(u))[steps].sum() / np.abs(np.diff(lp))[steps].sum()

    smooth = np.sin(t)
    assert index(smooth) == pytest.approx(1.0, abs=5e-3) and not metrics.chatters(index(smooth))
    cycle = index(smooth + 0.05 * (-1.0) ** np.arange(t.size))
    assert cycle > 10 and metrics.chatters(cycle)
