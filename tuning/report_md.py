"""report.md of a tuning run: its text from the summary `tuning.report.write` builds (the
problem, the method, start against tuned gains, constraints, held-out outcomes, margins,
sensitivities), and the labels of its figures."""

from __future__ import annotations

import numpy as np

from dscjax import metrics
from dscjax.divergence import OUTCOMES  # (docs/tuning.md, "The held-out check")
from dscjax.markdown import escape, number, table, window
from tuning import elasticity, margins
from tuning.config import ROWS, TERMS

STATS_METRICS = ("linf_error_window", "user_linf_error_window", "l2_error_window", "max_abs_u",
                 "l2_u", "tv_u_window", "sampled_linf_window", "delayed_linf_window",
                 "delayed_tv_u")


# the figures' labels, in the order of report.md's nominal table
LABELS = {"linf_error_window": "L-inf error on [t0, T]",
          "user_linf_error_window": "L-inf error on [t0, T] against the config's y_r",
          "l2_error_window": "L2 error on [t0, T]",
          "user_l2_error_window": "L2 error on [t0, T] against the config's y_r",
          "linf_error": "L-inf error on [0, T]",
          "user_linf_error": "L-inf error on [0, T] against the config's y_r",
          "max_abs_u": "max |u| on [0, T]", "max_abs_u_window": "max |u| on [t0, T]",
          "l2_u": "L2(u)", "tv_u": "TV(u) on [0, T]", "tv_u_window": "TV(u) on [t0, T]",
          "chattering_index": "chattering index on [t0, T] (chatters above "
                              f"{metrics.CHATTER_RATIO:g})",
          "sampled_linf_window": "L-inf error on [t0, T], the other discretisation",
          "delayed_linf_window": "L-inf error on [t0, T], the input delayed",
          "delayed_tv_u": "TV(u) on [0, T], the input delayed"}


ERRORS = ("linf_error_window", "l2_error_window", "linf_error", "sampled_linf_window",
          "delayed_linf_window")


def heldout_warning(summary: dict, cfg) -> str | None:
    """The sentence put first when the tuned gains lose held-out plants (diverged, tracked only
    once refined, diverged sampled, or chattering: a small error with an input that switches
    is not tracking), None if on none: that must not hide in a table."""
    h = summary.get("heldout")
    if not h:
        return None
    a, b = h["start"], h["tuned"]
    chatter = f"chatter (chattering index above {metrics.CHATTER_RATIO:g})"
    lost = {"diverged": (b["n_diverged"], a["n_diverged"]),
            "RK4 diverged at dt (the loop stiff there; tracked only once refined)":
            (b["n_refined"], a["n_refined"])}
    if "sampled" in b:
        lost[f"diverged with {summary['second_loop']}"] = (b["sampled"]["n_diverged"],
                                                           a["sampled"]["n_diverged"])
    lost[chatter] = (b.get("n_chattering", 0), a.get("n_chattering", 0))
    lost = {how: kk for how, kk in lost.items() if kk[0]}
    if not lost:
        return None
    what = "; ".join(f"{how} on {k} of {b['n']} held-out plants (start gains: {k0})"
                     for how, (k, k0) in lost.items())
    verb = " and ".join(w for w, on in (("DIVERGE", set(lost) - {chatter}),
                                        ("CHATTER", chatter in lost)) if on)
    if cfg.robust.batch:
        where = f"a training batch of {cfg.robust.batch} plants"
        fix = (f"train on more plants (e.g. `--batch {4 * cfg.robust.batch}`) or with "
               f"`--aggregate max`, over ranges covering the held-out ones")
    else:
        where = "the nominal plant only"
        fix = ("tune robustly, e.g. `dscjax tune --batch 8 --aggregate cvar --cvar-level "
               "0.25` ([tuning.robust] in a config)")
    return (f"the tuned gains {verb}: {what}; they were tuned on {where}: do not deploy "
            f"them as they are; {fix}")


BATCHES = {"train": "training batch", "heldout": "held-out batch"}


