"""`dscjax tune`'s methods at equal wall time: cma_path (the default), cma (plain CMA-ES, the
baseline) and adam (exact gradients).

    python experiments/bench_tuning.py                    # the default problem, 9 seeds (docs)
    python experiments/bench_tuning.py --problem robust --seeds 18 --budget 100
    python experiments/bench_tuning.py --quick            # 2 seeds, T = 2 s: JSON only

Problems: `default`, what `dscjax tune` solves (the paper's example from its gains: smooth
L-inf error on [1 s, T] with max|u| <= the start's and TV(u) <= 1.5 x the start's, nominal
plant), and `robust` (the same, CVaR 0.25 over 8 plants, hysteresis +-30 %). Each seed runs
every method in turn for --budget seconds of wall time, compilation included (each method
compiles its own programs), with that seed. Per method: medians over seeds of the best feasible
loss, the nominal L-inf error of the best gains and how much lower it is than the start's, and
the held-out batch (256 plants, seed 12345) refined as the tuner's report does ("stiff": track
only once refined; "diverged": at every step tried); against cma, seed by seed: wins, the
paired sign test (two-sided p, ties dropped) and the geometric mean of the loss ratios.
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
from dscjax.runspec import RunSpec  # noqa: E402
from tuning import report  # noqa: E402

METHODS = ("cma_path", "cma", "adam")  # cma is the baseline of the paired comparisons
BASELINE = "cma"


def build(problem: str, t_final: float, heldout: int):
    robust = (tuning.BatchSpec(batch=8, seed=0, aggregate="cvar", cvar_level=0.25)
              if problem == "robust" else tuning.BatchSpec(batch=0))
    cfg = tuning.TuningConfig(robust=robust, heldout=tuning.BatchSpec(batch=heldout, seed=12345))
    return tuning.build_problem(dscjax.paper_example(), RunSpec.make(t_final=t_final), cfg)


def with_method(problem, method: str, budget: float, seed: int):
    """The problem searched by `method` for `budget` seconds with `seed`: no count or patience
    stops it; plain CMA-ES ends where its own criteria stop it (no restart)."""
    opt = dataclasses.replace(problem.cfg.optimizer, name=method, time_limit=budget,
                              steps=10**7, patience=0, seed=seed,
                              **({"restarts": 0} if method == "cma" else {}))
    return dataclasses.replace(problem, cfg=dataclasses.replace(problem.cfg, optimizer=opt))


def figures(problem, per_plant, z) -> dict:
    """The nominal figures of the gains z, and the held-out batch's (refined)."""
    def host(d):
        return {k: np.asarray(v) for k, v in jax.device_get(d).items()}

    nominal = host(per_plant(z, {}))
    out = {k: float(nominal[k]) for k in ("linf_error_window", "max_abs_u", "tv_u")}
    if problem.heldout:
        ov = {k: jax.numpy.asarray(v) for k, v in problem.heldout.items()}
        h = report.batch_stats(report.refined(problem, z, ov, host(per_plant(z, ov))))
        linf = h["linf_error_window"] or {"median": math.nan, "p95": math.nan}
        out["heldout"] = {"median": linf["median"], "p95": linf["p95"],
                          "diverged": h["n_diverged"], "stiff": h["n_refined"]}
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
                   help="seeds 0 .. N-1 (default 9; 2 quick)")
    p.add_argument("--budget", type=positive(float), default=None,
                   help="seconds of wall time per method and seed, compilation included "
                   "(default 100; 10 quick)")
    a = p.parse_args(argv)
    quick = a.quick
    seeds = a.seeds or (2 if quick else 9)
    budget = a.budget or (10.0 if quick else 100.0)
    t_final = 2.0 if quick else 20.0
    bench = Bench(f"tuning_{a.problem}", f"Gain tuning at equal wall time, the {a.problem} "
                  "problem", quick=quick)
    problem = build(a.problem, t_final, 16 if quick else 256)
    per_plant = jax.jit(problem.objective.per_plant)
    unravel = ravel_pytree(problem.z0)[1]
    start = figures(problem, per_plant, problem.z0)
    runs = {m: [] for m in METHODS}
    for seed in range(seeds):
        for m in METHODS:
            problem.objective.compiled.clear()  # every method compiles its own programs
            res = tuning.run(with_method(problem, m, budget, seed))
            tr = res.trace
            loss = tr.best_loss if tr.best_feasible else math.inf
            runs[m].append({"seed": seed, "loss": loss, "evaluations": tr.evaluations,
                            "gradients": tr.gradients, "iterations": tr.iterations,
                            "figures": figures(problem, per_plant, unravel(tr.best_z))})
            print(f"  seed {seed} {m}: best {loss:.4g}, {tr.iterations} iterations",
                  file=sys.stderr, flush=True)
            bench.read_load()

    bench.add(method="(start gains)", best_loss="", linf_nominal=start["linf_error_window"],
              x_lower="", tv_u=start["tv_u"], max_abs_u=start["max_abs_u"],
              **_heldout(start.get("heldout")))
    base = [r["loss"] for r in runs[BASELINE]]
    for m, rs in runs.items():
        loss = [r["loss"] for r in rs]
        i = int(np.argsort(loss)[len(loss) // 2])  # the median run's gains
        f = rs[i]["figures"]
        row = {"method": m, "best_loss": median(loss), "linf_nominal": f["linf_error_window"],
               "x_lower": start["linf_error_window"] / f["linf_error_window"],
               "tv_u": f["tv_u"], "max_abs_u": f["max_abs_u"], **_heldout(f.get("heldout")),
               "evaluations": int(median([r["evaluations"] for r in rs])),
               "gradients": int(median([r["gradients"] for r in rs]))}
        if m != BASELINE:
            wins = sum(x < y for x, y in zip(loss, base, strict=True))
            losses = sum(x > y for x, y in zip(loss, base, strict=True))
            ratios = [x / y for x, y in zip(loss, base, strict=True)
                      if math.isfinite(x) and math.isfinite(y) and y > 0]
            row |= {f"wins_vs_{BASELINE}": f"{wins} of {len(loss)}",
                    "sign_test_p": sign_test(wins, losses),
                    "geo_mean_ratio": math.exp(np.mean(np.log(ratios))) if ratios else math.nan}
        bench.add(**row)
    bench.note(f"T = {t_final:g} s, {budget:g} s per method and seed (compilation included), "
               f"seeds 0-{seeds - 1}; the nominal and held-out columns are the median run's "
               f"gains'; {problem.n_params} tuned numbers; held-out: "
               f"{len(next(iter(problem.heldout.values()))) if problem.heldout else 0} plants.")
    bench.finish()
    return 0


def _heldout(h) -> dict:
    if not h:
        return {}
    return {"heldout_median": h["median"], "heldout_p95": h["p95"],
            "heldout_diverged": h["diverged"], "heldout_stiff": h["stiff"]}


if __name__ == "__main__":
    raise SystemExit(main())
