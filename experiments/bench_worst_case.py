"""Worst-case search: projected gradient ascent against random sampling and CMA-ES at equal
search time (issue 14's target).

    python experiments/bench_worst_case.py                 # the target: 20 s, 60 s per method
    python experiments/bench_worst_case.py --quick         # 5 s horizon, 15 s per method

The paper's example and gains; alpha, lam, psi, g_1, g_2 within +-30 %, theta_1 within +-50 %;
a Fourier disturbance of K = 16 harmonics over the horizon with |dbar| <= 0.5. Each method gets
--time-limit seconds of search (compilation timed apart). Target: the gradient search's worst
value >= 1.5 x the best of random sampling and >= the best of CMA-ES. Prints a table and writes
results/bench_worst_case.json (or --out), plus the search's own files under results/.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

# the box and waveform (shared with bench_adversarial.py)
BOX = ("hysteresis.alpha=30%", "hysteresis.lam=30%", "hysteresis.psi=30%", "plant.g[0]=30%",
       "plant.g[1]=30%", "plant.theta[0]=50%")
DISTURBANCE = "fourier:16:0.5"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 s horizon, 15 s per method")
    ap.add_argument("--t-final", type=float, default=None)
    ap.add_argument("--time-limit", type=float, default=None)
    ap.add_argument("--starts", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gradient", default="time_parallel", choices=("time_parallel", "batch"))
    ap.add_argument("--coarsening", type=int, default=None)
    ap.add_argument("--methods", default="gradient,random,cma")
    ap.add_argument("--out", default="results/bench_worst_case.json")
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import dscjax
    from dscjax.files import write_json
    from dscjax.params import parse_range
    from dscjax.worst import (
        DEFAULT_COARSENING,
        DEFAULT_STARTS,
        best_value,
        make_problem,
        worst_case,
    )
    from dscjax.worst.report import summary, write

    t_final = args.t_final or (5.0 if args.quick else 20.0)
    limit = args.time_limit or (15.0 if args.quick else 60.0)
    starts = args.starts or DEFAULT_STARTS
    coarsening = args.coarsening or DEFAULT_COARSENING
    methods = args.methods.split(",")
    ranges = [parse_range(s) for s in BOX]
    problem = make_problem(dscjax.paper_example(), ranges, DISTURBANCE, t_final=t_final,
                           dt=1e-3)
    load = os.getloadavg()
    t0 = time.perf_counter()
    result = worst_case(problem, time_limit=limit, starts=starts, seed=args.seed,
                        gradient=args.gradient, coarsening=coarsening, methods=methods,
                        progress=lambda m, tr, lim: print(
                            f"  {m:8s} {tr.seconds:6.1f}/{lim:g} s  best {best_value(tr):.6g}  "
                            f"({tr.evaluations} evaluations)", flush=True))
    wall = time.perf_counter() - t0
    best = {m: best_value(tr) for m, tr in result.traces.items()}
    ratio_random = best["gradient"] / best["random"] if "random" in best else None
    ratio_cma = best["gradient"] / best["cma"] if "cma" in best else None
    print(f"\nworst case of {problem.metric}, T = {t_final:g} s, {limit:g} s per method, "
          f"M = {starts} starts ({args.gradient} gradient at {coarsening} dt), "
          f"load {load[0]:.2f} at the start, "
          f"{os.getloadavg()[0]:.2f} at the end; {os.cpu_count()} CPUs")
    print(f"{'method':10s} {'best':>12s} {'evals':>7s} {'iters':>6s} {'search s':>9s} "
          f"{'compile s':>9s}")
    for m, tr in result.traces.items():
        print(f"{m:10s} {best_value(tr):12.6g} {tr.evaluations:7d} {tr.iterations:6d} "
              f"{tr.seconds:9.1f} {tr.compile_seconds:9.1f}")
    print(f"nominal {result.nominal_value:.6g}; re-checked worst {result.value:.6g} "
          f"({result.method})")
    if ratio_random is not None and ratio_cma is not None:
        print(f"gradient / random = {ratio_random:.3f} (target >= 1.5: "
              f"{'met' if ratio_random >= 1.5 else 'NOT met'}); gradient / CMA-ES = "
              f"{ratio_cma:.3f} (target >= 1: {'met' if ratio_cma >= 1 else 'NOT met'})")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    search_dir = out.with_suffix("")
    search_dir.mkdir(parents=True, exist_ok=True)
    write(result, search_dir)
    write_json(out, {"summary": summary(result), "ratio_gradient_random": ratio_random,
                     "ratio_gradient_cma": ratio_cma, "t_final": t_final, "time_limit": limit,
                     "starts": starts, "gradient": args.gradient, "coarsening": coarsening,
                     "wall_s": wall,
                     "loadavg_start": load, "loadavg_end": os.getloadavg(),
                     "cpus": os.cpu_count(), "machine": platform.platform(),
                     "traces": {m: {"t": tr.t, "best": tr.best}
                                for m, tr in result.traces.items()}})
    print(f"wrote {out} and {search_dir}/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
