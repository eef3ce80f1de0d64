"""Plots of trajectories, and the one way dscjax makes a figure.

Every figure of the project is a `matplotlib.figure.Figure` made by `saved` below (made,
styled and saved in one `with` block): the object API, never pyplot, so no backend is chosen or
changed and no global state (a notebook's display backend, its rcParams) is touched; styles
apply through `matplotlib.rc_context` (`GRID`, the light grid of the figures that have one).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from dscjax import files

# One colour per signal across every figure of the project.
COLORS = {"y": "#1f77b4", "yr": "#444444", "e": "#d62728", "u": "#2ca02c", "w": "#9467bd",
          "x": ("#1f77b4", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f",
                "#aec7e8")}
# The axis label of each signal, and of time, in every figure that draws it.
AXIS_LABEL = {"t": "time $t$ [s]", "e": "tracking error $e = y - y_r$ [-]",
              "u": "control input $u$ [-]", "w": "hysteresis output $w$ [-]"}
# The light grid of every figure that has one: a style for `saved`'s rc.
GRID = {"axes.grid": True, "grid.alpha": 0.3}
LOG_GRID = GRID | {"axes.grid.which": "both"}  # lines at the minor ticks too (log axes)


@contextlib.contextmanager
def saved(path: Path | str, dpi: int | None, nrows: int = 1, ncols: int = 1, *, figsize, rc=None,
          **kwargs):
    """(Figure, axes) like `pyplot.subplots` for the block, but a Figure no pyplot state knows
    about (it needs no backend), in the constrained layout, saved to `path` at `dpi` (None: the
    figure's own, matplotlib's default) when the block ends; the block and the saving under the
    style `rc` (`matplotlib.rc_context`), where given."""
    import matplotlib
    from matplotlib.figure import Figure

    with matplotlib.rc_context(rc):
        fig = Figure(figsize=figsize, layout="constrained")
        yield fig, fig.subplots(nrows, ncols, **kwargs)
        files.save_figure(fig, path, dpi=dpi)


def hysteresis_loop(ax, hysteresis, u, w, label: str, color: str = COLORS["w"],
                    lines: bool = True) -> None:
    """One w(u) loop of a hysteresis model on `ax` (`dscjax hysteresis`, `dscjax reproduce`'s
    Fig. 1 of every model), with, if `lines`, the lines w = lam_eff u + d_1 limits between
    which the model's decomposition (eqs. 5, 9-12) keeps it for large |u|."""
    if lines:
        lam = float(hysteresis.effective_slope())
        lo, hi = (float(x) for x in hysteresis.d1_limits())
        ug = np.linspace(-np.max(np.abs(u)), np.max(np.abs(u)), 2)
        for d1, name in ((lo, f"$w = {lam:.3g}\\,u + d_1$ limits"), (hi, None)):
            ax.plot(ug, lam * ug + d1, color="#999999", lw=0.8, ls=":", label=name)
    ax.plot(u, w, color=color, lw=1.4, label=label)
    ax.set_xlabel(AXIS_LABEL["u"])


def legend_below(fig, ax, ncol: int | None = None, handles=None, **kwargs) -> None:
    """The legend of `ax`'s curves (or of `handles`, the artists to list) outside the axes,
    under them (it can never hide a curve), in `ncol` columns (None: all in one row)."""
    handles = handles or ax.get_legend_handles_labels()[0]
    fig.legend(handles=handles, loc="outside lower center", ncol=ncol or len(handles),
               frameon=False, **kwargs)


def until_divergence(traj, keys) -> tuple[np.ndarray, dict, float | None]:
    """(t, {key: the signal `traj.key` as floats}, the divergence time, None if none) of a
    run, a diverged run's signals NaN after its divergence (the state is frozen afterwards:
    nothing to show)."""
    t = np.asarray(traj.t)
    signals = {k: np.array(getattr(traj, k), dtype=float) for k in keys}
    if not bool(np.asarray(traj.diverged)):
        return t, signals, None
    t_bad = float(np.asarray(traj.t_diverged))
    for v in signals.values():
        v[t > t_bad] = np.nan
    return t, signals, t_bad


def diverged_at_top(ax, x, v, diverged, **style) -> None:
    """The points x[diverged] (they have no value) as crosses at the top of the others' values
    v (at 1.0 where every point diverged), in `style`."""
    if diverged.any():
        top = np.nanmax(v[~diverged]) if (~diverged).any() else 1.0
        ax.plot(x[diverged], np.full(diverged.sum(), top), "x", **style)


def plot_trajectory(traj, path: Path | str, title: str = ""):
    """The Figure (saved to `path`) of four panels: states against the reference, tracking
    error, u, w; a diverged run drawn up to its marked divergence."""
    t, signals, t_bad = until_divergence(traj, ("x", "yr", "e", "u", "w"))
    with saved(path, 110, 2, 2, rc=GRID, figsize=(10, 7), sharex=True) as (fig, ax):
        ax[0, 0].plot(t, signals["yr"], color=COLORS["yr"], lw=1.2, ls="--",
                      label="reference $y_r$")
        for i, xi in enumerate(signals["x"].T):
            ax[0, 0].plot(t, xi, color=COLORS["x"][i % len(COLORS["x"])], lw=1.0,
                          label=f"$x_{i + 1}$" + (" = output y" if i == 0 else ""))
        for a, key in zip(ax.ravel()[1:], "euw", strict=True):
            a.plot(t, signals[key], color=COLORS[key], lw=1.0)
        for a, label, panel in (
                (ax[0, 0], "state $x_i$, reference $y_r$ [-]", "states against the reference"),
                (ax[0, 1], AXIS_LABEL["e"], "tracking error"),
                (ax[1, 0], AXIS_LABEL["u"], "control input"),
                (ax[1, 1], AXIS_LABEL["w"], "hysteresis output")):
            a.set_ylabel(label)
            a.set_title(panel)
            a.set_xlim(t[0], t[-1])  # the whole horizon, also where a diverged run is not drawn
            if t_bad is not None:
                a.axvline(t_bad, color="#d62728", lw=1.0, ls=":",
                          label=f"diverged at t = {t_bad:.4g} s (frozen afterwards, not drawn)")
        for a in ax[1]:
            a.set_xlabel(AXIS_LABEL["t"])
        legend_below(fig, ax[0, 0], fontsize=9)
        if title:
            fig.suptitle(title)
    return fig
