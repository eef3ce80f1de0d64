"""The simulator core: the paper's example, 20 s at dt = 1e-3 (20,000 RK4 steps).

    python experiments/bench_core.py            # full sizes (docs/benchmarks.md)
    python experiments/bench_core.py --quick    # 2 s, small batches: JSON only

One trajectory (float64; every step saved, and metrics only) against scipy's solve_ivp (RK45,
rtol 1e-6) on the independent plain-Python loop of tests/reference_paper.py, and against diffrax
with the same RK4 tableau and dt on dscjax's vector field; batched throughput in closed-loop
RK4 steps per second against the batch size, float32 and float64 (hysteresis alpha, lam, psi
+-30 %), against the same program without 512-bit vectors (on AVX-512 CPUs) and against plain
`jax.vmap`; the compile time; whether changing a gain recompiles. The compiled programs are
timed alone (`simulate._simulate`, `_simulate_batch`: no host-side checks).
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from harness import Bench, diffrax_rk4, median, parser, reference_loop  # noqa: E402

import dscjax  # noqa: E402
from dscjax import params, xla  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from dscjax.simulate import _simulate, _simulate_batch, canonical, run_reported  # noqa: E402

DT = 1e-3


def spec(t_final: float, save_every: int | None = None) -> RunSpec:
    n = int(round(t_final / DT))
    return RunSpec.make(t_final, DT, save_every=save_every or n)


def scipy_run(t_final: float):
    from scipy.integrate import solve_ivp

    ref = reference_loop()
    x0 = ref.initial_state()
    return lambda: solve_ivp(ref.rhs, (0.0, t_final), x0, method="RK45", rtol=1e-6)


def diffrax_run(setup, t_final: float):
    """diffrax's diffeqsolve with the classical RK4 tableau at dt on dscjax's vector field (the
    last state only), its largest difference from dscjax's last state and diffrax's version;
    None without diffrax (`pip install -e ".[bench]"`)."""
    peer = diffrax_rk4()
    if peer is None:
        return None
    diffrax, rk4 = peer
    from jax.flatten_util import ravel_pytree

    from dscjax.closed_loop import initial_state, prepared, vector_field

    s = prepared(setup)
    y0, unravel = ravel_pytree(initial_state(s))
    n = int(round(t_final / DT))

    @jax.jit
    def solve(args, y0):
        def field(t, y, args):
            return ravel_pytree(vector_field(t, unravel(y), args)[0])[0]

        return diffrax.diffeqsolve(
            diffrax.ODETerm(field), rk4, t0=0.0, t1=t_final, dt0=DT, y0=y0, args=args,
            saveat=diffrax.SaveAt(t1=True), stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=n + 10).ys

    ours = dscjax.simulate(setup, t_final, DT, save_every=n)
    diff = float(jnp.max(jnp.abs(solve(s, y0)[-1][:2] - ours.x[-1])))
    return (lambda: solve(s, y0)), diff, diffrax.__version__


def compile_and_recompile(setup, t_final: float) -> tuple[float, bool]:
    """Seconds of tracing and compiling a simulation at a step count not used before (first
    call minus a later call), and whether changing a gain recompiled."""
    sp = spec(t_final - 0.5)
    t0 = time.perf_counter()
    jax.block_until_ready(_simulate(setup, sp, None, None))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(_simulate(setup, sp, None, None))
        runs.append(time.perf_counter() - t0)
    size = _simulate.top._cache_size()
    for k1 in (8.0, 9.0, 11.0):
        changed = params.set(setup, "controller.k", np.array([k1, 0.5]))
        jax.block_until_ready(dscjax.simulate(changed, spec=sp).x)
    return first - median(runs), _simulate.top._cache_size() != size


def hysteresis_batch(b: int, dtype) -> dict:
    rng = np.random.default_rng(0)
    return {"hysteresis.alpha": jnp.asarray(rng.uniform(0.7, 1.3, b), dtype),
            "hysteresis.lam": jnp.asarray(rng.uniform(1.0, 1.86, b), dtype),
            "hysteresis.psi": jnp.asarray(rng.uniform(0.0735, 0.1365, b), dtype)}


def batched(bench: Bench, dtype, b: int, horizon: float, reps: int, wide: bool, vmap: bool
            ) -> dict[str, float]:
    """Steps per second of `simulate_batch`'s program on B plants, and of its baselines: the
    same program without 512-bit vectors (`wide`) and plain jax.vmap of `run` (`vmap`)."""
    setup = canonical(dscjax.paper_example(dtype=dtype))
    sp = spec(horizon)
    over = hysteresis_batch(b, dtype)
    runs = {"dscjax": lambda: _simulate_batch(setup, sp, over).metrics}
    if wide:
        narrow = jax.jit(run_reported)
        runs["256-bit"] = lambda: narrow(setup, sp, over).metrics
    if vmap:
        plain = jax.jit(jax.vmap(lambda a: run_reported(
            params.set(setup, "hysteresis.alpha", a), sp).metrics))
        runs["vmap"] = lambda: plain(over["hysteresis.alpha"])
    steps = b * sp.n_steps
    return {k: steps / median(v) for k, v in bench.interleaved(runs, reps).items()}


def main(argv=None) -> int:
    p = parser(__doc__, "timed calls per case")
    a = p.parse_args(argv)
    quick = a.quick
    repeats = a.repeats or (3 if quick else 7)
    t_final = 2.0 if quick else 20.0
    horizon = 0.5 if quick else 20.0  # of the batched runs
    sizes = (64, 1024) if quick else (1, 64, 1024, 8192, 32768)
    vmap_size = 1024 if quick else 8192
    n, n_batch = int(round(t_final / DT)), int(round(horizon / DT))
    bench = Bench("core", "The simulator core", quick=quick)
    setup = canonical(dscjax.paper_example())

    compile_s, recompiled = compile_and_recompile(setup, t_final)
    every, only = spec(t_final, 1), spec(t_final)
    cases = {"every step saved": lambda: _simulate(setup, every, None, None),
             "metrics only": lambda: _simulate(setup, only, None, None),
             "scipy": scipy_run(t_final)}
    dx = diffrax_run(setup, t_final)
    if dx is not None:
        cases["diffrax"] = dx[0]
    ms = {k: 1e3 * median(v) for k, v in bench.interleaved(cases, repeats).items()}
    what = f"one trajectory, float64, {n:,} steps [ms]"
    for case in ("every step saved", "metrics only"):
        bench.add(case=f"{what}, {case}", dscjax=ms[case], baseline="scipy RK45, rtol 1e-6",
                  baseline_value=ms["scipy"], x_baseline=ms["scipy"] / ms[case])
    if dx is not None:
        bench.add(case=f"{what}, metrics only", dscjax=ms["metrics only"],
                  baseline="diffrax, same RK4 tableau and dt", baseline_value=ms["diffrax"],
                  x_baseline=ms["diffrax"] / ms["metrics only"])
        bench.note(f"diffrax {dx[2]} and dscjax agree to {dx[1]:.1e} in the last state.")
    else:
        bench.note("diffrax is not installed (`pip install -e \".[bench]\"`): no diffrax row.")

    wide = bool(xla.compiler_options())
    for dtype in (np.float32, np.float64):
        for b in sizes:
            rate = batched(bench, dtype, b, horizon, reps=repeats if b * n_batch <= 2e8 else
                           max(2, repeats // 2), wide=wide, vmap=b == vmap_size)
            case = f"batched, {np.dtype(dtype).name}, B = {b:,}, {n_batch:,} steps [steps/s]"
            print(f"  {case}: {rate['dscjax']:.3g}", flush=True)
            for key, label in (("256-bit", "256-bit vectors"), ("vmap", "plain jax.vmap of run")):
                if key in rate:
                    bench.add(case=case, dscjax=rate["dscjax"], baseline=label,
                              baseline_value=rate[key], x_baseline=rate["dscjax"] / rate[key])
            if len(rate) == 1:
                bench.add(case=case, dscjax=rate["dscjax"])
    if not wide:
        bench.note("This CPU has no AVX-512 (or XLA_FLAGS sets the vector width): the batched "
                   "programs are compiled without 512-bit vectors, and no row compares them.")
    bench.add(case="compile time of a simulation [s]", dscjax=compile_s)
    bench.add(case="changing a gain recompiles", dscjax="yes" if recompiled else "no")
    bench.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
