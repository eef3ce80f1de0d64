"""The order-6 start of the scaling study tracks where the example's uniform gains diverge, as
docs/tuning.md and docs/numerics.md say.

START (k_i, tau_i, the adaptation rates, eps and the sat width; the rest is
order_n_example(6)'s) was found by CMA-ES on batched ETDRK4 runs (the search:
`git show b260497:experiments/order_n_start.py`).
"""

import numpy as np
import pytest

import dscjax

START = dict(
    k=np.array([1.589, 1.214, 2.407, 2.415, 1.487, 0.7754]),
    tau=np.array([0.2317, 0.02329, 0.3151, 0.09354, 0.04346]),
    gamma_g=np.array([0.6882, 0.8046, 1.251, 1.351, 0.7702, 3.526]),
    gamma_phi=np.array([0.3463, 0.3644, 0.6199, 0.4614, 0.5244]),
    gamma_zeta=1.996, gamma_d=1.502, sat_width=0.03819, eps=1.184)


def test_order6_default_gains_diverge_at_once():
    traj = dscjax.simulate(dscjax.order_n_example(6, dtype=np.float64), 0.1, 1e-3,
                           throw=False, refine=0, solver="etdrk4")
    assert bool(traj.diverged) and float(traj.t_diverged) < 0.05


def test_order6_start_tracks_with_etdrk4_not_rk4():
    """START tracks under ETDRK4 at dt = 1e-3, and what it tracks is the loop's own
    solution: halving the step changes the windowed L-inf by < 0.1 % (a converged figure, not
    one the integrator makes). Classical RK4 at the same step blows up within 0.1 s."""
    setup = dscjax.order_n_example(6, dtype=np.float64, **START)
    runs = [dscjax.simulate(setup, 5.0, dt, throw=False, refine=0, solver="etdrk4",
                            save_every=every) for dt, every in ((1e-3, 1000), (5e-4, 2000))]
    assert not any(bool(r.diverged) for r in runs)
    coarse, fine = (float(r.metrics["linf_error_window"]) for r in runs)
    assert np.isfinite(coarse) and coarse == pytest.approx(fine, rel=1e-3)
    rk4 = dscjax.simulate(setup, 0.1, 1e-3, throw=False, refine=0, solver="rk4")
    assert bool(rk4.diverged) and float(rk4.t_diverged) < 0.1
