"""The paper's simulation study (Section 4) in one call: Figures 1-6, Fig. 1 for every
hysteresis model of dscjax, the adaptive estimates, a summary of every run and a check of each
claim the paper makes from its figures.

    import dscjax.reproduce
    summary = dscjax.reproduce.reproduce("results/paper")

Runs (all on the paper's example, eq. 73, with the readings of docs/paper-readings.md):
    dsc                  the DSC with hysteresis compensation, eqs. (13)-(32)
    dsc_no_dhat          "without considering hysteresis", reading A: d_hat = 0 (no robust term)
    dsc_no_dhat_no_zeta  reading B: also zeta_hat = 1, so u = ubar
    backstepping         adaptive backstepping with the same gains (controllers/backstepping.py)

The package, by topic: `runs` (the catalogue of runs, Fig. 1's loops, metrics and estimates
of a run), `claims` (the paper's claims checked, the readings they rest on), `figures`
(Figs. 1-6 and the estimates), `markdown` (summary.md). This module runs them in order.

Colours identify the run and are the same in every figure (`STYLE`); Fig. 1, which has no
controller, uses the hysteresis output's colour of `plotting.COLORS`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence

import jax

from dscjax import files, ts_sweep
from dscjax.reproduce import complexity as cx
from dscjax.reproduce import sampling, theory_section
from dscjax.reproduce.claims import check_claims, claim_lines, summarize
from dscjax.reproduce.figures import FIGURES, figures
from dscjax.reproduce.markdown import summary_markdown
from dscjax.reproduce.runs import STYLE, family_loops, run_all, setups

# Defaults of `reproduce` (and of `dscjax reproduce`): 20 s horizon, RK4 step 1 ms (the paper
# gives neither), PNG figures at 150 dpi, complexity study n = 2..8 with 3 builds per law.
T_FINAL = 20.0
DT = 1e-3
DPI = 150
COMPLEXITY_ORDERS = tuple(range(2, 9))
COMPLEXITY_REPEATS = 3
ROWS = "complexity_rows.json"  # where each control law's measurement is saved at once


def reproduce(out="results/paper", fmt: str | None = "png", t_final: float = T_FINAL,
              dt: float = DT, dpi: int = DPI, complexity: bool = False,
              complexity_orders: Sequence[int] = COMPLEXITY_ORDERS,
              complexity_repeats: int = COMPLEXITY_REPEATS,
              log: Callable[[str], None] | None = None, resume: bool = False,
              theory: bool = False, theory_orders: Sequence[int] = (2,),
              theory_alpha0: Sequence[float] | None = None,
              theory_mu: float | None = None) -> dict:
    """Run the study and write every figure, summary.json and summary.md to `out`.

    Args:
        out: output directory (created).
        fmt: "png" or "pdf"; None writes no figures (the summaries only).
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
    if fmt not in ("png", "pdf", None):
        raise ValueError(f"fmt must be 'png', 'pdf' or None (got {fmt!r})")
    t_start = time.perf_counter()
    if log is None:
        def log(msg):
            print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)
    out = files.mkdir(out)
    log(f"reproducing Section 4 of the paper: T = {t_final:g} s, dt = {dt:g} s -> {out}/")
    family = family_loops()  # its backlash entry is the paper's (4), Fig. 1
    log(f"Fig. 1 hysteresis loops integrated (and for {', '.join(family)})")
    trajs = run_all(t_final, dt, log)
    summary = summarize(trajs, t_final, dt)
    paths = {}
    if fmt:
        log("writing figures")
        paths = figures(trajs, family, out, fmt, dpi)
    log("the controller sampled at Ts = 0.1-20 ms: paper's and default-tuned gains")
    summary["sampling"] = sampling.study(setups()["dsc"], t_final, dt,
                                         window_start=summary["window_start"])
    if fmt:
        paths["sampling"] = out / f"{FIGURES['sampling']}.{fmt}"
        ts_sweep.plot(summary["sampling"], paths["sampling"],
                      {"paper": STYLE["dsc"]["color"], "tuned": "#2ca02c"}, dpi, sampling.LABELS)
    if complexity:
        log(f"measuring the control laws for n = {', '.join(map(str, complexity_orders))} "
            f"({complexity_repeats} builds each; this takes minutes)")
        result = cx.study(complexity_orders, repeats=complexity_repeats, log=log,
                          rows_path=out / ROWS, resume=resume)
        files.write_json(out / "complexity.json", result)
        if fmt:
            paths["complexity"] = out / f"{FIGURES['complexity']}.{fmt}"
            cx.plot(result, paths["complexity"], dpi=dpi)
        summary["complexity"] = result
        summary["claims"] = check_claims(summary["runs"], result)
    if theory:
        summary["theory"] = theory_section.run(
            out / "theory", setups()["dsc"], trajs["dsc"], orders=theory_orders,
            alpha0=theory_alpha0, mu=theory_mu, t_final=t_final, fmt=fmt, dpi=dpi, log=log)
    summary["figures"] = {k: str(p) for k, p in paths.items()}
    summary["jax_version"] = jax.__version__
    summary["wall_time_s"] = time.perf_counter() - t_start
    files.write_json(out / "summary.json", summary)
    files.write_text(out / "summary.md", summary_markdown(summary))
    log(f"wrote {written(summary)} to {out}/ ({summary['wall_time_s']:.1f} s)")
    return summary


def written(summary: dict) -> str:
    """What `reproduce` wrote, in words: "9 figures, summary.json and summary.md"."""
    n = len(summary["figures"])
    return (f"{n} figures, " if n else "") + "summary.json and summary.md"


__all__ = ["COMPLEXITY_ORDERS", "COMPLEXITY_REPEATS", "DPI", "DT", "ROWS", "T_FINAL",
           "claim_lines", "reproduce", "setups", "written"]