def batch_counts(summary: dict, key: str = "heldout") -> str:
    """A batch's outcomes (summary[key]), start -> tuned gains, as sweeps report theirs: the
    line of report.md and of the console."""
    a, b = summary[key]["start"], summary[key]["tuned"]

    def counts(a, b):
        return "; ".join(f"{words} {a[k]} -> {b[k]}" for k, words in OUTCOMES.items())

    text = f"{BATCHES[key]} ({a['n']} plants, start -> tuned gains): {counts(a, b)}"
    if "n_chattering" in b:
        text += (f"; of the plants that did not diverge, chattering (chattering index above "
                 f"{metrics.CHATTER_RATIO:g}) {a['n_chattering']} -> {b['n_chattering']}")
    if "sampled" in b:
        text += f". With {summary['second_loop']}: {counts(a['sampled'], b['sampled'])}"
    return text


def warnings(s: dict) -> list[str]:
    """The warnings report.md opens with and the console ends with."""
    return [f"{lead}{s[key]}{tail}" for key, lead, tail in (
        ("heldout_warning", "", ""), ("margins_warning", "a margin fails: ", ""),
        ("sensitivity_warning", "", ' (see "Sensitivity of the constraints" in report.md)'))
        if s.get(key)]


def run_sentence(run: dict) -> str:
    """How the search went (report.json's "run"), in one line of report.md and the console."""
    return (f"Run: {run['iterations']} iterations, {run['evaluations']} evaluations of the loss "
            f"of which {run['gradient_evaluations']} with an exact gradient"
            + (f" (resumed at {run['resumed_from']})" if run["resumed_from"] else "")
            + f", {run['rejected']} rejected"
            + (f"; restarted afresh {run['restarts']} time(s)" if run.get("restarts") else "")
            + f"; stopped: {run['stop_reason']}. Best at iteration "
            f"{run['best_iteration']} (loss {run['best_loss']:.5g}, "
            f"{'feasible' if run['best_feasible'] else 'NOT feasible'}). Wall time "
            f"{run['wall_s']:.1f} s in this invocation, of which compilation "
            f"{run['compile_s']:.1f} s"
            + (f"; the whole command up to this report {run['wall_total_s']:.1f} s"
               if run["wall_total_s"] else "") + ".")


def _ratio(a, b):
    return "-" if a is None or b is None or b == 0 else f"{a / b:.3g}x"


