"""The paper's simulation study (Section 4) in one call: Figures 1-6, the adaptive estimates, a
summary of every run and a check of each claim the paper makes from its figures.

    import dscjax.reproduce
    summary = dscjax.reproduce.reproduce("results/paper")

Runs (all on the paper's example, eq. 73, with the readings of docs/paper-readings.md):
    dsc                  the DSC with hysteresis compensation, eqs. (13)-(32)
    dsc_no_dhat          "without considering hysteresis", reading A: d_hat = 0 (no robust term)
    dsc_no_dhat_no_zeta  reading B: also zeta_hat = 1, so u = ubar
    backstepping         adaptive backstepping with the same gains (controllers/backstepping.py)

Colours identify the run and are the same in every figure (`STYLE`); Fig. 1, which has no
controller, uses the hysteresis output's colour of `plotting.COLORS`.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import files
from dscjax.controllers.backstepping import with_backstepping
from dscjax.examples import paper_example
from dscjax.integrate import rk4_step
from dscjax.plotting import COLORS, subplots
from dscjax.simulate import divergence_report, simulate

RUNS = ("dsc", "dsc_no_dhat", "dsc_no_dhat_no_zeta", "backstepping")
# Defaults of `reproduce` (and of `dscjax reproduce`): 20 s horizon, RK4 step 1 ms (the paper
# gives neither), PNG figures at 150 dpi, complexity study n = 2..8 with 3 builds per law.
T_FINAL = 20.0
DT = 1e-3
DPI = 150
COMPLEXITY_ORDERS = tuple(range(2, 9))
COMPLEXITY_REPEATS = 3
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
FIGURES = {
    "fig1": "fig1_hysteresis",
    "fig2": "fig2_compensation",
    "fig3": "fig3_dsc_control",
    "fig4": "fig4_dsc_hysteresis_output",
    "fig5": "fig5_backstepping_error",
    "fig6": "fig6_backstepping_control",
    "estimates": "fig_estimates",
    "complexity": "fig_complexity",
}
METRIC_FIELDS = ("linf_error", "linf_error_after_1s", "l2_error", "l2_error_after_1s",
                 "max_abs_u", "max_abs_u_after_1s", "max_abs_w", "tv_u")
ESTIMATES = ("theta_hat_g1", "theta_hat_2", "phi_hat_1", "zeta_hat", "d_hat")

# Two controllers "track alike" when their errors (after the first second) are within this
# factor of each other, in both the L-infinity and the L2 norm. The paper gives no number.
ALIKE_FACTOR = 2.0
# "Smaller control amplitude" by less than this relative margin is reported as marginal: the
# claim holds to the letter but a reader of two plots would call the amplitudes equal.
AMPLITUDE_MARGIN = 0.05

INTERPRETATIONS = [
    "Gains: the text prints 'k_1 = 10, k_1 = 0.45'; read k_1 = 10, k_2 = 0.45 (= 1/4 + alpha_0 "
    "with alpha_0 = 0.2, eq. 55).",
    "Not given and irrelevant because f_2 = 0: gamma_g2 = 8, eta_2 = 0.01, theta_hat_2(0) = 0.",
    "w(0) = 0 (not given). Horizon 20 s (not given). RK4 with dt = 1e-3 s (the paper gives no "
    "solver).",
    "sgn(S_2) is replaced by sat(S_2/0.01), as the paper's simulation says; |S_2| in (32) is "
    "kept exact.",
    "In the rho_n term of (30) there is no 1/g_min (as printed).",
    "The example does not use the L-infinity initialisation (67)-(68): the initial estimates "
    "are those of Section 4 and S_1(0) = x_1(0) - y_r(0) = 0.08.",
    "In (6) the printed sgn(u) is read as sgn(u') (Su et al. 2000); in the closed loop u' is the "
    "exact derivative of the control law along the vector field (one forward-mode derivative).",
    "Fig. 2 'without considering the effect of hysteresis' has two readings: A drops the robust "
    "term (d_hat = 0); B also freezes zeta_hat = 1 so that u = ubar. Both are shown.",
    "Eq. (79), the backstepping law, is garbled. The baseline is standard adaptive backstepping "
    "with the DSC's parameterisation, robust term and adaptive laws (S_i -> z_i, z_i' -> "
    "alpha_(i-1)'), z_2 = x_2 - alpha_1 with no filter and no c_2, and alpha_1' exact by the chain "
    "rule along the nominal model x_1' = g_nom (x_2 + theta_hat_g1 f_1), g_nom = g_min = 1, "
    "computed by automatic differentiation.",
    "The backstepping law has no cross term -z_1 in alpha_2 and no damping term for the "
    "mismatch between the nominal and the true x_1' ((79) has neither).",
    f"'Track alike' is read as: errors after the first second within a factor {ALIKE_FACTOR:g} "
    "of each other in both L-infinity and L2. 'Control amplitude' is read as max |u| over the "
    "whole horizon (also reported after the first second); a DSC amplitude smaller by less "
    f"than {100 * AMPLITUDE_MARGIN:g} % is reported as marginal.",
]


def setups(dtype=None) -> dict:
    """The four closed loops of the study, by run name."""
    return {
        "dsc": paper_example(dtype=dtype),
        "dsc_no_dhat": paper_example(variant="no_dhat", dtype=dtype),
        "dsc_no_dhat_no_zeta": paper_example(variant="no_dhat_no_zeta", dtype=dtype),
        "backstepping": with_backstepping(paper_example(dtype=dtype)),
    }


# -- Fig. 1 ------------------------------------------------------------------------------------


def hysteresis_loops(amplitudes: Sequence[float] = (3.5, 6.5), omega: float = 2.3,
                     t_final: float = 3 * 2 * math.pi / 2.3, dt: float = 1e-3) -> dict:
    """w(t) of eq. (4) for u = k sin(omega t), integrated by RK4 from w(0) = 0 (Fig. 1).

    Returns {k: (t, u, w)} as NumPy arrays.
    """
    hyst = paper_example().hysteresis
    n_steps = int(round(t_final / dt))

    def rate(t, w, k):
        u, du = k * jnp.sin(omega * t), k * omega * jnp.cos(omega * t)
        return hyst.rate(u, du, w)

    @jax.jit
    def loop(k):
        def step(w, i):
            t = i * dt
            return rk4_step(rate, t, w, dt, k), w

        w_end, ws = jax.lax.scan(step, jnp.zeros(()), jnp.arange(n_steps))
        return jnp.append(ws, w_end)

    t = np.arange(n_steps + 1) * dt
    return {k: (t, k * np.sin(omega * t), np.asarray(loop(jnp.asarray(k)))) for k in amplitudes}


# -- running the study -------------------------------------------------------------------------


def _metrics(traj, window_start: float) -> dict:
    m = {k: float(v) for k, v in traj.metrics.items()}
    t, u = np.asarray(traj.t), np.asarray(traj.u)
    return dict(
        linf_error=m["linf_error"], linf_error_after_1s=m["linf_error_window"],
        l2_error=m["l2_error"], l2_error_after_1s=m["l2_error_window"],
        max_abs_u=m["max_abs_u"], max_abs_u_after_1s=float(np.max(np.abs(u[t >= window_start]))),
        max_abs_w=m["max_abs_w"], tv_u=m["tv_u"],
    )


def _estimates(traj) -> dict[str, np.ndarray]:
    c = traj.ctrl
    return {
        "theta_hat_g1": np.asarray(c.theta_hat[:, 0]), "theta_hat_2": np.asarray(c.theta_hat[:, 1]),
        "phi_hat_1": np.asarray(c.phi_hat[:, 0]), "zeta_hat": np.asarray(c.zeta_hat),
        "d_hat": np.asarray(c.d_hat),
    }


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


def summarize(trajs: dict, t_final: float, dt: float) -> dict:
    """Metrics of every run, the estimates' ranges and the check of every claim."""
    window = 1.0 if t_final > 1.0 else 0.0
    runs = {}
    for name, traj in trajs.items():
        est = _estimates(traj)
        runs[name] = dict(
            label=LABELS[name], **_metrics(traj, window), diverged=bool(traj.diverged),
            t_diverged=float(traj.t_diverged) if bool(traj.diverged) else None,
            estimates={k: dict(min=float(v.min()), max=float(v.max()), final=float(v[-1]))
                       for k, v in est.items()},
        )
    return dict(
        paper="Robust adaptive DSC for nonlinear systems with hysteresis input, Acta Automatica "
              "Sinica 2010, Section 4 (eq. 73)",
        t_final=t_final, dt=dt, window_start=window, runs=runs, claims=check_claims(runs),
        interpretations=INTERPRETATIONS, alike_factor=ALIKE_FACTOR,
        amplitude_margin=AMPLITUDE_MARGIN,
    )


