"""The runs of the study: the four closed loops on the paper's example, Fig. 1's hysteresis
loops, and what is read off each trajectory (metrics, adaptive estimates)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from dscjax.config import hysteresis_example, paper_example
from dscjax.controllers.backstepping import with_backstepping
from dscjax.hysteresis import sine_loops
from dscjax.simulate import divergence_report, simulate

LABELS = {
    "dsc": "DSC with hysteresis compensation",
    "dsc_no_dhat": r"DSC without compensation, reading A: $\hat d \equiv 0$",
    "dsc_no_dhat_no_zeta": r"DSC without compensation, reading B: $\hat d \equiv 0$, "
                           r"$\hat\zeta \equiv 1$",
    "backstepping": "adaptive backstepping",
}
STYLE = {
    "dsc": dict(color="#1f77b4", ls="-", lw=1.3),
    "dsc_no_dhat": dict(color="#ff7f0e", ls="--", lw=1.3),
    "dsc_no_dhat_no_zeta": dict(color="#7f7f7f", ls="-.", lw=1.3),
    "backstepping": dict(color="#d62728", ls="-", lw=1.3),
}
METRIC_FIELDS = ("linf_error", "linf_error_after_1s", "l2_error", "l2_error_after_1s",
                 "max_abs_u", "max_abs_u_after_1s", "max_abs_w", "tv_u")
FIG1_AMPLITUDES = (3.5, 6.5)  # Fig. 1's two loops: u = k sin(FIG1_OMEGA t) for these k
FIG1_OMEGA = 2.3
FAMILY = ("backlash", "pi", "gpi", "bouc_wen")  # the hysteresis models of the Fig. 1 family
ESTIMATES = ("theta_hat_g1", "theta_hat_2", "phi_hat_1", "zeta_hat", "d_hat")


def setups() -> dict:
    """The four closed loops of the study, by run name."""
    return {
        "dsc": paper_example(),
        "dsc_no_dhat": paper_example(variant="no_dhat"),
        "dsc_no_dhat_no_zeta": paper_example(variant="no_dhat_no_zeta"),
        "backstepping": with_backstepping(paper_example()),
    }


def family_loops(amplitudes: Sequence[float] = FIG1_AMPLITUDES, omega: float = FIG1_OMEGA,
                 t_final: float = 3 * 2 * math.pi / FIG1_OMEGA, dt: float = 1e-3) -> dict:
    """{kind: (model, t (N+1,), u (K, N+1), w (K, N+1))}: Fig. 1's input applied to every
    hysteresis model at its example's values (`hysteresis_example`), K = len(amplitudes)."""
    models = {kind: hysteresis_example(kind).hysteresis for kind in FAMILY}
    return {kind: (m, *sine_loops(m, amplitudes, omega, t_final, dt)) for kind, m in models.items()}


def run_metrics(traj) -> dict:
    """The metrics of `METRIC_FIELDS` of one run (its windowed ones named "_after_1s")."""
    return {k: float(traj.metrics[k.replace("_after_1s", "_window")]) for k in METRIC_FIELDS}


def estimates(traj) -> dict[str, np.ndarray]:
    """The adaptive estimates of `ESTIMATES` along one run."""
    c = traj.ctrl
    columns = (c.theta_hat[:, 0], c.theta_hat[:, 1], c.phi_hat[:, 0], c.zeta_hat, c.d_hat)
    return {k: np.asarray(v) for k, v in zip(ESTIMATES, columns, strict=True)}


def run_all(t_final: float = 20.0, dt: float = 1e-3, log: Callable[[str], None] = print) -> dict:
    """Simulate the four runs; returns {name: Trajectory} (saved at every step)."""
    trajs = {}
    for name, setup in setups().items():
        t0 = time.perf_counter()
        traj = simulate(setup, t_final, dt, save_every=1, throw=False)
        jax.block_until_ready(traj.x)
        note = "" if not bool(traj.diverged) else "  DIVERGED: " + divergence_report(traj)[0]
        log(f"simulated {name:<20} ({time.perf_counter() - t0:.1f} s){note}")
        trajs[name] = traj
    return trajs
