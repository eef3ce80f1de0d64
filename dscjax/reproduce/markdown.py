"""summary.md: the claims, the runs, the estimates, the complexity and theory sections."""

from __future__ import annotations

from pathlib import Path

from dscjax.reproduce.runs import ESTIMATES, METRIC_FIELDS
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