def _ratio(a, b):
    return a / b if b else float("inf")


def check_claims(runs: dict, complexity: dict | None = None) -> list[dict]:
    """Each claim of the paper: what the paper shows, what we measured, whether it holds."""
    d, b = runs["dsc"], runs["backstepping"]
    claims = []
    for reading, key in (("A (d_hat = 0)", "dsc_no_dhat"),
                         ("B (d_hat = 0, zeta_hat = 1)", "dsc_no_dhat_no_zeta")):
        r = runs[key]
        q_inf = _ratio(r["linf_error_after_1s"], d["linf_error_after_1s"])
        q_2 = _ratio(r["l2_error_after_1s"], d["l2_error_after_1s"])
        claims.append(dict(
            id=f"compensation_improves_tracking_{key.removeprefix('dsc_')}",
            claim=f"Tracking is poor once hysteresis compensation is ignored, reading {reading}",
            paper="Fig. 2: the error without compensation (dashed) is visibly larger than with it",
            measured=f"error after 1 s without / with compensation: L-inf x{q_inf:.2f}, "
                     f"L2 x{q_2:.2f}",
            ratio_linf=q_inf, ratio_l2=q_2, holds=bool(q_inf > 1.0 and q_2 > 1.0)))
    q_inf = _ratio(b["linf_error_after_1s"], d["linf_error_after_1s"])
    q_2 = _ratio(b["l2_error_after_1s"], d["l2_error_after_1s"])
    alike = all(1.0 / ALIKE_FACTOR <= q <= ALIKE_FACTOR for q in (q_inf, q_2))
    claims.append(dict(
        id="dsc_and_backstepping_track_alike",
        claim="DSC and backstepping have similar tracking performance",
        paper="Figs. 2 and 5: tracking errors of similar size",
        measured=f"error after 1 s backstepping / DSC: L-inf x{q_inf:.2f}, L2 x{q_2:.2f} "
                 f"(alike: within x{ALIKE_FACTOR:g})",
        ratio_linf=q_inf, ratio_l2=q_2, holds=bool(alike)))
    q_u = _ratio(b["max_abs_u"], d["max_abs_u"])
    q_u1 = _ratio(b["max_abs_u_after_1s"], d["max_abs_u_after_1s"])
    claims.append(dict(
        id="dsc_smaller_control_amplitude",
        claim="The DSC needs a smaller control amplitude than backstepping",
        paper="Figs. 3 and 6: the DSC's u has the smaller amplitude",
        measured=f"max abs u: DSC {d['max_abs_u']:.3f}, backstepping {b['max_abs_u']:.3f} "
                 f"(backstepping {100 * (q_u - 1):+.1f} %); after 1 s: "
                 f"{d['max_abs_u_after_1s']:.3f} vs {b['max_abs_u_after_1s']:.3f} "
                 f"({100 * (q_u1 - 1):+.1f} %)",
        ratio_max_u=q_u, ratio_max_u_after_1s=q_u1, holds=bool(q_u > 1.0),
        verdict="yes" if q_u > 1.0 + AMPLITUDE_MARGIN else (
            f"marginal (within {100 * AMPLITUDE_MARGIN:g} %)" if q_u > 1.0 else "no")))
    bounded = {name: not r["diverged"] and all(
        math.isfinite(e["min"]) and math.isfinite(e["max"]) for e in r["estimates"].values())
        for name, r in runs.items()}
    est_max = max(max(abs(e["min"]), abs(e["max"])) for r in runs.values()
                  for e in r["estimates"].values())
    claims.append(dict(
        id="signals_bounded",
        claim="All closed-loop signals stay bounded (Theorem 1)",
        paper="Theorem 1; the figures show bounded u and w",
        measured=f"no run diverged: {all(bounded.values())}; largest estimate in magnitude "
                 f"{est_max:.3g}",
        holds=bool(all(bounded.values()))))
    if complexity is not None:
        claims.append(complexity_claim(complexity))
    for c in claims:
        c.setdefault("verdict", "yes" if c["holds"] else "no")
    return claims