def text(s: dict, problem) -> str:
    sim, cfg = problem.objective.sim, problem.cfg
    nom = s["nominal"]
    lines = ["# dscjax tune: report", ""]
    for w in warnings(s):
        lines += [f"> **Warning: {w}.**", ""]
    lines += [f"**Problem.** {s['problem']}", ""]
    lines += [
        f"Plant: `{type(problem.setup.plant).__name__}`, order n = {problem.setup.order}; "
        f"T = {sim.t_final:g} s, dt = {sim.dt:g} s, metric window [t0, T] = "
        f"{window(sim.window_start, sim.t_final)}.",
        method_text(problem),
        "Objective per plant: " + ", ".join(
            f"{k} {getattr(cfg.objective, k):g}" for k in TERMS if getattr(cfg.objective, k))
        + "".join(f"; penalty weight of the {name} bound {weight:g}" for name, bound, weight in (
            ("max|u|", s["bound_max_abs_u"], cfg.objective.u_max_weight),
            ("TV(u)", s["bound_tv_u"], cfg.objective.tv_max_weight)) if bound) + ".",
        "",
        run_sentence(s["run"]),
    ]
    lines += [f"Note: {note}." for note in s["notes"]]
    lines += [f"**Warning:** {w}." for w in s["warnings"]]
    lines += ["", "## Nominal plant", ""]
    if s.get("shifted_reference"):
        lines += ["The controller tracks a shifted reference (its initialisation moves y_r(0) to "
                  "x_1(0), the offset decaying): the error tuned and every error figure below is "
                  "measured against it unless it says \"against the config's y_r\".", ""]
    a, b = nom["start"], nom["tuned"]
    lines += table(("", "start gains", "tuned gains", "tuned / start"), [
        *((escape(label(k, s)), number(a[k]), number(b[k]), _ratio(b[k], a[k])) for k in LABELS
          if k in a),
        *((label, bool(a[k]), bool(b[k]), "") for k, label in (
            ("diverged", "diverged"), ("sampled_diverged", "diverged, the other discretisation"),
            ("delayed_diverged", "diverged, the input delayed")) if k in a)])
    if s["constraints"]["tuned"]:
        lines += ["", "## Constraints (nominal plant, checked exactly on every RK4 step)", "",
                  *table(("constraint", "bound (tuned)", "start", "tuned",
                          "margin (bound - tuned)", "tuned"), [
                      (escape(b["name"]), f"{b['bound']:.6g}", f"{a['value']:.6g}",
                       f"{b['value']:.6g}",
                       f"{b['margin']:.4g} ({100 * b['relative_margin']:.2f} %)",
                       f"**{'met' if b['met'] else 'violated'}**")
                      for a, b in _pairs(s["constraints"])])]
        if s["bound_max_abs_u"] or s["bound_tv_u"]:
            lines += ["", effort_span(s)]
    if s.get("sensitivity"):
        lines += sensitivity_section(s["sensitivity"])
    if s.get("train_constraints"):
        whose = ("per plant, the start gains' own figures on each training plant"
                 if s["effort_bounds"] == "per_plant" else "the nominal plant's, for every plant")
        lines += ["", "## Constraints per training plant (checked exactly on every RK4 step)",
                  "", f"Bounds: {whose} (`effort_bounds = \"{s['effort_bounds']}\"`).", "",
                  *table(("constraint", "bounds", "met (start)", "met (tuned)",
                          "worst plant (tuned)", "its value / bound", "margin (bound - value)"),
                         [_train_row(a, b) for a, b in _pairs(s["train_constraints"])])]
    if s.get("margins"):
        lines += margins.markdown(s["margins"], nom)
    if s["requirements"]["tuned"]:
        lines += ["", "## Requirements (nominal plant)", "",
                  *table(("requirement", "start", "tuned", "worst margin (tuned)"), [
                      (b["name"], *("met" if r["met_fraction"] == 1 else "violated"
                                    for r in (a, b)),
                       f"{b['worst_margin']:.4g}" + "".join(
                           f", {k} {b[k]:.4g}" for k in ("overshoot", "settling_time", "peak")
                           if k in b))
                      for a, b in _pairs(s["requirements"])])]
    for key in [k for k in BATCHES if k in s]:
        b = cfg.robust if key == "train" else cfg.heldout
        rng = ", ".join(r.resolve(problem.setup).spec() for r in b.ranges)
        st, tu = s[key]["start"], s[key]["tuned"]
        title = f"{BATCHES[key].capitalize()}: {st['n']} plants"
        lines += ["", f"## {title} ({rng}; {b.method.name}, seed {b.seed})", "",
                  *table(("", "start median", "tuned median", "start p95", "tuned p95",
                          "start max", "tuned max"), [
                      (escape(label(m, s)), *(number(d[q]) for q in ("median", "p95", "max")
                                               for d in (st[m], tu[m])))
                      for m in STATS_METRICS if st.get(m) is not None and tu.get(m) is not None])]
        lines += ["", f"{batch_counts(s, key)}. The figures above are over the plants that "
                  f"did not diverge (in the loop they name)."]
        if s[key]["requirements"]["tuned"]:
            lines += [""] + [f"- {r['name']}: met on {100 * r['met_fraction']:.1f} % of the "
                             f"plants with the tuned gains (start: {100 * a['met_fraction']:.1f} %)"
                             for a, r in _pairs(s[key]["requirements"])]
    lines += ["", "## Gains", "", *table(("parameter", "start", "tuned"), [
        (f"`{name}`", *(", ".join(f"{x:.5g}" for x in np.atleast_1d(np.asarray(v, float)))
                        for v in (a, s["gains"]["tuned"][name])))
        for name, a in s["gains"]["start"].items()])]
    # the command that runs the loop tuned
    lines += ["", f"Run the loop tuned ({s['loop']}) with `{s['simulate_command']}`.", ""]
    if s["figures"]:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in s["figures"]] + [""]
    return "\n".join(lines)


def _pairs(d: dict):
    """The rows of `d`'s start and tuned gains side by side."""
    return zip(d["start"], d["tuned"], strict=True)


