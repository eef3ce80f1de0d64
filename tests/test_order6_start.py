"""The order-6 start of the scaling study (`experiments/order_n_start.py`'s STARTS[6]) tracks
where the example's uniform gains diverge, as docs/tuning.md and docs/numerics.md say."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import dscjax


def _starts():
    path = Path(__file__).resolve().parents[1] / "experiments" / "order_n_start.py"
    spec = importlib.util.spec_from_file_location("order_n_start", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.STARTS


def test_order6_default_gains_diverge_at_once():
    traj = dscjax.simulate(dscjax.order_n_example(6, dtype=np.float64), 0.1, 1e-3,
                           throw=False, refine=0, solver="etdrk4")
    assert bool(traj.diverged) and float(traj.t_diverged) < 0.05


def test_order6_start_tracks_with_etdrk4_not_rk4():
    """STARTS[6] tracks under ETDRK4 at dt = 1e-3, and what it tracks is the loop's own
    solution: halving the step changes the windowed L-inf by < 0.1 % (a converged figure, not
    one the integrator makes). Classical RK4 at the same step blows up within 0.1 s."""
    setup = dscjax.order_n_example(6, dtype=np.float64, **_starts()[6])
    runs = [dscjax.simulate(setup, 5.0, dt, throw=False, refine=0, solver="etdrk4",
                            save_every=every) for dt, every in ((1e-3, 1000), (5e-4, 2000))]
    assert not any(bool(r.diverged) for r in runs)
    coarse, fine = (float(r.metrics["linf_error_window"]) for r in runs)
    assert np.isfinite(coarse) and coarse == pytest.approx(fine, rel=1e-3)
    rk4 = dscjax.simulate(setup, 0.1, 1e-3, throw=False, refine=0, solver="rk4")
    assert bool(rk4.diverged) and float(rk4.t_diverged) < 0.1
