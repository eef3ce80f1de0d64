"""Running metrics (inside the scan) against the same definitions on saved arrays and numpy."""

import numpy as np
import pytest
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
    # the array functions of metrics.py agree too
    assert float(metrics.l2(full.e, full.t, 1.0)) == pytest.approx(m["l2_error_window"], rel=1e-10)
    assert float(metrics.linf(full.e, full.t, 1.0)) == pytest.approx(m["linf_error_window"])
    assert float(metrics.rms(full.e, full.t)) == pytest.approx(m["rms_error"], rel=1e-10)
    assert float(metrics.total_variation(full.u)) == pytest.approx(m["tv_u"], rel=1e-10)


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

    g = jax.grad(loss)(paper_setup.controller.k)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)
