"""Model mismatch: will gains tuned on the backlash-like model survive the real actuator?

Three sets of DSC gains, each evaluated by a sweep (`dscjax.sweep.run_sweep`, float32 as
`dscjax sweep` runs) on every hysteresis model of dscjax with its parameters spread +-30 %
(uniform, `--plants` plants per model, another seed than any training batch):

- paper: the paper's gains (Section 4);
- tuned_backlash: `dscjax tune`'s defaults on the paper's (backlash-like) plant: the DSC gains,
  nominal plant, stopped by `--tune-time`;
- tuned_all: tuned across all four models at once, starting from tuned_backlash
  (`--robust-start paper` starts from the paper's gains). A model is a class (static
  structure), so one batch cannot mix kinds: `tuning.combine` makes one objective of four
  `build_problem`s, one per kind, each with its own plants (default `--batch 0`: the model's
  nominal plant, one trajectory, reverse mode; `--batch B`: B plants of that model's ranges,
  CVaR at 25 %, forward mode, whose compilation took 335 s on the loaded 2-core machine) and
  its own start scales (so each kind's loss is about 1 at the start gains), and takes the mean
  (`--combine mean`) or max of the four; one jitted step differentiates all of it. Stopped by
  `--robust-time`.

The ranges (+-30 %; `PATH*` scales a whole vector with one factor):
backlash alpha, lam, psi; pi p0, p*, r*; gpi p0, p*, r*, envelope_left[0], envelope_right[0];
bouc_wen a, b, beta, gamma.

    python experiments/mismatch_study.py [--plants 256] [--t-final 10] [--out results/mismatch]

Prints the table (windowed L-inf error on [1 s, T]: median, p95, max, diverged, per model and
gains), writes mismatch.json and mismatch.png to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np

KINDS = ("backlash", "pi", "gpi", "bouc_wen")
RANGES = {
    "backlash": ("hysteresis.alpha", "hysteresis.lam", "hysteresis.psi"),
    "pi": ("hysteresis.p0", "hysteresis.p*", "hysteresis.r*"),
    "gpi": ("hysteresis.p0", "hysteresis.p*", "hysteresis.r*", "hysteresis.envelope_left[0]",
            "hysteresis.envelope_right[0]"),
    "bouc_wen": ("hysteresis.a", "hysteresis.b", "hysteresis.beta", "hysteresis.gamma"),
}
SPREAD = 0.30
GAINS = ("paper", "tuned_backlash", "tuned_all")
METRIC = "linf_error_window"


def plant(kind: str):
    from dscjax.config import hysteresis_example

    return hysteresis_example(kind)


def ranges(kind: str):
    from dscjax.params import Param, Range

    return tuple(Range(Param.parse(p), rel=SPREAD) for p in RANGES[kind])


def tune(kinds, args, batch: int, time_limit: float, start):
    """Gains tuned by `tuning` with `dscjax tune`'s defaults from the controller `start` on
    `kinds` (one problem per kind, combined when there are several): each kind's nominal
    plant when batch = 0, else a robust batch of that kind."""
    import tuning
    from dscjax.runspec import RunSpec

    options = RunSpec.make(t_final=args.t_final, dt=args.dt)
    problems = []
    for i, kind in enumerate(kinds):
        cfg = tuning.TuningConfig(
            optimizer=dataclasses.replace(tuning.OptimizerSpec(), name="adam",  # (combine)
                                          time_limit=time_limit),
            robust=tuning.BatchSpec(batch=batch, seed=100 + i, ranges=ranges(kind),
                                    aggregate="cvar", cvar_level=0.25),
            heldout=tuning.BatchSpec(batch=0))
        problems.append(tuning.build_problem(plant(kind).replace(controller=start), options,
                                             cfg))
    problem = problems[0] if len(problems) == 1 else tuning.combine(problems, args.combine)
    t0 = time.perf_counter()
    result = tuning.run(problem)
    info = {"iterations": len(result.history), "stop": result.stop_reason,
            "wall_s": time.perf_counter() - t0, "compile_s": result.compile_s,
            "mode": problem.mode, "best_loss": result.trace.best_loss}
    print(f"  tuned on {', '.join(kinds)}: {info['iterations']} iterations in "
          f"{info['wall_s']:.0f} s ({result.stop_reason}), best loss {info['best_loss']:.3f}",
          flush=True)
    return result.best_setup.controller, info


def evaluate(controller, kind: str, args) -> dict:
    """Windowed L-inf error of `controller` over `--plants` plants of `kind`."""
    from dscjax.sweep import SweepSettings, run_sweep

    setup = plant(kind).replace(controller=controller)
    settings = SweepSettings(samples=args.plants, ranges=ranges(kind), seed=args.seed,
                             worst=0, random=0)
    res = run_sweep(setup, settings, args.t_final, args.dt)
    v = np.asarray(res.columns[METRIC], dtype=float)
    diverged = np.asarray(res.columns["diverged"], dtype=bool)
    ok, u = v[~diverged], np.asarray(res.columns["max_abs_u"], dtype=float)[~diverged]
    q = (lambda p: float(np.quantile(ok, p))) if ok.size else (lambda p: float("nan"))
    return {"median": q(0.5), "p95": q(0.95), "max": q(1.0), "diverged": int(diverged.sum()),
            "n": int(v.size), "max_abs_u_p95": float(np.quantile(u, 0.95)) if u.size else
            float("nan"), "values": v.tolist()}


def table(results: dict) -> list[str]:
    rows = ["| model | gains | L-inf e on [1 s, T]: median | p95 | max | diverged | median "
            "/ paper's | max abs u: p95 |", "|---|---|---|---|---|---|---|---|"]
    for kind in KINDS:
        base = results["paper"][kind]["median"]
        for g in GAINS:
            r = results[g][kind]
            rows.append(f"| {kind} | {g} | {r['median']:.4g} | {r['p95']:.4g} | {r['max']:.4g} "
                        f"| {r['diverged']}/{r['n']} | {r['median'] / base:.2f} | "
                        f"{r['max_abs_u_p95']:.3g} |")
    return rows


def figure(results: dict, path: Path, t_final: float) -> None:
    import matplotlib
    import matplotlib.ticker

    from dscjax.plotting import subplots
    from dscjax.reproduce import RC

    colors = {"paper": "#7f7f7f", "tuned_backlash": "#1f77b4", "tuned_all": "#d62728"}
    with matplotlib.rc_context(RC):
        fig, axes = subplots(1, len(KINDS), figsize=(12.0, 3.3), sharey=True)
        for ax, kind in zip(axes, KINDS, strict=True):
            for g in GAINS:
                v = np.sort(np.asarray(results[g][kind]["values"], dtype=float))
                v = v[np.isfinite(v)]
                ax.step(v, np.arange(1, v.size + 1) / v.size, where="post", color=colors[g],
                        lw=1.3, label=g)
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_title(f"{kind} (parameters ±{SPREAD:.0%})", fontsize=9)
            ax.set_xlabel(f"L∞ error on [1, {t_final:g}] s")
        axes[0].set_ylabel("fraction of plants ≤ x")
        axes[0].legend(loc="center", fontsize=8)
        fig.savefig(path, dpi=80)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", type=int, default=256, help="plants per model (default 256)")
    ap.add_argument("--t-final", type=float, default=10.0, help="horizon [s] (default 10)")
    ap.add_argument("--dt", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=7, help="seed of the evaluation plants")
    ap.add_argument("--tune-time", type=float, default=120.0,
                    help="time limit of the tuning on the backlash model [s], compilation "
                    "included (default 120)")
    ap.add_argument("--robust-time", type=float, default=300.0,
                    help="time limit of the robust tuning over all models [s], compilation "
                    "included (default 300)")
    ap.add_argument("--batch", type=int, default=0,
                    help="plants per model of the tuning over all models (default 0: each "
                    "model's nominal plant)")
    ap.add_argument("--robust-start", choices=("tuned_backlash", "paper"),
                    default="tuned_backlash", help="start gains of the tuning over all models")
    ap.add_argument("--combine", choices=("mean", "max"), default="mean",
                    help="how the four models' CVaRs are combined (default mean)")
    ap.add_argument("--out", default="results/mismatch")
    args = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)  # tuning in float64; sweeps cast to float32
    from dscjax import files
    from dscjax.config import paper_example

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load_start, t_start = os.getloadavg(), time.perf_counter()
    print(f"load average at start: {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}")
    gains, tuning_info = {"paper": paper_example().controller}, {}
    gains["tuned_backlash"], tuning_info["tuned_backlash"] = tune(
        ("backlash",), args, 0, args.tune_time, gains["paper"])
    gains["tuned_all"], tuning_info["tuned_all"] = tune(
        KINDS, args, args.batch, args.robust_time, gains[args.robust_start])
    results = {g: {} for g in GAINS}
    for kind in KINDS:
        for g in GAINS:
            t0 = time.perf_counter()
            results[g][kind] = evaluate(gains[g], kind, args)
            print(f"  swept {g} on {kind}: {time.perf_counter() - t0:.1f} s", flush=True)
    load_end = os.getloadavg()
    wall = time.perf_counter() - t_start
    rows = table(results)
    print("\n".join(rows))
    print(f"wall {wall:.0f} s; load average at end: {load_end[0]:.2f} {load_end[1]:.2f} "
          f"{load_end[2]:.2f}")
    files.write_json(out / "mismatch.json", {
        "settings": vars(args), "ranges": {k: [f"{p}=±{SPREAD:.0%}" for p in v]
                                           for k, v in RANGES.items()},
        "tuning": tuning_info, "results": results, "table": rows, "wall_s": wall,
        "loadavg_start": load_start, "loadavg_end": load_end,
        "gains": {g: {f.name: np.asarray(getattr(c, f.name)).tolist()
                      for f in dataclasses.fields(c) if not f.metadata.get("static")}
                  for g, c in gains.items()}})
    figure(results, out / "mismatch.png", args.t_final)
    print(f"wrote {out}/mismatch.json, mismatch.png")


if __name__ == "__main__":
    main()
