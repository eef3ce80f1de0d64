"""`dscjax tune`'s search methods at equal wall time on paired seeds: the default (`cma`:
CMA-ES of 64 candidates a generation, restarted afresh with twice the population when it
stalls or stops) against `previous` (the default before it: restarted only at CMA-ES's own
stop) and `adam`.

    python experiments/bench_tuning.py                          # 10 seeds, 200 s (docs)
    python experiments/bench_tuning.py --methods cma --marks 100  # and what 100 s gave
    python experiments/bench_tuning.py --methods cma,previous,adam --seeds 3
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
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from harness import Bench, median, parser, positive  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import dscjax  # noqa: E402
import tuning  # noqa: E402
from dscjax import params  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from tuning.config import DSC_GAINS  # noqa: E402
from tuning.runner import heldout_ranges  # noqa: E402

# name -> [tuning.optimizer] settings; the first is the default, BASELINE the comparison's
METHODS = {"cma": {}, "previous": {"stall": 0}, "adam": {"name": tuning.Adam()}}
BASELINE = "previous"
PLANTS, SEED = 32, 777  # the held-out blow-up check


def build(problem: str, t_final: float):
    robust = (tuning.BatchSpec(batch=8, seed=0, aggregate=tuning.CVaR(), cvar_level=0.25)
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
    held = params.sample_overrides(setup, ranges, PLANTS, SEED)
    for ts in (1e-3, 5e-4):
        sp = RunSpec.make(t_final, ts, sample_time=ts, refine=1)
        out[f"heldout_blowups_{1e3 * ts:g}ms"] = int(
            np.asarray(dscjax.simulate_batch(setup, held, spec=sp).diverged).sum())
    out["constraints_ok"] = bool(ok)
    out["meets"] = bool(ok and d["delay_ok"] and out["heldout_blowups_1ms"] == 0
                        and out["heldout_blowups_0.5ms"] == 0)
    return out


def judged(problem, tr, unravel, t_final: float, seed: int, key: str) -> dict:
    """The run record of a search's incumbent (`judge`'s figures), printed on stderr."""
    setup = problem.selection.apply(problem.setup, unravel(tr.best_z))
    f = judge(problem, jax.tree.map(np.asarray, setup), t_final)
    print(f"  seed {seed} {key}: {f['exponential-euler']['ratio']:.1f}x (forward Euler "
          f"{f['euler']['ratio']:.1f}x), meets {f['meets']} (delay "
          f"{f['delayed']['delay_ok']}, held-out blow-ups "
          f"{f['heldout_blowups_1ms']}/{f['heldout_blowups_0.5ms']}), "
          f"{tr.iterations} generations, {tr.restarts} restarts", file=sys.stderr, flush=True)
    return {"seed": seed, "ratio": f["exponential-euler"]["ratio"],
            "ratio_fe": f["euler"]["ratio"], "meets": f["meets"],
            "delay_ok": f["delayed"]["delay_ok"], "figures": f,
            "evaluations": tr.evaluations, "iterations": tr.iterations,
            "restarts": tr.restarts, "search_s": tr.seconds, "best_loss": tr.best_loss,
            "best_feasible": bool(tr.best_feasible),
            "gains": {k: np.asarray(v).tolist() for k, v in unravel(tr.best_z).items()}}


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
                   "(default 200, the default time limit; 10 quick)")
    p.add_argument("--marks", default="",
                   help="comma-separated seconds before --budget at which each search's "
                   "incumbent is judged too (the search stopped and resumed there)")
    p.add_argument("--methods", default="cma,previous",
                   help=f"comma-separated, of {', '.join(METHODS)} (default cma,previous)")
    a = p.parse_args(argv)
    methods = a.methods.split(",")
    if any(m not in METHODS for m in methods):
        p.error(f"--methods: names of {', '.join(METHODS)} (got {a.methods!r})")
    quick = a.quick
    seeds = a.seeds or (2 if quick else 10)
    budget = a.budget or (10.0 if quick else 200.0)
    t_final = 2.0 if quick else 20.0
    bench = Bench(f"tuning_{a.problem}", f"Gain tuning at equal wall time, the {a.problem} "
                  "problem", quick=quick)
    problem = build(a.problem, t_final)
    unravel = ravel_pytree(problem.z0)[1]
    marks = sorted({float(x) for x in a.marks.split(",") if x} - {budget})
    if any(not 0 < x < budget for x in marks):
        p.error(f"--marks: seconds in (0, {budget:g}) (got {a.marks!r})")
    def label(m: str, x: float) -> str:  # a row: the method, and the mark if not the budget
        return m if x == budget else f"{m} @{x:g} s"

    runs = {label(m, x): [] for m in methods for x in [*marks, budget]}
    for seed in range(seeds):
        for m in methods:
            problem.programs.clear()  # every method compiles its own programs
            jax.clear_caches()
            with tempfile.TemporaryDirectory() as out:
                done = 0.0  # one search, stopped and resumed at each mark (bitwise the same)
                for x in [*marks, budget]:
                    res = tuning.run(with_method(problem, m, x - done, seed), out,
                                     resume=done > 0)
                    done = x
                    runs[label(m, x)].append(judged(problem, res.trace, unravel, t_final,
                                                    seed, label(m, x)))
            bench.read_load()

    def score(r):  # what the sign test compares: the ratio of a run that meets, else 0
        return r["ratio"] if r["meets"] else 0.0

    for (method, x), (m, rs) in zip([(m, x) for m in methods for x in [*marks, budget]],
                                    runs.items(), strict=True):
        s = [score(r) for r in rs]
        base = runs.get(label(BASELINE, x))  # the baseline at the same time
        row = {"method": m, "median_x": median([r["ratio"] for r in rs]),
               "worst_x": min(r["ratio"] for r in rs),
               "worst_x_forward_euler": min(r["ratio_fe"] for r in rs),
               "median_loss": median([r["best_loss"] for r in rs]),
               "meet": f"{sum(r['meets'] for r in rs)} of {len(rs)}",
               "delay_ok": f"{sum(r['delay_ok'] for r in rs)} of {len(rs)}",
               "generations_per_s": median([r["iterations"] / r["search_s"] for r in rs]),
               "evaluations_per_s": median([r["evaluations"] / r["search_s"] for r in rs])}
        if base is not None and method != BASELINE:
            base = [score(r) for r in base]
            wins = sum(x > y for x, y in zip(s, base, strict=True))
            losses = sum(x < y for x, y in zip(s, base, strict=True))
            row |= {f"wins_vs_{BASELINE}": f"{wins} of {len(s)}",
                    "sign_test_p": sign_test(wins, losses)}
        bench.add(**row)
    bench.note(f"T = {t_final:g} s, {budget:g} s per method and seed (compilation included"
               + ("; 'x @S s': its incumbent after S s of the same search" if marks else "")
               + "), "
               f"seeds 0-{seeds - 1}; x: the start gains' windowed L-inf over the tuned "
               f"gains' (nominal plant, sampled at 1 ms); {problem.n_params} tuned numbers; "
               f"'meet': every constraint in both discretisations, the delayed loop, no "
               f"held-out blow-up at 1 and 0.5 ms.")
    bench.finish(extra={"runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
