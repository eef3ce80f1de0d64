"""Scaling study: tuning every DSC design number of the order-n family (n = 2, 4, 6), the
gradient method (cma_grad) against CMA-ES at equal wall time, on the deployable problem
(L-inf on [1 s, T] with max|u| <= start's and TV(u) <= 1.5 x start's, nominal plant).

    python experiments/tune_scaling.py                       # n = 2, 4, 6, 100 s per method
    python experiments/tune_scaling.py --orders 2,4 --budget 60

A start must not diverge: for each n the script tries (tau, k, T) in the order of
START_TRIES (larger tau and smaller k first calm the stiff filters; a shorter horizon ends
before a late blow-up) and reports which it used, or that none was found. Prints a table
(best feasible objective against the number of tuned numbers) and writes OUT.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

START_TRIES = tuple((tau, k, t) for t in (20.0, 5.0) for tau in (0.05, 0.1, 0.2)
                    for k in (4.0, 2.0, 1.0))


def start_problem(n: int, method: str):
    """(problem, (tau, k, T)) for the first start that does not diverge, or (None, tried)."""
    import dscjax
    import tuning
    from dscjax.config import SimOptions

    tried = []
    for tau, k, t_final in START_TRIES:
        setup = dscjax.order_n_example(n, tau=tau, k=k)
        cfg = tuning.TuningConfig(optimizer=tuning.OptimizerSpec(name=method),
                                  heldout=tuning.BatchSpec(batch=0))
        try:
            return tuning.build_problem(setup, SimOptions(t_final=t_final), cfg), (tau, k,
                                                                                   t_final)
        except dscjax.ConfigError as err:
            tried.append({"tau": tau, "k": k, "t_final": t_final, "error": str(err)[:120]})
    return None, tried


def main():
    import dataclasses

    import jax

    jax.config.update("jax_enable_x64", True)
    import tuning

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--orders", default="2,4,6")
    p.add_argument("--budget", type=float, default=100.0)
    p.add_argument("--methods", default="cma,cma_grad")
    p.add_argument("--out", default="results/tune_scaling")
    args = p.parse_args()
    rows = []
    for n in (int(x) for x in args.orders.split(",")):
        problem, start = start_problem(n, "cma")
        if problem is None:
            print(f"  n = {n}: no stable start among {len(start)} tried", file=sys.stderr)
            rows.append({"n": n, "start": None, "tried": start})
            continue
        row = {"n": n, "n_params": problem.n_params, "start": dict(zip(("tau", "k", "t_final"),
                                                                        start, strict=True)),
               "start_linf": problem.objective.scales.linf, "methods": {}}
        for m in args.methods.split(","):
            spec = dataclasses.replace(problem.cfg.optimizer, name=m, time_limit=args.budget,
                                       steps=10**7, patience=0)
            pm = dataclasses.replace(problem, cfg=dataclasses.replace(problem.cfg,
                                                                      optimizer=spec))
            load = os.getloadavg()[0]
            res = tuning.run(pm, None)
            row["methods"][m] = {"best_loss": float(res.state.best_loss),
                                 "feasible": bool(res.state.best_feasible),
                                 "generations": int(res.state.iteration),
                                 "gradient_evaluations": res.gradient_evaluations,
                                 "compile_s": res.compile_s, "load": load}
            print(f"  n = {n} ({problem.n_params} numbers) {m}: best {res.state.best_loss:.4g} "
                  f"({'feasible' if res.state.best_feasible else 'infeasible'}), load "
                  f"{load:.1f}", file=sys.stderr, flush=True)
        rows.append(row)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.json").write_text(json.dumps({"budget_s": args.budget, "rows": rows},
                                              indent=1) + "\n")
    print(f"\nBest feasible objective at equal wall time ({args.budget:g} s per method)")
    print(f"{'n':>2} {'numbers':>8} {'start (tau, k, T)':>20} " + " ".join(
        f"{m:>12}" for m in args.methods.split(",")) + "  load")
    for r in rows:
        if r["start"] is None:
            print(f"{r['n']:>2} {'':>8} {'none stable':>20}")
            continue
        s = r["start"]
        print(f"{r['n']:>2} {r['n_params']:>8} {str((s['tau'], s['k'], s['t_final'])):>20} "
              + " ".join(f"{v['best_loss'] if v['feasible'] else float('inf'):>12.4g}"
                         for v in r["methods"].values())
              + f"  {max(v['load'] for v in r['methods'].values()):.1f}")


if __name__ == "__main__":
    main()
