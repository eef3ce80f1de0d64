"""Plots of trajectories (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

# One colour per signal across every figure of the project.
COLORS = {"y": "#1f77b4", "yr": "#444444", "e": "#d62728", "u": "#2ca02c", "w": "#9467bd",
          "x": ("#1f77b4", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f",
                "#aec7e8")}


def plot_trajectory(traj, path: Path | str, title: str = "") -> None:
    """Four panels: output against reference, tracking error, control u, hysteresis output w."""
    t = np.asarray(traj.t)
    x = np.asarray(traj.x)
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.5), sharex=True, constrained_layout=True)
    a = ax[0, 0]
    a.plot(t, np.asarray(traj.yr), color=COLORS["yr"], lw=1.2, ls="--", label="$y_r$")
    for i in range(x.shape[1]):
        a.plot(t, x[:, i], color=COLORS["x"][i % len(COLORS["x"])], lw=1.0,
               label=f"$x_{i + 1}$" + (" = y" if i == 0 else ""))
    a.set_ylabel("state")
    a.legend(loc="upper right", ncol=2, fontsize=8)
    a.set_title("states against the reference")
    a = ax[0, 1]
    a.plot(t, np.asarray(traj.e), color=COLORS["e"], lw=1.0)
    a.set_ylabel("$e = y - y_r$")
    a.set_title("tracking error")
    a = ax[1, 0]
    a.plot(t, np.asarray(traj.u), color=COLORS["u"], lw=1.0)
    a.set_ylabel("$u$")
    a.set_title("control input")
    a = ax[1, 1]
    a.plot(t, np.asarray(traj.w), color=COLORS["w"], lw=1.0)
    a.set_ylabel("$w$")
    a.set_title("hysteresis output")
    for a in ax[1]:
        a.set_xlabel("time $t$ [s]")
    for a in ax.ravel():
        a.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