def _growth_text(fit: dict) -> str:
    if fit["r2_geometric"] >= fit["r2_power"]:
        return f"x{fit['ratio_per_order']:.2f} per order"
    return f"~ n^{fit['exponent']:.2f}"


def complexity_claim(result: dict) -> dict:
    fd, fb = result["fits"]["dsc"]["eqns"], result["fits"]["backstepping"]["eqns"]
    holds = (fb["ratio_per_order"] >= 2.0 and fb["r2_geometric"] >= fb["r2_power"]
             and fd["exponent"] <= 1.5)
    rows = result["rows"]
    n_max = max(result["orders"])
    eq = {r["controller"]: r["eqns"] for r in rows if r["n"] == n_max}
    return dict(
        id="dsc_removes_explosion_of_complexity",
        claim="The DSC eliminates backstepping's explosion of complexity",
        paper="Asserted (Introduction, Remarks 4 and 6), never measured",
        measured=f"jaxpr equations of the law, n = {min(result['orders'])}..{n_max}: "
                 f"DSC {_growth_text(fd)}, backstepping {_growth_text(fb)}; at n = {n_max}: "
                 f"{eq.get('dsc')} vs {eq.get('backstepping')}",
        dsc_eqns_exponent=fd["exponent"], backstepping_eqns_ratio=fb["ratio_per_order"],
        holds=bool(holds))


