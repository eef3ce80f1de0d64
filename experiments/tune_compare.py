"""Gradient tuning against CMA-ES and random search at equal wall-clock budget.

    python experiments/tune_compare.py            # 2 problems x 3 methods x 100 s, T = 20 s
    python experiments/tune_compare.py --quick    # T = 5 s, 20 s budget each

Problems (both: the paper's example, the default tuned set, the default objective = smooth
L-inf error on [1 s, T] with max|u| <= the start gains' max|u|, start = the paper's gains):
  nominal  the nominal plant (what `dscjax tune` does by default)
  robust   CVaR at level 0.25 over a training batch of 8 plants, hysteresis +-30 %

Every method's budget includes its own compilation. CMA-ES and random search evaluate a
whole population as one batched simulation. Writes results/tune_compare.json and
results/tune_compare.png (best loss so far against wall time).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np


def build(name: str, t_final: float):
    import dscjax
    import tuning
    from dscjax.config import SimOptions

    robust = tuning.BatchSpec(batch=8, seed=0, aggregate="cvar", cvar_level=0.25) \
        if name == "robust" else tuning.BatchSpec(batch=0)
    cfg = tuning.TuningConfig(robust=robust, heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(), SimOptions(t_final=t_final), cfg)


def final_figures(problem, flat_z):
    """Exact L-inf error on the window and max|u| of a point, on the nominal plant."""
    import jax
    from jax.flatten_util import ravel_pytree

    z = ravel_pytree(problem.z0)[1](flat_z)
    m = jax.jit(problem.objective.per_plant)(z, {})
    values = jax.device_get(problem.selection.values(z))
    return {"linf_error_window": float(m["linf_error_window"]),
            "max_abs_u": float(m["max_abs_u"]), "tv_u": float(m["tv_u"]),
            "diverged": bool(m["diverged"]),
            "gains": {k: np.asarray(values[k]).tolist() for k in problem.selection.names}}


def main():
    import jax

    jax.config.update("jax_enable_x64", True)
    from tuning import baselines

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--budget", type=float, default=None, help="seconds per method")
    p.add_argument("--problems", default="nominal,robust")
    p.add_argument("--out", default="results/tune_compare")
    args = p.parse_args()
    try:  # fail before spending the gradient method's budget, not after
        baselines.require_cma()
    except ModuleNotFoundError as err:
        sys.exit(f"tune_compare: {err}")
    t_final = 5.0 if args.quick else 20.0
    budget = args.budget or (20.0 if args.quick else 100.0)
    print(f"tune_compare: T = {t_final:g} s, {budget:g} s per method; load average "
          f"{os.getloadavg()[0]:.2f}", file=sys.stderr)
    results = {"t_final": t_final, "budget_s": budget, "quick": args.quick,
               "load_average_start": os.getloadavg(), "problems": {}}
    for name in args.problems.split(","):
        problem = build(name, t_final)
        start = final_figures(problem, np.asarray(
            jax.flatten_util.ravel_pytree(problem.z0)[0]))
        entry = {"n_params": problem.n_params, "start": start, "methods": {}}
        for method in ("gradient", "cma_es", "random_search"):
            print(f"  {name}: {method} ...", file=sys.stderr, flush=True)
            trace = getattr(baselines, method)(problem, budget)
            t, best = trace.best_curve()
            fig = final_figures(problem, trace.best_z) if trace.best_z is not None else None
            entry["methods"][method] = {
                "label": trace.method, "evaluations": trace.evaluations,
                "best_loss": trace.best_loss, "t": t.tolist(), "best_curve": best.tolist(),
                "info": trace.info, "best_point_nominal": fig}
            print(f"    best loss {trace.best_loss:.4g} after {trace.evaluations} evaluations"
                  + (f"; nominal L-inf {fig['linf_error_window']:.4g}, max|u| "
                     f"{fig['max_abs_u']:.4g}" if fig else ""), file=sys.stderr, flush=True)
        results["problems"][name] = entry
    results["load_average_end"] = os.getloadavg()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.json").write_text(json.dumps(results, indent=2) + "\n")
    _plot(results, Path(f"{out}.png"))
    _table(results)
    print(f"wrote {out}.json, {out}.png", file=sys.stderr)


def _table(r):
    print(f"\nBest loss at equal wall-clock budget ({r['budget_s']:g} s each, T = "
          f"{r['t_final']:g} s; loss 1 ~ the start gains)")
    print(f"{'problem':<9} {'method':<24} {'evals':>7} {'best loss':>10} {'L-inf [t0,T]':>13} "
          f"{'max|u|':>8}")
    for name, e in r["problems"].items():
        print(f"{name:<9} {'(start gains)':<24} {'':>7} {'':>10} "
              f"{e['start']['linf_error_window']:>13.4g} {e['start']['max_abs_u']:>8.4g}")
        for m in e["methods"].values():
            f = m["best_point_nominal"] or {}
            print(f"{name:<9} {m['label']:<24} {m['evaluations']:>7} {m['best_loss']:>10.4g} "
                  f"{f.get('linf_error_window', float('nan')):>13.4g} "
                  f"{f.get('max_abs_u', float('nan')):>8.4g}")


def _plot(r, path):
    from dscjax.plotting import subplots

    probs = list(r["problems"])
    fig, ax = subplots(1, len(probs), figsize=(5.5 * len(probs), 4), squeeze=False,
                           layout="constrained")
    colors = {"gradient": "#d62728", "cma_es": "#1f77b4", "random_search": "#7f7f7f"}
    for a, name in zip(ax[0], probs, strict=True):
        for key, m in r["problems"][name]["methods"].items():
            t, b = np.asarray(m["t"]), np.asarray(m["best_curve"])
            ok = np.isfinite(b)
            a.step(t[ok], b[ok], where="post", color=colors[key], label=m["label"])
        a.set_yscale("log")
        a.set_xlabel("wall time [s] (compilation included)")
        a.set_ylabel("best loss so far")
        a.set_title(f"{name} (T = {r['t_final']:g} s)")
        a.grid(alpha=0.3, which="both")
        a.legend()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
