"""The order-6 start of the scaling study (`experiments/tune_scaling.py`'s STARTS[6]) tracks
where the example's uniform gains diverge, as docs/tuning.md and docs/numerics.md say."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import dscjax


def _starts():
    path = Path(__file__).resolve().parents[1] / "experiments" / "tune_scaling.py"
    spec = importlib.util.spec_from_file_location("tune_scaling", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.STARTS


def test_order6_default_gains_diverge_at_once():
    traj = dscjax.simulate(dscjax.order_n_example(6, dtype=np.float64), 0.1, 1e-3,
                           throw=False, refine=0, solver="etdrk4")
    assert bool(traj.diverged) and float(traj.t_diverged) < 0.05


def test_order6_start_tracks_20s_with_etdrk4_not_rk4():
    setup = dscjax.order_n_example(6, dtype=np.float64, **_starts()[6])
    traj = dscjax.simulate(setup, 20.0, 1e-3, throw=False, refine=0, solver="etdrk4",
                           save_every=1000)
    assert not bool(traj.diverged)
    assert float(traj.metrics["linf_error"]) == pytest.approx(0.30, abs=0.01)
    rk4 = dscjax.simulate(setup, 0.1, 1e-3, throw=False, refine=0, solver="rk4")
    assert bool(rk4.diverged) and float(rk4.t_diverged) == pytest.approx(0.004, abs=0.002)