# -- figures -----------------------------------------------------------------------------------


# The style of the paper's figures, applied with matplotlib.rc_context (never globally).
RC = {"font.size": 10, "axes.titlesize": 10, "legend.fontsize": 8.5, "axes.grid": True,
      "grid.alpha": 0.3}


def _finish(fig, out: Path, stem: str, fmt: str, dpi: int) -> Path:
    path = out / f"{stem}.{fmt}"
    fig.savefig(path, dpi=dpi)
    return path


def _time_axes(title: str, ylabel: str):
    fig, ax = subplots(figsize=(6.4, 3.8), layout="constrained")
    ax.set_xlabel("time $t$ [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    return fig, ax


def _time_axes_after(title: str, ylabel: str, t_after: float):
    """Two panels: the whole horizon, and t >= t_after, where the first second's peak no
    longer sets the scale."""
    fig, (ax, zoom) = subplots(2, 1, figsize=(6.4, 5.6), layout="constrained")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    zoom.set_xlabel("time $t$ [s]")
    zoom.set_ylabel(ylabel)
    zoom.set_title(f"after the first {t_after:g} s (the initial peak left out)", fontsize=9)
    return fig, ax, zoom


def _line_after(ax, traj, signal, name, t_after, **over):
    t = np.asarray(traj.t)
    keep = t >= t_after
    y = np.asarray(traj.e if signal == "e" else getattr(traj, signal))
    ax.plot(t[keep], y[keep], **(STYLE[name] | over))
    ax.set_xlim(t_after, t[-1])


def _legend_below(fig, ax, ncol=1):
    """Legend outside the axes, under them: it can never hide a curve."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=ncol, frameon=False)


def _line(ax, traj, signal, name, **over):
    t = np.asarray(traj.t)
    y = np.asarray(traj.e if signal == "e" else getattr(traj, signal))
    ax.plot(t, y, label=LABELS[name], **(STYLE[name] | over))


def figures(trajs: dict, loops: dict, out: Path, fmt: str = "png", dpi: int = 150) -> dict:
    """Write Figs. 1-6 and the estimates figure; returns {figure id: path}."""
    import matplotlib

    with matplotlib.rc_context(RC):
        return _figures(trajs, loops, out, fmt, dpi)


def _figures(trajs, loops, out, fmt, dpi):
    paths = {}
    hyst = paper_example().hysteresis
    lam, psi, alpha = (float(hyst.lam), float(hyst.psi), float(hyst.alpha))

    loop_colors = ("#8c564b", COLORS["w"])  # small loop brown, large loop the colour of w
    fig, axes = subplots(1, len(loops), figsize=(8.4, 3.9), sharey=True, layout="constrained")
    axes = np.atleast_1d(axes)
    umax = max(float(np.max(np.abs(u))) for _, u, _ in loops.values())
    ug = np.linspace(-umax, umax, 2)
    b = (lam - psi) / alpha
    for ax, (k, (_, u, w)), color in zip(axes, sorted(loops.items()), loop_colors, strict=False):
        ax.plot(ug, lam * ug + b, color="#999999", lw=0.8, ls=":",
                label=r"asymptotes $w = \lambda u \pm (\lambda-\psi)/\alpha$")
        ax.plot(ug, lam * ug - b, color="#999999", lw=0.8, ls=":")
        ax.plot(u, w, color=color, lw=1.4, label=f"$w(u)$, $u = {k:g}\\,\\sin(2.3t)$")
        ax.set_xlabel("control input $u$ [-]")
        ax.set_title(f"$k$ = {k:g}")
        ax.legend(loc="upper left", framealpha=0.95)
    axes[0].set_ylabel("hysteresis output $w$ [-]")
    fig.suptitle(f"Fig. 1  Backlash-like hysteresis (4), $w(0) = 0$: $\\alpha$ = {alpha:g}, "
                 f"$\\lambda$ = {lam:g}, $\\psi$ = {psi:g}")
    paths["fig1"] = _finish(fig, out, FIGURES["fig1"], fmt, dpi)

    fig, ax = _time_axes("Fig. 2  Tracking error of the DSC with and without hysteresis "
                         "compensation", "tracking error $e = y - y_r$ [-]")
    for name in ("dsc_no_dhat_no_zeta", "dsc_no_dhat", "dsc"):
        _line(ax, trajs[name], "e", name)
    _legend_below(fig, ax)
    paths["fig2"] = _finish(fig, out, FIGURES["fig2"], fmt, dpi)

    t_after = 1.0 if float(np.asarray(trajs["dsc"].t)[-1]) > 1.0 else 0.0
    for key, signal, title, ylabel in (
            ("fig3", "u", "Fig. 3  Control signal of the DSC", "control input $u$ [-]"),
            ("fig4", "w", "Fig. 4  Hysteresis output of the DSC loop",
             "hysteresis output $w$ [-]")):
        fig, ax, zoom = _time_axes_after(title, ylabel, t_after)
        _line(ax, trajs["dsc"], signal, "dsc")
        ax.axvspan(t_after, float(np.asarray(trajs["dsc"].t)[-1]), color="#999999",
                   alpha=0.08, lw=0, label=f"shown below: $t \\geq$ {t_after:g} s")
        _line_after(zoom, trajs["dsc"], signal, "dsc", t_after)
        _legend_below(fig, ax, ncol=2)
        paths[key] = _finish(fig, out, FIGURES[key], fmt, dpi)

    faint = dict(lw=0.9, alpha=0.55)
    fig, ax = _time_axes("Fig. 5  Tracking error of adaptive backstepping",
                         "tracking error $e = y - y_r$ [-]")
    _line(ax, trajs["dsc"], "e", "dsc", **faint)
    _line(ax, trajs["backstepping"], "e", "backstepping")
    _legend_below(fig, ax, ncol=2)
    paths["fig5"] = _finish(fig, out, FIGURES["fig5"], fmt, dpi)

    fig, ax = _time_axes("Fig. 6  Control signal of adaptive backstepping",
                         "control input $u$ [-]")
    _line(ax, trajs["dsc"], "u", "dsc", **faint)
    _line(ax, trajs["backstepping"], "u", "backstepping")
    _legend_below(fig, ax, ncol=2)
    paths["fig6"] = _finish(fig, out, FIGURES["fig6"], fmt, dpi)

    paths["estimates"] = _estimates_figure(trajs, out, fmt, dpi)
    return paths


def _estimates_figure(trajs, out, fmt, dpi):
    setup = paper_example()
    g, theta = np.asarray(setup.plant.g, float), np.asarray(setup.plant.theta, float)
    lam = float(setup.hysteresis.lam)
    true = {"theta_hat_g1": (theta[0] / g[0], r"$\theta_1/g_1$"),
            "phi_hat_1": (1.0 / g[0], r"$1/g_1$"),
            "zeta_hat": (1.0 / (lam * g[1]), r"$1/(\lambda g_2)$")}
    panels = (("theta_hat_g1", r"$\hat\theta_{g1}$ [-]"), ("phi_hat_1", r"$\hat\phi_1$ [-]"),
              ("zeta_hat", r"$\hat\zeta$ [-]"), ("d_hat", r"$\hat d$ [-]"))
    fig, axes = subplots(2, 2, figsize=(8.4, 5.6), sharex=True, layout="constrained")
    for ax, (key, ylabel) in zip(axes.ravel(), panels, strict=True):
        for name in ("dsc", "backstepping"):
            traj = trajs[name]
            ax.plot(np.asarray(traj.t), _estimates(traj)[key], label=LABELS[name], **STYLE[name])
        if key in true:
            value, sym = true[key]
            ax.axhline(value, color="#444444", lw=0.9, ls=":", label="true value")
            ax.annotate(f"{sym} = {value:.3g}", xy=(1.0, value), xycoords=("axes fraction", "data"),
                        xytext=(-4, 3), textcoords="offset points", ha="right", va="bottom",
                        fontsize=8, color="#444444")
        ax.set_ylabel(ylabel)
        ax.margins(y=0.12)
    for ax in axes[1]:
        ax.set_xlabel("time $t$ [s]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3, frameon=False)
    fig.suptitle(r"Adaptive estimates of the DSC and of backstepping ($\hat\theta_2 \equiv 0$ "
                 r"because $f_2 = 0$; not shown)")
    return _finish(fig, out, FIGURES["estimates"], fmt, dpi)


# -- summary.md --------------------------------------------------------------------------------


def _cell(text: str) -> str:
    """Text safe inside a markdown table cell."""
    return str(text).replace("|", "\\|")


def summary_markdown(summary: dict) -> str:
    lines = ["# Reproduction of the paper's Section 4", "",
             f"Horizon {summary['t_final']:g} s, RK4 step {summary['dt']:g} s; 'after 1 s' is the "
             f"window t >= {summary['window_start']:g} s. Wall time "
             f"{summary.get('wall_time_s', float('nan')):.1f} s.", "",
             "## Claims of the paper", "",
             "| claim | the paper shows | we measured | holds in our run |",
             "|---|---|---|---|"]
    for c in summary["claims"]:
        cells = (_cell(c["claim"]), _cell(c["paper"]), _cell(c["measured"]))
        verdict = c.get("verdict", "yes" if c["holds"] else "no")
        lines.append("| " + " | ".join(cells) + f" | {verdict if c['holds'] else '**no**'} |")
    lines += ["", "## Runs", "",
              "| run | L∞ e | L∞ e after 1 s | L2 e | L2 e after 1 s | max abs u | "
              "max abs u after 1 s | max abs w | TV(u) | diverged |",
              "|---|" + "---|" * 9]
    for name, r in summary["runs"].items():
        vals = " | ".join(f"{r[k]:.4g}" for k in METRIC_FIELDS)
        lines.append(f"| {name} | {vals} | {'yes' if r['diverged'] else 'no'} |")
    lines += ["", "## Adaptive estimates (min / max / final)", "",
              "| run | " + " | ".join(ESTIMATES) + " |", "|---|" + "---|" * len(ESTIMATES)]
    for name, r in summary["runs"].items():
        cells = " | ".join("{min:.3g} / {max:.3g} / {final:.3g}".format(**r["estimates"][k])
                           for k in ESTIMATES)
        lines.append(f"| {name} | {cells} |")
    if "complexity" in summary:
        cx = summary["complexity"]
        lines += ["", "## Explosion of complexity (control law only)", "",
                  "| n | controller | jaxpr eqns | FLOPs | trace [s] | compile [s] | "
                  "eval [us] |", "|---|---|---|---|---|---|---|"]
        for r in cx["rows"]:
            lines.append(f"| {r['n']} | {r['controller']} | {r['eqns']} | {r['flops']:.0f} | "
                         f"{r['trace_s']:.3g} | {r['compile_s']:.3g} | "
                         f"{r['eval_s'] * 1e6:.3g} |")
        lines += ["", "Fitted growth (ratio per order; power-law exponent):", ""]
        for c, fits in cx["fits"].items():
            parts = [f"{m}: x{f['ratio_per_order']:.2f}/order, n^{f['exponent']:.2f}"
                     for m, f in fits.items() if f["ratio_per_order"]]
            lines.append(f"- {c}: " + "; ".join(parts))
    if "theory" in summary:
        from dscjax.reproduce_theory import markdown

        lines += ["", markdown(summary["theory"])]
    lines += ["", "## Interpretations", ""] + [f"- {s}" for s in summary["interpretations"]]
    lines += ["", "Figures: " + ", ".join(f"`{Path(p).name}`"
                                          for p in summary["figures"].values()), ""]
    return "\n".join(lines)


# -- the whole study ---------------------------------------------------------------------------


def reproduce(out="results/paper", fmt: str = "png", t_final: float = T_FINAL, dt: float = DT,
              dpi: int = DPI, complexity: bool = False,
              complexity_orders: Sequence[int] = COMPLEXITY_ORDERS,
              complexity_repeats: int = COMPLEXITY_REPEATS,
              log: Callable[[str], None] | None = None, resume: bool = False,
              theory: bool = False, theory_orders: Sequence[int] = (2,),
              theory_alpha0: Sequence[float] | None = None,
              theory_mu: float | None = None) -> dict:
    """Run the study and write every figure, summary.json and summary.md to `out`.

    Args:
        out: output directory (created).
        fmt: "png" or "pdf".
        t_final, dt: horizon and RK4 step of the closed-loop runs.
        dpi: resolution of raster figures.
        complexity: also measure the control laws for n in complexity_orders
            (`dscjax.complexity`), writing complexity.json and fig_complexity.
        log: progress callback (default: print to stderr with elapsed time).
        resume: with complexity, reuse the control-law measurements an interrupted run saved
            in `out/complexity_rows.json` (each is saved as soon as it is made).
        theory: also check Theorem 1 (`dscjax.reproduce_theory`): V(t) of (44) on the DSC
            run, written to `out/theory/lyapunov.npz`, and the alpha_0 study for each order in
            theory_orders (alpha_0 values theory_alpha0, mu theory_mu; defaults in
            `reproduce_theory.run`), with a section in summary.md.

    Returns:
        The summary (as written to summary.json); `claim_lines(summary)` states each claim's
        verdict in one line.
    """
    if fmt not in ("png", "pdf"):
        raise ValueError(f"fmt must be 'png' or 'pdf' (got {fmt!r})")
    t_start = time.perf_counter()
    if log is None:
        def log(msg):
            print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log(f"reproducing Section 4 of the paper: T = {t_final:g} s, dt = {dt:g} s -> {out}/")
    loops = hysteresis_loops()
    log("Fig. 1 hysteresis loops integrated")
    trajs = run_all(t_final, dt, log)
    summary = summarize(trajs, t_final, dt)
    log("writing figures")
    paths = figures(trajs, loops, out, fmt, dpi)
    if complexity:
        from dscjax import complexity as cx

        log(f"measuring the control laws for n = {', '.join(map(str, complexity_orders))} "
            f"({complexity_repeats} builds each; this takes minutes)")
        result = cx.study(complexity_orders, repeats=complexity_repeats, log=log,
                          rows_path=out / "complexity_rows.json", resume=resume)
        files.write_json(out / "complexity.json", result)
        path = out / f"{FIGURES['complexity']}.{fmt}"
        cx.plot(result, path, colors={k: STYLE[k]["color"] for k in ("dsc", "backstepping")},
                dpi=dpi)
        paths["complexity"] = path
        summary["complexity"] = result
        summary["claims"] = check_claims(summary["runs"], result)
    if theory:
        from dscjax import reproduce_theory

        summary["theory"] = reproduce_theory.run(
            out / "theory", setups()["dsc"], trajs["dsc"], orders=theory_orders,
            alpha0=theory_alpha0, mu=theory_mu, t_final=t_final, fmt=fmt, dpi=dpi, log=log)
    summary["figures"] = {k: str(p) for k, p in paths.items()}
    summary["jax_version"] = jax.__version__
    summary["wall_time_s"] = time.perf_counter() - t_start
    files.write_json(out / "summary.json", summary)
    files.write_text(out / "summary.md", summary_markdown(summary))
    log(f"wrote {len(paths)} figures, summary.json and summary.md to {out}/ "
        f"({summary['wall_time_s']:.1f} s)")
    return summary


def claim_lines(summary: dict) -> list[str]:
    """One line per claim of the paper: the verdict, the claim, what we measured."""
    return [f"claim {c['verdict'].upper() if c['holds'] else 'FAILS'}: {c['claim']}: "
            f"{c['measured']}" for c in summary["claims"]]


__all__ = ["claim_lines", "reproduce", "setups", "run_all", "summarize", "check_claims", "figures",
           "hysteresis_loops", "summary_markdown", "RUNS", "LABELS", "STYLE", "FIGURES"]
