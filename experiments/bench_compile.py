"""Compilation: dscjax's lean programs (XLA:CPU's loop fusion emitters) against XLA's default
(its MLIR fusion emitters), compile time and run time, against the batch size.

    python experiments/bench_compile.py            # full sizes (docs/benchmarks.md)
    python experiments/bench_compile.py --quick    # 2 s, fewer sizes: JSON only

The paper's example, float64, dt = 1e-3: one trajectory (20 s) continuous and sampled at 1 ms,
batches of B plants (hysteresis alpha, lam, psi +-30 %; 5 s), and `jax.value_and_grad` of the
windowed L2 error in the 13 DSC design numbers through one trajectory (20 s): time-parallel
(the default) of the continuous loop and of the loop sampled at 1 ms, and JAX's own reverse
mode of the scan. Each case runs in a fresh process without a persistent cache: both programs
compiled in turn, `repeats` times each (caches cleared between; the median), then run
interleaved (the median). dscjax compiles lean one trajectory, a batch of at most
`xla.LEAN_ROWS` rows and gradients (`dscjax.xla`).
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
from harness import Bench, child_call, cold_env, median, parser, run_child  # noqa: E402

import dscjax  # noqa: E402
import tuning  # noqa: E402
from dscjax import xla  # noqa: E402
from dscjax.integrate import Checkpointed, TimeParallel  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from dscjax.simulate import canonical, run_reported  # noqa: E402
from tuning.runner import PAPER_PLANT_FREEZE  # noqa: E402

DT = 1e-3
OPTIONS = {"lean": xla.LEAN, "default": {xla.EMITTERS: True}}


def program(case: str, t_final: float):
    """(function, arguments) of one case: 'one:continuous', 'one:sampled', 'batch:B',
    'grad:time-parallel', 'grad:sampled' (time-parallel, sampled at 1 ms), 'grad:scan'."""
    setup = canonical(dscjax.paper_example())
    kind, _, what = case.partition(":")
    n = int(round(t_final / DT))
    if kind == "one":
        spec = RunSpec.make(t_final, DT, save_every=n, sample_time=None if what == "continuous"
                            else DT).program()
        return run_reported, (setup, spec, None, None)
    if kind == "batch":
        b = int(what)
        rng = np.random.default_rng(0)
        h = setup.hysteresis
        over = {f"hysteresis.{k}": jnp.asarray(float(getattr(h, k)) * rng.uniform(0.7, 1.3, b))
                for k in ("alpha", "lam", "psi")}
        return run_reported, (setup, RunSpec.make(t_final, DT, save_every=n).program(), over)
    sel = tuning.Selection.build(setup, tuning.config.DSC_GAINS, freeze=PAPER_PLANT_FREEZE)
    gradient = Checkpointed(None) if what == "scan" else TimeParallel()
    spec = RunSpec.make(t_final, DT, save_every=n, refine=0, gradient=gradient,
                        sample_time=DT if what == "sampled" else None).program()

    def loss(z):
        return dscjax.run(sel.apply(setup, z), spec).metrics["l2_error_window"]

    return jax.value_and_grad(loss), (sel.init(setup),)


def measure(argv) -> int:
    """--child CASE T REPEATS: compile and run the case both ways; print JSON."""
    case, t_final, repeats = argv[0], float(argv[1]), int(argv[2])
    fn, args = program(case, t_final)
    jax.jit(lambda x: x + 1.0)(1.0)  # the backend's start-up, outside the timings
    compile_s = {k: [] for k in OPTIONS}
    compiled = {}
    for _ in range(repeats):
        for name, options in OPTIONS.items():
            jax.clear_caches()
            t0 = time.perf_counter()
            compiled[name] = jax.jit(fn, compiler_options=options).lower(*args).compile()
            compile_s[name].append(time.perf_counter() - t0)
    bench = Bench("compile-child", "")
    runs = bench.interleaved({k: (lambda c=c: c(*args)) for k, c in compiled.items()},
                             repeats + 2)
    print(json.dumps({"compile": {k: median(v) for k, v in compile_s.items()},
                      "run": {k: median(v) for k, v in runs.items()}}))
    return 0


def _options(argv):
    p = parser(__doc__, "compiles per program")
    return p.parse_args(argv)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if (code := child_call(argv, measure)) is not None:
        return code
    a = _options(argv)
    one_t, batch_t = (2.0, 1.0) if a.quick else (20.0, 5.0)
    sizes = (4, 16) if a.quick else (4, 8, 16, 64, 256)
    repeats = a.repeats or (2 if a.quick else 3)
    bench = Bench("compile", "Compilation: lean against XLA's default emitters", quick=a.quick)
    cases = [("one:continuous", one_t), ("one:sampled", one_t),
             *((f"batch:{b}", batch_t) for b in sizes),
             ("grad:time-parallel", one_t), ("grad:sampled", one_t), ("grad:scan", one_t)]
    script = Path(__file__).resolve()
    for case, t_final in cases:
        run, out = run_child(script, case, t_final, repeats, env=cold_env("XLA_FLAGS"))
        if out is None:
            bench.add(case=case, error=run.stderr.strip().splitlines()[-1][:200])
            continue
        kind, _, what = case.partition(":")
        label = {"one": f"one trajectory, {what}", "batch": f"batch of {what}",
                 "grad": f"value_and_grad, {what}"}[kind] + f", {t_final:g} s"
        lean_here = kind != "batch" or int(what) <= xla.LEAN_ROWS
        c, r = out["compile"], out["run"]
        bench.add(case=label, dscjax_compiles="lean" if lean_here else "default",
                  compile_lean_s=c["lean"], compile_default_s=c["default"],
                  run_lean_ms=1e3 * r["lean"], run_default_ms=1e3 * r["default"],
                  run_lean_over_default=r["lean"] / r["default"])
        print(f"  {label}: compile {c['lean']:.2f} / {c['default']:.2f} s, run "
              f"{1e3 * r['lean']:.1f} / {1e3 * r['default']:.1f} ms", flush=True)
    bench.note("Compile times include lowering; each is the median of the cold compiles in its "
               "process, without a persistent cache.")
    bench.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
