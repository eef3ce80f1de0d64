"""`dscjax tune`'s search methods at equal wall time on paired seeds: the default (`cma`:
CMA-ES with a population sized to the CPU's throughput, IPOP restarts) against `small` (the
same at cma's own population for 13 numbers, 11, the default's before it) and `adam`.

    python experiments/bench_tuning.py                          # 10 seeds, 100 s (docs)
    python experiments/bench_tuning.py --methods cma,small,adam --seeds 3
    python experiments/bench_tuning.py --problem robust --methods cma
    python experiments/bench_tuning.py --quick                  # 2 seeds, T = 2 s: JSON only

Problems: `default`, what `dscjax tune` solves (the paper's example from its gains, the
controller sampled at 1 ms by exponential Euler: smooth L-inf error on [1 s, T] with max|u| <=
the start's and TV(u) <= 1.5 x the start's, the forward-Euler and the one-sample-delayed loops
checked; nominal plant), and `robust` (the same, CVaR 0.25 over 8 plants, hysteresis +-30 %).
Each seed runs every method in turn for --budget seconds of wall time, compilation included.

Each best point is judged on the nominal plant: its windowed L-inf against the start gains'
(exponential and forward Euler), every constraint in both discretisations, the loop with the
input delayed one sample (L-inf at most 2 x the undelayed, TV(u) at most 1.5 x its bound: no
limit cycle), and the held-out plants (32, the default held-out box, seed 777) that blow up at
Ts = 1 ms and 0.5 ms (one refinement). A run "meets" when all of these hold. Per method: the
median and worst ratio, the worst forward-Euler ratio, the runs that meet, generations and
evaluations per second; against the baseline, seed by seed on the ratio (a run that does not
meet counts 0): wins and the paired sign test (two-sided p, ties dropped), where it ran.
"""

from __future__ import annotations

import dataclasses
import math
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from harness import Bench, median, parser, positive  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import dscjax  # noqa: E402
import tuning  # noqa: E402
from dscjax import params  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from tuning.params import DSC_GAINS  # noqa: E402
from tuning.runner import heldout_ranges  # noqa: E402

# name -> [tuning.optimizer] settings; the first is the default, BASELINE the comparison's
METHODS = {"cma": {}, "small": {"popsize": 11, "growth": 1}, "adam": {"name": "adam"}}
BASELINE = "small"
PLANTS, SEED = 32, 777  # the held-out blow-up check


def build(problem: str, t_final: float):
    robust = (tuning.BatchSpec(batch=8, seed=0, aggregate="cvar", cvar_level=0.25)
              if problem == "robust" else tuning.BatchSpec(batch=0))
    cfg = tuning.TuningConfig(robust=robust, heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(),
                                RunSpec.make(t_final=t_final, sample_time=1e-3), cfg)


def with_method(problem, method: str, budget: float, seed: int):
    """The problem searched by `method` for `budget` seconds with `seed` (no iteration count
    or patience stops it)."""
    opt = dataclasses.replace(problem.cfg.optimizer, **METHODS[method], time_limit=budget,
                              steps=None, patience=0, seed=seed)
    return dataclasses.replace(problem, cfg=dataclasses.replace(problem.cfg, optimizer=opt))


def judge(problem, setup, t_final: float) -> dict:
    """The figures of the gains of `setup` against the start's (see the module docstring)."""
    start = problem.setup
    sc = problem.objective.scales
    ov = {p: np.stack([np.asarray(params.get(s, p)) for s in (start, setup)])
          for p in DSC_GAINS}
    out, ok = {}, True
    for disc, delay in (("exponential-euler", 0), ("euler", 0), ("exponential-euler", 1)):
        spec = RunSpec.make(t_final, 1e-3, sample_time=1e-3, discretisation=disc, delay=delay,
                            refine=0)
        m = {k: np.asarray(v) for k, v in
             dscjax.simulate_batch(start, ov, spec=spec).metrics.items()}
        tag = "delayed" if delay else disc
        out[tag] = {"linf": float(m["linf_error_window"][1]),
                    "ratio": float(m["linf_error_window"][0] / m["linf_error_window"][1]),
                    "max_abs_u": float(m["max_abs_u"][1]), "tv_u": float(m["tv_u"][1])}
    for tag in ("exponential-euler", "euler"):
        f = out[tag]
        ok &= f["max_abs_u"] <= sc.u_max * (1 + 1e-9) and f["tv_u"] <= sc.tv_max * (1 + 1e-9)
    d = out["delayed"]
    d["delay_ok"] = bool(d["linf"] <= 2 * out["exponential-euler"]["linf"]
                         and d["tv_u"] <= 1.5 * sc.tv_max)
    ranges = params.check(heldout_ranges(start), start, "heldout")
    held = params.sample_overrides(setup, ranges, PLANTS, SEED, "uniform")
    for ts in (1e-3, 5e-4):
        sp = RunSpec.make(t_final, ts, sample_time=ts, refine=1)
        out[f"heldout_blowups_{1e3 * ts:g}ms"] = int(
            np.asarray(dscjax.simulate_batch(setup, held, spec=sp).diverged).sum())
    out["constraints_ok"] = bool(ok)
    out["meets"] = bool(ok and d["delay_ok"] and out["heldout_blowups_1ms"] == 0
                        and out["heldout_blowups_0.5ms"] == 0)
    return out