def _train_row(a: dict, b: dict) -> tuple:
    """A row of the per-training-plant constraints table: start (a) against tuned (b)."""
    rng = (f"{b['bound_min']:.4g} to {b['bound_max']:.4g}" if b["bounds"] == "per_plant"
           else f"{b['bound_min']:.4g}")
    worst = ("diverged" if b["worst_value"] is None else
             f"{b['worst_value']:.6g} / {b['worst_bound']:.6g}")
    margin = ("-" if b["worst_margin"] is None else
              f"{b['worst_margin']:.4g} ({100 * b['worst_relative_margin']:.2f} %)")
    return (escape(b["name"]), rng, f"{a['n_met']} of {a['n']}", f"**{b['n_met']} of {b['n']}**",
            b["worst_plant"], worst, margin)


def label(key: str, s: dict) -> str:
    """A nominal row's label; the error figures say which reference they are against where
    the controller tracks a shifted one."""
    if s.get("shifted_reference") and key in ERRORS:
        return (LABELS[key] + " against the shifted y_r the controller tracks"
                + (" (tuned)" if key == "linf_error_window" else ""))
    return LABELS[key]


def effort_span(s: dict) -> str:
    """Where the effort bounds are measured, and the effort on the window beside them: a start
    transient can set a bound that the steady state never needs."""
    a, b = s["nominal"]["start"], s["nominal"]["tuned"]
    return (f"The effort bounds are measured over the whole horizon [0, T], the start-up "
            f"transient included. On [t0, T] the start gains use max|u| "
            f"{number(a.get('max_abs_u_window'))} and TV(u) {number(a.get('tv_u_window'))}, the "
            f"tuned {number(b.get('max_abs_u_window'))} and {number(b.get('tv_u_window'))}: "
            f"numbers for tuning.objective.u_max and tv_max bound them by your actuator.")


def sensitivity_section(sens: dict) -> list[str]:
    """report.md's "Sensitivity of the constraints": a row per tuned number, a column per
    constraint."""
    rows = sens["rows"]
    step = 100 * sens["step"]
    return ["", "## Sensitivity of the constraints (nominal plant, tuned gains)", "",
             f"e = d ln r / d ln g of each constraint r = value / bound <= 1 to each tuned "
             f"number g: a {step:g} % change of g moves r by about |e| x {step:g} %. **Bold**: "
             f"that change breaks it to first order. Not finite: any change may break it.", "",
             *table(("tuned number", *(f"{escape(r['name'])} (margin "
                                       f"{100 * r['relative_margin']:.3g} %)" for r in rows)),
                    [(f"`{name}`", *(f"**{v}**" if name in r["fragile"] else v for r, v in (
                        (r, elasticity.text(r["elasticity"][name])) for r in rows)))
                     for name in rows[0]["elasticity"]])]


def method_text(problem) -> str:
    """What is tuned and how, for report.md and the console's start line."""
    opt, mode = problem.cfg.optimizer, problem.mode.name
    tuned = f"Tuned: {problem.n_params} numbers ({', '.join(problem.selection.names)}). Method:"
    if not opt.name.generations:
        words = ("plant-by-plant (the aggregate's worst plants)" if mode == "plants" else
                 f"{mode}-mode")
        return (f"{tuned} {words} exact gradients: projected descent with optax's Adam scaling, "
                f"initial step {opt.learning_rate:g} in log-space.")
    cma = (f"CMA-ES (sigma0 {opt.sigma0:g} in log-space, population "
           f"{opt.popsize or f'sized to about {ROWS} trajectories a generation'}, seed "
           f"{opt.seed})")
    stalls = (f" or on a stall (its best loss falling by less than {100 * opt.stall_gain:g} % "
              f"over {opt.stall} generations)" if opt.stall else "")
    grows = f", the population x {opt.growth}" if opt.growth > 1 else ""
    restarts = (f" Restarted from the start point at its own stop{stalls}{grows}, at most "
                f"{opt.restarts} times." if opt.restarts else "")
    return (f"{tuned} {opt.name.name}: {cma}; one batched simulation per generation, no "
            f"gradient." + restarts)
