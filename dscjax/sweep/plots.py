"""Figures of a sweep: histogram and heatmap of the windowed L-inf error, worst-case traces.

Every function writes one PNG (`dscjax.plotting.saved`: no backend is chosen or changed).
"""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib
import numpy as np
from matplotlib.colors import LogNorm, Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from dscjax.params import Param
from dscjax.plotting import AXIS_LABEL, GRID, diverged_at_top, legend_below, saved, until_divergence

_SYMBOLS = {
    "hysteresis.alpha": "α", "hysteresis.lam": "λ", "hysteresis.psi": "ψ",
    "hysteresis.w0": "w(0)", "plant.dbar_amp": "disturbance amplitude",
    "plant.dbar_bias": "disturbance bias", "plant.dbar_freq": "disturbance frequency [rad/s]",
    "plant.delta_freq": "Δ frequency [rad/s]",
}
_VECTOR = {"plant.g": "g_{}", "plant.theta": "θ_{}", "plant.x0": "x_{}(0)", "controller.k": "k_{}"}


def param_label(name: str) -> str:
    """'α (hysteresis.alpha)', 'g_2 (plant.g[1])', ..."""
    p = Param.parse(name)
    sym = (_VECTOR[p.path].format(p.index + 1) if p.path in _VECTOR and p.index is not None
           else _SYMBOLS.get(name))
    return f"{sym}  ({name})" if sym else name


def error_label(t0: float, t_final: float) -> str:
    return f"windowed L∞ error  max |y − y_r| over [{t0:g} s, {t_final:g} s]"


# A colour scale whose span is below this fraction of the median is called out in the title.
NARROW = 0.1


def _spread(v: np.ndarray) -> tuple[str, float | None]:
    """How wide the colour scale of the finite values v is, in words, and that span relative
    to their median (None unless the median is > 0): a narrow scale (say 0.0221-0.0226)
    paints 2 % differences as the whole colour range."""
    lo, hi, med = v.min(), v.max(), np.median(v)
    rel = (hi - lo) / med if med > 0 else None
    if rel is None or hi <= lo:
        return f"colours span {lo:.3g} to {hi:.3g}", rel
    return (f"colours span {lo:.3g} to {hi:.3g} = "
            + (f"{100 * rel:.2g} % of the median" if rel < 10 else f"a factor {hi / lo:.3g}"),
            rel)


def _use_log(v) -> bool:
    v = v[np.isfinite(v) & (v > 0)]
    return v.size > 1 and v.max() / v.min() > 20


def plot_histogram(err, diverged, path, *, t0, t_final, nominal, threshold, title,
                   refined) -> None:
    """Histogram of the windowed L-inf error of the samples that did not diverge; those that
    tracked only after refinement (`refined`: a smaller step / ETDRK4) stacked in orange."""
    err = np.asarray(err, np.float64)
    div = np.asarray(diverged, bool)
    ref = np.asarray(refined, bool) & ~div
    keep = ~div & np.isfinite(err)
    v = err[keep]
    with saved(path, 110, rc=GRID, figsize=(8, 5.4)) as (fig, ax):
        if v.size:
            log = _use_log(v)
            lo, hi = (v[v > 0].min(), v.max()) if log else (v.min(), v.max())
            if hi <= lo:
                hi = lo * 1.01 + 1e-12
            bins = (np.geomspace(lo, hi, 61) if log else np.linspace(lo, hi, 61))
            plain, after = err[keep & ~ref], err[keep & ref]
            ax.hist([plain, after], bins=bins, color=["#1f77b4", "#ff7f0e"], alpha=0.85,
                    stacked=True, label=[f"samples that track ({plain.size:,})",
                                         f"tracked after refinement ({after.size:,})"])
            if log:
                ax.set_xscale("log")
            ax.axvline(np.median(v), color="#444444", lw=1.2, ls="-",
                       label=f"median {np.median(v):.3g}")
        if np.isfinite(nominal):
            ax.axvline(nominal, color="black", lw=1.5, ls="--",
                       label=f"nominal setup {nominal:.3g}")
        label = f"degraded above {threshold:.3g} ({int(np.sum(v > threshold)):,} samples)"
        if v.size and threshold > v.max() + 0.5 * (v.max() - v.min()):
            # far to the right of every sample: say so instead of squashing the histogram
            ax.plot([], [], color="#d62728", lw=1.5, ls=":", label=label + ", off the axis")
        else:
            ax.axvline(threshold, color="#d62728", lw=1.5, ls=":", label=label)
        ax.set_xlabel(error_label(t0, t_final))
        ax.set_ylabel("number of samples")
        ax.set_title((f"{title}\n" if title else "") + f"{int(div.sum()):,} diverged at every step "
                     f"tried ({100 * div.mean():.2f} %, not shown)", fontsize=10)
        legend_below(fig, ax, 2, fontsize=8)