def sign_test(wins: int, losses: int) -> float:
    """Two-sided p of the paired sign test (exact binomial, ties dropped)."""
    n = wins + losses
    if n == 0:
        return 1.0
    k = min(wins, losses)
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2**n)


def main(argv=None) -> int:
    p = parser(__doc__)
    p.add_argument("--problem", choices=("default", "robust"), default="default")
    p.add_argument("--seeds", type=positive(), default=None,
                   help="seeds 0 .. N-1 (default 10; 2 quick)")
    p.add_argument("--budget", type=positive(float), default=None,
                   help="seconds of wall time per method and seed, compilation included "
                   "(default 100; 10 quick)")
    p.add_argument("--methods", default="cma,small",
                   help=f"comma-separated, of {', '.join(METHODS)} (default cma,small)")
    a = p.parse_args(argv)
    methods = a.methods.split(",")
    if any(m not in METHODS for m in methods):
        p.error(f"--methods: names of {', '.join(METHODS)} (got {a.methods!r})")
    quick = a.quick
    seeds = a.seeds or (2 if quick else 10)
    budget = a.budget or (10.0 if quick else 100.0)
    t_final = 2.0 if quick else 20.0
    bench = Bench(f"tuning_{a.problem}", f"Gain tuning at equal wall time, the {a.problem} "
                  "problem", quick=quick)
    problem = build(a.problem, t_final)
    unravel = ravel_pytree(problem.z0)[1]
    runs = {m: [] for m in methods}
    for seed in range(seeds):
        for m in methods:
            problem.objective.compiled.clear()  # every method compiles its own programs
            res = tuning.run(with_method(problem, m, budget, seed))
            tr = res.trace
            setup = problem.selection.apply(problem.setup, unravel(tr.best_z))
            f = judge(problem, jax.tree.map(np.asarray, setup), t_final)
            runs[m].append({"seed": seed, "ratio": f["exponential-euler"]["ratio"],
                            "ratio_fe": f["euler"]["ratio"], "meets": f["meets"],
                            "delay_ok": f["delayed"]["delay_ok"], "figures": f,
                            "evaluations": tr.evaluations, "iterations": tr.iterations,
                            "search_s": tr.seconds, "best_loss": tr.best_loss,
                            "best_feasible": bool(tr.best_feasible),
                            "gains": {k: np.asarray(v).tolist()
                                      for k, v in unravel(tr.best_z).items()}})
            print(f"  seed {seed} {m}: {f['exponential-euler']['ratio']:.1f}x (forward Euler "
                  f"{f['euler']['ratio']:.1f}x), meets {f['meets']} (delay "
                  f"{f['delayed']['delay_ok']}, held-out blow-ups "
                  f"{f['heldout_blowups_1ms']}/{f['heldout_blowups_0.5ms']}), "
                  f"{tr.iterations} generations", file=sys.stderr, flush=True)
            bench.read_load()

    def score(r):  # what the sign test compares: the ratio of a run that meets, else 0
        return r["ratio"] if r["meets"] else 0.0

    base = [score(r) for r in runs[BASELINE]] if BASELINE in runs else None
    for m, rs in runs.items():
        s = [score(r) for r in rs]
        row = {"method": m, "median_x": median([r["ratio"] for r in rs]),
               "worst_x": min(r["ratio"] for r in rs),
               "worst_x_forward_euler": min(r["ratio_fe"] for r in rs),
               "median_loss": median([r["best_loss"] for r in rs]),
               "meet": f"{sum(r['meets'] for r in rs)} of {len(rs)}",
               "delay_ok": f"{sum(r['delay_ok'] for r in rs)} of {len(rs)}",
               "generations_per_s": median([r["iterations"] / r["search_s"] for r in rs]),
               "evaluations_per_s": median([r["evaluations"] / r["search_s"] for r in rs])}
        if base is not None and m != BASELINE:
            wins = sum(x > y for x, y in zip(s, base, strict=True))
            losses = sum(x < y for x, y in zip(s, base, strict=True))
            row |= {f"wins_vs_{BASELINE}": f"{wins} of {len(s)}",
                    "sign_test_p": sign_test(wins, losses)}
        bench.add(**row)
    bench.note(f"T = {t_final:g} s, {budget:g} s per method and seed (compilation included), "
               f"seeds 0-{seeds - 1}; x: the start gains' windowed L-inf over the tuned "
               f"gains' (nominal plant, sampled at 1 ms); {problem.n_params} tuned numbers; "
               f"'meet': every constraint in both discretisations, the delayed loop, no "
               f"held-out blow-up at 1 and 0.5 ms.")
    bench.finish(extra={"runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
