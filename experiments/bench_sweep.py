"""Benchmark of robustness sweeps (issue 5): the paper's example, 20 s at dt = 1e-3.

Measured in ONE run, medians of several repetitions:

- throughput of the sweep's block program (`dscjax.sweep`, metrics only) in closed-loop RK4
  steps per second against the batch size 1 ... 65,536, float32 and float64;
- scipy `solve_ivp` (RK45, rtol 1e-6) one plant at a time on a few plants (the independent
  numpy closed loop of tests/reference_paper.py), as "equivalent RK4 steps" per second
  (T/dt per plant / wall time), and the ratio;
- end to end, compilation included: `dscjax sweep --samples 100000` (20 s horizon) in a fresh
  process, wall time, the sweep's own steps/s, and its peak RSS; peak RSS also at 10^4 samples
  (flat within 20 % is the target);
- 4 forced host devices against 1 (float64, separate processes): identical results?
  (also the spmd/shard_map mode, for comparison).

    python experiments/bench_sweep.py            # full (~25 min on 2 quiet cores)
    python experiments/bench_sweep.py --quick    # smoke run (~3 min): short horizons

Prints a table and writes JSON (default results/bench_sweep.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import dscjax  # noqa: E402
from dscjax import params  # noqa: E402
from dscjax.metrics import default_window  # noqa: E402
from dscjax.sweep.device import METRICS, Runner  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import reference_paper  # noqa: E402

DT = 1e-3
SIZES_FULL = (1, 16, 256, 1024, 4096, 16384, 65536)
SIZES_QUICK = (1, 256, 4096, 16384)


def _table(b, seed=0):
    """The default sweep's parameters, rounded to float32 so that float32 and float64 runs
    simulate the same plants."""
    setup = dscjax.paper_example()
    ranges = [r.resolve(setup) for r in params.default_ranges()]
    table = params.sample_table(ranges, "uniform", b, seed)
    return ranges, table.astype(np.float32).astype(np.float64)


def bench_throughput(dtype, sizes, repeats, horizon):
    setup = dscjax.paper_example(dtype=dtype)
    n = int(round(horizon / DT))
    rows, outputs = [], {}
    for b in sizes:
        ranges, table = _table(b)
        runner = Runner(setup, [r.param for r in ranges], n, DT,
                        default_window(horizon, None), 1e6, b, devices=jax.devices()[:1])
        t0 = time.perf_counter()
        out = runner(table, 1)
        first = time.perf_counter() - t0
        reps = repeats if b * n <= 3e8 else max(1, repeats // 2)
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            runner(table, 1)
            times.append(time.perf_counter() - t0)
        t_med = float(np.median(times))
        outputs[b] = out
        rows.append(dict(batch=b, dtype=np.dtype(dtype).name, seconds=t_med, repeats=reps,
                         steps_per_s=b * n / t_med, first_call_s=first,
                         compile_s=max(first - t_med, 0.0)))
        print(f"  {np.dtype(dtype).name:8s} B={b:6d}  {b * n / t_med:10.3g} steps/s  "
              f"({t_med:.3f} s per run, first call {first:.2f} s)", flush=True)
    return rows, outputs


def bench_scipy(n_plants, horizon):
    from scipy.integrate import solve_ivp

    _, table = _table(n_plants, seed=1)
    rows = []
    for alpha, lam, psi in table:
        p = dict(reference_paper.P, alpha=alpha, lam=lam, psi=psi)
        x0 = reference_paper.initial_state(p)
        t0 = time.perf_counter()
        sol = solve_ivp(lambda t, x, p=p: reference_paper.rhs(t, x, p), (0.0, horizon), x0,
                        method="RK45", rtol=1e-6)
        wall = time.perf_counter() - t0
        rows.append(dict(alpha=alpha, lam=lam, psi=psi, seconds=wall, nfev=int(sol.nfev),
                         success=bool(sol.success)))
        print(f"  scipy RK45 rtol 1e-6: {wall:.2f} s, {sol.nfev} evaluations "
              f"(alpha={alpha:.3f}, lam={lam:.3f}, psi={psi:.3f})", flush=True)
    t_med = float(np.median([r["seconds"] for r in rows]))
    return dict(plants=rows, seconds_per_plant=t_med,
                equivalent_steps_per_s=horizon / DT / t_med)


def _rss_run(args, host_devices=1):
    """`dscjax ARGS` in a fresh process: wall time, the time inside main(), and the child's
    own peak RSS (MiB)."""
    code = textwrap.dedent(f"""
        import resource, sys, time
        from dscjax.cli.main import main
        t0 = time.perf_counter()
        rc = main({args!r})
        wall = time.perf_counter() - t0
        print("BENCH", rc, wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
              file=sys.stderr)
        sys.exit(rc)
    """)
    env = dict(os.environ)
    if host_devices > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count="
                            f"{host_devices}").strip()
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    line = [ln for ln in proc.stderr.splitlines() if ln.startswith("BENCH")]
    if proc.returncode != 0 or not line:
        raise RuntimeError(f"dscjax {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    _, _, inner_wall, rss = line[-1].split()
    return wall, float(inner_wall), float(rss), proc.stderr


def bench_end_to_end(samples, horizon, repeats, tmp, host_devices=1):
    rows = []
    for i in range(repeats):
        out = Path(tmp) / f"e2e_{samples}_{horizon:g}_{i}"
        wall, inner, rss, err = _rss_run(
            ["sweep", "--samples", str(samples), "--t-final", str(horizon), "--out", str(out),
             "--quiet", "--overwrite"], host_devices)
        summary = json.loads((out / "summary.json").read_text())
        rows.append(dict(wall_s=wall, main_s=inner, sweep_s=summary["run"]["wall_s"],
                         sweep_steps_per_s=summary["run"]["steps_per_s"], peak_rss_mib=rss,
                         end_to_end_steps_per_s=samples * horizon / DT / wall))
        print(f"  sweep {samples:,} x {horizon:g} s: {wall:.1f} s end to end "
              f"({samples * horizon / DT / wall:.3g} steps/s incl. start-up and compilation; "
              f"sweep loop {summary['run']['wall_s']:.1f} s), peak RSS {rss:.0f} MiB",
              flush=True)
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    return dict(samples=samples, horizon=horizon, host_devices=host_devices, runs=rows,
                median=med)


def bench_devices(horizon, samples=64, chunk=16):
    script = textwrap.dedent("""
        import sys, jax
        jax.config.update("jax_enable_x64", True)
        import numpy as np, dscjax
        from dscjax.sweep import SweepSettings, run_sweep
        res = run_sweep(dscjax.paper_example(), SweepSettings(samples=%d, chunk=%d,
                        dtype="float64", parallel=sys.argv[2]), %r, 1e-3)
        np.savez(sys.argv[1], n_devices=res.info["devices"], **res.columns)
    """) % (samples, chunk, horizon)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, n_dev, mode in (("one", 1, "per_device"), ("four", 4, "per_device"),
                                  ("four_spmd", 4, "spmd")):
            env = dict(os.environ, JAX_PLATFORMS="cpu")
            env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") +
                                f" --xla_force_host_platform_device_count={n_dev}").strip()
            path = Path(tmp) / f"{name}.npz"
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", script, str(path), mode], env=env, check=True)
            with np.load(path) as z:
                out[name] = {k: z[k] for k in z.files}
            out[name + "_s"] = time.perf_counter() - t0
    one = out["one"]

    def compare(other):
        keys = [k for k in one if k != "n_devices"]
        same = all(np.array_equal(one[k], other[k]) for k in keys)
        rel = max(float(np.max(np.abs(one[k].astype(float) - other[k].astype(float))
                               / np.maximum(np.abs(one[k].astype(float)), 1e-300)))
                  for k in METRICS)
        return same, rel

    same4, rel4 = compare(out["four"])
    same_spmd, rel_spmd = compare(out["four_spmd"])
    res = dict(samples=samples, chunk=chunk, horizon=horizon,
               devices=[int(out[k]["n_devices"]) for k in ("one", "four", "four_spmd")],
               identical_per_device=same4, max_rel_diff_per_device=rel4,
               identical_spmd=same_spmd, max_rel_diff_spmd=rel_spmd,
               wall_s={k: out[k + "_s"] for k in ("one", "four", "four_spmd")})
    print(f"  1 vs 4 devices (float64, {samples} samples): per_device identical = {same4} "
          f"(max rel diff {rel4:.2g}); spmd identical = {same_spmd} (max rel diff "
          f"{rel_spmd:.2g})", flush=True)
    return res


def precision(out32, out64):
    """float32 against float64 on the same samples (the largest common batch)."""
    b = max(set(out32) & set(out64))
    a, r = out32[b], out64[b]
    ok = (a["status"] == 0) & (r["status"] == 0)
    rel = {}
    for m in ("linf_error_window", "l2_error_window", "max_abs_u", "tv_u"):
        d = (np.abs(a[m][ok].astype(float) - r[m][ok]) / np.maximum(np.abs(r[m][ok]), 1e-300))
        rel[m] = dict(median=float(np.median(d)), p99=float(np.quantile(d, 0.99)),
                      max=float(np.max(d)))
    return dict(batch=b, rel_diff=rel, status_agree=bool(np.all(a["status"] == r["status"])))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="short horizons, small sizes")
    p.add_argument("--out", default=str(ROOT / "results" / "bench_sweep.json"))
    p.add_argument("--repeats", type=int, default=None, help="timed runs per batch size")
    p.add_argument("--e2e-repeats", type=int, default=None, help="end-to-end runs")
    p.add_argument("--e2e-host-devices", type=int, default=1, metavar="N",
                   help="end to end with N forced host devices (XLA_FLAGS), e.g. one per core")
    p.add_argument("--skip", nargs="*", default=(), choices=("throughput", "scipy", "e2e",
                                                              "rss", "devices"))
    a = p.parse_args(argv)
    quick = a.quick
    repeats = a.repeats or (2 if quick else 3)
    e2e_rep = a.e2e_repeats or (1 if quick else 3)
    horizon = 2.0 if quick else 20.0
    sizes = SIZES_QUICK if quick else SIZES_FULL
    e2e_samples, e2e_horizon = (100_000, 0.5) if quick else (100_000, 20.0)
    rss_horizon = 0.2 if quick else 2.0
    load0 = os.getloadavg()
    result = dict(quick=quick, machine=dict(cpus=os.cpu_count(), platform=platform.platform(),
                                            jax=jax.__version__, load_avg_start=load0,
                                            xla_flags=os.environ.get("XLA_FLAGS", "")),
                  dt=DT, horizon=horizon)
    print(f"dscjax sweep benchmark ({'quick' if quick else 'full'}): paper example, dt = {DT}, "
          f"{os.cpu_count()} CPUs, jax {jax.__version__}, load average "
          f"{load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}; XLA_FLAGS "
          f"{os.environ.get('XLA_FLAGS', '')!r}", flush=True)
    if "throughput" not in a.skip:
        print(f"throughput of the block program, T = {horizon:g} s:", flush=True)
        r32, o32 = bench_throughput(np.float32, sizes, repeats, horizon)
        r64, o64 = bench_throughput(np.float64, sizes, repeats, horizon)
        result["throughput"] = r32 + r64
        result["float32_vs_float64"] = precision(o32, o64)
    if "scipy" not in a.skip:
        print(f"scipy solve_ivp one plant at a time, T = {horizon:g} s:", flush=True)
        result["scipy"] = bench_scipy(2 if quick else 5, horizon)
    with tempfile.TemporaryDirectory() as tmp:
        if "e2e" not in a.skip:
            print("end to end (fresh process, compilation included):", flush=True)
            result["end_to_end"] = bench_end_to_end(e2e_samples, e2e_horizon, e2e_rep, tmp,
                                                    a.e2e_host_devices)
        if "rss" not in a.skip:
            print(f"peak RSS, T = {rss_horizon:g} s:", flush=True)
            result["rss"] = {str(n): bench_end_to_end(n, rss_horizon, 1, tmp)["median"]
                             ["peak_rss_mib"] for n in (10_000, 100_000)}
    if "devices" not in a.skip:
        print("device count:", flush=True)
        result["devices"] = bench_devices(0.5 if quick else 2.0)
    result["load_avg_end"] = os.getloadavg()
    _report(result)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(f"wrote {out}")


def _report(r):
    print("\n== summary ==")
    if "throughput" in r:
        print(f"{'dtype':8s} {'batch':>7s} {'steps/s':>10s} {'x scipy':>9s}")
        sc = r.get("scipy", {}).get("equivalent_steps_per_s")
        for row in r["throughput"]:
            ratio = f"{row['steps_per_s'] / sc:9.0f}" if sc else "        -"
            print(f"{row['dtype']:8s} {row['batch']:7d} {row['steps_per_s']:10.3g} {ratio}")
    if "scipy" in r:
        print(f"scipy RK45 rtol 1e-6: {r['scipy']['seconds_per_plant']:.2f} s per plant = "
              f"{r['scipy']['equivalent_steps_per_s']:.3g} equivalent steps/s")
    if "float32_vs_float64" in r:
        f = r["float32_vs_float64"]
        print(f"float32 vs float64, same plants (B={f['batch']}), relative difference "
              "median / p99 / max:")
        for k, v in f["rel_diff"].items():
            print(f"  {k:18s} {v['median']:.2g} / {v['p99']:.2g} / {v['max']:.2g}")
    if "end_to_end" in r:
        e = r["end_to_end"]
        m = e["median"]
        print(f"end to end {e['samples']:,} plants x {e['horizon']:g} s: {m['wall_s']:.1f} s "
              f"({m['end_to_end_steps_per_s']:.3g} steps/s; target < 120 s and >= 2e7 steps/s "
              f"for 20 s), peak RSS {m['peak_rss_mib']:.0f} MiB")
    if "rss" in r:
        a, b = r["rss"]["10000"], r["rss"]["100000"]
        print(f"peak RSS 10^4: {a:.0f} MiB, 10^5: {b:.0f} MiB (ratio {b / a:.3f}; target "
              f"within 20 %)")
    if "devices" in r:
        d = r["devices"]
        print(f"1 vs 4 devices: identical = {d['identical_per_device']} (per_device), "
              f"{d['identical_spmd']} (spmd, max rel diff {d['max_rel_diff_spmd']:.2g})")
    print(f"load average at start {r['machine']['load_avg_start']}, at end "
          f"{tuple(round(x, 2) for x in r['load_avg_end'])}")


if __name__ == "__main__":
    main()
