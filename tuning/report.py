"""The evidence of a tuning run: start against tuned gains on the nominal plant, on the
training batch and on a fresh held-out batch, every verdict with its effort (TV(u) and the
chattering index, docs/numerics.md); the constraints' margins and their elasticities to the
tuned numbers (`tuning.elasticity`); report.md, report.json and PNG figures."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import files, metrics, validation
from dscjax.params import assumption_warnings as with_ranges
from dscjax.plotting import subplots
from dscjax.reproduce import sampling
from dscjax.runspec import auto_stride
from dscjax.simulate import counted_levels, level_spec, refine_rows, simulate, simulate_batch
from tuning import elasticity, margins
from tuning.objective import shifted_reference, within
from tuning.runner import loop_words, simulate_command

STATS_METRICS = ("linf_error_window", "user_linf_error_window", "l2_error_window", "max_abs_u",
                 "l2_u", "tv_u_window", "sampled_linf_window", "delayed_linf_window",
                 "delayed_tv_u")
LABELS = {"linf_error_window": "L-inf error on [t0, T]", "l2_error_window": "L2 error on [t0, T]",
          "sampled_linf_window": "L-inf error on [t0, T], the other discretisation",
          "delayed_linf_window": "L-inf error on [t0, T], the input delayed",
          "delayed_tv_u": "TV(u) on [0, T], the input delayed",
          "max_abs_u": "max |u| on [0, T]", "l2_u": "L2(u)", "linf_error": "L-inf error on [0, T]",
          "tv_u": "TV(u) on [0, T]", "loss": "objective J",
          "max_abs_u_window": "max |u| on [t0, T]", "tv_u_window": "TV(u) on [t0, T]",
          "chattering_index": "chattering index on [t0, T] (chatters above "
                              f"{metrics.CHATTER_RATIO:g})",
          "user_linf_error_window": "L-inf error on [t0, T] against the config's y_r",
          "user_linf_error": "L-inf error on [0, T] against the config's y_r",
          "user_l2_error_window": "L2 error on [t0, T] against the config's y_r"}
# where the controller tracks a shifted reference, the error figures measured against it
SHIFTED = " against the shifted y_r the controller tracks"
ERRORS = ("linf_error_window", "l2_error_window", "linf_error", "sampled_linf_window",
          "delayed_linf_window")


def _md(text: str) -> str:
    """A label for a markdown table cell (a bare | would split the cell)."""
    return text.replace("|", "\\|")


def evaluate(problem, z0, z1) -> dict[str, Any]:
    """Per-plant figures for the start (z0) and tuned (z1) points: nominal, train, held-out."""
    obj = problem.objective
    per_plant = jax.jit(obj.per_plant)
    out = {"nominal": {}, "train": None, "heldout": None}
    for tag, z in (("start", z0), ("tuned", z1)):
        out["nominal"][tag] = _host(per_plant(z, {}))
    if obj.overrides:
        out["train"] = {tag: refined(problem, z, obj.overrides, _host(per_plant(z)))
                        for tag, z in (("start", z0), ("tuned", z1))}
    if problem.heldout:
        ov = {k: jnp.asarray(v) for k, v in problem.heldout.items()}
        out["heldout"] = {tag: refined(problem, z, ov, _host(per_plant(z, ov)))
                          for tag, z in (("start", z0), ("tuned", z1))}
    return out


def refined(problem, z, overrides, m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A batch's per-plant figures with the plants that diverged at the tuning's step re-run
    at `simulate`'s refinement levels, as sweeps do (a divergence of the integrator is not one
    of the loop); each check loop c alike. Adds `refined` and c_refined (the level that
    tracked, 0: the tuning's step); the refined plants' exact metrics and `diverged` are the
    refined runs', their loss and smooth surrogates stay the objective's."""
    m = dict(m)
    setup = jax.tree.map(np.asarray, problem.selection.apply(problem.setup, z))
    ov = {k: np.asarray(v) for k, v in overrides.items()}
    names = jax.eval_shape(metrics.finalize, metrics.running_init(np.float64), 1.0)
    keys = sorted(names.keys() & m.keys())
    m["refined"] = _refine(setup, ov, problem.objective.sim, m, {k: k for k in keys})
    for k in [k for k in m if k.startswith("user_")]:  # the refined runs do not measure them
        m[k] = np.where(m["refined"] > 0, np.nan, np.asarray(m[k], float))
    for c in problem.objective.checks:
        m[f"{c.name}_refined"] = _refine(setup, ov, c.sim, m, {
            "diverged": f"{c.name}_diverged", "linf_error_window": f"{c.name}_linf_window",
            "tv_u": f"{c.name}_tv_u"})
    return m


def _refine(setup, ov, sim, m, keys: dict[str, str]) -> np.ndarray:
    """Re-run the rows of `m` diverged at the refinement levels of `sim`, updating `m`'s
    `keys` (simulate's name -> m's) in place; returns the level that tracked per row (0: the
    tuning's step, or none)."""
    keys = {"diverged": keys.pop("diverged", "diverged"), **keys}
    diverged = np.asarray(m[keys["diverged"]]).astype(bool)
    if not diverged.any() or not sim.refine:
        return np.zeros(diverged.shape, np.int32)

    def level(j, idx):  # rows idx at refinement level j (level 0, the tuning's step, is m)
        spec = level_spec(sim, j).replace(refine=0)
        traj = simulate_batch(setup, {k: v[idx] for k, v in ov.items()}, spec=spec)
        return {"diverged": traj.diverged, **{k: traj.metrics[k] for k in keys if k != "diverged"}}

    rows = {k: np.asarray(m[mk], dtype=bool if k == "diverged" else float)
            for k, mk in keys.items()}
    rows, levels = refine_rows(rows, lambda r: r["diverged"], level, counted_levels(sim))
    for k, mk in keys.items():
        m[mk] = rows[k]
    return np.where(rows["diverged"], 0, levels).astype(np.int32)


