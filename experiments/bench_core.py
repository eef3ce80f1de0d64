"""Benchmark of the simulator core (issue 2): the paper's example, 20 s at dt = 1e-3.

Everything is measured in ONE run on this machine, as ratios against baselines timed in the
same run, medians of several repetitions after compilation:

- single trajectory: dscjax (full trajectory saved; metrics only) against scipy solve_ivp
  (RK45, rtol 1e-6) on the same closed loop (the independent numpy implementation of
  tests/reference_paper.py), and diffrax with a classical RK4 tableau on dscjax's vector field
  at the same dt (if diffrax is installed: `pip install -e ".[bench]"`);
- batched throughput in closed-loop RK4 steps per second, vmap over the hysteresis
  parameters, float32 and float64, batch 1 ... 32768; also plain `jax.vmap(simulate)`;
- compile time, and whether changing a gain recompiles.

    python experiments/bench_core.py            # full (~10 min on 2 cores)
    python experiments/bench_core.py --quick    # smoke run (~1 min)

Prints a table and writes JSON (default results/bench_core.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import dscjax  # noqa: E402
from dscjax import params  # noqa: E402
from dscjax.simulate import _simulate, _simulate_batch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import reference_paper  # noqa: E402

T_FINAL, DT = 20.0, 1e-3
N_STEPS = int(round(T_FINAL / DT))


def median_time(fn, repeats):
    out = fn()
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), times


def bench_scipy(repeats):
    from scipy.integrate import solve_ivp

    x0 = reference_paper.initial_state()
    times, nfev = [], 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = solve_ivp(reference_paper.rhs, (0.0, T_FINAL), x0, method="RK45", rtol=1e-6)
        times.append(time.perf_counter() - t0)
        nfev = sol.nfev
    return float(np.median(times)), nfev


def bench_diffrax(setup, repeats):
    try:
        import diffrax
    except ImportError:
        return None
    from jax.flatten_util import ravel_pytree

    from dscjax.closed_loop import initial_state, prepared, vector_field

    class RK4(diffrax.AbstractERK):
        tableau = diffrax.ButcherTableau(
            c=np.array([0.5, 0.5, 1.0]),
            b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
            b_error=np.zeros(4),
            a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        )
        interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

        def order(self, terms):
            return 4

    s = prepared(setup)
    y0, unravel = ravel_pytree(initial_state(s))

    def field(t, y, args):
        return ravel_pytree(vector_field(t, unravel(y), args)[0])[0]

    @jax.jit
    def solve(args, y0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field), RK4(), t0=0.0, t1=T_FINAL, dt0=DT, y0=y0, args=args,
            saveat=diffrax.SaveAt(t1=True), stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=N_STEPS + 10)
        return sol.ys

    t_med, _ = median_time(lambda: solve(s, y0), repeats)
    # same trajectory as dscjax (same tableau and grid; diffrax forms t_k by summation)
    ours = dscjax.simulate(setup, T_FINAL, DT, save_every=N_STEPS)
    diff = float(jnp.max(jnp.abs(solve(s, y0)[-1][:2] - ours.x[-1])))
    return t_med, diff


def bench_single(setup, repeats):
    full, _ = median_time(lambda: _simulate(setup, DT, 1.0, 1e6, n_steps=N_STEPS,
                                            save_every=1), repeats)
    only, _ = median_time(lambda: _simulate(setup, DT, 1.0, 1e6, n_steps=N_STEPS,
                                            save_every=N_STEPS), repeats)
    return full, only


def bench_compile(setup):
    """Wall time of a first call (trace + compile + run) at a step count not used before."""
    n = N_STEPS - 1000
    t0 = time.perf_counter()
    jax.block_until_ready(_simulate(setup, DT, 1.0, 1e6, n_steps=n, save_every=n))
    first = time.perf_counter() - t0
    run, _ = median_time(lambda: _simulate(setup, DT, 1.0, 1e6, n_steps=n, save_every=n), 3)
    jax.block_until_ready(dscjax.simulate(setup, T_FINAL - 1.0, DT, save_every=n).x)
    size = _simulate._cache_size()
    for k1 in (8.0, 9.0, 11.0):
        s = params.set(setup, "controller.k", np.array([k1, 0.5]))
        jax.block_until_ready(dscjax.simulate(s, T_FINAL - 1.0, DT, save_every=n).x)
    recompiled = _simulate._cache_size() != size
    return first - run, recompiled


def bench_batch(dtype, sizes, repeats, horizon):
    setup = dscjax.paper_example(dtype=dtype)
    n = int(round(horizon / DT))
    rows = []
    for b in sizes:
        rng = np.random.default_rng(0)
        over = {
            "hysteresis.alpha": jnp.asarray(rng.uniform(0.7, 1.3, b), dtype),
            "hysteresis.lam": jnp.asarray(rng.uniform(1.0, 1.86, b), dtype),
            "hysteresis.psi": jnp.asarray(rng.uniform(0.0735, 0.1365, b), dtype),
        }

        def run(over=over):
            return _simulate_batch(setup, over, DT, 1.0, 1e6, n_steps=n, save_every=n).metrics

        t0 = time.perf_counter()
        jax.block_until_ready(run())
        first = time.perf_counter() - t0
        reps = repeats if b * n <= 2e8 else max(2, repeats // 2)
        t_med, _ = median_time(run, reps)
        rows.append(dict(batch=b, dtype=np.dtype(dtype).name, seconds=t_med,
                         steps_per_s=b * n / t_med, first_call_s=first))
        print(f"  {np.dtype(dtype).name:8s} B={b:6d}  {b * n / t_med:10.3g} steps/s "
              f"({t_med:.3f} s per run)", flush=True)
    return rows


def bench_plain_vmap(dtype, b, repeats, horizon):
    """jax.vmap of the single-trajectory simulation (batch-first layout), for comparison."""
    setup = dscjax.paper_example(dtype=dtype)
    n = int(round(horizon / DT))
    alphas = jnp.asarray(np.linspace(0.7, 1.3, b), dtype)
    from dscjax.simulate import run

    @jax.jit
    def batched(alphas):
        return jax.vmap(lambda a: run(params.set(setup, "hysteresis.alpha", a), DT, 1.0, 1e6,
                                      n_steps=n, save_every=n).metrics)(alphas)

    t_med, _ = median_time(lambda: batched(alphas), repeats)
    return b * n / t_med


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small batches, few repeats")
    p.add_argument("--out", default=str(ROOT / "results" / "bench_core.json"))
    p.add_argument("--repeats", type=int, default=None)
    a = p.parse_args(argv)
    repeats = a.repeats or (3 if a.quick else 7)
    setup = dscjax.paper_example()

    print(f"dscjax core benchmark: paper example, T = {T_FINAL} s, dt = {DT}, "
          f"{N_STEPS} RK4 steps; {os.cpu_count()} CPUs, jax {jax.__version__}; XLA_FLAGS "
          f"{os.environ.get('XLA_FLAGS', '')!r}", flush=True)
    compile_s, recompiled = bench_compile(setup)
    full, only = bench_single(setup, repeats)
    sc, nfev = bench_scipy(max(3, repeats // 2))
    dx = bench_diffrax(setup, repeats)
    print(f"  single: dscjax {full * 1e3:.1f} ms (every step saved), {only * 1e3:.1f} ms "
          f"(metrics only); scipy RK45 {sc * 1e3:.1f} ms ({nfev} evaluations)"
          + (f"; diffrax RK4 {dx[0] * 1e3:.1f} ms" if dx else "; diffrax not installed"),
          flush=True)

    sizes = [1, 64, 1024, 8192] if a.quick else [1, 8, 64, 512, 2048, 8192, 16384, 32768]
    horizon = 2.0 if a.quick else T_FINAL
    batch = []
    for dtype in (np.float32, np.float64):
        batch += bench_batch(dtype, sizes, repeats, horizon)
    plain = {np.dtype(d).name: bench_plain_vmap(d, 8192, max(2, repeats // 2), 2.0)
             for d in (np.float32, np.float64)}

    best = {d: max((r for r in batch if r["dtype"] == d), key=lambda r: r["steps_per_s"])
            for d in ("float32", "float64")}
    result = dict(
        machine=dict(cpus=os.cpu_count(), platform=platform.platform(), jax=jax.__version__,
                     python=platform.python_version(),
                     xla_flags=os.environ.get("XLA_FLAGS", "")),
        settings=dict(t_final=T_FINAL, dt=DT, steps=N_STEPS, repeats=repeats, quick=a.quick,
                      batch_horizon_s=horizon),
        single=dict(dscjax_full_s=full, dscjax_metrics_only_s=only, scipy_rk45_s=sc,
                    scipy_nfev=nfev, speedup_vs_scipy_full=sc / full,
                    speedup_vs_scipy_metrics_only=sc / only,
                    diffrax_rk4_s=dx[0] if dx else None,
                    diffrax_max_abs_diff=dx[1] if dx else None,
                    speedup_vs_diffrax=(dx[0] / only) if dx else None),
        compile=dict(compile_s=compile_s, gain_change_recompiles=recompiled),
        batch=batch, best=best, plain_jax_vmap_steps_per_s_B8192=plain,
        targets=dict(single_speedup_vs_scipy=25.0, float32_steps_per_s=3e7,
                     float64_steps_per_s=1.5e7),
    )
    print("\n| measure | value | target |\n|---|---|---|")
    print(f"| single run vs scipy RK45 (every step saved) | {sc / full:.1f}x "
          f"({full * 1e3:.1f} vs {sc * 1e3:.0f} ms) | >= 25x |")
    print(f"| single run vs scipy RK45 (metrics only) | {sc / only:.1f}x ({only * 1e3:.1f} ms) | "
          f">= 25x |")
    if dx:
        print(f"| single run vs diffrax RK4 (same tableau, dt) | {dx[0] / only:.1f}x "
              f"({dx[0] * 1e3:.1f} ms; max |dx| {dx[1]:.1e}) | - |")
    for d, target in (("float32", 3e7), ("float64", 1.5e7)):
        r = best[d]
        print(f"| batched {d}, best batch {r['batch']} | {r['steps_per_s']:.3g} steps/s | "
              f">= {target:.1e} |")
        print(f"| plain jax.vmap(simulate) {d}, B=8192 | {plain[d]:.3g} steps/s | - |")
    print(f"| compile time (trace + XLA) | {compile_s:.2f} s | - |")
    print(f"| changing a gain recompiles | {'yes' if recompiled else 'no'} | no |")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
