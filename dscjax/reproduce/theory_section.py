"""`dscjax reproduce --theory`: Theorem 1 on the paper's example and the alpha_0 study.

Writes into DIR/theory/:
    lyapunov.npz        t, V and its terms (surface, filter, theta, phi, zeta, d), the filter
                        errors y, dV/dt along the vector field, B_(i+1), the bound (65)
    fig_lyapunov.png    V(t) with its terms stacked; V against the bounds (65) and (71)
    alpha0_n{n}.json    the alpha_0 study for each order n (`alpha0_study`)
    fig_alpha0.png      ||S_1||_inf and the bound (72) against alpha_0, log axes
    theory.json         everything summarised (the paper's example and every study row)
and returns the summary `reproduce` adds to summary.json (`markdown.theory_markdown` writes
its section of summary.md). The paper's example satisfies (55)
and (60) only as inequalities, up to `theory.certified_alpha0`: it is checked with that
alpha_0 and the mu that makes (72) smallest.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from dscjax import files
from dscjax.plotting import AXIS_LABEL, saved
from dscjax.reproduce import alpha0 as alpha0_study
from dscjax.reproduce import theory
from dscjax.reproduce.figures import RC

GROUPS = (  # (term of (44), label, colour) in stacking order
    ("surface", r"$S_i^2/(2g_i)$, $S_n^2/2$", "#1f77b4"),
    ("filter", r"$y_{i+1}^2/2$ (filter errors)", "#ff7f0e"),
    ("theta", r"$\tilde\theta^2/(2\gamma_g)$", "#2ca02c"),
    ("phi", r"$\tilde\phi^2/(2\gamma_\phi)$", "#9467bd"),
    ("zeta", r"$\beta\tilde\zeta^2/(2\gamma_\zeta)$", "#8c564b"),
    ("d", r"$\tilde d^2/(2\gamma_d)$", "#e377c2"),
)
ALPHA0_PAPER = 0.2  # what k_2 = 0.45 = 1/4 + alpha_0 suggests (docs/paper-readings.md)


def best_mu(controller, M, C0: float, g_max: float, n: int) -> tuple[float, float, dict]:
    """(mu, certified alpha_0, {gain: the alpha_0 it allows}) with the smallest (72) for fixed
    gains (`theory.certified_alpha0` at that mu): alpha_0(mu) grows with mu (the tau rule (60)),
    C(mu) = C0 + (n-1) mu/2; over a log grid of mu in [1e-4, 1e4] and the mu at which the tau
    rule stops binding."""
    _, allows = theory.certified_alpha0(controller, M, 1.0)
    others = min(v for k, v in allows.items() if not k.startswith("tau_"))
    room = [1 / float(tau) - 0.25 - others for tau in controller.tau]  # for M^2/(2 mu) in (60)
    candidates = [float(m) ** 2 / (2 * r) for m, r in zip(np.asarray(M), room, strict=True)
                  if r > 0]

    def bound(mu):
        a0 = theory.certified_alpha0(controller, M, mu)[0]
        return theory.bound_72(C0 + (n - 1) * mu / 2, a0, g_max) if a0 > 0 else math.inf

    mu = min((float(mu) for mu in (*np.geomspace(1e-4, 1e4, 801),
                                    *(m * (1 + 1e-12) for m in candidates))), key=bound)
    if bound(mu) == math.inf:
        raise ValueError("no mu > 0 certifies a positive alpha_0 for these gains")
    return mu, *theory.certified_alpha0(controller, M, mu)


def paper_check(setup, traj) -> tuple[dict, dict]:
    """(summary, arrays for lyapunov.npz) of Theorem 1 on the paper's example run."""
    lv = theory.lyapunov(setup, traj)
    probe = theory.check(setup, traj, 1.0, 1.0)  # M and the slack do not depend on alpha_0, mu
    M = probe["M_measured"]
    n = setup.order
    C0 = probe["e_M"] + probe["slack"]
    g_max = float(lv.truth.g_max)
    mu, a0, allows = best_mu(setup.controller, M, C0, g_max, n)
    res = theory.check(setup, traj, a0, mu)
    c = setup.controller
    gains = [dict(gain=g, paper=float(v), rule=r, at_0_2=float(sum(base) + ALPHA0_PAPER / s))
             for g, v, r, base, s in theory.gain_rules(c, M, mu)]
    x0 = np.asarray(setup.plant.x0)
    yr0 = float(setup.reference(0.0))
    est0 = {k: np.asarray(getattr(c, f"{k}0")).tolist()
            for k in ("theta_hat", "phi_hat", "zeta_hat", "d_hat")}
    init = dict(
        estimates=est0, yr0=yr0, x1_0=float(x0[0]), c=np.asarray(c.c).tolist(), x0=x0.tolist(),
        S0=np.asarray(traj.S[0]).tolist(), y0=np.asarray(lv.y[0]).tolist(),
        uses_67=not any(np.any(v) for v in est0.values()),
        uses_68=bool(yr0 == float(x0[0]) and np.allclose(np.asarray(c.c), x0[1:])),
    )
    b72_paper = theory.bound_72(C0 + (n - 1) * mu / 2, ALPHA0_PAPER, g_max)
    terms = lv.arrays()
    V, sums = terms["V"], term_sums(terms)
    s1_after = np.asarray(traj.S)[np.asarray(traj.t) >= 1.0, 0]  # none if T < 1 s
    summary = dict(
        alpha0=a0, mu=mu, binding_gain=min(allows, key=allows.get), allows=allows, gains=gains,
        init=init,
        M_measured=np.asarray(M).tolist(), V0=res["V0"], V_max=res["V_max"], V_end=float(V[-1]),
        t_V_max=float(np.asarray(lv.t)[int(np.argmax(V))]),
        frac_V_decreasing=float(np.mean(res["V_dot"] < 0)),
        S1_inf=res["S1_inf"],
        S1_inf_after_1s=float(np.max(np.abs(s1_after))) if s1_after.size else None,
        **{k: res[k] for k in ("e_M", "slack", "C", "bound_71", "bound_72", "margin_63",
                               "margin_65", "d", "d_n_max", "holds", "assumptions")},
        bound_72_at_alpha0_paper=b72_paper,
        terms_at_t0={k: float(v[0]) for k, v in sums.items()},
        terms_max={k: float(np.max(v)) for k, v in sums.items()},
    )
    arrays = terms | dict(V_dot=res["V_dot"], bound_65=res["bound_65"], B=res["B"],
                          alpha0=np.asarray(a0), mu=np.asarray(mu), C=np.asarray(res["C"]))
    return summary, arrays