def _host(d):
    return {k: np.asarray(v) for k, v in jax.device_get(d).items()}


def batch_stats(m: dict[str, np.ndarray]) -> dict[str, Any]:
    ok = ~m["diverged"].astype(bool)
    refined = ok & (np.asarray(m.get("refined", 0)) > 0)
    # as a sweep's rows: tracked at the tuning's step, after refinement, or diverged
    out: dict[str, Any] = {"n": int(m["diverged"].size), "n_tracked": int((ok & ~refined).sum()),
                           "n_refined": int(refined.sum()), "n_diverged": int((~ok).sum())}
    masks = {}
    for c in ("sampled", "delayed"):  # the same three outcomes in each check loop
        if f"{c}_diverged" in m:
            masks[c] = c_ok = ~m[f"{c}_diverged"].astype(bool)
            ref = c_ok & (np.asarray(m.get(f"{c}_refined", 0)) > 0)
            out[c] = {"n_tracked": int((c_ok & ~ref).sum()), "n_refined": int(ref.sum()),
                      "n_diverged": int((~c_ok).sum())}
    for key in STATS_METRICS + ("loss",):
        if key not in m:
            continue
        v = m[key] if key == "loss" else m[key][masks.get(key.split("_")[0], ok)]
        v = np.asarray(v, float)
        v = v[np.isfinite(v)] if key.startswith("user_") else v  # (not measured once refined)
        out[key] = None if v.size == 0 else {
            "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "max": float(np.max(v)), "mean": float(np.mean(v))}
    if "chattering_index" in m:  # the plants that track in the loop tuned but chatter
        out["n_chattering"] = int(sum(metrics.chatters(v) for v in
                                      np.asarray(m["chattering_index"], float)[ok]))
    return out


def requirement_checks(problem, m: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    rows = []
    for i, r in enumerate(problem.objective.requirements):
        met = np.asarray(m[f"req{i}_met"]) > 0
        row = {"name": r.name, "met_fraction": float(np.mean(met)),
               "worst_margin": float(np.max(m[f"req{i}_margin"]))}
        for k in ("overshoot", "settling_time", "peak"):
            if f"req{i}_{k}" in m:
                row[k] = float(np.max(m[f"req{i}_{k}"]))
        rows.append(row)
    return rows


def constraint_checks(scales, m: dict[str, Any], checks=()) -> list[dict[str, Any]]:
    """The bounds checked exactly on one plant's metrics `m` (every RK4 step): name, value,
    bound, margin and met (within `BOUND_RTOL`; never for a diverged plant). Each check loop
    (`CheckLoop`) adds its rows: its windowed L-inf and effort bounds."""
    rows = []
    diverged = bool(np.asarray(m.get("diverged", False)))
    for c in checks:
        diverged = diverged or bool(np.asarray(m[f"{c.name}_diverged"]))
    for name, key, bound in _checks((scales.u_max, scales.tv_max), m, checks):
        value = float(np.asarray(m[key]))
        margin = float(bound) - value
        rows.append({"name": name, "key": key, "value": value, "bound": float(bound),
                     "margin": margin,
                     "relative_margin": margin / float(bound),
                     "met": bool(not diverged and np.isfinite(value)
                                 and bool(within(value, float(bound))))})
    return rows


def _checks(bounds, m, checks) -> list[tuple]:
    """(name, metric, bound) of each bound (max|u|, TV(u), the check loops') there is."""
    out = list(zip(("max|u|", "TV(u)"), ("max_abs_u", "tv_u"), bounds, strict=True))
    for c in checks:
        out.append((f"L-inf on [t0,T], {c.label}", f"{c.name}_linf_window",
                    c.linf_factor * np.asarray(m["linf_error_window"], float)))
        out += [(f"{what}, {c.label}", f"{c.name}_{key}",
                 b if f == 1 else f * np.asarray(b, float))
                for what, key, b, f in c.bounded(bounds)]
    return [c for c in out if c[2] is not None]


def train_constraint_checks(scales, m: dict[str, Any], checks=()) -> list[dict[str, Any]]:
    """The bounds checked exactly on every training plant (`m` as `evaluate` gives it), each
    against its own or the nominal bound: how many meet it, and the worst plant (the smallest
    relative margin; a diverged plant meets nothing and is the worst)."""
    diverged = np.asarray(m["diverged"]).astype(bool)
    n = diverged.size
    rows = []
    for c in checks:
        diverged = diverged | np.asarray(m[f"{c.name}_diverged"]).astype(bool)
    for name, key, bound in _checks(scales.bounds(train=True), m, checks):
        b = np.broadcast_to(np.asarray(bound, float), (n,))
        v = np.asarray(m[key], float).reshape(n)
        with np.errstate(invalid="ignore"):
            met = ~diverged & np.isfinite(v) & within(v, b)
            rel = np.where(diverged | ~np.isfinite(v), -np.inf, (b - v) / b)
        worst = int(np.argmin(rel))
        measured = bool(np.isfinite(rel[worst]))
        rows.append({"name": name, "bounds": "per_plant" if np.ndim(bound) else "nominal",
                     "n": n, "n_met": int(met.sum()), "worst_plant": worst,
                     "worst_value": float(v[worst]) if measured else None,
                     "worst_bound": float(b[worst]),
                     "worst_margin": float(b[worst] - v[worst]) if measured else None,
                     "worst_relative_margin": float(rel[worst]) if measured else None,
                     "bound_min": float(b.min()), "bound_max": float(b.max())})
    return rows


def problem_sentence(problem) -> str:
    """The problem in one sentence (report.md's first line)."""
    cfg, sc, sim = problem.cfg, problem.objective.scales, problem.objective.sim
    what = {"linf": "the L-inf tracking error", "l2": "the L2 tracking error",
            "effort_l2": "L2(u)", "effort_max": "max|u|", "effort_tv": "TV(u)"}
    if shifted_reference(problem.setup) is not None:
        for k in ("linf", "l2"):
            what[k] += " (against the reference the controller tracks: y_r shifted by its "
            what[k] += "initialisation to start at x_1(0))"
    terms = [what[k] for k in what if getattr(cfg.objective, k)]
    where = ("the nominal plant" if not cfg.robust.batch else
             f"the {cfg.robust.aggregate}"
             + (f" at level {cfg.robust.cvar_level:g}" if cfg.robust.aggregate == "cvar" else "")
             + f" over {cfg.robust.batch} training plants")
    cons = []
    for name, per, bound, key, factor in (
            ("max|u|", sc.u_max_train, sc.u_max, "u_max", ""),
            ("TV(u)", sc.tv_max_train, sc.tv_max, "tv_max", f"{cfg.objective.tv_max_factor:g} x ")):
        if per is not None:
            cons.append(f"{name} <= {factor}the start gains' {name} on each training plant "
                        f"({per.min():.4g} to {per.max():.4g}; nominal plant {bound:.4g})")
        elif bound is not None:
            cons.append(f"{name} <= {bound:.4g}" + (f" ({factor}the start gains' on the nominal "
                        f"plant)" if getattr(cfg.objective, key) == "start" else ""))
    on = "" if sc.per_plant else " on " + (
        "the nominal plant" if not cfg.robust.batch else "every training plant")
    return (f"Minimise {' + '.join(terms)} on [{sim.window_start:g}, {sim.t_final:g}] s over "
            f"{problem.n_params} design numbers on {where}"
            + (f", subject to {' and '.join(cons)}{on}" if cons else ", unconstrained") + ".")


def trajectories(problem, z0, z1, save_every: int = 10):
    """The start and tuned loops on the nominal plant for the figures, saved every
    `save_every` steps or more (`runspec.auto_stride`)."""
    sim = problem.objective.sim
    spec = sim.replace(save_every=max(save_every, auto_stride(sim.n_steps)), refine=0)
    out = {}
    for tag, z in (("start", z0), ("tuned", z1)):
        setup = jax.tree.map(np.asarray, problem.selection.apply(problem.setup, z))
        out[tag] = simulate(setup, spec=spec, throw=False)
    return out


def write(out: Path, result, *, plots: bool = True, t_start: float | None = None) -> dict:
    """Evaluate, then write report.json (the summary returned), report.md and (with plots) the
    PNGs; `t_start` (perf_counter at the command's start) gives the whole wall time."""
    problem, tr = result.problem, result.trace
    sc, checks = problem.objective.scales, problem.objective.checks
    z0, z1 = problem.z0, jax.device_get(result.best_z)
    ev = evaluate(problem, z0, z1)
    nom = {tag: _measured({k: float(np.asarray(v)) for k, v in ev["nominal"][tag].items()
                           if np.ndim(v) == 0}) for tag in ("start", "tuned")}
    summary: dict[str, Any] = {
        "nominal": nom,
        "bound_max_abs_u": sc.u_max, "bound_tv_u": sc.tv_max,
        "effort_bounds": problem.cfg.objective.effort_bounds,
        "bounds_train": _bounds_train(sc), "problem": problem_sentence(problem),
        "constraints": {tag: constraint_checks(sc, ev["nominal"][tag], checks)
                        for tag in ("start", "tuned")},
        "sample_time": problem.objective.sim.sample_time,
        "second_loop": second_label(problem),
        "requirements": {tag: requirement_checks(problem, ev["nominal"][tag])
                         for tag in ("start", "tuned")},
        "run": {
            "iterations": tr.iterations, "resumed_from": result.resumed_from,
            "rejected": result.rejected, "stop_reason": result.stop_reason,
            "restarts": tr.restarts, "best_iteration": tr.best_iteration,
            "best_loss": tr.best_loss, "best_feasible": tr.best_feasible,
            "wall_s": result.wall_s, "compile_s": result.compile_s, "wall_total_s": None,
            "gradient": problem.mode, "method": problem.cfg.optimizer.name,
            "evaluations": tr.evaluations, "gradient_evaluations": tr.gradients,
            "n_params": problem.n_params},
        "gains": {"start": _values(problem, z0), "tuned": _values(problem, z1)},
        "settings": problem.describe(),
        "notes": list(problem.notes),
        "warnings": assumption_warnings(problem)
        + [f"tuned gains: {w}" for w in validation.assumption_warnings(result.best_setup)
           if w not in validation.assumption_warnings(problem.setup)],
    }
    if ev["train"] is not None and (sc.u_max is not None or sc.tv_max is not None or checks):
        summary["train_constraints"] = {tag: train_constraint_checks(sc, ev["train"][tag], checks)
                                        for tag in ("start", "tuned")}
    for key in ("train", "heldout"):
        if ev[key] is not None:
            summary[key] = {tag: batch_stats(ev[key][tag]) for tag in ("start", "tuned")}
            summary[key]["requirements"] = {tag: requirement_checks(problem, ev[key][tag])
                                            for tag in ("start", "tuned")}
    summary["heldout_warning"] = heldout_warning(summary, problem.cfg)
    summary["shifted_reference"] = shifted_reference(problem.setup) is not None
    # with the held-out check and the margins: `--heldout 0`, a quick run, skips all three
    summary["sensitivity"] = (None if not (problem.heldout and summary["constraints"]["tuned"])
                              else elasticity.constraints(problem, z1,
                                                          summary["constraints"]["tuned"]))
    summary["sensitivity_warning"] = elasticity.warning(summary["sensitivity"])
    summary["simulate_command"] = simulate_command(problem)
    summary["loop"] = loop_words(problem.objective.sim)
    summary["heldout_box"] = ([r.resolve(problem.setup).spec() for r in problem.cfg.heldout.ranges]
                              if problem.heldout else None)
    # the margins come with the held-out check (`--heldout 0` skips them)
    summary["margins"] = margins.evaluate(problem, z0, z1, ev) if problem.heldout else None
    summary["margins_warning"] = (None if summary["margins"] is None else
                                  "; ".join(margins.failures(summary["margins"])) or None)
    out = Path(out)
    figures = (_plots(out, result, ev, trajectories(problem, z0, z1), problem.objective.sim,
                      problem) if plots else [])
    st = (summary["margins"] or {}).get("sample_time")
    if plots and st is not None:
        sampling.plot(st, out / "sampling.png", {"start": "#7f7f7f", "tuned": "#d62728"}, 110,
                      labels={"start": "start gains", "tuned": "tuned gains"})
        figures.append("sampling.png")
    summary["figures"] = figures
    if t_start is not None:
        summary["run"]["wall_total_s"] = time.perf_counter() - t_start
    files.write_json(out / "report.json", summary)
    files.write_text(out / "report.md", _markdown(summary, problem, figures))
    return summary


def second_label(problem) -> str | None:
    """The second loop in words ("the states by forward Euler"), None without one."""
    return next((c.label for c in problem.objective.checks if c.name == "sampled"), None)


def _bounds_train(sc) -> dict[str, Any] | None:
    """The per-plant bounds of the training batch (None: the nominal ones for every plant)."""
    if not sc.per_plant:
        return None
    return {"max_abs_u": None if sc.u_max_train is None else sc.u_max_train.tolist(),
            "tv_u": None if sc.tv_max_train is None else sc.tv_max_train.tolist(),
            "n_start_diverged": sc.n_train_fallback}


def heldout_warning(summary: dict, cfg) -> str | None:
    """The sentence put first when the tuned gains lose held-out plants (diverged, tracked only
    once refined, diverged sampled, or chattering: a small error with an input that switches
    is not tracking), None if on none: that must not hide in a table."""
    h = summary.get("heldout")
    if not h:
        return None
    lost = {"diverged": (h["tuned"]["n_diverged"], h["start"]["n_diverged"]),
            "RK4 diverged at dt (the loop stiff there; tracked only once refined)":
            (h["tuned"]["n_refined"], h["start"]["n_refined"])}
    if "sampled" in h["tuned"]:
        lost[f"diverged with {summary['second_loop']}"] = (h["tuned"]["sampled"]["n_diverged"],
                                                 h["start"]["sampled"]["n_diverged"])
    chatter = f"chatter (chattering index above {metrics.CHATTER_RATIO:g})"
    lost[chatter] = (h["tuned"].get("n_chattering", 0), h["start"].get("n_chattering", 0))
    lost = {how: kk for how, kk in lost.items() if kk[0]}
    if not lost:
        return None
    n = h["tuned"]["n"]
    what = "; ".join(f"{how} on {k} of {n} held-out plants (start gains: {k0})"
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


def heldout_counts(summary: dict) -> str | None:
    """The held-out outcomes, start -> tuned gains, as sweeps report theirs (None: no batch)."""
    h = summary.get("heldout")
    if not h:
        return None
    a, b = h["start"], h["tuned"]

    def counts(a, b):
        return (f"tracked {a['n_tracked']} -> {b['n_tracked']}; tracked after refinement (a "
                f"numerically stiff run re-done with ETDRK4 at a smaller step) {a['n_refined']} "
                f"-> {b['n_refined']}; diverged at every step tried {a['n_diverged']} -> "
                f"{b['n_diverged']}")

    text = f"held-out batch ({a['n']} plants, start -> tuned gains): {counts(a, b)}"
    if "sampled" in b:
        text += (f". With {summary['second_loop']}: "
                 f"{counts(a['sampled'], b['sampled'])}")
    return text


def _measured(m: dict[str, float]) -> dict[str, float]:
    """A diverged plant's metrics as NaN (null in report.json: not measured); its loss stays."""
    if not m.get("diverged"):
        return m
    return {k: v if k in ("loss", "diverged") else float("nan") for k, v in m.items()}


def assumption_warnings(problem) -> list[str]:
    """The paper's assumptions the start setup violates, at the nominal plant or at an end of
    the training or held-out ranges."""
    out, cfg = [], problem.cfg
    for key, b in (("robust", cfg.robust), ("heldout", cfg.heldout)):
        ranges = [r.resolve(problem.setup) for r in b.ranges] if b.batch else []
        for w in with_ranges(problem.setup, ranges, f"tuning.{key}.ranges"):
            if w not in out:
                out.append(w)
    return out


def _values(problem, z):
    values = jax.device_get(problem.selection.values(z))
    return {name: np.asarray(values[name]).tolist() for name in problem.selection.names}


def _f(v, digits=4):
    return "-" if v is None or v != v else f"{v:.{digits}g}"  # None or NaN: not measured


def _ratio(a, b):
    return "-" if a is None or b is None or b == 0 else f"{a / b:.3g}x"


def _own(s: dict, key: str) -> str:
    """" on the nominal plant, each training plant its own" where that bound is per plant."""
    per = s.get("bounds_train") or {}
    return " on the nominal plant, each training plant its own" if per.get(key) else ""


def _markdown(s: dict, problem, figures) -> str:
    sim = problem.objective.sim
    run = s["run"]
    nom = s["nominal"]
    cfg = problem.cfg
    lines = ["# dscjax tune: report", ""]
    if s.get("heldout_warning"):
        lines += [f"> **Warning: {s['heldout_warning']}.**", ""]
    if s.get("margins_warning"):
        lines += [f"> **Warning: a margin fails: {s['margins_warning']}.**", ""]
    if s.get("sensitivity_warning"):
        lines += [f"> **Warning: {s['sensitivity_warning']} (\"Sensitivity of the "
                  f"constraints\" below).**", ""]
    lines += [f"**Problem.** {s['problem']}", ""]
    lines += [
        f"Plant: `{type(problem.setup.plant).__name__}`, order n = {problem.setup.order}; "
        f"T = {sim.t_final:g} s, dt = {sim.dt:g} s, metric window [t0, T] = "
        f"[{sim.window_start:g}, {sim.t_final:g}] s.",
        f"Loop tuned: {s['loop']}.",
        f"Tuned: {problem.n_params} numbers ({', '.join(problem.selection.names)}). "
        f"Method: {method_sentence(cfg.optimizer, run['gradient'])}",
        "Objective per plant: " + ", ".join(
            f"{k} {getattr(cfg.objective, k):g}" for k in ("linf", "l2", "effort_l2",
                                                          "effort_max", "effort_tv")
            if getattr(cfg.objective, k)) + (
            f"; max|u| <= {s['bound_max_abs_u']:.4g}{_own(s, 'max_abs_u')} (penalty weight "
            f"{cfg.objective.u_max_weight:g})" if s["bound_max_abs_u"] else "")
        + (f"; TV(u) <= {s['bound_tv_u']:.4g}{_own(s, 'tv_u')} (penalty weight "
           f"{cfg.objective.tv_max_weight:g})" if s["bound_tv_u"] else "")
        + (f"; over a training batch of {cfg.robust.batch} plants ({cfg.robust.aggregate}"
           + (f" at level {cfg.robust.cvar_level:g}" if cfg.robust.aggregate == "cvar" else "")
           + ")" if cfg.robust.batch else "; nominal plant only") + ".",
        "",
        f"Run: {run['iterations']} iterations, {run['evaluations']} evaluations of the loss "
        f"of which {run['gradient_evaluations']} with an exact gradient"
        + (f" (resumed at {run['resumed_from']})" if run["resumed_from"] else "")
        + f", {run['rejected']} rejected"
        + (f"; restarted afresh {run['restarts']} time(s) (CMA-ES from the start point after "
           f"its own criteria stopped it; adam from a random point after its step collapsed)"
           if run.get("restarts") else "")
        + f"; stopped: {run['stop_reason']}. Best at iteration "
        f"{run['best_iteration']} (loss {run['best_loss']:.5g}, "
        f"{'feasible' if run['best_feasible'] else 'NOT feasible'}). Wall time "
        f"{run['wall_s']:.1f} s in this invocation, of which compilation {run['compile_s']:.1f} s"
        + (f"; the whole command up to this report {run['wall_total_s']:.1f} s"
           if run["wall_total_s"] else "") + ".",
    ]
    for note in s["notes"]:
        lines.append(f"Note: {note}.")
    for w in s["warnings"]:
        lines.append(f"**Warning:** {w}.")
    lines += ["", "## Nominal plant", ""]
    if s.get("shifted_reference"):
        lines += ["The controller tracks a shifted reference (its initialisation moves y_r(0) "
                  "to x_1(0), the offset decaying): the error tuned and every error figure "
                  "below is measured against it unless it says \"against the config's "
                  "y_r\".", ""]
    lines += ["| | start gains | tuned gains | tuned / start |", "|---|---|---|---|"]
    for key in ("linf_error_window", "user_linf_error_window", "l2_error_window",
                "user_l2_error_window", "linf_error", "user_linf_error", "max_abs_u",
                "max_abs_u_window", "l2_u", "tv_u", "tv_u_window", "chattering_index",
                "sampled_linf_window", "delayed_linf_window", "delayed_tv_u"):
        if key in nom["start"]:
            a, b = nom["start"][key], nom["tuned"][key]
            lines.append(f"| {_md(_label(key, s))} | {_f(a)} | {_f(b)} | {_ratio(b, a)} |")
    for key, label in (("diverged", "diverged"),
                       ("sampled_diverged", "diverged, the other discretisation"),
                       ("delayed_diverged", "diverged, the input delayed")):
        if key in nom["start"]:
            lines.append(f"| {label} | {bool(nom['start'][key])} | {bool(nom['tuned'][key])} "
                         f"| |")
    if s["constraints"]["tuned"]:
        lines += ["", "## Constraints (nominal plant, checked exactly on every RK4 step)", "",
                  "| constraint | bound (tuned) | start | tuned | margin (bound - tuned) | tuned |",
                  "|---|---|---|---|---|---|"]
        for a, b in zip(s["constraints"]["start"], s["constraints"]["tuned"], strict=True):
            lines.append(f"| {_md(b['name'])} | {b['bound']:.6g} | {a['value']:.6g} | "
                         f"{b['value']:.6g} | {b['margin']:.4g} "
                         f"({100 * b['relative_margin']:.2f} %) | "
                         f"**{'met' if b['met'] else 'violated'}** |")
        if s["bound_max_abs_u"] or s["bound_tv_u"]:
            lines += ["", effort_span(s)]
    if s.get("sensitivity"):
        lines += sensitivity_section(s["sensitivity"])
    if s.get("train_constraints"):
        per = s["effort_bounds"] == "per_plant"
        lines += ["", "## Constraints per training plant (checked exactly on every RK4 step)",
                  "", ("Bounds: per plant, the start gains' own figures on each training plant "
                       "(`effort_bounds = \"per_plant\"`)." if per else
                       "Bounds: the nominal plant's, for every training plant "
                       "(`effort_bounds = \"nominal\"`)."), "",
                  "| constraint | bounds | met (start) | met (tuned) | worst plant (tuned) | "
                  "its value / bound | margin (bound - value) |", "|---|---|---|---|---|---|---|"]
        for a, b in zip(s["train_constraints"]["start"], s["train_constraints"]["tuned"],
                        strict=True):
            rng = (f"{b['bound_min']:.4g} to {b['bound_max']:.4g}" if b["bounds"] == "per_plant"
                   else f"{b['bound_min']:.4g}")
            worst = ("diverged" if b["worst_value"] is None else
                     f"{b['worst_value']:.6g} / {b['worst_bound']:.6g}")
            margin = ("-" if b["worst_margin"] is None else
                      f"{b['worst_margin']:.4g} ({100 * b['worst_relative_margin']:.2f} %)")
            lines.append(f"| {_md(b['name'])} | {rng} | {a['n_met']} of {a['n']} | "
                         f"**{b['n_met']} of {b['n']}** | {b['worst_plant']} | {worst} | "
                         f"{margin} |")
    if s.get("margins"):
        short = {tag: nom[tag].get("linf_error_window") for tag in ("start", "tuned")}
        lines += margins.markdown(s["margins"], {k: None if v is None or v != v else v
                                                 for k, v in short.items()})
    if s["requirements"]["tuned"]:
        lines += ["", "## Requirements (nominal plant)", "",
                  "| requirement | start | tuned | worst margin (tuned) |", "|---|---|---|---|"]
        for a, b in zip(s["requirements"]["start"], s["requirements"]["tuned"], strict=True):
            extra = "".join(f", {k} {b[k]:.4g}" for k in ("overshoot", "settling_time", "peak")
                            if k in b)
            lines.append(f"| {b['name']} | {'met' if a['met_fraction'] == 1 else 'violated'} | "
                         f"{'met' if b['met_fraction'] == 1 else 'violated'} | "
                         f"{b['worst_margin']:.4g}{extra} |")
    for key, title in (("train", "Training batch"), ("heldout", "Held-out batch")):
        if key not in s:
            continue
        b = cfg.robust if key == "train" else cfg.heldout
        rng = ", ".join(r.resolve(problem.setup).spec() for r in b.ranges)
        st, tu = s[key]["start"], s[key]["tuned"]
        lines += ["", f"## {title}: {st['n']} plants ({rng}; {b.method}, seed {b.seed})", "",
                  "| | start median | tuned median | start p95 | tuned p95 | start max | "
                  "tuned max |", "|---|---|---|---|---|---|---|"]
        for m in STATS_METRICS:
            a, c = st.get(m), tu.get(m)
            if a is None or c is None:
                continue
            lines.append(f"| {_md(_label(m, s))} | {_f(a['median'])} | {_f(c['median'])} | "
                         f"{_f(a['p95'])} | {_f(c['p95'])} | {_f(a['max'])} | {_f(c['max'])} |")
        lines += ["", f"Plants: tracked {st['n_tracked']} (start) and {tu['n_tracked']} "
                  f"(tuned); tracked after refinement (a numerically "
                  f"stiff run re-done with ETDRK4 at a smaller step, as sweeps do) "
                  f"{st['n_refined']} and {tu['n_refined']}; diverged at every step tried "
                  f"{st['n_diverged']} and {tu['n_diverged']}"
                  + (f"; of the plants that did not diverge, chattering (chattering index "
                     f"above {metrics.CHATTER_RATIO:g}) {st['n_chattering']} and "
                     f"{tu['n_chattering']}" if "n_chattering" in tu else "") + "."]
        if "sampled" in tu:
            a, c = st["sampled"], tu["sampled"]
            lines.append(f"With {s['second_loop']}: tracked "
                         f"{a['n_tracked']} and {c['n_tracked']}; tracked after refinement "
                         f"{a['n_refined']} and {c['n_refined']}; diverged {a['n_diverged']} "
                         f"and {c['n_diverged']}.")
        lines.append("The figures above are over the plants that did not diverge (in the "
                     "loop they name).")
        reqs = s[key]["requirements"]["tuned"]
        if reqs:
            lines += [""] + [f"- {r['name']}: met on {100 * r['met_fraction']:.1f} % of the "
                             f"plants with the tuned gains (start: "
                             f"{100 * a['met_fraction']:.1f} %)"
                             for r, a in zip(reqs, s[key]["requirements"]["start"], strict=True)]
    lines += ["", "## Gains", "", "| parameter | start | tuned |", "|---|---|---|"]
    for name in s["gains"]["start"]:
        lines.append(f"| `{name}` | {_fmt_val(s['gains']['start'][name])} | "
                     f"{_fmt_val(s['gains']['tuned'][name])} |")
    lines += ["", run_sentence(s), ""]
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)


def _label(key: str, s: dict) -> str:
    """A nominal row's label; the error figures say which reference they are against where
    the controller tracks a shifted one."""
    label = LABELS[key]
    if s.get("shifted_reference") and key in ERRORS:
        label += SHIFTED + (" (tuned)" if key == "linf_error_window" else "")
    return label


def effort_span(s: dict) -> str:
    """Where the effort bounds are measured, and the effort on the window beside them: a start
    transient can set a bound that the steady state never needs."""
    a, b = s["nominal"]["start"], s["nominal"]["tuned"]
    return (f"The effort bounds are measured over the whole horizon [0, T], the start-up "
            f"transient included (the actuator must survive it, and a bound on the window "
            f"alone would let the search buy its error with an unbounded transient). On the "
            f"window [t0, T], where the error is measured, the start gains use max|u| "
            f"{_f(a.get('max_abs_u_window'))} and TV(u) {_f(a.get('tv_u_window'))}, the "
            f"tuned gains {_f(b.get('max_abs_u_window'))} and {_f(b.get('tv_u_window'))}: a "
            f"bound over [0, T] does not hold the window's effort to the start's figure there "
            f"(numbers for tuning.objective.u_max and tv_max bound it by your actuator's "
            f"limits).")


def sensitivity_section(sens: dict) -> list[str]:
    """report.md's "Sensitivity of the constraints": a row per tuned number, a column per
    constraint."""
    rows = sens["rows"]
    step = 100 * sens["step"]
    lines = ["", "## Sensitivity of the constraints (nominal plant, tuned gains)", "",
             f"d ln r / d ln g of each constraint r = value / bound <= 1 to each tuned number "
             f"g, by reverse mode through the loop tuned (one pass per figure the constraints "
             f"read): a {step:g} % change of g moves r by about |d ln r / d ln g| x {step:g} %. "
             f"**Bold**: that change breaks the constraint to first order (r (1 + "
             f"{sens['step']:g} |e|) > 1). Not finite: the loop's tangent grew without bound "
             f"over the run (the loop depends sensitively on its gains: chaotic or "
             f"chattering); any change may break the constraint.", "",
             "| tuned number | " + " | ".join(
                 f"{_md(r['name'])} (margin {100 * r['relative_margin']:.3g} %)" for r in rows)
             + " |", "|---|" + "---|" * len(rows)]
    for name in rows[0]["elasticity"]:
        cells = []
        for r in rows:
            v = elasticity.text(r["elasticity"][name])
            cells.append(f"**{v}**" if name in r["fragile"] else v)
        lines.append(f"| `{name}` | " + " | ".join(cells) + " |")
    return lines


def run_sentence(s: dict) -> str:
    """report.md's last line: the command that runs the loop tuned."""
    return f"Run the loop tuned ({s['loop']}) with `{s['simulate_command']}`."


def _mode_words(mode: str) -> str:
    return "plant-by-plant (the aggregate's worst plants)" if mode == "plants" else f"{mode}-mode"


def method_sentence(opt, mode: str) -> str:
    if opt.name == "adam":
        return (f"{_mode_words(mode)} exact gradients: projected gradient descent with "
                f"optax's Adam scaling, initial step {opt.learning_rate:g} in log-space, x1.2 "
                f"after an improvement, halved (from the last good point) after a worse one.")
    cma = (f"CMA-ES (sigma0 {opt.sigma0:g} in log-space, population "
           f"{opt.popsize or 'default (4 + 3 ln n)'}, seed {opt.seed})")
    grows = f" and {opt.growth} times the population" if opt.growth > 1 else ""
    restarts = (f" When CMA-ES's own criteria stop it before the budget ends, a fresh CMA-ES "
                f"starts from the start point{grows} (at most {opt.restarts} times; the best "
                f"point is kept)." if opt.restarts else "")
    return (f"{opt.name}: {cma}; one batched simulation per generation, no gradient."
            + restarts)


def _fmt_val(v):
    a = np.atleast_1d(np.asarray(v, dtype=float))
    return ", ".join(f"{x:.5g}" for x in a)


def plot_loss_curve(history, path, *, u_max: float | None = None, batch: bool = False):
    """loss_curve.png: the loss (best loss, rejected steps), the L-inf error and max|u| (its
    bound) per iteration, a panel each. Returns the Figure (saved)."""
    it = np.array([r["iteration"] for r in history])
    loss = np.array([r["loss"] for r in history], dtype=float)
    best = np.array([r["best_loss"] for r in history], dtype=float)
    acc = np.array([bool(r["accepted"]) for r in history])
    linf = np.array([r["linf_window"] for r in history], dtype=float)
    umax = np.array([r["max_abs_u"] for r in history], dtype=float)
    fig, ax = subplots(1, 3, figsize=(14, 4))
    ax[0].semilogy(it, loss, lw=1, label="loss of the iteration")
    ax[0].semilogy(it, best, lw=1.5, label="best loss so far")
    if (~acc).any():
        ax[0].semilogy(it[~acc], loss[~acc], "rx", label="rejected step")
    ax[0].set(ylabel="objective J [-] (about 1 at the start gains)", title="loss")
    ax[1].semilogy(it, linf, color="#d62728", lw=1, label="L-inf error on [t0, T]")
    worst = " (worst training plant)" if batch else ""
    ax[1].set(ylabel="L-inf tracking error on [t0, T] [-]", title="tracking error" + worst)
    ax[2].plot(it, umax, color="#2ca02c", lw=1, label="max|u|" + worst)
    if u_max:
        ax[2].axhline(u_max, color="k", ls=":", lw=1, label=f"bound on max|u| ({u_max:.4g})")
    ax[2].set(ylabel="max|u| [-]", title="control amplitude")
    for a in ax:
        a.set_xlabel("iteration")
        a.grid(alpha=0.3, which="both")
        a.legend(fontsize=8)
    files.save_figure(fig, path, dpi=110)
    return fig


def _plots(out: Path, result, ev, trajs, sim, problem) -> list[str]:
    figures, sc = [], problem.objective.scales
    if result.history:
        plot_loss_curve(result.history, out / "loss_curve.png", u_max=sc.u_max,
                        batch=bool(problem.objective.overrides))
        figures.append("loss_curve.png")

    fig, ax = subplots(4, 1, figsize=(10, 11), layout="constrained")
    for tag, color in (("start", "#7f7f7f"), ("tuned", "#d62728")):
        tr = trajs[tag]
        t, e, u = np.asarray(tr.t), np.asarray(tr.e), np.asarray(tr.u)
        label = f"{tag} (" + (f"diverged at {float(tr.t_diverged):.3g} s" if bool(tr.diverged)
                              else f"L-inf on [t0,T] {float(tr.metrics['linf_error_window']):.3g}"
                              ) + ")"
        ax[0].plot(t, e, color=color, lw=0.9, label=label)
        win = t >= sim.window_start
        ax[1].plot(t[win], e[win], color=color, lw=0.9, label=tag)
        tv = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(u)))])
        ax[3].plot(t, tv, color=color, lw=1.2,
                   label=f"{tag} (TV(u) on every step {float(tr.metrics['tv_u']):.4g})")
        ax[2].plot(t, u, color="#2ca02c" if tag == "tuned" else color, lw=0.9,
                   label=f"{tag} (max|u| {float(tr.metrics['max_abs_u']):.3g})")
    if sc.u_max:
        for sgn in (1, -1):
            ax[2].axhline(sgn * sc.u_max, color="k", ls=":", lw=0.8)
    ax[0].set(ylabel="e = y - y_r [-]", title="tracking error, whole horizon")
    ax[1].set(ylabel="e on [t0, T] [-]",
              title=f"tracking error on the window [{sim.window_start:g}, {sim.t_final:g}] s")
    ax[2].set(ylabel="u [-]", title="control input (dotted: the bound on max|u|)")
    if sc.tv_max:
        ax[3].axhline(sc.tv_max, color="k", ls=":", lw=0.8,
                      label=f"bound on TV(u) ({sc.tv_max:.4g})")
    ax[3].set(ylabel="sum |du| [-]", xlabel="time t [s]", title="total variation of u up to t "
              "(curves: on the saved grid, a lower bound; labels: exact)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(loc="upper right", fontsize=8)
    files.save_figure(fig, out / "before_after.png", dpi=110)
    figures.append("before_after.png")

    if ev["heldout"] is not None:
        fig, ax = subplots(1, 2, figsize=(11, 4), layout="constrained")
        for i, key in enumerate(("linf_error_window", "max_abs_u")):
            for tag, color in (("start", "#7f7f7f"), ("tuned", "#d62728")):
                m = ev["heldout"][tag]
                v = np.sort(m[key][~m["diverged"].astype(bool)])
                if not v.size:
                    continue
                frac = np.arange(1, v.size + 1) / v.size
                ax[i].step(v, frac, where="post", color=color, lw=1.5,
                           label=f"{tag}: median {np.median(v):.3g}, p95 "
                           f"{np.percentile(v, 95):.3g}")
                for q, ls in ((50, "-"), (95, "--")):
                    ax[i].axvline(np.percentile(v, q), color=color, lw=0.8, ls=ls)
            if key == "linf_error_window":
                ax[i].set_xscale("log")
            elif sc.u_max:
                ax[i].axvline(sc.u_max, color="k", ls=":", lw=1, label="bound (nominal plant)")
            ax[i].set(xlabel=LABELS[key], ylabel="fraction of plants")
            ax[i].legend(fontsize=8, loc="lower right")
            ax[i].grid(alpha=0.3, which="both")
        n = ev["heldout"]["start"]["diverged"].size
        fig.suptitle(f"held-out batch of {n} plants: distribution (ECDF) with the start and the "
                     f"tuned gains (solid: median, dashed: p95)")
        files.save_figure(fig, out / "heldout.png", dpi=110)
        figures.append("heldout.png")
    return figures
