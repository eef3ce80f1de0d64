"""`dscjax tune`'s methods at equal wall time on the deployable problem: the default against
its baseline, plain CMA-ES, and against exact gradients.

    python experiments/tune_compare.py                 # 2 problems x 3 methods x 100 s, T = 20 s
    python experiments/tune_compare.py --quick         # T = 5 s, 30 s each, 32 held-out plants
    python experiments/tune_compare.py --rounds 3      # medians over 3 interleaved rounds

Problems (the paper's example, the default tuned set and objective: smooth L-inf error on
[1 s, T] subject to max|u| <= the start gains' and TV(u) <= 1.5 x the start gains', start =
the paper's gains):
  nominal  the nominal plant (what `dscjax tune` does by default)
  robust   CVaR at level 0.25 over a training batch of 8 plants, hysteresis alpha, lam, psi
           +-30 %

Methods (every budget includes the method's own compilation; the CMA-ES methods simulate a
whole population as one batched program):
  cma          CMA-ES (sigma0 = 0.3 in log-space, default population), no restart: the
               baseline
  cma_path     CMA-ES + a line search along its own evolution path in the same batch, in
               its first 50 generations: `dscjax tune`'s default
  adam         exact gradients, Adam's scaling

A method may carry [tuning.optimizer] options after colons, e.g. `cma_path:sigma0=0.5` or
`adam:learning_rate=0.05` (integers, floats, true/false), to compare variants.

Rounds run every method in turn (interleaved, so that they share the machine's load); the
table reports medians over rounds and the load average beside each run. Held-out figures of
each method's best gains come from the tuner's own held-out batch (256 plants, seed 12345),
refined as the tuner's report does: "div" counts plants that diverge at every step tried,
"stiff" those that diverge with classical RK4 at dt only and track once refined.
Writes OUT.json and OUT_<problem>.png (best feasible objective against wall time).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

METHODS = ("cma", "cma_path", "adam")
LABELS = {"cma": "CMA-ES", "cma_path": "CMA-ES + path line (default)",
          "adam": "Adam (exact gradients)"}


def build(name: str, t_final: float, heldout: int):
    import dscjax
    import tuning
    from dscjax.runspec import RunSpec

    robust = tuning.BatchSpec(batch=8, seed=0, aggregate="cvar", cvar_level=0.25) \
        if name == "robust" else tuning.BatchSpec(batch=0)
    cfg = tuning.TuningConfig(robust=robust,
                              heldout=tuning.BatchSpec(batch=heldout, seed=12345))
    return tuning.build_problem(dscjax.paper_example(), RunSpec.make(t_final=t_final), cfg)


def _option(text: str):
    key, _, value = text.partition("=")
    if value.lower() in ("true", "false"):
        return key, value.lower() == "true"
    try:
        return key, int(value)
    except ValueError:
        return key, float(value)


def with_method(problem, method: str, budget: float, seed: int):
    base, *extra = method.split(":")
    # the baseline is plain CMA-ES (issue 13: the cma package, sigma0 0.3, its default
    # population): it ends where cma's own criteria stop it, no restart
    opt = {"cma": dict(name="cma", restarts=0), "cma_path": dict(name="cma_path"),
           "adam": dict(name="adam")}[base] | dict(_option(x) for x in extra)
    cfg = problem.cfg
    spec = dataclasses.replace(cfg.optimizer, time_limit=budget, steps=10**7, patience=0,
                               seed=seed, **opt)
    return dataclasses.replace(problem, cfg=dataclasses.replace(cfg, optimizer=spec))


def run_method(problem, method, budget, seed):
    import tuning

    res = tuning.run(with_method(problem, method, budget, seed), None)
    tr = res.trace
    return {"best_flat": np.asarray(tr.best_z, float), "best_loss": tr.best_loss,
            "best_feasible": tr.best_feasible, "evaluations": tr.evaluations,
            "gradient_evaluations": tr.gradients, "iterations": tr.iterations,
            "compile_s": res.compile_s, "restarts": tr.restarts,
            "curve": [(r["wall_s"], r["best_loss"] if r["best_feasible"] else math.inf)
                      for r in res.history]}


def figures(problem, flat):
    """Nominal figures with the exact constraint checks, and held-out statistics."""
    import jax
    from jax.flatten_util import ravel_pytree

    from tuning import report

    z = ravel_pytree(problem.z0)[1](flat)
    per_plant = jax.jit(problem.objective.per_plant)
    m = {k: np.asarray(v) for k, v in jax.device_get(per_plant(z, {})).items()}
    out = {"nominal": {k: float(m[k]) for k in ("linf_error_window", "max_abs_u", "tv_u")}
           | {"diverged": bool(m["diverged"])},
           "constraints": report.constraint_checks(problem.objective.scales, m),
           "gains": {k: np.asarray(v).tolist() for k, v in jax.device_get(
               problem.selection.values(z)).items()}}
    if problem.heldout:
        h = {k: np.asarray(v) for k, v in jax.device_get(per_plant(z, problem.heldout)).items()}
        # plants that diverge only numerically at dt are re-run refined, as the tuner's report
        h = report.refined(problem, z, problem.heldout, h)
        ok = ~h["diverged"].astype(bool)
        out["heldout"] = {"n": int(ok.size), "n_diverged": int((~ok).sum()),
                          "n_refined": int((h["refined"] > 0).sum())} | {
            k: {"median": float(np.median(h[k][ok])), "p95": float(np.percentile(h[k][ok], 95)),
                "max": float(np.max(h[k][ok]))} if ok.any() else None
            for k in ("linf_error_window", "max_abs_u", "tv_u")}
    return out


def main():
    import jax

    jax.config.update("jax_enable_x64", True)
    from jax.flatten_util import ravel_pytree

    from dscjax.search import require_cma

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--budget", type=float, default=None, help="seconds per method and round")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--first-seed", type=int, default=0,
                   help="round r uses seed FIRST_SEED + r (default 0), for more paired rounds")
    p.add_argument("--problems", default="nominal,robust")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--heldout", type=int, default=None)
    p.add_argument("--out", default="results/tune_compare")
    args = p.parse_args()
    try:
        require_cma()
    except ModuleNotFoundError as err:
        sys.exit(f"tune_compare: {err}")
    t_final = 5.0 if args.quick else 20.0
    budget = args.budget or (30.0 if args.quick else 100.0)
    heldout = args.heldout if args.heldout is not None else (32 if args.quick else 256)
    methods = args.methods.split(",")
    print(f"tune_compare: T = {t_final:g} s, {budget:g} s per method, {args.rounds} round(s); "
          f"load average {os.getloadavg()[0]:.2f}", file=sys.stderr)
    results = {"t_final": t_final, "budget_s": budget, "rounds": args.rounds,
               "load_average_start": os.getloadavg(), "problems": {}}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for name in args.problems.split(","):
        problem = build(name, t_final, heldout)
        entry = {"n_params": problem.n_params,
                 "start": figures(problem, np.asarray(ravel_pytree(problem.z0)[0], float)),
                 "runs": {m: [] for m in methods}}
        for r in range(args.rounds):
            for m in methods:
                load = os.getloadavg()[0]
                # every method compiles its own programs (the objective caches them)
                problem.objective.compiled.clear()
                res = run_method(problem, m, budget, seed=args.first_seed + r)
                res["seed"] = args.first_seed + r
                res["load"] = load
                res["figures"] = figures(problem, res.pop("best_flat"))
                entry["runs"][m].append(res)
                f = res["figures"]["nominal"]
                print(f"  {name} round {r} {m}: best {res['best_loss']:.4g} "
                      f"({'feasible' if res['best_feasible'] else 'infeasible'}), "
                      f"{res['evaluations']} evaluations, {res['gradient_evaluations']} "
                      f"gradients; {res['iterations']} iterations, {res['restarts']} "
                      f"restarts; L-inf {f['linf_error_window']:.4g}; load {load:.1f}",
                      file=sys.stderr, flush=True)
                Path(f"{out}.json").write_text(json.dumps(results | {"problems": {
                    **results["problems"], name: entry}}, indent=1) + "\n")
        results["problems"][name] = entry
    results["load_average_end"] = os.getloadavg()
    Path(f"{out}.json").write_text(json.dumps(results, indent=1) + "\n")
    for name in results["problems"]:
        _plot(results, name, Path(f"{out}_{name}.png"))
    _table(results)
    print(f"wrote {out}.json, {out}_<problem>.png", file=sys.stderr)


def _med(values):
    v = [x for x in values if x is not None]
    return float(np.median(v)) if v else float("nan")


def _table(r):
    print(f"\nBest feasible objective at equal wall time ({r['budget_s']:g} s each, T = "
          f"{r['t_final']:g} s; medians over {r['rounds']} round(s); loss ~1 at the start)")
    print(f"{'problem':<8} {'method':<30} {'evals':>7} {'grads':>6} {'best loss':>10} "
          f"{'L-inf nom.':>10} {'x lower':>8} {'TV(u)':>7} {'max|u|':>7} {'held-out med/p95':>18}"
          f" {'div':>4} {'stiff':>5} {'load':>5}")
    for name, e in r["problems"].items():
        s = e["start"]
        print(f"{name:<8} {'(start gains)':<30} {'':>7} {'':>6} {'':>10} "
              f"{s['nominal']['linf_error_window']:>10.4g} {'':>8} {s['nominal']['tv_u']:>7.4g} "
              f"{s['nominal']['max_abs_u']:>7.4g}")
        for m, runs in e["runs"].items():
            if not runs:
                continue
            best = [x["best_loss"] if x["best_feasible"] else float("inf") for x in runs]
            i = int(np.argsort(best)[len(best) // 2])  # the median run's figures
            f = runs[i]["figures"]
            h = f.get("heldout") or {}
            hl = h.get("linf_error_window") or {}
            label = LABELS.get(m, m)[:30]
            print(f"{name:<8} {label:<30} {_med([x['evaluations'] for x in runs]):>7.0f} "
                  f"{_med([x['gradient_evaluations'] for x in runs]):>6.0f} "
                  f"{_med(best):>10.4g} {f['nominal']['linf_error_window']:>10.4g} "
                  f"{s['nominal']['linf_error_window'] / f['nominal']['linf_error_window']:>8.3g}"
                  f" {f['nominal']['tv_u']:>7.4g} {f['nominal']['max_abs_u']:>7.4g} "
                  f"{hl.get('median', float('nan')):>9.4g}/{hl.get('p95', float('nan')):<8.4g}"
                  f" {h.get('n_diverged', 0):>4} {h.get('n_refined', 0):>5}"
                  f" {_med([x['load'] for x in runs]):>5.1f}")


def _plot(r, name, path):
    from dscjax.plotting import subplots

    colors = {"cma": "#1f77b4", "cma_path": "#2ca02c", "adam": "#9467bd"}
    extra = iter(("#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#000000"))
    fig, ax = subplots(1, 1, figsize=(7, 4.5), layout="constrained")
    for m, runs in r["problems"][name]["runs"].items():
        # a variant ("cma_path:sigma0=0.5") gets a colour of its own, the same for its rounds
        colors.setdefault(m, next(extra, None))
        for i, run in enumerate(runs):
            c = np.asarray(run["curve"], float).reshape(-1, 2)
            ok = np.isfinite(c[:, 1])
            ax.step(c[ok, 0], c[ok, 1], where="post", color=colors.get(m, None), lw=1.2,
                    alpha=1.0 if i == 0 else 0.5, label=LABELS.get(m, m) if i == 0 else None)
    ax.set_yscale("log")
    ax.set_xlabel("wall time [s] (compilation included)")
    ax.set_ylabel("best feasible objective so far")
    ax.set_title(f"{name}: T = {r['t_final']:g} s, {r['rounds']} round(s)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
