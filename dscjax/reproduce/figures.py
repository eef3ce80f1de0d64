"""Figures 1-6 of the paper and the adaptive estimates, in the paper's style (applied with
`matplotlib.rc_context`, never globally); colours identify the run (`runs.STYLE`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dscjax.config import paper_example
from dscjax.metrics import default_window
from dscjax.plotting import AXIS_LABEL, COLORS, GRID, hysteresis_loop, legend_below, saved
from dscjax.reproduce import theory
from dscjax.reproduce.runs import FIG1_AMPLITUDES, FIG1_OMEGA, LABELS, STYLE, estimates

FIGURES = {
    "fig1": "fig1_hysteresis",
    "fig1_family": "fig1_hysteresis_family",
    "fig2": "fig2_compensation",
    "fig3": "fig3_dsc_control",
    "fig4": "fig4_dsc_hysteresis_output",
    "fig5": "fig5_backstepping_error",
    "fig6": "fig6_backstepping_control",
    "estimates": "fig_estimates",
    "complexity": "fig_complexity",
    "sampling": "fig_sampling",
}

# The style of the paper's figures, applied with matplotlib.rc_context (never globally).
RC = GRID | {"font.size": 10, "axes.titlesize": 10, "legend.fontsize": 8.5}
LOOP_COLORS = ("#8c564b", COLORS["w"])  # Fig. 1's loops: the small one brown, the large one w's


def _line(ax, traj, signal, name, t_after=None, **over):
    """A run's signal against time, labelled; from t_after on (unlabelled), if given."""
    t, y = np.asarray(traj.t), np.asarray(getattr(traj, signal))
    if t_after is None:
        ax.plot(t, y, label=LABELS[name], **(STYLE[name] | over))
        return
    keep = t >= t_after
    ax.plot(t[keep], y[keep], **(STYLE[name] | over))
    ax.set_xlim(t_after, t[-1])


def figures(trajs: dict, family: dict, out: Path, fmt: str = "png", dpi: int = 150) -> dict:
    """Write Figs. 1-6, the estimates figure and Fig. 1 of every hysteresis model (`family`,
    `runs.family_loops`; Fig. 1 is its backlash entry, the paper's (4)); returns {figure id:
    path}."""
    hyst, _, u, w = family["backlash"]
    title = (f"Fig. 1  Backlash-like hysteresis (4), $w(0) = 0$: $\\alpha$ = "
             f"{float(hyst.alpha):g}, $\\lambda$ = {float(hyst.lam):g}, $\\psi$ = "
             f"{float(hyst.psi):g}")
    paths = {"fig1": loop_figure(hyst, FIG1_AMPLITUDES, FIG1_OMEGA, u, w, title,
                                 out / f"{FIGURES['fig1']}.{fmt}", dpi)}
    t_end = float(np.asarray(trajs["dsc"].t)[-1])
    t_after = default_window(t_end)  # Figs. 3 and 4 add a panel after it
    dsc = (("dsc", {}),)
    without = [(name, {}) for name in ("dsc_no_dhat_no_zeta", "dsc_no_dhat", "dsc")]
    against = (("dsc", dict(lw=0.9, alpha=0.55)), ("backstepping", {}))  # the DSC faint
    for key, signal, title, runs, zoom in (
            ("fig2", "e", "Fig. 2  Tracking error of the DSC with and without hysteresis "
             "compensation", without, False),
            ("fig3", "u", "Fig. 3  Control signal of the DSC", dsc, True),
            ("fig4", "w", "Fig. 4  Hysteresis output of the DSC loop", dsc, True),
            ("fig5", "e", "Fig. 5  Tracking error of adaptive backstepping", against, False),
            ("fig6", "u", "Fig. 6  Control signal of adaptive backstepping", against, False)):
        paths[key] = out / f"{FIGURES[key]}.{fmt}"
        # one panel against time; with zoom a second one, t >= t_after, where the first
        # second's peak no longer sets the scale
        with saved(paths[key], dpi, 2 if zoom else 1, 1, rc=RC,
                   figsize=(6.4, 5.6 if zoom else 3.8), squeeze=False) as (fig, axes):
            axes = axes[:, 0]
            axes[0].set_title(title)
            for ax in axes:
                ax.set_ylabel(AXIS_LABEL[signal])
            axes[-1].set_xlabel(AXIS_LABEL["t"])
            for name, over in runs:
                _line(axes[0], trajs[name], signal, name, **over)
            if zoom:
                axes[1].set_title(f"after the first {t_after:g} s (the initial peak left out)",
                                  fontsize=9)
                axes[0].axvspan(t_after, t_end, color="#999999", alpha=0.08, lw=0,
                                label=f"shown below: $t \\geq$ {t_after:g} s")
                _line(axes[1], trajs["dsc"], signal, "dsc", t_after)
            legend_below(fig, axes[0], ncol=1 if key == "fig2" else 2)  # Fig. 2's labels: long
    paths["estimates"] = _estimates_figure(trajs, out / f"{FIGURES['estimates']}.{fmt}", dpi)
    paths["fig1_family"] = _family_figure(family, out / f"{FIGURES['fig1_family']}.{fmt}", dpi)
    return paths


