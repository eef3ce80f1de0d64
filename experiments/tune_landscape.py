"""Why exact gradients do not pay off on the robust tuning problem (issue 13): the loss along
the exact gradient at CMA-ES's incumbent, and an L-BFGS polish against CMA-ES's own progress.

    python experiments/tune_landscape.py             # seed 1: CMA-ES 30 s, then 60 s more
    python experiments/tune_landscape.py --quick     # T = 5 s: 10 s, then 10 s

The robust problem of tune_compare (CVaR at level 0.25 over 8 training plants, T = 20 s):

1. CMA-ES (plain, tune_compare's baseline) for A s; its incumbent is x.
2. At x: the exact gradient g (the tuner's gradient mode) and the loss at x -/+ h g/|g| for
   h = 1e-9 ... 1e-1 (one batch), beside the linear model -/+ h |g|, and whether the point
   meets the constraints exactly (max|u|, TV(u) on every plant). At each h, the training
   plants that diverge at the tuning's step and whether they track once refined as the
   report refines (ETDRK4 at dt, dt/2, ...): an integrator's cliff ("stiff") or the loop's.
3. From x, for B s: L-BFGS (two-loop recursion, 10 pairs; each iteration one batched line
   search over 12 step sizes along its direction, the best feasible point taken when it is
   better, then one exact gradient there; it stops early when a steepest-descent step
   (no curvature pairs) finds no better feasible point at any step size), against CMA-ES
   with the same seed run for A + B s (its best at A s and where it ended; the two runs
   share the seed, not their wall-clock pace).
Prints a table; writes OUT.json. Float64 throughout.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def probe(problem, x, hs):
    """Loss at x -/+ h d (d = g/|g|) and the plants that diverge there, refined."""
    import jax
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from tuning import report, search

    g = np.asarray(search.grad_fn(problem)(jnp.asarray(x))[2], float)
    d = g / np.linalg.norm(g)
    lo, hi = search.z_box(problem)
    pts = np.clip(np.concatenate([x[None] - hs[:, None] * d[None],
                                  x[None] + hs[:, None] * d[None]]), lo, hi)
    # x itself in the same batch: the changes are differences within one program
    r = jax.device_get(search.batch_fn(problem)(jnp.asarray(np.vstack([pts, x[None]]))))
    loss0 = r["loss"][-1]
    unravel = ravel_pytree(problem.z0)[1]
    per_plant = jax.jit(problem.objective.per_plant)
    ov = problem.objective.overrides
    rows = []
    for i, p in enumerate(pts):
        z = unravel(jnp.asarray(p))
        m = {k: np.asarray(v) for k, v in jax.device_get(per_plant(z, ov)).items()}
        div = np.flatnonzero(m["diverged"])
        stiff = report.refined(problem, z, ov, m)["diverged"] if div.size else m["diverged"]
        rows.append({"h": float(hs[i % hs.size]), "sign": -1 if i < hs.size else 1,
                     "change": float(r["loss"][i]) - float(loss0),
                     "linear": (-1 if i < hs.size else 1) * float(hs[i % hs.size])
                     * float(np.linalg.norm(g)),
                     "feasible": bool(r["feasible"][i]),
                     "diverged_plants": div.tolist(),
                     "diverged_refined": np.flatnonzero(stiff).tolist()})
    return float(loss0), float(np.linalg.norm(g)), rows


LBFGS_STEP_RANGE = (1e-4, 3.0)  # the line search's step sizes, x the L-BFGS step


def lbfgs(problem, x, loss, budget, width=12, memory=10, step_range=LBFGS_STEP_RANGE):
    """L-BFGS from x for `budget` s, compilation included. `loss`: the loss at x, a feasible
    point's; None: the first gradient's own evaluation of x (inf if x is infeasible, so that
    any feasible point improves on it). Its line search tries geomspace(*step_range, width)
    x the L-BFGS step. Returns (curve [(s, best feasible loss)], the number of steps that
    improved, why it stopped)."""
    import jax.numpy as jnp

    from tuning import search

    t0 = time.perf_counter()
    lo, hi = search.z_box(problem)
    batch = search.batch_fn(problem).lower(jnp.asarray(np.tile(x, (width, 1)))).compile()
    grad = search.grad_fn(problem).lower(jnp.asarray(x)).compile()

    def gradient(p):
        loss_p, feasible, g_p = grad(jnp.asarray(p))
        loss_p = float(loss_p)
        return (loss_p if bool(feasible) and math.isfinite(loss_p) else math.inf,
                np.asarray(g_p, float))

    loss_x, g = gradient(x)
    loss = loss_x if loss is None else loss
    pairs, curve, better = [], [(time.perf_counter() - t0, loss)], 0
    stop = "time"
    steps = np.geomspace(*step_range, width)  # x the L-BFGS step (initially 0.05 in z)
    while time.perf_counter() - t0 < budget:
        q, alphas = g.copy(), []
        for s, y in reversed(pairs):
            a = (s @ q) / (y @ s)
            q -= a * y
            alphas.append(a)
        q *= (pairs[-1][0] @ pairs[-1][1]) / (pairs[-1][1] @ pairs[-1][1]) if pairs else \
            0.05 / np.linalg.norm(g)
        for (s, y), a in zip(pairs, reversed(alphas), strict=True):
            q += s * (a - (y @ q) / (y @ s))
        pts = np.clip(x[None] - steps[:, None] * q[None], lo, hi)
        r = batch(jnp.asarray(pts))
        f = np.where(np.asarray(r["feasible"]) & np.isfinite(np.asarray(r["loss"])),
                     np.asarray(r["loss"], float), np.inf)
        j = int(np.argmin(f))
        if f[j] < loss:
            g_new = gradient(pts[j])[1]
            better += 1
            s, y = pts[j] - x, g_new - g
            if y @ s > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y):
                pairs = (pairs + [(s, y)])[-memory:]
            x, loss, g = pts[j], float(f[j]), g_new
        elif pairs:  # no step size helped: forget the curvature pairs (steepest descent next)
            pairs = []
        else:  # steepest descent found nothing better either: it would repeat itself
            curve.append((time.perf_counter() - t0, loss))
            stop = "steepest descent found no better feasible point"
            break
        curve.append((time.perf_counter() - t0, loss))
    return curve, better, stop


def main():
    import jax

    jax.config.update("jax_enable_x64", True)
    import tune_compare as tc

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--first", type=float, default=None, help="A: CMA-ES seconds before x")
    p.add_argument("--then", type=float, default=None, help="B: seconds from x")
    p.add_argument("--out", default="results/tune_landscape")
    args = p.parse_args()
    a = args.first or (10.0 if args.quick else 30.0)
    b = args.then or (10.0 if args.quick else 60.0)
    problem = tc.build("robust", 5.0 if args.quick else 20.0, 0)
    load0 = os.getloadavg()[0]
    cma_a = tc.run_method(problem, "cma", a, args.seed)
    x = cma_a["best_flat"]
    hs = np.geomspace(1e-9, 1e-1, 9)
    loss0, gnorm, rows = probe(problem, x, hs)
    curve, better, stop = lbfgs(problem, x, cma_a["best_loss"], b)
    problem.objective.compiled.clear()
    cma_ab = tc.run_method(problem, "cma", a + b, args.seed)
    at = [c for t, c in cma_ab["curve"] if t <= a]
    out = {"seed": args.seed, "first_s": a, "then_s": b, "mode": problem.mode,
           "load_average": [load0, os.getloadavg()[0]],
           "cma_first": {"best": cma_a["best_loss"], "generations": cma_a["iterations"]},
           "gradient_norm": gnorm, "probe": rows,
           "lbfgs": {"start": cma_a["best_loss"], "end": curve[-1][1],
                     "iterations": len(curve) - 1, "better_steps": better,
                     "gradients": better + 1, "stop": stop, "curve": curve},
           "cma_continued": {"at_first": at[-1] if at else math.inf,
                             "end": cma_ab["best_loss"], "end_s": cma_ab["curve"][-1][0],
                             "generations": cma_ab["iterations"]}}
    print(f"\nrobust problem, seed {args.seed}: CMA-ES {a:g} s -> incumbent loss {loss0:.5g} "
          f"({cma_a['iterations']} generations), |grad| {gnorm:.3g} ({problem.mode} mode)")
    print(f"{'h (z)':>8} {'side':>5} {'change':>11} {'linear':>11} {'feasible':>9} "
          f"{'diverged at dt':>16} {'after refining':>15}")
    for r in rows:
        print(f"{r['h']:>8.1e} {('-g', '+g')[r['sign'] > 0]:>5} {r['change']:>+11.3e} "
              f"{r['linear']:>+11.3e} {str(r['feasible']):>9} {str(r['diverged_plants']):>16} "
              f"{str(r['diverged_refined']):>15}")
    lb, cc = out["lbfgs"], out["cma_continued"]
    print(f"\nnext {b:g} s from the incumbent: L-BFGS {lb['start']:.4g} -> {lb['end']:.4g} "
          f"({lb['iterations']} iterations, {lb['better_steps']} better; stopped: {stop}, "
          f"{lb['curve'][-1][0]:.1f} s); CMA-ES with the same seed: {cc['at_first']:.4g} at "
          f"{a:g} s -> {cc['end']:.4g} at {cc['end_s']:.1f} s ({cc['generations']} "
          f"generations); load {load0:.1f}-{os.getloadavg()[0]:.1f}")
    path = Path(f"{args.out}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
