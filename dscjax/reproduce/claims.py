"""The paper's claims checked against the runs, and the readings of the paper they rest on."""

from __future__ import annotations

import math

from dscjax.metrics import default_window
from dscjax.reproduce.complexity import growth_text
from dscjax.reproduce.runs import LABELS, estimates, run_metrics

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
    "Not given: w(0) = 0, the horizon 20 s, the solver (RK4 with dt = 1e-3 s).",
    "sgn(S_2) is replaced by sat(S_2/0.01), as the paper's simulation says; |S_2| in (32) is "
    "kept exact.",
    "In the rho_n term of (30) there is no 1/g_min (as printed).",
    "No L-infinity initialisation (67)-(68): Section 4's initial estimates, S_1(0) = x_1(0) - "
    "y_r(0) = 0.08.",
    "sgn(u) in (6) is read sgn(u') (Su et al. 2000); u' is the exact derivative of the control "
    "law along the vector field (one forward-mode derivative).",
    "Fig. 2 'without considering the effect of hysteresis': reading A drops the robust term "
    "(d_hat = 0); B also freezes zeta_hat = 1 (u = ubar). Both are shown.",
    "Eq. (79), the backstepping law, is garbled. The baseline is adaptive backstepping with the "
    "DSC's parameterisation, robust term and adaptive laws (S_i -> z_i, z_i' -> alpha_(i-1)'), "
    "z_2 = x_2 - alpha_1 (no filter, no c_2), alpha_1' by automatic differentiation along the "
    "nominal x_1' = g_nom (x_2 + theta_hat_g1 f_1), g_nom = g_min = 1.",
    "The backstepping law has no cross term -z_1 in alpha_2 and no damping term for the "
    "mismatch between the nominal and the true x_1' ((79) has neither).",
    f"'Track alike': errors after the first second within a factor {ALIKE_FACTOR:g} of each "
    "other in L-infinity and L2. 'Control amplitude': max |u| over the whole horizon (also "
    f"reported after 1 s); a DSC amplitude smaller by less than {100 * AMPLITUDE_MARGIN:g} % is "
    "marginal.",
]


def summarize(trajs: dict, t_final: float, dt: float) -> dict:
    """Metrics of every run, the estimates' ranges and the check of every claim."""
    window = default_window(t_final)
    runs = {name: dict(
        label=LABELS[name], **run_metrics(traj), diverged=bool(traj.diverged),
        t_diverged=float(traj.t_diverged) if bool(traj.diverged) else None,
        estimates={k: dict(min=float(v.min()), max=float(v.max()), final=float(v[-1]))
                   for k, v in estimates(traj).items()},
    ) for name, traj in trajs.items()}
    return dict(
        paper="Robust adaptive DSC for nonlinear systems with hysteresis input, Acta Automatica "
              "Sinica 2010, Section 4 (eq. 73)",
        t_final=t_final, dt=dt, window_start=window, runs=runs, claims=check_claims(runs),
        interpretations=INTERPRETATIONS, alike_factor=ALIKE_FACTOR,
        amplitude_margin=AMPLITUDE_MARGIN,
    )


def check_claims(runs: dict, complexity: dict | None = None) -> list[dict]:
    """Each claim of the paper: what the paper shows, what we measured, whether it holds."""
    d, b = runs["dsc"], runs["backstepping"]

    def ratio(r, key):  # of run r to the DSC
        return r[key] / d[key] if d[key] else float("inf")

    claims = []
    for reading, key in (("A (d_hat = 0)", "dsc_no_dhat"),
                         ("B (d_hat = 0, zeta_hat = 1)", "dsc_no_dhat_no_zeta")):
        q_inf, q_2 = (ratio(runs[key], f"{m}_error_after_1s") for m in ("linf", "l2"))
        claims.append(dict(
            id=f"compensation_improves_tracking_{key.removeprefix('dsc_')}",
            claim=f"Tracking is poor once hysteresis compensation is ignored, reading {reading}",
            paper="Fig. 2: the error without compensation (dashed) is visibly larger than with it",
            measured=f"error after 1 s without / with compensation: L-inf x{q_inf:.2f}, "
                     f"L2 x{q_2:.2f}",
            ratio_linf=q_inf, ratio_l2=q_2, holds=bool(q_inf > 1.0 and q_2 > 1.0)))
    q_inf, q_2 = (ratio(b, f"{m}_error_after_1s") for m in ("linf", "l2"))
    alike = all(1.0 / ALIKE_FACTOR <= q <= ALIKE_FACTOR for q in (q_inf, q_2))
    claims.append(dict(
        id="dsc_and_backstepping_track_alike",
        claim="DSC and backstepping have similar tracking performance",
        paper="Figs. 2 and 5: tracking errors of similar size",
        measured=f"error after 1 s backstepping / DSC: L-inf x{q_inf:.2f}, L2 x{q_2:.2f} "
                 f"(alike: within x{ALIKE_FACTOR:g})",
        ratio_linf=q_inf, ratio_l2=q_2, holds=bool(alike)))
    q_u, q_u1 = (ratio(b, k) for k in ("max_abs_u", "max_abs_u_after_1s"))
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
    bounded = all(not r["diverged"] and all(math.isfinite(e["min"]) and math.isfinite(e["max"])
                                            for e in r["estimates"].values())
                  for r in runs.values())
    est_max = max(max(abs(e["min"]), abs(e["max"])) for r in runs.values()
                  for e in r["estimates"].values())
    claims.append(dict(
        id="signals_bounded",
        claim="All closed-loop signals stay bounded (Theorem 1)",
        paper="Theorem 1; the figures show bounded u and w",
        measured=f"no run diverged: {bounded}; largest estimate in magnitude {est_max:.3g}",
        holds=bool(bounded)))
    if complexity is not None:
        fd, fb = (complexity["fits"][c]["eqns"] for c in ("dsc", "backstepping"))
        n_max = max(complexity["orders"])
        eq = {r["controller"]: r["eqns"] for r in complexity["rows"] if r["n"] == n_max}
        claims.append(dict(
            id="dsc_removes_explosion_of_complexity",
            claim="The DSC eliminates backstepping's explosion of complexity",
            paper="Asserted (Introduction, Remarks 4 and 6), never measured",
            measured=f"jaxpr equations of the law, n = {min(complexity['orders'])}..{n_max}: "
                     f"DSC {growth_text(fd)}, backstepping {growth_text(fb)}; at n = {n_max}: "
                     f"{eq.get('dsc')} vs {eq.get('backstepping')}",
            dsc_eqns_exponent=fd["exponent"], backstepping_eqns_ratio=fb["ratio_per_order"],
            holds=bool(fb["ratio_per_order"] >= 2.0 and fb["r2_geometric"] >= fb["r2_power"]
                       and fd["exponent"] <= 1.5)))
    for c in claims:
        c.setdefault("verdict", "yes" if c["holds"] else "no")
    return claims


def claim_lines(summary: dict) -> list[str]:
    """One line per claim of the paper: the verdict, the claim, what we measured."""
    return [f"claim {c['verdict'].upper() if c['holds'] else 'FAILS'}: {c['claim']}: "
            f"{c['measured']}" for c in summary["claims"]]