def term_sums(arrays: dict) -> dict:
    """{group of `GROUPS`: its terms of (44) summed over i, (T,)} of lyapunov.npz's arrays."""
    return {k: np.sum(np.reshape(arrays[k], (len(arrays["t"]), -1)), axis=1) for k, _, _ in GROUPS}


def plot_lyapunov(arrays: dict, summary: dict, path: Path, dpi: int = 150) -> Path:
    """Top: V(t) of (44) with its terms stacked. Bottom: V against (65) and (71), log axis."""
    t = arrays["t"]
    with saved(path, dpi, 2, 1, rc=RC, figsize=(8.8, 6.4), sharex=True,
               height_ratios=(3, 2)) as (fig, (top, bottom)):
        top.stackplot(t, *term_sums(arrays).values(), labels=[lab for _, lab, _ in GROUPS],
                      colors=[c for _, _, c in GROUPS], alpha=0.85, lw=0)
        top.plot(t, arrays["V"], color="k", lw=0.8, label="$V$ (44)")
        top.set(ylabel="$V$ and its terms [-]", title="Lyapunov function (44) along the paper's "
                "example (its own gains and initialisation)")
        bottom.semilogy(t, arrays["V"], color="k", lw=1.0, label="$V(t)$")
        bottom.semilogy(t, arrays["bound_65"], color="#d62728", ls="--", lw=1.0,
                        label="bound (65)")
        bottom.axhline(summary["bound_71"], color="#7f7f7f", ls=":", lw=1.0,
                       label="$C/(2\\alpha_0)$ (71)")
        bottom.set(xlabel=AXIS_LABEL["t"], ylabel="[-]", title=f"against Theorem 1 with the "
                   f"certified $\\alpha_0$ = {summary['alpha0']:.3g}, $\\mu$ = {summary['mu']:.3g} "
                   "(data-driven $M$)")
        for ax in (top, bottom):
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return path


def run(out, setup, traj, orders: Sequence[int] = (2,), alpha0: Sequence[float] | None = None,
        mu: float | None = None, t_final: float = 20.0, fmt: str | None = "png", dpi: int = 150,
        log: Callable[[str], None] = print) -> dict:
    """Theorem 1 on the paper's run `traj` (saved at every step) of `setup`, and the alpha_0
    study for each order (`alpha0.default_options(n)` unless `alpha0`, `mu` are given; the
    horizon at most `t_final`), written into `out` (no figures if `fmt` is None). Returns
    theory.json's summary."""
    t0 = time.perf_counter()
    out = files.mkdir(out)
    paper, arrays = paper_check(setup, traj)
    files.write_npz(out / "lyapunov.npz", arrays)  # each value as np.asarray
    figs = {}
    if fmt:
        figs["lyapunov"] = str(plot_lyapunov(arrays, paper, out / f"fig_lyapunov.{fmt}", dpi))
    log(f"theory: V(t) of (44) on the paper's example, certified alpha_0 = "
        f"{paper['alpha0']:.3g} (its figures in summary.md)")
    studies = []
    for n in orders:
        opts = alpha0_study.default_options(n, alpha0=alpha0, mu=mu)
        opts = dataclasses.replace(opts, t_final=min(t_final, opts.t_final))
        log(f"theory: alpha_0 study, n = {n}, {len(opts.alpha0)} values of alpha_0, "
            f"mu = {opts.mu:g}, T = {opts.t_final:g} s")
        res = alpha0_study.study(alpha0_study.base_setup(n), opts, log=log)
        files.write_json(out / f"alpha0_n{n}.json", res)
        studies.append(res)
    if fmt:
        figs["alpha0"] = str(alpha0_study.plot(studies, out / f"fig_alpha0.{fmt}", dpi))
    summary = dict(paper=paper, studies=studies, figures=figs,
                   wall_s=time.perf_counter() - t0)
    files.write_json(out / "theory.json", summary)
    return summary
