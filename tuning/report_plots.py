"""The figures of a tuning run: the loss curve, start against tuned trajectories, the
held-out distributions and the margins' Ts sweep (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dscjax import ts_sweep
from dscjax.markdown import window
from dscjax.plotting import AXIS_LABEL, GRID, LOG_GRID, saved
from tuning.report_md import LABELS

COLORS = {"start": "#7f7f7f", "tuned": "#d62728"}  # of the start and the tuned gains


def plot_loss_curve(history, path, *, u_max: float | None = None, batch: bool = False):
    """loss_curve.png: the loss (best loss, rejected steps), the L-inf error and max|u| (its
    bound) per iteration, a panel each. Returns the Figure (saved)."""
    it, loss, best, linf, umax = (np.array([r[k] for r in history], dtype=float) for k in (
        "iteration", "loss", "best_loss", "linf_window", "max_abs_u"))
    acc = np.array([bool(r["accepted"]) for r in history])
    with saved(path, 110, 1, 3, rc=LOG_GRID, figsize=(14, 4)) as (fig, ax):
        ax[0].semilogy(it, loss, lw=1, label="loss of the iteration")
        ax[0].semilogy(it, best, lw=1.5, label="best loss so far")
        if (~acc).any():
            ax[0].semilogy(it[~acc], loss[~acc], "rx", label="rejected step")
        ax[0].set(ylabel="objective J [-] (about 1 at the start gains)", title="loss")
        ax[1].semilogy(it, linf, color="#d62728", lw=1, label="L-inf error on [t0, T]")
        worst = " (worst training plant)" if batch else ""
        ax[1].set(ylabel="L-inf tracking error on [t0, T] [-]", title="tracking error" + worst)
        ax[2].plot(it, umax, color="#2ca02c", lw=1, label="max|u|" + worst)
        if u_max:
            ax[2].axhline(u_max, color="k", ls=":", lw=1, label=f"bound on max|u| ({u_max:.4g})")
        ax[2].set(ylabel="max|u| [-]", title="control amplitude")
        for a in ax:
            a.set_xlabel("iteration")
            a.legend(fontsize=8)
    return fig


def draw(out: Path, result, ev, trajs, sampling: dict | None) -> list[str]:
    """The figures of `result` (`ev`: `report.evaluate`'s figures, `trajs`: the start and
    tuned loops on the nominal plant, `sampling`: the margins' Ts sweep, None without one)
    written to `out`; returns their file names."""
    problem = result.problem
    figures, sc, sim = [], problem.scales, problem.objective.sim
    if result.history:
        plot_loss_curve(result.history, out / "loss_curve.png", u_max=sc.u_max,
                        batch=bool(problem.objective.overrides))
        figures.append("loss_curve.png")

    with saved(out / "before_after.png", 110, 4, 1, rc=GRID, figsize=(10, 11)) as (fig, ax):
        for tag, color in COLORS.items():
            tr = trajs[tag]
            t, e, u = np.asarray(tr.t), np.asarray(tr.e), np.asarray(tr.u)
            how = (f"diverged at {float(tr.t_diverged):.3g} s" if bool(tr.diverged) else
                   f"L-inf on [t0,T] {float(tr.metrics['linf_error_window']):.3g}")
            ax[0].plot(t, e, color=color, lw=0.9, label=f"{tag} ({how})")
            win = t >= sim.window_start
            ax[1].plot(t[win], e[win], color=color, lw=0.9, label=tag)
            tv = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(u)))])
            ax[3].plot(t, tv, color=color, lw=1.2,
                       label=f"{tag} (TV(u) on every step {float(tr.metrics['tv_u']):.4g})")
            ax[2].plot(t, u, color="#2ca02c" if tag == "tuned" else color, lw=0.9,
                       label=f"{tag} (max|u| {float(tr.metrics['max_abs_u']):.3g})")
        if sc.u_max:
            for sgn in (1, -1):
                ax[2].axhline(sgn * sc.u_max, color="k", ls=":", lw=0.8)
        ax[0].set(ylabel=AXIS_LABEL["e"], title="tracking error, whole horizon")
        ax[1].set(ylabel="e on [t0, T] [-]",
                  title=f"tracking error on the window {window(sim.window_start, sim.t_final)}")
        ax[2].set(ylabel=AXIS_LABEL["u"], title="control input (dotted: the bound on max|u|)")
        if sc.tv_max:
            ax[3].axhline(sc.tv_max, color="k", ls=":", lw=0.8,
                          label=f"bound on TV(u) ({sc.tv_max:.4g})")
        ax[3].set(ylabel="sum |du| [-]", xlabel=AXIS_LABEL["t"], title="total variation of u up "
                  "to t (curves: on the saved grid, a lower bound; labels: exact)")
        for a in ax:
            a.legend(loc="upper right", fontsize=8)
    figures.append("before_after.png")

    if ev["heldout"] is not None:
        with saved(out / "heldout.png", 110, 1, 2, rc=LOG_GRID, figsize=(11, 4)) as (fig, ax):
            for i, key in enumerate(("linf_error_window", "max_abs_u")):
                for tag, color in COLORS.items():
                    m = ev["heldout"][tag]
                    v = np.sort(m[key][~m["diverged"].astype(bool)])
                    if not v.size:
                        continue
                    frac = np.arange(1, v.size + 1) / v.size
                    ax[i].step(v, frac, where="post", color=color, lw=1.5,
                               label=f"{tag}: median {np.median(v):.3g}, p95 "
                               f"{np.percentile(v, 95):.3g}")
                    for q, ls in ((50, "-"), (95, "--")):
                        ax[i].axvline(np.percentile(v, q), color=color, lw=0.8, ls=ls)
                if key == "linf_error_window":
                    ax[i].set_xscale("log")
                elif sc.u_max:
                    ax[i].axvline(sc.u_max, color="k", ls=":", lw=1, label="bound (nominal plant)")
                ax[i].set(xlabel=LABELS[key], ylabel="fraction of plants")
                ax[i].legend(fontsize=8, loc="lower right")
            n = ev["heldout"]["start"]["diverged"].size
            fig.suptitle(f"held-out batch of {n} plants: distribution (ECDF) with the start "
                         f"and the tuned gains (solid: median, dashed: p95)")
        figures.append("heldout.png")
    if sampling is not None:
        ts_sweep.plot(sampling, out / "sampling.png", COLORS, 110,
                      {"start": "start gains", "tuned": "tuned gains"})
        figures.append("sampling.png")
    return figures
