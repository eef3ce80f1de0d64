"""Devices (issue 28): dscjax on the CPU against an accelerator, and against plain JAX.

1. Batch throughput (closed-loop RK4 steps per second) of the paper's loop over plants with
   alpha, lam, psi within +-30 %, on the accelerator if there is one (else the CPU): the
   sweep's block program (`dscjax.sweep.device.Runner`, metrics only), a plain `jax.vmap` of a
   hand-written `lax.scan` RK4 of the same loop (below; it shares no code with dscjax) with
   its windowed L-inf error, and diffrax with the RK4 tableau on that same vector field
   (final state only; the `bench` extra, skipped with a note when not installed).
2. One trajectory (`dscjax.simulate`, metrics only) on the CPU and on the accelerator.
3. The batch gradient: the mean windowed L-inf error over B plants, its gradient with respect
   to the eight adaptation and filter gains (`jax.value_and_grad` through `simulate_batch`)
   against its forward run, on each device.

    python experiments/bench_device.py            # full: 20 s, batches up to 2^20 (for a GPU)
    python experiments/bench_device.py --quick    # 64 plants, 0.1 s, no gradient (CI's smoke run)

--quick leaves the gradient out (`--quick --only gradient` runs it at the quick sizes).
On the shared harness (experiments/harness.py): a table, results/bench/device.json and, unless
--quick, the section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from harness import Bench, diffrax_rk4, median  # noqa: E402

import dscjax  # noqa: E402
from dscjax import params  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from dscjax.simulate import run  # noqa: E402
from dscjax.sweep.device import Runner  # noqa: E402

DT = 1e-3
SIZES_FULL = (1024, 16384, 131072, 524288, 1048576)
SIZES_QUICK = (64,)
SECTIONS = ("throughput", "single", "gradient")
GAINS = ("controller.k", "controller.gamma_g", "controller.gamma_phi", "controller.gamma_zeta",
         "controller.gamma_d", "controller.tau")

# -- the paper's loop by hand (eqs. 73-78, adaptive laws 17, 29, 31, 32, filter 18, hysteresis
# 4, u' by the chain rule), as tests/reference_paper.py writes it, in jax.numpy -------------------

P = dict(g1=1.0, g2=1.0, th1=0.1, k1=10.0, k2=0.45, gam=8.0, eta1=0.01, eta2=0.01, eta_z=0.01,
         eta_d=0.01, sigma=0.01, eps=0.01, gmin=1.0, tau=0.01, c2=0.1, width=0.01)


def field(t, X, hyst):
    """dX/dt of X = [x1, x2, w, z2, theta_g1, theta_2, phi_1, zeta, d_hat]; hyst = (alpha,
    lam, psi)."""
    alpha, lam, psi = hyst
    x1, x2, w, z2, th1h, th2h, ph1, zeta, dh = X
    p, eps = P, P["eps"]
    yr, yr1, yr2 = jnp.sin(t), jnp.cos(t), -jnp.sin(t)
    s1 = x1 - yr
    f1 = x1 * x1
    x2d = -th1h * f1 - s1 * 0.04 / (2 * eps * p["gmin"]) - p["k1"] * s1 + ph1 * yr1
    z2dot = (x2d - z2) / p["tau"]
    s2 = x2 - z2 - p["c2"]
    rho2 = 0.1 * (x1 * x1 + x2 * x2)
    q = s2 / p["width"]
    sat = jnp.clip(q, -1.0, 1.0)
    ubar = -p["k2"] * s2 - s2 * rho2**2 / (2 * eps) + z2dot - sat * dh
    u = zeta * ubar
    x1dot = p["g1"] * x2 + p["th1"] * f1 + 0.2 * jnp.sin(x2)
    x2dot = p["g2"] * w + 0.1 * (x1 * x1 + x2 * x2) * jnp.sin(t) ** 3
    th1dot = p["gam"] * (f1 * s1 - p["eta1"] * th1h)
    th2dot = p["gam"] * (-p["eta2"] * th2h)
    ph1dot = -p["gam"] * (yr1 * s1 + p["sigma"] * ph1)
    zetadot = -p["gam"] * (ubar * s2 + p["eta_z"] * zeta)
    dhdot = p["gam"] * (jnp.abs(s2) - p["eta_d"] * dh)
    s1dot = x1dot - yr1
    x2d_dot = (-th1dot * f1 - th1h * 2 * x1 * x1dot - s1dot * 0.04 / (2 * eps * p["gmin"])
               - p["k1"] * s1dot + ph1dot * yr1 + ph1 * yr2)
    z2ddot = (x2d_dot - z2dot) / p["tau"]
    s2dot = x2dot - z2dot
    rho2dot = 0.2 * (x1 * x1dot + x2 * x2dot)
    satdot = jnp.where(jnp.abs(q) < 1.0, s2dot / p["width"], 0.0)
    ubardot = (-p["k2"] * s2dot - (s2dot * rho2**2 + 2 * s2 * rho2 * rho2dot) / (2 * eps)
               + z2ddot - satdot * dh - sat * dhdot)
    udot = zetadot * ubar + zeta * ubardot
    wdot = alpha * jnp.abs(udot) * (lam * u - w) + psi * udot
    return jnp.stack([x1dot, x2dot, wdot, z2dot, th1dot, th2dot, ph1dot, zetadot, dhdot])


def x0(dtype):
    x1, x2, th1h, ph1 = 0.08, 0.1, 0.05, 1.0
    z2 = -th1h * x1 * x1 - (x1 - 0.0) * 0.04 / (2 * P["eps"] * P["gmin"]) - P["k1"] * x1 + ph1
    return jnp.asarray([x1, x2, 0.0, z2, th1h, 0.0, ph1, 0.5, 1.0], dtype)


def plain_linf(hyst, n_steps: int, window_start: float, dtype):
    """The windowed L-inf tracking error of one plant: a hand-written lax.scan of RK4."""
    dt = jnp.asarray(DT, dtype)

    def step(carry, k):
        X, worst = carry
        t = k.astype(dtype) * dt
        k1 = field(t, X, hyst)
        k2 = field(t + dt / 2, X + dt / 2 * k1, hyst)
        k3 = field(t + dt / 2, X + dt / 2 * k2, hyst)
        k4 = field(t + dt, X + dt * k3, hyst)
        X = X + dt / 6 * (k1 + 2 * (k2 + k3) + k4)
        t1 = t + dt
        err = jnp.abs(X[0] - jnp.sin(t1))
        worst = jnp.where(t1 >= window_start, jnp.maximum(worst, err), worst)
        return (X, worst), None

    X = x0(dtype)
    start = jnp.where(window_start <= 0, jnp.abs(X[0]), jnp.zeros((), dtype))
    (_, worst), _ = jax.lax.scan(step, (X, start), jnp.arange(n_steps))
    return worst


def diffrax_solver(n_steps: int, dtype):
    """A vmapped diffrax solve of the same loop (RK4 tableau, final state), or None."""
    peer = diffrax_rk4()
    if peer is None:
        return None
    diffrax, rk4 = peer

    def one(hyst):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: field(t, y, args)), rk4, t0=0.0,
            t1=n_steps * DT, dt0=DT, y0=x0(dtype), args=hyst, saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=diffrax.ConstantStepSize(), max_steps=n_steps + 10)
        return sol.ys[-1]

    return jax.jit(jax.vmap(one))


# -- the three comparisons ----------------------------------------------------------------------


def plants(setup, b: int):
    ranges = [r.resolve(setup) for r in params.default_ranges(setup)]
    table = params.Uniform().draw(ranges, b, 0).astype(np.float32).astype(np.float64)
    return ranges, table


def throughput(bench: Bench, device, sizes, t_final: float, dtype, repeats: int) -> None:
    setup = dscjax.paper_example(dtype=dtype)
    spec = RunSpec.make(t_final, DT, window_start=min(1.0, t_final / 2))
    n = spec.n_steps
    window = float(spec.window_start)
    for b in sizes:
        ranges, table = plants(setup, b)
        runner = Runner(setup, [r.param for r in ranges], spec, devices=[device],
                        tile=b)  # one program of b rows: the batch-size curve
        hyst = tuple(jax.device_put(jnp.asarray(table[:, j], dtype), device) for j in range(3))
        plain = jax.jit(jax.vmap(lambda a, lam, psi: plain_linf((a, lam, psi), n, window,
                                                                dtype)))
        cases = {"dscjax": lambda runner=runner, table=table: runner([table], len(table)),
                 "vmap+scan": lambda plain=plain, hyst=hyst: plain(*hyst)}
        solve = diffrax_solver(n, dtype)
        if solve is not None:
            cases["diffrax"] = lambda solve=solve, hyst=hyst: solve(hyst)
        times = bench.interleaved(cases, repeats=repeats)
        ours = runner([table], len(table))["linf_error_window"]
        theirs = np.asarray(plain(*hyst))
        rel = np.abs(ours - theirs) / np.maximum(np.abs(ours), 1e-30)
        row = {"case": "batch throughput", "device": device.platform, "rows": b}
        row |= {k: b * n / median(v) for k, v in times.items()}
        if solve is None:
            row["diffrax"] = "not installed"
        bench.add(**row, unit=f"steps/s (dscjax vs vmap+scan, windowed L-inf: relative "
                  f"difference median {np.median(rel):.1e}, max {np.max(rel):.1e})")


def single(bench: Bench, devices, t_final: float, repeats: int) -> None:
    setup = dscjax.paper_example()
    spec = RunSpec.make(t_final, DT, save_every=int(round(t_final / DT)))
    cases = {d.platform: (lambda d=d: dscjax.simulate(setup, spec=spec, device=d, throw=False))
             for d in devices}
    times = bench.interleaved(cases, repeats=repeats)
    for d in devices:
        bench.add(case="one trajectory (float64)", device=d.platform, rows=1,
                  dscjax=1e3 * median(times[d.platform]), unit="ms")


def gradient(bench: Bench, devices, b: int, t_final: float, repeats: int) -> None:
    setup = dscjax.paper_example()
    ranges, table = plants(setup, b)
    ov = params.overrides(setup, [r.param for r in ranges], table)
    gains = {p: params.get(setup, p) for p in GAINS}
    spec = RunSpec.make(t_final, DT, refine=0, save_every=int(round(t_final / DT)))

    def loss(g):
        traj = run(params.set_many(setup, g), spec, overrides=ov)
        return jnp.mean(traj.metrics["linf_error_window"])

    for d in devices:
        with jax.default_device(d):
            g = jax.device_put(gains, d)
            forward, both = jax.jit(loss), jax.jit(jax.value_and_grad(loss))
            times = bench.interleaved({"forward": lambda f=forward, g=g: f(g),
                                       "value_and_grad": lambda f=both, g=g: f(g)},
                                      repeats=repeats)
        fw, vg = median(times["forward"]), median(times["value_and_grad"])
        bench.add(case="batch gradient / forward (float64)", device=d.platform, rows=b,
                  dscjax=vg / fw, unit=f"x (forward {fw:.3g} s, value and gradient {vg:.3g} s)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes at a 0.1 s horizon")
    ap.add_argument("--sizes", help="batch sizes, comma-separated (default: "
                    f"{','.join(map(str, SIZES_FULL))}; --quick {SIZES_QUICK[0]})")
    ap.add_argument("--t-final", type=float, help="horizon [s] (default 20; --quick 0.1)")
    ap.add_argument("--repeats", type=int, help="timed runs per case (default 5; --quick 2)")
    ap.add_argument("--gradient-batch", type=int, help="plants of the batch gradient "
                    "(default 1024; --quick 8)")
    ap.add_argument("--only", action="append", choices=SECTIONS, help="run only this "
                    f"comparison (repeat; default all: {', '.join(SECTIONS)}; --quick all but "
                    "gradient)")
    a = ap.parse_args(argv)
    quick = a.quick
    only = a.only or [s for s in SECTIONS if not (quick and s == "gradient")]
    sizes = (tuple(int(s) for s in a.sizes.split(",")) if a.sizes else
             SIZES_QUICK if quick else SIZES_FULL)
    t_final = a.t_final or (0.1 if quick else 20.0)
    repeats = a.repeats or (2 if quick else 5)
    grad_b = a.gradient_batch or (8 if quick else 1024)
    cpu = jax.devices("cpu")[0]
    accel = [d for d in dscjax.device.visible() if d.platform != "cpu"][:1]
    target = (accel or [cpu])[0]
    bench = Bench("device", "Devices: the CPU against an accelerator", quick=quick)
    print(f"bench_device: batches {sizes} on {target.platform} "
          f"({getattr(target, 'device_kind', '')}), T = {t_final:g} s", file=sys.stderr)
    if "throughput" in only:
        throughput(bench, target, sizes, t_final, np.float32, repeats)
    if "single" in only:
        single(bench, [cpu, *accel], t_final, repeats)
    if "gradient" in only:
        gradient(bench, [cpu, *accel], grad_b, t_final, max(repeats // 2, 2))
    else:
        bench.note("the batch gradient was not measured (not asked for; --quick leaves it "
                   "out)")
    if not accel:
        bench.note("no accelerator seen: the GPU rows are missing (run this on a GPU machine "
                   "with `pip install -e \".[cuda,bench]\"`)")
    if "throughput" in only and diffrax_solver(1, np.float32) is None:
        bench.note("diffrax is not installed (`pip install -e \".[bench]\"`): its column is "
                   "empty")
    bench.note(f"{t_final:g} s at dt = {DT:g} ({int(round(t_final / DT)):,} steps per "
               "plant). Batch throughput in float32: vmap+scan is a hand-written RK4 of the "
               "same loop with its windowed L-inf error (float32 round-off differs between "
               "the two programs, and a few sensitive plants amplify it: docs/sweeps.md); "
               "diffrax keeps the final state only. "
               "The gradient is that of the mean windowed L-inf error over the plants with "
               f"respect to {len(GAINS)} gain vectors ({', '.join(GAINS)}).")
    bench.finish()


if __name__ == "__main__":
    main()
