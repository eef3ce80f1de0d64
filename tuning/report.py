"""The evidence of a tuning run: start against tuned gains on the nominal plant, on the
training batch and on a fresh held-out batch, every verdict with its effort (TV(u) and the
chattering index, docs/numerics.md); the constraints' margins and their elasticities to the
tuned numbers (`tuning.elasticity`); report.md, report.json and PNG figures."""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import files, validation, xla
from dscjax.divergence import outcome_counts
from dscjax.markdown import window
from dscjax.params import assumption_warnings as with_ranges
from dscjax.pure import metric_names
from dscjax.runspec import auto_stride, loop_words
from dscjax.simulate import counted_levels, level_spec, refine_rows, simulate, simulate_batch
from tuning import elasticity, margins, report_md
from tuning.config import TERMS
from tuning.objective import CHECK_FIGURES, exact_constraints, plant_count, within
from tuning.reductions import shifted_reference
from tuning.report_plots import draw
from tuning.runner import join_plants, simulate_command


@functools.partial(xla.jit, lean=True)
def _per_plant(objective, z, overrides, bounds=None):
    """`Objective.per_plant`, compiled once per structure (the objective an argument)."""
    return objective.per_plant(z, overrides, bounds)


def evaluate(problem, z0, z1) -> dict[str, Any]:
    """Per-plant figures for the start (z0) and tuned (z1) points: nominal, train (its real
    plants), held-out; every plant in one batched program (`plant_table`)."""
    obj, zs = problem.objective.program(), {"start": z0, "tuned": z1}
    groups = {"nominal": {}, "train": obj.overrides, "heldout": problem.heldout}
    groups = {tag: dict(g) for tag, g in groups.items() if g is not None}
    table, bounds, rows = plant_table(obj, groups)
    per = {t: _host(_per_plant(obj, z, table, bounds)) for t, z in zs.items()}
    if not table:  # the nominal plant alone
        return {"nominal": per, "train": None, "heldout": None}
    out = {"nominal": jax.tree.map(lambda v: v[0], per), "train": None, "heldout": None}
    for tag, real in (("train", problem.n_train), ("heldout", None)):
        if tag in groups:
            ov = {k: np.asarray(v)[:real] for k, v in groups[tag].items()}
            out[tag] = {t: refined(problem, zs[t], ov, {
                k: v[rows[tag]][:real] for k, v in per[t].items()}) for t in zs}
    return out


def plant_table(obj, groups: dict) -> tuple[dict, tuple, dict[str, slice]]:
    """({path: (N, ...)}, each row's effort bounds, {group: its rows}) of the batches of
    `groups` ({group: {path: (n, ...)}}; "nominal" first, its batch empty: the nominal plant)
    stacked, each path a batch does not vary at its nominal value: one program for them all.
    The training batch ("train", padding included) keeps its own bounds, the other rows the
    nominal ones. Without any batch: ({}, the nominal bounds, {}), the nominal plant alone."""
    sc = obj.scales
    if not any(groups.values()):
        return {}, sc.bounds(train=False), {}
    sizes = {tag: plant_count(g) for tag, g in groups.items()}
    ends = np.cumsum(list(sizes.values())).tolist()
    rows = {tag: slice(end - n, end) for (tag, n), end in zip(sizes.items(), ends, strict=True)}
    joined = functools.reduce(functools.partial(join_plants, obj.setup), groups.values())
    table = {p: jnp.asarray(v) for p, v in joined.items()}
    bounds = tuple(b if per is None else np.concatenate([
        np.asarray(per, float) if tag == "train" else np.full(n, b) for tag, n in sizes.items()])
        for b, per in zip(sc.bounds(train=False), (sc.u_max_train, sc.tv_max_train),
                          strict=True))
    return table, bounds, rows


def both(f, pair: dict) -> dict:
    """f of the start and of the tuned gains' entry of `pair`."""
    return {tag: f(pair[tag]) for tag in margins.NAMES}


