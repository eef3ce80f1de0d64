"""The files of a worst-case search (`dscjax worst-case`, `dscjax.worst.worst_case`):

    worst.json            the metric, its value, the parameters by config path, the waveform
    worst_config.toml     a complete config of the worst case (`dscjax simulate --config`)
    worst_trajectory.npz  t, x, u, w, e at every step; t_half = k dt/2 and dbar on that grid
    report.md             each method's best value against search time
    worst_vs_nominal.png, worst_disturbance.png, search_progress.png
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from dscjax import config, files
from dscjax.disturbance import half_step_grid
from dscjax.markdown import table, window
from dscjax.plotting import AXIS_LABEL, saved
from dscjax.worst import Result, assumption_warnings, best_value

FILES = ("worst.json", "worst_config.toml", "worst_trajectory.npz", "report.md")
FIGURES = ("worst_vs_nominal.png", "worst_disturbance.png", "search_progress.png")
SHARES = (0.1, 0.25, 0.5, 1.0)  # report.md's best values at these shares of the search time


def summary(result: Result) -> dict:
    """The content of worst.json."""
    p = result.problem
    values, dist = p.values_at(result.z)
    return {
        "metric": p.metric,
        "value": result.value,  # +inf (null in strict JSON) if the loop diverges
        "diverged": result.diverged,
        "t_diverged": result.t_diverged,
        "refinements": result.refinements,
        "method": result.method,
        "parameters": values,
        "disturbance": dist,
        "nominal_value": result.nominal_value,
        "ranges": {r.name: [r.low, r.high] for r in p.ranges},
        "simulation": p.spec.to_table() | {"window_start": float(p.spec.window_start)},
        "methods": {m: {"best_value": best_value(tr),  # -inf (null) before a finite one
                        "evaluations": tr.evaluations, "iterations": tr.iterations,
                        "search_s": tr.seconds, "compile_s": tr.compile_seconds,
                        "diverged_candidates": len(tr.diverged_z)}
                    for m, tr in result.traces.items()},
        "info": result.info,
        "warnings": assumption_warnings(p),
    }


def write(result: Result, out: Path, plots: bool = True) -> list[str]:
    """Write every file of the module docstring into `out`; the names written."""

    out = Path(out)
    p = result.problem
    files.write_json(out / "worst.json", summary(result))
    found = verdict(result) if result.diverged else repr(result.value)
    header = (f"dscjax worst-case: the worst case of {p.metric} found: {found}\n"
              f"Reproduce: dscjax simulate --config worst_config.toml")
    # [simulation]: the run the user gave (not the search's metrics-only settings: it replays
    # as a whole trajectory), in the worst setup's dtype
    dtype = str(np.result_type(np.asarray(result.setup.plant.x0)))
    options = (p.options if p.options is not None else p.spec).replace(dtype=dtype)
    files.write_text(out / "worst_config.toml",
                     config.to_toml(result.setup, options, header=header))
    worst = result.trajectory
    dt_used = float(np.asarray(worst.dt))
    t_half = half_step_grid(p.spec.t_final, dt_used)
    dbar = np.asarray(jax.vmap(result.setup.plant.dbar)(t_half))
    files.write_npz(out / "worst_trajectory.npz", {
        **{k: getattr(worst, k) for k in ("t", "x", "u", "w", "e")}, "t_half": t_half,
        "dbar": dbar, "dt": dt_used})
    files.write_text(out / "report.md", report_md(result))
    if plots:
        _plot_worst(out / FIGURES[0], worst, result.nominal, result)
        _plot_disturbance(out / FIGURES[1], t_half, dbar, result)
        _plot_progress(out / FIGURES[2], result)
    return [*FILES, *(FIGURES if plots else ())]


def verdict(result: Result) -> str:
    """The worst value found (6 digits), or when the loop diverges."""
    return (f"the loop diverges at t = {result.t_diverged:.6g} s (at every refinement level)"
            if result.diverged else f"{result.value:.6g}")


def searched(problem) -> str:
    """The box and the waveform searched, e.g. "plant.g[1]=0.7:1.3 and fourier:2:0.5"."""
    return ((", ".join(r.spec() for r in problem.ranges) or "no parameter")
            + (f" and {problem.disturbance.spec()}" if problem.disturbance else ""))


def methods_table(result: Result) -> list[str]:
    """Each method's best value, evaluations, iterations and seconds (report.md and the
    console)."""
    return table(("method", "best value", "evaluations", "iterations", "search s", "compile s"),
                 [(m, f"{best_value(tr):.6g}", tr.evaluations, tr.iterations,
                   f"{tr.seconds:.1f}", f"{tr.compile_seconds:.1f}")
                  for m, tr in result.traces.items()])


def report_md(result: Result) -> str:
    p = result.problem
    warnings = assumption_warnings(p)
    lines = [f"# Worst case of {p.metric}", "",
             f"Worst value: **{verdict(result)}**, found by {result.method}; nominal: "
             f"{result.nominal_value:.6g}.", "",
             f"Horizon {p.spec.t_final:g} s, dt {float(p.spec.dt):g} s, window "
             f"{window(p.spec.window_start, p.spec.t_final)}. Searched: {searched(p)}.", "",
             *(f"Warning: {w}." for w in warnings), *([""] if warnings else []),
             "## Methods (equal search time; compilation apart)", "", *methods_table(result),
             "", "## Best value against search time", ""]
    rows = []
    for m, tr in result.traces.items():
        t, best = _curve(tr)
        at = np.searchsorted(t, np.array(SHARES) * (t[-1] if t.size else 0.0), side="right") - 1
        rows.append((m, *(f"{best[i]:.6g}" if i >= 0 else "-" for i in at)))
    lines += table(("method", *(f"{f:.0%} of time" for f in SHARES)), rows)
    lines += ["", "The tables hold the search's batch values; the worst value above is "
              "`simulate`'s (with refinement), as `dscjax simulate --config worst_config.toml` "
              "reproduces it.", ""]
    return "\n".join(lines)


def _curve(trace) -> tuple[np.ndarray, np.ndarray]:
    """(search seconds, best value so far) at the end of each iteration."""
    return (np.array([r["seconds"] for r in trace.history], dtype=float),
            -np.array([r["best_loss"] for r in trace.history], dtype=float))


def _plot_worst(path, worst, nominal, result):
    """worst_vs_nominal.png: e and u of the nominal and the worst case, one colour and line
    style per case in both panels, each panel with its legend. Returns the Figure."""
    with saved(path, 110, 2, 1, figsize=(9, 6), sharex=True) as (fig, ax):
        for traj, name, style, color in ((nominal, "nominal", "--", "#444444"),
                                         (worst, "worst case", "-", "#d62728")):
            t = np.asarray(traj.t)
            for a, signal in zip(ax, (traj.e, traj.u), strict=True):
                a.plot(t, np.asarray(signal), ls=style, lw=1.0, label=name, color=color)
        for a, signal in zip(ax, "eu", strict=True):
            a.set_ylabel(AXIS_LABEL[signal])
            a.legend(loc="upper right")
        ax[1].set_xlabel(AXIS_LABEL["t"])
        ax[0].set_title(f"worst case of {result.problem.metric}: {result.value:.4g} "
                        f"(nominal {result.nominal_value:.4g})")
    return fig


def _plot_disturbance(path, t_half, dbar, result):
    with saved(path, 110, figsize=(9, 3.2)) as (fig, ax):
        ax.plot(t_half, dbar, lw=1.0, color="#d62728")
        spec = result.problem.disturbance
        if spec is not None:
            for s in (-1, 1):
                ax.axhline(s * spec.bound, color="#444444", ls=":", lw=0.8)
        ax.set_xlabel(AXIS_LABEL["t"])
        ax.set_ylabel(r"$\bar d(t)$ [-]")
        ax.set_title("worst disturbance" + (f" ({spec.spec()})" if spec else ""))


def _plot_progress(path, result):
    with saved(path, 110, figsize=(7, 4)) as (fig, ax):
        for m, tr in result.traces.items():
            ax.step(*_curve(tr), where="post", label=m)
        ax.set_xlabel("search time [s]")
        ax.set_ylabel(f"best {result.problem.metric}")
        ax.legend()


__all__ = ["FILES", "FIGURES", "methods_table", "report_md", "searched", "summary",
           "verdict", "write"]
