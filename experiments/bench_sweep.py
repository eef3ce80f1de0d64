"""Robustness sweeps: `dscjax sweep` end to end, its memory, and each hysteresis model's cost.

    python experiments/bench_sweep.py            # full sizes (docs/benchmarks.md)
    python experiments/bench_sweep.py --quick    # small sweeps, short horizons: JSON only

- End to end: `dscjax sweep --samples 100000` over 20 s (its default dtype) in a fresh
  process, start-up and compilation included (no persistent compilation cache), median of
  --repeats: wall time and closed-loop RK4 steps per second, against scipy's solve_ivp (RK45,
  rtol 1e-6) one plant at a time on the plain-Python loop of tests/reference_paper.py.
- Peak RSS of the command at two sample counts: the end-to-end runs' and a tenth of it.
- Per hysteresis model (`--example paper | pi | gpi | bouc_wen`, each model's default ranges):
  the sweep's block program's time per plant against the backlash-like model's, compilation
  excluded, the models timed in turn; and float32 against float64 on the same plants.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from harness import Bench, Child, child, median, parser, reference_loop  # noqa: E402

from dscjax import params  # noqa: E402
from dscjax.config import example  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from dscjax.sweep import SweepSettings  # noqa: E402
from dscjax.sweep.device import Runner, tile_rows  # noqa: E402

DT = 1e-3
MODELS = ("paper", "pi", "gpi", "bouc_wen")


def sweep_command(samples: int, t_final: float, out: Path) -> Child:
    """`dscjax sweep` in a fresh process, compilation included (no persistent cache)."""
    env = dict(os.environ, DSCJAX_NO_COMPILATION_CACHE="1")
    run = child([sys.executable, "-m", "dscjax.cli.main", "sweep", "--samples", samples,
                 "--t-final", t_final, "--out", out, "--no-plot", "--quiet", "--overwrite"],
                env=env)
    if run.returncode != 0:
        raise SystemExit(f"bench_sweep: dscjax sweep failed:\n{run.stderr[-3000:]}")
    return run


def scipy_seconds(n_plants: int, t_final: float) -> float:
    """Median seconds of one plant (the default sweep's ranges) by solve_ivp."""
    from scipy.integrate import solve_ivp

    ref = reference_loop()
    setup = example("paper")
    table = params.Uniform().draw([r.resolve(setup) for r in params.default_ranges(setup)],
                                  n_plants, 1)
    times = []
    for alpha, lam, psi in table:
        p = dict(ref.P, alpha=alpha, lam=lam, psi=psi)
        t0 = time.perf_counter()
        solve_ivp(lambda t, x, p=p: ref.rhs(t, x, p), (0.0, t_final), ref.initial_state(p),
                  method="RK45", rtol=1e-6)
        times.append(time.perf_counter() - t0)
    return median(times)


def runner(name: str, dtype, plants: int, t_final: float, seed: int = 0):
    """The sweep's block program for one example (its default ranges), and its table."""
    setup = example(name, dtype=dtype)
    ranges = [r.resolve(setup) for r in params.default_ranges(setup)]
    table = params.Uniform().draw(ranges, plants, seed).astype(np.float32)
    run = Runner(setup, [r.param for r in ranges], RunSpec.make(t_final, DT),
                 devices=jax.devices()[:1], tile=tile_rows(jax.devices()[0].platform, plants))
    return lambda: run([table], plants)


def main(argv=None) -> int:
    p = parser(__doc__, "end-to-end runs (median)")
    a = p.parse_args(argv)
    quick = a.quick
    samples, horizon = (10_000, 0.2) if quick else (100_000, 20.0)
    plants, model_horizon = (256, 1.5) if quick else (10_000, 2.0)
    repeats = a.repeats or (1 if quick else 3)
    bench = Bench("sweep", "Robustness sweeps", quick=quick)

    with tempfile.TemporaryDirectory() as tmp:
        runs = [sweep_command(samples, horizon, Path(tmp) / f"e2e{i}") for i in range(repeats)]
        summary = json.loads((Path(tmp) / "e2e0" / "summary.json").read_text())
        loop = median([json.loads((Path(tmp) / f"e2e{i}" / "summary.json").read_text())
                       ["run"]["wall_s"] for i in range(repeats)])
        few = samples // 10
        rss_few = sweep_command(few, horizon, Path(tmp) / "few").peak_rss_mib
    bench.read_load()
    steps = samples * int(round(horizon / DT))
    wall = median([r.wall_s for r in runs])
    scipy_s = scipy_seconds(2 if quick else 5, horizon)
    what = f"{samples:,} plants x {horizon:g} s, {SweepSettings().dtype}"
    bench.add(case=f"end to end, {what} [s]", dscjax=wall, baseline="scipy RK45, one plant "
              "at a time", baseline_value=scipy_s * samples, x_baseline=scipy_s * samples / wall)
    bench.add(case=f"end to end, {what} [steps/s]", dscjax=steps / wall)
    bench.add(case=f"run_sweep alone (compilation included), {what} [steps/s]",
              dscjax=steps / loop)
    rss = median([r.peak_rss_mib for r in runs])
    bench.add(case=f"peak RSS, {what} [MiB]", dscjax=rss, baseline=f"{few:,} plants",
              baseline_value=rss_few, x_baseline=rss / rss_few)
    runs_word = f"median of {repeats} fresh processes" if repeats > 1 else "one fresh process"
    bench.note(f"End to end: {runs_word} (`dscjax sweep --samples "
               f"{samples} --t-final {horizon:g}`, DSCJAX_NO_COMPILATION_CACHE=1); "
               f"{summary['n_diverged']} of {samples:,} plants diverged. scipy: the median "
               "plant's seconds times the plants.")

    runners = {m: runner(m, np.float32, plants, model_horizon) for m in MODELS}
    runners["paper, float64"] = runner("paper", np.float64, plants, model_horizon)
    out = {m: jax.device_get(r()) for m, r in runners.items()}
    times = bench.interleaved(runners, repeats=3 if quick else 7, warmup=0)
    base = median(times["paper"]) / plants
    for m in MODELS:
        per = median(times[m]) / plants
        bench.add(case=f"block program per plant, {m}, {model_horizon:g} s [ms]", dscjax=1e3 * per,
                  baseline="paper (backlash-like)", baseline_value=1e3 * base,
                  x_baseline=per / base)
    f32, f64 = out["paper"], out["paper, float64"]
    ok = (f32["status"] == 0) & (f64["status"] == 0)
    key = "linf_error_window"
    rel = np.abs(f32[key][ok] - f64[key][ok]) / np.abs(f64[key][ok])
    bench.add(case=f"float32 vs float64, windowed L-inf, {plants:,} plants, relative "
              "difference (median / p99 / max)",
              dscjax=f"{np.median(rel):.2g} / {np.quantile(rel, 0.99):.2g} / {rel.max():.2g}")
    bench.note(f"Per model: {plants:,} plants of each example's default ranges (+-30 %), "
               f"float32, medians of interleaved calls after compilation.")
    bench.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