def refined(problem, z, overrides, m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A batch's per-plant figures with the plants that diverged at the tuning's step re-run
    at `simulate`'s refinement levels, as sweeps do (a divergence of the integrator is not one
    of the loop); each check loop c alike. Adds `refined` and c_refined (the level that
    tracked, 0: the tuning's step); the refined plants' exact metrics and `diverged` are the
    refined runs', their loss and smooth surrogates stay the objective's."""
    m = dict(m)
    setup = problem.setup_at(z)
    ov = {k: np.asarray(v) for k, v in overrides.items()}
    keys = sorted(({*metric_names(), "diverged"}) & m.keys())
    m["refined"] = _refine(setup, ov, problem.objective.sim, m, {k: k for k in keys})
    for k in [k for k in m if k.startswith("user_")]:  # the refined runs do not measure them
        m[k] = np.where(m["refined"] > 0, np.nan, np.asarray(m[k], float))
    for c in problem.objective.checks:
        figures = {"diverged": "diverged"} | {key: k for k, key in CHECK_FIGURES.items()}
        m[f"{c.name}_refined"] = _refine(setup, ov, c.sim, m, {
            key: f"{c.name}_{k}" for key, k in figures.items()})
    return m


def _refine(setup, ov, sim, m, keys: dict[str, str]) -> np.ndarray:
    """Re-run the rows of `m` diverged at the refinement levels of `sim`, updating `m`'s
    `keys` (simulate's name -> m's) in place; returns the level that tracked per row (0: the
    tuning's step, or none)."""
    diverged = np.asarray(m[keys["diverged"]]).astype(bool)
    if not diverged.any() or not sim.refine:
        return np.zeros(diverged.shape, np.int32)

    def level(j, idx):  # rows idx at refinement level j (level 0, the tuning's step, is m)
        spec = level_spec(sim.replace(refine=0), j)
        traj = simulate_batch(setup, {k: v[idx] for k, v in ov.items()}, spec=spec)
        return {"diverged": traj.diverged, **{k: traj.metrics[k] for k in keys if k != "diverged"}}

    rows = {k: np.asarray(m[mk], dtype=bool if k == "diverged" else float)
            for k, mk in keys.items()}
    rows, levels = refine_rows(rows, lambda r: r["diverged"], level, counted_levels(sim))
    m.update({mk: rows[k] for k, mk in keys.items()})
    return np.where(rows["diverged"], 0, levels).astype(np.int32)


def _host(d):
    return {k: np.asarray(v) for k, v in jax.device_get(d).items()}


def batch_stats(m: dict[str, np.ndarray]) -> dict[str, Any]:
    ok, counts = outcome_counts(m["diverged"], m.get("refined", 0))
    out: dict[str, Any] = {"n": int(ok.size), **counts}
    masks = {}  # the same three outcomes in each check loop c (its metrics c_...)
    for c in (k.removesuffix("_diverged") for k in m if k.endswith("_diverged")):
        masks[c], out[c] = outcome_counts(m[f"{c}_diverged"], m.get(f"{c}_refined", 0))
    for key in (k for k in report_md.STATS_METRICS + ("loss",) if k in m):
        mask = next((masks[c] for c in masks if key.startswith(f"{c}_")), ok)
        v = np.asarray(m[key] if key == "loss" else m[key][mask], float)
        v = v[np.isfinite(v)] if key.startswith("user_") else v  # (not measured once refined)
        out[key] = None if v.size == 0 else {
            "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "max": float(np.max(v)), "mean": float(np.mean(v))}
    if "chattering_index" in m:  # the plants that track in the loop tuned but chatter
        out["n_chattering"] = margins.batch_figures(m)["n_chattering"]
    return out


def requirement_checks(problem, m: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    return [{"name": r.name, "met_fraction": float(np.mean(np.asarray(m[f"req{i}_met"]) > 0)),
             "worst_margin": float(np.max(m[f"req{i}_margin"])),
             **{k: float(np.max(m[f"req{i}_{k}"])) for k in ("overshoot", "settling_time", "peak")
                if f"req{i}_{k}" in m}}
            for i, r in enumerate(problem.objective.requirements)]


def constraint_checks(scales, m: dict[str, Any], checks=()) -> list[dict[str, Any]]:
    """The bounds checked exactly on one plant's metrics `m` (every RK4 step): name, value,
    bound, margin and met (within `BOUND_RTOL`; never for a diverged plant). Each check loop
    (`CheckLoop`) adds its rows: its windowed L-inf and effort bounds."""
    return [{"name": name, "key": key, "value": float(v[0]), "bound": float(b[0]),
             "margin": float(b[0] - v[0]), "relative_margin": float((b[0] - v[0]) / b[0]),
             "met": bool(met[0])}
            for name, key, _, v, b, _, met in _exact((scales.u_max, scales.tv_max), m, checks, 1)]


def _exact(bounds, m, checks, n: int):
    """(name, metric, bound, values (n,), bounds (n,), unmeasured (n,), met (n,)) of each bound
    there is (`exact_constraints`) on the n plants of `m`: unmeasured where a loop diverged or
    the value is not finite, met within `BOUND_RTOL` where measured."""
    diverged = np.broadcast_to(np.asarray(m.get("diverged", False)), (n,)).astype(bool)
    for c in checks:
        diverged = diverged | np.asarray(m[f"{c.name}_diverged"]).astype(bool)
    linf = np.asarray(m.get("linf_error_window", np.nan), float)
    for name, key, bound in exact_constraints(bounds, linf, checks):
        b = np.broadcast_to(np.asarray(bound, float), (n,))
        v = np.asarray(m[key], float).reshape(n)
        bad = diverged | ~np.isfinite(v)
        yield name, key, bound, v, b, bad, ~bad & within(v, b)


def train_constraint_checks(scales, m: dict[str, Any], checks=()) -> list[dict[str, Any]]:
    """The bounds checked exactly on every training plant (`m` as `evaluate` gives it), each
    against its own or the nominal bound: how many meet it, and the worst plant (the smallest
    relative margin; a diverged plant meets nothing and is the worst)."""
    n = np.asarray(m["diverged"]).size
    rows = []
    for name, _, bound, v, b, bad, met in _exact(scales.bounds(train=True), m, checks, n):
        with np.errstate(invalid="ignore"):
            rel = np.where(bad, -np.inf, (b - v) / b)
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
    cfg, sc, sim = problem.cfg, problem.scales, problem.objective.sim
    shifted = ("" if shifted_reference(problem.setup) is None else " (against the reference "
               "the controller tracks: y_r shifted by its initialisation to start at x_1(0))")
    terms = [t[3] + (shifted if k in ("linf", "l2") else "") for k, t in TERMS.items()
             if getattr(cfg.objective, k)]
    where = ("the nominal plant" if not cfg.robust.batch else
             f"the {cfg.robust.over} over {cfg.robust.batch} training plants")
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
    return (f"Minimise {' + '.join(terms)} on {window(sim.window_start, sim.t_final)} over "
            f"{problem.n_params} design numbers on {where}"
            + (f", subject to {' and '.join(cons)}{on}" if cons else ", unconstrained") + ".")


def trajectories(problem, z0, z1):
    """The start and tuned loops on the nominal plant for the figures, saved every 10 steps
    or more (`runspec.auto_stride`)."""
    sim = problem.objective.sim
    spec = sim.replace(save_every=max(10, auto_stride(sim.n_steps)), refine=0)
    return both(lambda z: simulate(problem.setup_at(z), spec=spec, throw=False),
                {"start": z0, "tuned": z1})


def run_record(result) -> dict[str, Any]:
    """How the search went (report.json's "run"; the whole command's wall time, None here, is
    set once the report is done)."""
    problem, tr = result.problem, result.trace
    return {"iterations": tr.iterations, "resumed_from": result.resumed_from,
            "rejected": result.rejected, "stop_reason": result.stop_reason,
            "restarts": tr.restarts, "best_iteration": tr.best_iteration,
            "best_loss": tr.best_loss, "best_feasible": tr.best_feasible,
            "wall_s": result.wall_s, "compile_s": result.compile_s, "wall_total_s": None,
            "gradient": problem.mode.name, "method": problem.cfg.optimizer.name.name,
            "evaluations": tr.evaluations, "gradient_evaluations": tr.gradients,
            "n_params": problem.n_params}


def write(out: Path, result, *, plots: bool = True, t_start: float | None = None) -> dict:
    """Evaluate, then write report.json (the summary returned), report.md and (with plots) the
    PNGs; `t_start` (perf_counter at the command's start) gives the whole wall time (None: not
    reported)."""
    problem = result.problem
    sc, checks = problem.scales, problem.objective.checks
    z0, z1 = problem.z0, jax.device_get(result.best_z)
    ev = evaluate(problem, z0, z1)
    summary: dict[str, Any] = {
        "nominal": both(_measured, ev["nominal"]),
        "bound_max_abs_u": sc.u_max, "bound_tv_u": sc.tv_max,
        "effort_bounds": problem.cfg.objective.effort_bounds.name,
        # the per-plant bounds of the training batch (None: the nominal ones for every plant)
        "bounds_train": None if not sc.per_plant else {
            "max_abs_u": sc.u_max_train, "tv_u": sc.tv_max_train,
            "n_start_diverged": sc.n_train_fallback},
        "problem": problem_sentence(problem),
        "constraints": both(lambda m: constraint_checks(sc, m, checks), ev["nominal"]),
        "sample_time": problem.objective.sim.sample_time,
        # the second loop in words ("the states by forward Euler"), None without one
        "second_loop": next((c.label for c in checks if c.name == "sampled"), None),
        "requirements": both(functools.partial(requirement_checks, problem), ev["nominal"]),
        "run": run_record(result),
        "gains": both(problem.values_at, {"start": z0, "tuned": z1}),
        "settings": problem.describe(),
        "notes": list(problem.notes),
        "warnings": assumption_warnings(problem)
        + [f"tuned gains: {w}" for w in validation.assumption_warnings(result.best_setup)
           if w not in validation.assumption_warnings(problem.setup)],
    }
    if ev["train"] is not None and (sc.u_max is not None or sc.tv_max is not None or checks):
        summary["train_constraints"] = both(lambda m: train_constraint_checks(sc, m, checks),
                                            ev["train"])
    for key in (k for k in ("train", "heldout") if ev[k] is not None):
        summary[key] = both(batch_stats, ev[key])
        summary[key]["requirements"] = both(functools.partial(requirement_checks, problem), ev[key])
    # the sensitivities and the margins come with the held-out check (`--heldout 0` skips all
    # three: a quick run)
    sens = (elasticity.constraints(problem, z1, summary["constraints"]["tuned"])
            if problem.heldout else None)
    mg = margins.evaluate(problem, z0, z1, ev) if problem.heldout else None
    summary |= {
        "heldout_warning": report_md.heldout_warning(summary, problem.cfg),
        "shifted_reference": shifted_reference(problem.setup) is not None,
        "sensitivity": sens, "sensitivity_warning": elasticity.warning(sens),
        "simulate_command": simulate_command(problem), "loop": loop_words(problem.objective.sim),
        "heldout_box": ([r.resolve(problem.setup).spec() for r in problem.cfg.heldout.ranges]
                        if problem.heldout else None),
        "margins": mg,
        "margins_warning": None if mg is None else "; ".join(margins.failures(mg)) or None}
    out = Path(out)
    summary["figures"] = draw(out, result, ev, trajectories(problem, z0, z1),
                              (mg or {}).get("sample_time")) if plots else []
    if t_start is not None:
        summary["run"]["wall_total_s"] = time.perf_counter() - t_start
    files.write_json(out / "report.json", summary)
    files.write_text(out / "report.md", report_md.text(summary, problem))
    return summary


def _measured(m: dict[str, np.ndarray]) -> dict[str, float]:
    """One plant's scalar figures, a diverged plant's as NaN (null in report.json: not
    measured) but its loss."""
    gone = bool(np.asarray(m["diverged"]))
    return {k: float("nan") if gone and k not in ("loss", "diverged") else float(np.asarray(v))
            for k, v in m.items() if np.ndim(v) == 0}


def assumption_warnings(problem) -> list[str]:
    """The paper's assumptions the start setup violates, at the nominal plant or at an end of
    the training or held-out ranges."""
    found, cfg = [], problem.cfg
    for key, b in (("robust", cfg.robust), ("heldout", cfg.heldout)):
        ranges = [r.resolve(problem.setup) for r in b.ranges] if b.batch else []
        found += with_ranges(problem.setup, ranges, f"tuning.{key}.ranges")
    return list(dict.fromkeys(found))  # each once, in the order first found
