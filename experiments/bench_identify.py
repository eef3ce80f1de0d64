"""Identification: exact-Jacobian Levenberg-Marquardt against finite differences and CMA-ES.

    python experiments/bench_identify.py            # the example record (docs)
    python experiments/bench_identify.py --quick    # 2 s of it: JSON only

The plant experiment of docs/identification.md (dscjax/data/record.csv: the paper's loop, 10 s
sampled at 5 ms; free: g_1, theta_1, alpha, lam, psi; 4 segments), the same residuals (the
jitted simulation of `dscjax.identify`) minimised from the same start four ways: dscjax's
Levenberg-Marquardt on exact forward-mode Jacobians; scipy's least_squares ("trf") with
2-point finite-difference Jacobians; CMA-ES (pycma, populations simulated as one vmapped
batch) on the sum of squares until it reaches the exact fit's cost (or 60 s); and
optimistix's Levenberg-Marquardt (the JAX library's, vectorised jacfwd), the solver dscjax's
replaces. Each method's compilation is timed apart (a warm-up fit), then the fit itself:
iterations, simulations (one per residual evaluation; a Jacobian column counts as one),
wall time to the final cost, and the error of the identified numbers against the truth; the
exact and the finite-difference fits run `--repeats` times, alternating, their medians
reported.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from harness import Bench, median, parser  # noqa: E402

import dscjax  # noqa: E402
from dscjax.identify import Problem, read, solve  # noqa: E402
from dscjax.identify.fit import _flat  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FREE = ["plant.g[0]", "plant.theta[0]", "hysteresis.alpha", "hysteresis.lam", "hysteresis.psi"]
TRUTH = np.array([1.1, 0.15, 0.8, 1.6, 0.12])  # how dscjax/data/record.csv was made
CMA_BUDGET = 60.0  # [s] CMA-ES's time to reach the exact fit's cost


def problem_of(quick: bool) -> Problem:
    rec = read(ROOT / "dscjax" / "data" / "record.csv", order=2)
    if quick:
        rec = rec.part(0, 401)
    return Problem.make(dscjax.paper_example(), rec, FREE, plant=True, dt=1e-3,
                        segments=2 if quick else 4)


def error(problem, v) -> float:
    """The largest relative error of the identified numbers against the truth."""
    setup = problem.setup_at(jnp.asarray(v[:len(FREE)]))
    got = np.array([float(f.param.value(setup)) for f in problem.free])
    return float(np.max(np.abs(got - TRUTH) / np.abs(TRUTH)))


def exact(problem, v0):
    t0 = time.perf_counter()
    fit = solve(problem, {"z": v0[:len(FREE)], "x": v0[len(FREE):].reshape(
        problem.exp.segments, 2)})
    seconds = time.perf_counter() - t0
    p = v0.size
    v = np.concatenate([fit.theta["z"], np.ravel(fit.theta["x"])])
    # each step: the trial's residuals and p columns (one program)
    return {"cost": fit.cost, "iterations": fit.steps, "simulations": fit.steps * (p + 1),
            "seconds": seconds, "error": error(problem, v)}


def finite_differences(problem, v0):
    from scipy.optimize import least_squares

    count = [0]

    def f(v):
        count[0] += 1
        return np.asarray(_r(problem, jnp.asarray(v)), float)

    t0 = time.perf_counter()
    res = least_squares(f, np.asarray(v0), jac="2-point", method="trf", xtol=1e-10,
                        ftol=1e-10, gtol=1e-10, max_nfev=20000)
    seconds = time.perf_counter() - t0
    return {"cost": float(res.cost), "iterations": int(res.njev), "simulations": count[0],
            "seconds": seconds, "error": error(problem, res.x)}


# the residuals alone (the solver evaluates them with their Jacobian): what FD calls
_r = eqx.filter_jit(_flat)


@eqx.filter_jit
def _costs(problem, vs):
    return jax.vmap(lambda v: 0.5 * jnp.sum(_flat(problem, v) ** 2))(vs)


def cma_es(problem, v0, target: float, budget: float):
    import cma

    def batch(vs):
        return _costs(problem, vs)

    es = cma.CMAEvolutionStrategy(np.asarray(v0), 0.05, {"verbose": -9, "seed": 1,
                                                         "popsize": 32})
    sims, best, gens = 0, math.inf, 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < budget and best > target * (1 + 1e-6):
        x = np.asarray(es.ask())
        f = np.asarray(batch(jnp.asarray(x)), float)
        es.tell(list(x), list(np.where(np.isfinite(f), f, 1e30)))
        sims, gens = sims + len(x), gens + 1
        best = min(best, float(np.min(f)))
    return {"cost": best, "iterations": gens, "simulations": sims,
            "seconds": time.perf_counter() - t0, "error": error(problem, es.result.xbest)}


@eqx.filter_jit
def _optimistix(p, v):
    import optimistix as optx

    sol = optx.least_squares(lambda w, pp: _flat(pp, w),
                             optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10), v, p,
                             max_steps=200, throw=False)
    return sol.value, sol.stats["num_steps"]


def optimistix_lm(problem, v0):
    t0 = time.perf_counter()
    v, steps = jax.block_until_ready(_optimistix(problem, jnp.asarray(v0)))
    seconds = time.perf_counter() - t0
    r = np.asarray(_r(problem, v), float)
    return {"cost": 0.5 * float(r @ r), "iterations": int(steps),
            "simulations": int(steps) * (v0.size + 2), "seconds": seconds,
            "error": error(problem, np.asarray(v))}


def main() -> None:
    p = parser(__doc__, "fits of each of the exact and the finite-difference method, "
               "interleaved; their medians are reported (default 5)", default=5)
    args = p.parse_args()
    bench = Bench("identify", "Identification: exact Jacobians against finite differences "
                  "and CMA-ES", quick=args.quick)
    problem = problem_of(args.quick)
    start = problem.z0()
    v0 = np.concatenate([np.asarray(start["z"]), np.ravel(np.asarray(start["x"]))])
    rows = {}
    t0 = time.perf_counter()
    exact(problem, v0)  # compiles the residuals and the Jacobian
    compile_exact = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(_r(problem, jnp.asarray(v0)))  # the residuals alone: what FD calls
    compile_fd = time.perf_counter() - t0
    # the two fits alternate (A B A B ...): each ratio comes from neighbouring runs
    pairs = [(exact(problem, v0), finite_differences(problem, v0))
             for _ in range(args.repeats)]
    ratios = [e["seconds"] / f["seconds"] for e, f in pairs]
    for i, (name, compile_s) in enumerate((("exact Jacobians, Levenberg-Marquardt (dscjax)",
                                            compile_exact),
                                           ("finite differences, scipy least_squares",
                                            compile_fd))):
        rows[name] = pairs[0][i] | {"seconds": median([pr[i]["seconds"] for pr in pairs]),
                                    "compile_s": compile_s}
    target = rows["exact Jacobians, Levenberg-Marquardt (dscjax)"]["cost"]
    t0 = time.perf_counter()
    cma_es(problem, v0, target, 1.0)  # compiles the batch
    compile_cma = time.perf_counter() - t0
    budget = CMA_BUDGET
    rows["CMA-ES (pycma), batched"] = cma_es(problem, v0, target, budget) | {
        "compile_s": compile_cma}
    t0 = time.perf_counter()
    optimistix_lm(problem, v0)
    compile_optx = time.perf_counter() - t0
    rows["optimistix Levenberg-Marquardt (vectorised jacfwd)"] = optimistix_lm(
        problem, v0) | {"compile_s": compile_optx}
    for name, r in rows.items():
        bench.add(method=name, final_cost=r["cost"],
                  cost_over_exact=r["cost"] / target, iterations=r["iterations"],
                  simulations=r["simulations"], seconds=r["seconds"],
                  compile_seconds=r["compile_s"], parameter_error=r["error"])
    bench.note(f"The exact fit takes {median(ratios):.3g} x the finite-difference fit's wall "
               f"time (goal: at most 1/3), compilation apart: the median over {args.repeats} "
               f"pairs of neighbouring runs ({min(ratios):.3g}-{max(ratios):.3g}); the two "
               f"rows' seconds are the medians of those runs. Samples {len(problem.record)}, "
               f"segments {problem.exp.segments}, {v0.size} fitted numbers and start states.")
    bench.finish()


if __name__ == "__main__":
    main()
