"""Exact gradients: their cost against a forward run of the same objective, and their memory.

    python experiments/bench_gradient.py            # 20 s, a batch of 256 plants (docs)
    python experiments/bench_gradient.py --quick    # 2 s, a batch of 16: JSON only

J = L-inf + L2 of the tracking error on [1 s, T] (the paper's example, dt = 1e-3),
differentiated with respect to the 13 DSC design numbers the tuner tunes (log-space):

- one trajectory: value_and_grad by the time-parallel linearisation (the default), forward
  mode (jacfwd) and JAX's own reverse mode of the scan (`Checkpointed(None)`), each against
  the jitted forward run, timed in turn (compilation timed apart);
- the mean of J over a batch of plants (alpha, lam, psi +-30 %): reverse mode through the scan
  checkpointed every 100 steps (the default) and without checkpoints, and forward mode, against
  its forward run, each compiled and timed in a fresh process that also gives its peak RSS
  (stopped past --memory-limit-gib).

--quick leaves out the slowest programs to compile: JAX's reverse mode of one trajectory's scan
and the batch's gradient without checkpoints.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from harness import Bench, child, median, parser, positive  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import dscjax  # noqa: E402
import tuning  # noqa: E402
from dscjax.integrate import Checkpointed  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from tuning.runner import PAPER_PLANT_FREEZE  # noqa: E402

DT = 1e-3


def objectives(t_final: float, batch: int):
    """(J(z, gradient) of the nominal plant, mean J over `batch` plants with a checkpoint
    segment of `every` steps, z0)."""
    setup = dscjax.paper_example()
    sel = tuning.Selection.build(setup, tuning.DSC_GAINS, freeze=PAPER_PLANT_FREEZE)
    n = int(round(t_final / DT))
    save = 1000 if n % 1000 == 0 else n

    def cost(m):
        return m["linf_error_window"] + m["l2_error_window"]

    def J(z, gradient=None):  # None: the default, TimeParallel()
        spec = RunSpec.make(t_final, DT, save_every=save, refine=0, gradient=gradient)
        return cost(dscjax.simulate(sel.apply(setup, z), spec=spec, throw=False).metrics)

    rng = np.random.default_rng(0)
    h = setup.hysteresis
    over = {f"hysteresis.{k}": jnp.asarray(float(getattr(h, k)) * rng.uniform(0.7, 1.3, batch))
            for k in ("alpha", "lam", "psi")}

    def Jb(z, every=100):
        traj = dscjax.simulate_batch(sel.apply(setup, z), over, t_final, DT, refine=0,
                                     checkpoint_every=every)
        return jnp.mean(cost(traj.metrics))

    return J, Jb, sel.init(setup)


def compiled_and_timed(bench: Bench, fns: dict, arg, repeats: int):
    """{name: (median seconds, compile seconds)}: each compiled apart, then timed in turn."""
    jitted, compile_s = {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        jitted[name] = jax.jit(fn).lower(arg).compile()
        compile_s[name] = time.perf_counter() - t0
        print(f"  compiled {name} in {compile_s[name]:.1f} s", file=sys.stderr, flush=True)
    times = bench.interleaved({k: (lambda f=f: f(arg)) for k, f in jitted.items()}, repeats)
    return {k: (median(v), compile_s[k]) for k, v in times.items()}, jitted


def add_costs(bench: Bench, what: str, res: dict, labels: dict, base: str = "forward run"):
    t0 = res[base][0]
    for key, label in labels.items():
        if key not in res:
            continue
        bench.add(case=f"{what}: {label} [s]", dscjax=res[key][0], baseline=base,
                  baseline_value=t0, x_baseline=res[key][0] / t0, compile_s=res[key][1])


def batch_child(argv) -> int:
    """--child MODE T B REPEATS: compile and time one batch program; print seconds as JSON."""
    mode, t_final, batch, repeats = argv[0], float(argv[1]), int(argv[2]), int(argv[3])
    _, Jb, z0 = objectives(t_final, batch)
    fn = {"forward run": Jb, "checkpointed": jax.value_and_grad(Jb),
          "not checkpointed": jax.value_and_grad(lambda z: Jb(z, None)),
          "forward mode": jax.jacfwd(Jb)}[mode]
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(z0).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(z0))
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(z0))
        runs.append(time.perf_counter() - t0)
    print(json.dumps({"compile_s": compile_s, "median_s": median(runs)}))
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        return batch_child(argv[1:])
    p = parser(__doc__)
    p.add_argument("--repeats", type=positive(), default=None, help="timed calls per case")
    p.add_argument("--memory-limit-gib", type=positive(float), default=8.0)
    a = p.parse_args(argv)
    quick = a.quick
    t_final, batch = (2.0, 16) if quick else (20.0, 256)
    repeats = a.repeats or (3 if quick else 7)
    bench = Bench("gradient", "Exact gradients", quick=quick)
    J, _, z0 = objectives(t_final, batch)

    single = {"forward run": J, "time-parallel": jax.value_and_grad(J),
              "forward mode": jax.jacfwd(J)}
    if not quick:
        single["scan"] = jax.value_and_grad(lambda z: J(z, Checkpointed(None)))
    one, jitted = compiled_and_timed(bench, single, z0, repeats)
    add_costs(bench, f"one trajectory, {t_final:g} s", one, {
        "time-parallel": "value_and_grad, time-parallel (the default)",
        "forward mode": "jacfwd (forward mode)",
        "scan": "value_and_grad, JAX's reverse mode of the scan"})
    ref = np.asarray(ravel_pytree(jitted["time-parallel"](z0)[1])[0])
    others = {"forward mode": jitted["forward mode"](z0)}
    if "scan" in jitted:
        others["JAX's reverse mode of the scan"] = jitted["scan"](z0)[1]
    err = {k: float(np.max(np.abs(np.asarray(ravel_pytree(g)[0]) - ref)) / np.max(np.abs(ref)))
           for k, g in others.items()}
    bench.note(f"{len(ref)} numbers; largest difference from the time-parallel gradient, "
               "relative to its largest component: "
               + ", ".join(f"{k} {v:.1e}" for k, v in err.items()) + ".")

    modes = ["forward run", "checkpointed", "forward mode"] + ([] if quick else
                                                              ["not checkpointed"])
    limit = a.memory_limit_gib * 1024
    res, rss, script = {}, {}, Path(__file__).resolve()
    for mode in modes:
        run = child([sys.executable, script, "--child", mode, t_final, batch,
                     max(2, repeats // 2)], limit_mib=limit)
        if run.killed:
            rss[mode] = f"> {a.memory_limit_gib:g} GiB (stopped)"
            continue
        if run.returncode != 0:
            raise SystemExit(f"bench_gradient: {mode} failed:\n{run.stderr[-3000:]}")
        out = json.loads(run.stdout.strip().splitlines()[-1])
        res[mode], rss[mode] = (out["median_s"], out["compile_s"]), run.peak_rss_mib
    what = f"mean over {batch} plants, {t_final:g} s"
    add_costs(bench, what, res, {k: v for k, v in (
        ("checkpointed", "value_and_grad, checkpointed every 100 steps"),
        ("not checkpointed", "value_and_grad, not checkpointed"),
        ("forward mode", "jacfwd (forward mode)")) if k in res})
    for mode in modes[1:]:
        ratio = rss[mode] / rss["forward run"] if isinstance(rss[mode], float) else ""
        bench.add(case=f"{what}: peak RSS, {mode} [MiB]", dscjax=rss[mode],
                  baseline="forward run", baseline_value=rss["forward run"], x_baseline=ratio)
    bench.note("The batch: each program compiled, run and measured in a fresh process (peak RSS "
               "compilation included; medians of its own runs).")
    bench.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