def heatmap_grid(x, y, err, diverged, *, grid_x=None, grid_y=None):
    """Median windowed error per cell (diverged: +inf), the edges, the samples per cell and
    the cells where a sample diverged: one cell per grid point with grid_x/grid_y, else b x b
    cells (4 <= b <= 40, about 8 samples a cell)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    div = np.asarray(diverged, bool)
    e = np.where(div, np.inf, np.asarray(err, np.float64))
    if grid_x is not None and grid_y is not None:
        ex, ey = _edges_of(grid_x), _edges_of(grid_y)
    else:
        b = int(np.clip(np.sqrt(x.size / 8.0), 4, 40))
        ex, ey = (np.linspace(v.min(), v.max(), b + 1) for v in (x, y))
    nx, ny = len(ex) - 1, len(ey) - 1
    ix = np.clip(np.searchsorted(ex, x, side="right") - 1, 0, nx - 1)
    iy = np.clip(np.searchsorted(ey, y, side="right") - 1, 0, ny - 1)
    flat = ix * ny + iy
    count = np.bincount(flat, minlength=nx * ny)
    cells = np.split(e[np.argsort(flat, kind="stable")], np.cumsum(count)[:-1])  # cell by cell
    med = np.array([np.median(v) if v.size else np.nan for v in cells])
    div_cells = np.bincount(flat[div], minlength=nx * ny) > 0
    return med.reshape(nx, ny), ex, ey, count.reshape(nx, ny), div_cells.reshape(nx, ny)


def _edges_of(values):
    v = np.unique(np.asarray(values, np.float64))
    if v.size == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def plot_heatmap(x, y, err, diverged, path, *, names, t0, t_final, threshold, nominal_xy,
                 title, refined, grid_x=None, grid_y=None) -> dict:
    """Heatmap of the median windowed L-inf error over two parameters (hatched: a sample
    diverged at every step tried; red: median above `threshold`; x diverged, o `refined`
    samples); returns the cell statistics."""
    med, ex, ey, count, div_cells = heatmap_grid(x, y, err, diverged, grid_x=grid_x, grid_y=grid_y)
    div = np.asarray(diverged, bool)
    ref = np.asarray(refined, bool) & ~div
    finite = med[np.isfinite(med)]
    spread, rel = _spread(finite) if finite.size else (None, None)
    with saved(path, 110, figsize=(8, 6.6)) as (fig, ax):
        if finite.size:
            norm = (LogNorm(finite[finite > 0].min(), finite.max()) if _use_log(finite)
                    else Normalize(finite.min(), finite.max() if finite.max() > finite.min()
                                   else finite.min() + 1e-12))
        else:
            norm = Normalize(0, 1)
        shown = np.where(np.isfinite(med), med, np.nan)
        cmap = matplotlib.colormaps["viridis"].with_extremes(bad="#dddddd")
        mesh = ax.pcolormesh(ex, ey, shown.T, cmap=cmap, norm=norm, shading="flat")
        cb = fig.colorbar(mesh, ax=ax, pad=0.02)
        cb.set_label(f"cell median of max |y − y_r| on [{t0:g} s, {t_final:g} s]"
                     + ("\n" + spread if spread else ""), fontsize=9)
        hx, hy = np.repeat(ex, 2)[1:-1], np.repeat(ey, 2)[1:-1]
        xc, yc = 0.5 * (ex[1:] + ex[:-1]), 0.5 * (ey[1:] + ey[:-1])
        bad = ~(med <= threshold) & (count > 0)  # NaN-safe: diverged medians are inf
        if bad.any() and len(xc) > 1 and len(yc) > 1:
            ax.contour(xc, yc, bad.T.astype(float), levels=[0.5], colors="#d62728", linewidths=1.8)
        handles = [Line2D([], [], color="#d62728", lw=1.8,
                          label=f"tracking degraded: cell median > {threshold:.3g}"
                          f" ({int(bad.sum())} of {int((count > 0).sum())} cells)")]
        if div_cells.any():
            # hatch exactly the cells where a sample diverged at every step tried
            z = np.repeat(np.repeat(div_cells.astype(float), 2, axis=0), 2, axis=1)
            hatch = ax.contourf(hx, hy, z.T, levels=[0.5, 1.5], colors="none", hatches=["////"])
            hatch.set_edgecolor("#7f0000")
            hatch.set_linewidth(0.0)
            handles.append(Patch(facecolor="none", edgecolor="#7f0000", hatch="///",
                                 label=f"diverged at every step tried ({int(div_cells.sum())} "
                                 f"cells)"))
        # the refined and the diverged samples (at most 2000 of each, a seeded draw)
        for mask, style, handle in (
                (ref, dict(marker="o", s=10, facecolors="none", edgecolors="#ff7f0e", lw=0.7),
                 Line2D([], [], marker="o", ls="", mfc="none", color="#ff7f0e",
                        label=f"tracked after refinement ({int(ref.sum()):,} samples: stiff at "
                        "dt, re-run with ETDRK4)")),
                (div, dict(marker="x", s=14, c="#d62728", lw=0.8),
                 Line2D([], [], marker="x", ls="", color="#d62728",
                        label=f"diverged sample ({int(div.sum()):,})"))):
            idx = np.flatnonzero(mask)
            if idx.size > 2000:
                idx = np.random.default_rng(0).choice(idx, 2000, replace=False)
            if idx.size:
                ax.scatter(np.asarray(x)[idx], np.asarray(y)[idx], **style)
                handles.append(handle)
        ax.plot(*nominal_xy, marker="*", ms=15, mfc="white", mec="black", ls="")
        handles.append(Line2D([], [], marker="*", ms=12, mfc="white", mec="black", ls="",
                              label="nominal setup"))
        ax.set_xlim(ex[0], ex[-1])
        ax.set_ylim(ey[0], ey[-1])
        ax.set_xlabel(param_label(names[0]))
        ax.set_ylabel(param_label(names[1]))
        kind = "grid points" if grid_x is not None else f"{len(ex) - 1} x {len(ey) - 1} bins"
        narrow = (f"\nnote: the colour scale spans only {100 * rel:.2g} % of the median: the "
                  "cells differ little") if rel is not None and rel < NARROW else ""
        ax.set_title((f"{title}\n" if title else "") + f"windowed L∞ error over {kind}; other "
                     "swept parameters pooled" + narrow, fontsize=10)
        legend_below(fig, ax, 1, handles, fontsize=8)
    return {"x": names[0], "y": names[1], "x_edges": ex.tolist(), "y_edges": ey.tolist(),
            "median": np.where(np.isfinite(med), med, None).tolist(),
            "count": count.tolist(), "degraded_cells": int(bad.sum()),
            "diverged_cells": int(div_cells.sum()), "refined_samples": int(ref.sum()),
            "colour_scale": spread}


def plot_scan(x, err, diverged, path, *, name, t0, t_final, threshold, nominal_x,
              title) -> None:
    """One swept parameter: the windowed L-inf error against it (the 1-D 'heatmap')."""
    x, err = np.asarray(x), np.asarray(err, np.float64)
    div = np.asarray(diverged, bool)
    with saved(path, 110, rc=GRID, figsize=(8, 4.8)) as (fig, ax):
        ax.plot(x[~div], err[~div], ".", ms=3, color="#1f77b4", label="sample")
        diverged_at_top(ax, x, err, div, color="#d62728",
                        label=f"diverged ({int(div.sum())}), drawn at the top")
        ax.axhline(threshold, color="#d62728", ls=":", label=f"degraded above {threshold:.3g}")
        ax.axvline(nominal_x, color="black", ls="--", lw=1, label="nominal value")
        if _use_log(err[~div]):
            ax.set_yscale("log")
        ax.set_xlabel(param_label(name))
        ax.set_ylabel(error_label(t0, t_final).replace("windowed L∞ error  ", "L∞ error "))
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8)


def plot_traces(trajs: Sequence, labels: Sequence[str], kinds: Sequence[str], path, *,
                nominal, t0, title) -> None:
    """Tracking error e(t) and control u(t) of the worst samples (colour; dotted and ending
    in x where they diverged) and a random handful (grey), with the nominal setup (black
    dashed)."""
    with saved(path, 110, 2, 1, rc=GRID, figsize=(11, 7), sharex=True) as (fig, ax):
        colors = matplotlib.colormaps["tab10"].colors
        k = 0
        for tr, lab, kind in zip(trajs, labels, kinds, strict=True):
            t, signals, t_bad = until_divergence(tr, ("e", "u"))
            if kind == "random":
                style = dict(color="#999999", lw=0.8, alpha=0.8)
            else:
                style = dict(color=colors[k % 10], lw=1.1, ls="-" if kind == "worst" else ":")
                k += 1
            ax[0].plot(t, signals["e"], label=lab, **style)
            ax[1].plot(t, signals["u"], **style)
            if t_bad is not None:
                drawn = t <= t_bad
                ax[0].plot(t[drawn][-1:], signals["e"][drawn][-1:], "x", ms=8, color=style["color"])
        for a, signal in zip(ax, (nominal.e, nominal.u), strict=True):
            a.plot(np.asarray(nominal.t), np.asarray(signal), "k--", lw=1.2, label="nominal setup")
            a.axvline(t0, color="#bbbbbb", lw=0.8, ls=":")
        ax[0].annotate("window starts", (t0, 1.0), xycoords=("data", "axes fraction"),
                       xytext=(3, -12), textcoords="offset points", fontsize=8, color="#777777")
        ax[0].set_ylabel(AXIS_LABEL["e"])
        ax[1].set_ylabel(AXIS_LABEL["u"])
        ax[1].set_xlabel(AXIS_LABEL["t"])
        ax[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
        fig.suptitle(title, fontsize=11)


def trace_label(record: dict, names: Sequence[str], kind: str) -> str:
    """'worst #123: α=0.81 λ=1.2 ψ=0.09 | L∞w 0.012' (short, for the legend)."""
    parts = [f"{param_label(n).split('  (')[0]}={record['params'][n]:.3g}" for n in names[:4]]
    tail = (f"diverged at {record['t_diverged']:.3g} s" if record["diverged"]
            else f"L∞ on window {record['metrics']['linf_error_window']:.3g}")
    return f"{kind} #{record['sample']}: " + " ".join(parts) + f" | {tail}"


__all__ = ["heatmap_grid", "param_label", "plot_heatmap", "plot_histogram", "plot_scan",
           "plot_traces", "trace_label"]
