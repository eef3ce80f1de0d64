"""summary.md: the claims, the runs, the estimates, the complexity and theory sections."""

from __future__ import annotations

from pathlib import Path

from dscjax.reproduce.runs import ESTIMATES
from dscjax.reproduce.sampling import markdown as sampling_markdown
from dscjax.reproduce.theory_section import markdown as theory_markdown


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
    # the windowed figures lead: over the whole run, L∞ e is the initial error x1(0) - yr(0)
    window = f"on [{summary['window_start']:g}, {summary['t_final']:g}] s"
    heads = {"linf_error_after_1s": f"L∞ e {window}", "linf_error": "L∞ e on [0, T] (the "
             "initial error)", "l2_error_after_1s": f"L2 e {window}", "l2_error": "L2 e on [0, T]",
             "max_abs_u_after_1s": f"max abs u {window}", "max_abs_u": "max abs u on [0, T]",
             "max_abs_w": "max abs w", "tv_u": "TV(u)"}
    lines += ["", "## Runs", "", "| run | " + " | ".join(heads.values()) + " | diverged |",
              "|---|" + "---|" * (len(heads) + 1)]
    for name, r in summary["runs"].items():
        vals = " | ".join(f"{r[k]:.4g}" for k in heads)
        lines.append(f"| {name} | {vals} | {'yes' if r['diverged'] else 'no'} |")
    lines += ["", "## Adaptive estimates (min / max / final)", "",
              "| run | " + " | ".join(ESTIMATES) + " |", "|---|" + "---|" * len(ESTIMATES)]
    for name, r in summary["runs"].items():
        cells = " | ".join("{min:.3g} / {max:.3g} / {final:.3g}".format(**r["estimates"][k])
                           for k in ESTIMATES)
        lines.append(f"| {name} | {cells} |")
    if "sampling" in summary:
        lines += ["", sampling_markdown(summary["sampling"])]
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
        lines += ["", theory_markdown(summary["theory"])]
    lines += ["", "## Interpretations", ""] + [f"- {s}" for s in summary["interpretations"]]
    lines += ["", "Figures: " + ", ".join(f"`{Path(p).name}`"
                                          for p in summary["figures"].values()), ""]
    return "\n".join(lines)


__all__ = ["summary_markdown"]
