"""summary.md: the claims, the runs, the estimates, the complexity and theory sections."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dscjax.markdown import escape, number, table, window, yes
from dscjax.reproduce import theory
from dscjax.reproduce.alpha0 import table_markdown
from dscjax.reproduce.runs import ESTIMATES
from dscjax.reproduce.sampling import markdown as sampling_markdown


def _figures(summary: dict, folder: str) -> str:
    """"Figures: `a.png`, ...": the figures of a summary, by file name in `folder`."""
    return "Figures: " + ", ".join(f"`{folder}{Path(p).name}`" for p in summary["figures"].values())


def summary_markdown(summary: dict) -> str:
    lines = ["# Reproduction of the paper's Section 4", "",
             f"Horizon {summary['t_final']:g} s, RK4 step {summary['dt']:g} s; 'after 1 s' is the "
             f"window t >= {summary['window_start']:g} s. Wall time "
             f"{summary.get('wall_time_s', float('nan')):.1f} s.", "",
             "## Claims of the paper", "",
             *table(("claim", "the paper shows", "we measured", "holds in our run"),
                    [(*(escape(c[k]) for k in ("claim", "paper", "measured")),
                      c.get("verdict", "yes") if c["holds"] else yes(False))
                     for c in summary["claims"]])]
    # the windowed figures lead: over the whole run, L∞ e is the initial error x1(0) - yr(0)
    on = f"on {window(summary['window_start'], summary['t_final'])}"
    heads = {"linf_error_after_1s": f"L∞ e {on}", "linf_error": "L∞ e on [0, T] (the "
             "initial error)", "l2_error_after_1s": f"L2 e {on}", "l2_error": "L2 e on [0, T]",
             "max_abs_u_after_1s": f"max abs u {on}", "max_abs_u": "max abs u on [0, T]",
             "max_abs_w": "max abs w", "tv_u": "TV(u)"}
    runs = summary["runs"].items()
    lines += ["", "## Runs", "",
              *table(("run", *heads.values(), "diverged"),
                     [(name, *(f"{r[k]:.4g}" for k in heads), "yes" if r["diverged"] else "no")
                      for name, r in runs]),
              "", "## Adaptive estimates (min / max / final)", "",
              *table(("run", *ESTIMATES), [
                  (name, *("{min:.3g} / {max:.3g} / {final:.3g}".format(**r["estimates"][k])
                           for k in ESTIMATES)) for name, r in runs])]
    if "sampling" in summary:
        lines += ["", sampling_markdown(summary["sampling"])]
    if "complexity" in summary:
        cx = summary["complexity"]
        lines += ["", "## Explosion of complexity (control law only)", "",
                  *table(("n", "controller", "jaxpr eqns", "FLOPs", "trace [s]", "compile [s]",
                          "eval [us]"),
                         [(r["n"], r["controller"], r["eqns"], f"{r['flops']:.0f}",
                           f"{r['trace_s']:.3g}", f"{r['compile_s']:.3g}",
                           f"{r['eval_s'] * 1e6:.3g}") for r in cx["rows"]]),
                  "", "Fitted growth (ratio per order; power-law exponent):", "",
                  *(f"- {c}: " + "; ".join(f"{m}: x{f['ratio_per_order']:.2f}/order, "
                                           f"n^{f['exponent']:.2f}"
                                           for m, f in fits.items() if f["ratio_per_order"])
                    for c, fits in cx["fits"].items())]
    if "theory" in summary:
        lines += ["", theory_markdown(summary["theory"])]
    lines += ["", "## Interpretations", ""] + [f"- {s}" for s in summary["interpretations"]]
    if summary["figures"]:
        lines += ["", _figures(summary, ""), ""]
    return "\n".join(lines)


def theory_markdown(summary: dict) -> str:
    """The summary.md section on Theorem 1 (`theory_section.run`'s summary)."""
    p = summary["paper"]
    ini = p["init"]
    lines = [
        "## Theorem 1 along trajectories (`--theory`)", "",
        "V(t) of (44) with the true plant parameters (`theory/lyapunov.npz`, "
        "`theory/fig_lyapunov`). M_(i+1) of (59)-(60) is max |B_(i+1)| on the run: every "
        "bound is a **data-driven estimate**; C = e_M + (n-1) mu/2 + sat(S_n/w)'s slack in (48) "
        "(docs/theory.md).", "",
        "### The paper's example does not satisfy the theorem's assumptions", "",
        f"- Its gains follow (55) for no single alpha_0; as inequalities they allow alpha_0 <= "
        f"{p['alpha0']:.3g}, bound by {p['binding_gain']} (k_2 = 0.45 alone: "
        f"{p['allows'].get('k_2', float('nan')):.3g}):", "",
        *table(("gain", "paper", "rule (55)/(60)", "rule at alpha_0 = 0.2", "alpha_0 it allows"),
               [(g["gain"], f"{g['paper']:.4g}", g["rule"], f"{g['at_0_2']:.4g}", f"{a:.4g}")
                for g, a in zip(p["gains"], p["allows"].values(), strict=True)])]
    est = ini["estimates"]
    h, ratio = p["holds"], p["bound_72"] / p["S1_inf"]
    rows = [
        ("(63)", f"max(V' + 2 alpha_0 V - C) = {p['margin_63']:.3g}", "0"),
        ("(65)", f"max(V - bound) = {p['margin_65']:.3g}", "0"),
        ("(70)", f"V(0) = {p['V0']:.4g}", f"{p['bound_71']:.4g}"),
        ("(71)", f"max V = {p['V_max']:.4g} (t = {p['t_V_max']:.3g} s)", f"{p['bound_71']:.4g}"),
        ("(72)", f"{p['S1_inf']:.4g} (after 1 s: {number(p['S1_inf_after_1s'], '.3g')})",
         f"{p['bound_72']:.4g} (x{ratio:.3g})"),
    ]
    lines += [
        "",
        f"- Nor the L-inf initialisation (67)-(68): theta_hat = {est['theta_hat']}, phi_hat = "
        f"{est['phi_hat']}, zeta_hat = {est['zeta_hat']:g}, d_hat = {est['d_hat']:g} (67: 0); "
        f"y_r(0) = {ini['yr0']:g} != x_1(0) = {ini['x1_0']:g} (68; c_2 = {ini['c']} = x_2(0)). "
        f"So S(0) = {np.round(ini['S0'], 5).tolist()}; only (65) applies.", "",
        f"### Statements on the example (alpha_0 = {p['alpha0']:.3g}, mu = {p['mu']:.3g}, "
        f"M = {np.round(p['M_measured'], 4).tolist()} measured, C = {p['C']:.4g})", "",
        *table(("statement", "measured", "bound", "holds"), [
            *((f"{key} {escape(theory.STATEMENTS[key])}", measured, bound, yes(h[key]))
              for key, measured, bound in rows),
            (f"(12) {escape(theory.ASSUMPTIONS['(12)'])} (assumption)", f"{p['d_n_max']:.4g}",
             f"{p['d']:.4g}", yes(p["assumptions"]["(12)"]))]),
        "",
        f"V decreases at {100 * p['frac_V_decreasing']:.1f} % of the steps; V(end) = "
        f"{p['V_end']:.4g}. alpha_0 = 0.2 (k_2's, unlicensed) would give the bound "
        f"{p['bound_72_at_alpha0_paper']:.3g}.", "",
    ]
    for res in summary["studies"]:
        o = res["options"]
        rows = [r for r in res["rows"] if not r.get("skipped")]
        skipped = [r for r in res["rows"] if r.get("skipped")]
        n_hold = sum(r["all_hold"] for r in rows)
        dts = sorted({r["dt"] for r in rows})
        lines += [
            f"### alpha_0 study, n = {res['n']} (gains (55) holding eta, tau (60), L-inf "
            f"initialisation (67)-(68), mu = {o['mu']:g}, T = {o['t_final']:g} s)", "",
            f"RK4 steps: {', '.join(f'{d:g}' for d in dts)} s (the largest {o['dt_max']:g}/2^j "
            f"<= {o['dt_safety']:g} x 2.785 x min(tau, 1/(alpha max|u'|))). (63), (65), "
            f"(70)-(72) hold for {n_hold} of {len(rows)} values of alpha_0"
            + (f" ({len(skipped)} skipped: too stiff for max_steps = {o['max_steps']})"
               if skipped else "") + f". Wall time {res['wall_s']:.0f} s.", "",
            table_markdown(res), ""]
        if len(rows) > 1:
            a = np.log([r["alpha0"] for r in rows])
            slope_m, slope_b = (np.polyfit(a, np.log([r[k] for r in rows]), 1)[0]
                                for k in ("S1_inf", "bound_72"))
            cons = [r["conservatism"] for r in rows]
            lines += [f"‖S_1‖∞ falls like alpha_0^{slope_m:.2f} and the bound (72) like "
                      f"alpha_0^{slope_b:.2f}; the bound is {min(cons):.3g} to {max(cons):.3g} "
                      "times the measured error.", ""]
    if summary["figures"]:
        lines += [_figures(summary, "theory/") + ".", ""]
    return "\n".join(lines)


__all__ = ["summary_markdown", "theory_markdown"]