def loop_figure(hyst, amplitudes, omega: float, u, w, title: str, path: Path, dpi: int) -> Path:
    """w against u of one hysteresis model, one panel per amplitude A of u = A sin(omega t)
    (u, w of shape (K, N+1)): Fig. 1, and `dscjax hysteresis`'s loop.png."""
    with saved(path, dpi, 1, len(amplitudes), rc=RC, figsize=(4.2 * len(amplitudes), 3.9),
               sharey=True, squeeze=False) as (fig, axes):
        for i, (ax, a) in enumerate(zip(axes[0], amplitudes, strict=True)):
            hysteresis_loop(ax, hyst, u[i], w[i], f"$w(u)$, $u = {a:g}\\,\\sin({omega:g}t)$",
                            LOOP_COLORS[i % len(LOOP_COLORS)])
            ax.set_title(f"amplitude {a:g}")
            ax.legend(loc="upper left", framealpha=0.95)
        axes[0, 0].set_ylabel(AXIS_LABEL["w"])
        fig.suptitle(title)
    return path


def _family_figure(family: dict, path: Path, dpi: int) -> Path:
    """Fig. 1's input, u = k sin(2.3 t), into every hysteresis model: one panel per model,
    both amplitudes, the lines lam_eff u + d_1 limits (`plotting.hysteresis_loop`, as `dscjax
    hysteresis` draws one model)."""
    with saved(path, dpi, 1, len(family), rc=RC, figsize=(3.2 * len(family), 3.6),
               sharey=True, squeeze=False) as (fig, axes):
        for ax, (model, _, u, w) in zip(axes[0], family.values(), strict=True):
            big = int(np.argmax(np.max(np.abs(u), axis=1)))
            for i in range(len(u)):
                k = float(np.max(np.abs(u[i])))
                hysteresis_loop(ax, model, u[i], w[i], f"$k$ = {k:.3g}",
                                LOOP_COLORS[i % len(LOOP_COLORS)], lines=i == big)
            ax.set_title(model.title, fontsize=9)
            ax.legend(loc="upper left", framealpha=0.95, fontsize=7)
        axes[0, 0].set_ylabel(AXIS_LABEL["w"])
        fig.suptitle(r"Fig. 1 for every actuator model: $w(u)$ for $u = k\,\sin(2.3t)$, "
                     r"examples' parameters (docs/hysteresis.md)")
    return path


def _estimates_figure(trajs, path: Path, dpi: int) -> Path:
    tr = theory.truth(paper_example())  # what the estimates estimate
    panels = (("theta_hat_g1", r"$\hat\theta_{g1}$ [-]", tr.theta[0], r"$\theta_1/g_1$"),
              ("phi_hat_1", r"$\hat\phi_1$ [-]", tr.phi[0], r"$1/g_1$"),
              ("zeta_hat", r"$\hat\zeta$ [-]", tr.zeta, r"$1/(\lambda g_2)$"),
              ("d_hat", r"$\hat d$ [-]", None, None))  # (estimate, axis label, true value)
    with saved(path, dpi, 2, 2, rc=RC, figsize=(8.4, 5.6), sharex=True) as (fig, axes):
        for ax, (key, ylabel, value, sym) in zip(axes.ravel(), panels, strict=True):
            for name in ("dsc", "backstepping"):
                traj = trajs[name]
                ax.plot(np.asarray(traj.t), estimates(traj)[key], label=LABELS[name], **STYLE[name])
            if value is not None:
                value = float(value)
                ax.axhline(value, color="#444444", lw=0.9, ls=":", label="true value")
                ax.annotate(f"{sym} = {value:.3g}", xy=(1.0, value),
                            xycoords=("axes fraction", "data"), xytext=(-4, 3),
                            textcoords="offset points", ha="right", va="bottom", fontsize=8,
                            color="#444444")
            ax.set_ylabel(ylabel)
            ax.margins(y=0.12)
        for ax in axes[1]:
            ax.set_xlabel(AXIS_LABEL["t"])
        legend_below(fig, axes[0, 0], ncol=3)
        fig.suptitle(r"Adaptive estimates of the DSC and of backstepping ($\hat\theta_2 \equiv 0$ "
                     r"because $f_2 = 0$; not shown)")
    return path


__all__ = ["FIGURES", "RC", "figures", "loop_figure"]
