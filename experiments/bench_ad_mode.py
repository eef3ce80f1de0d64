"""The tuner's exact gradient of one plant: forward mode against the time-parallel reverse mode,
by the number of tuned numbers (what `--gradient auto` chooses between).

    python experiments/bench_ad_mode.py            # 20 s, 2 / 6 / 8 / 13 tuned numbers (docs)
    python experiments/bench_ad_mode.py --quick    # 2 s: JSON only

The default tuning problem (`dscjax tune`'s: the paper's example sampled at 1 ms, its check
loops, one plant), the gradient program adam runs (`tuning.search.grad_fn`, compiled as
dscjax compiles it) with `gradient = "forward"` and `"reverse"`, tuning the first p of the
13 DSC design numbers. Each (p, mode) runs in a fresh process without a persistent
compilation cache: its compile time is the first call's, cold; then the median of the timed
calls. Both modes form the Jacobians of every step; they differ in what follows (p tangents
carried forward, or the transposed recurrence).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from harness import Bench, child_call, cold_env, median, parser, run_child  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

import dscjax  # noqa: E402
import tuning  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from tuning import search  # noqa: E402
from tuning.config import DSC_GAINS, GRADIENTS  # noqa: E402

SIZES = (2, 6, 8, 13)  # tuned numbers: the first DSC_GAINS paths that hold this many


def paths(p: int) -> tuple[str, ...]:
    """The shortest prefix of DSC_GAINS that holds p tuned numbers."""
    setup = dscjax.paper_example()
    out, n = [], 0
    for path in DSC_GAINS:
        if n >= p:
            break
        out.append(path)
        n += int(np.size(dscjax.params.get(setup, path)))
    if n != p:
        raise SystemExit(f"no prefix of the DSC gains holds {p} numbers (got {n})")
    return tuple(out)


def measure(argv) -> int:
    """--child MODE P T REPEATS: compile the gradient cold, time it; print JSON."""
    mode, p, t_final, repeats = argv[0], int(argv[1]), float(argv[2]), int(argv[3])
    cfg = tuning.TuningConfig(params=paths(p), heldout=tuning.BatchSpec(batch=0),
                              optimizer=tuning.OptimizerSpec(name=tuning.Adam(),
                                                             gradient=GRADIENTS[mode],
                                                             time_limit=None))
    problem = tuning.build_problem(dscjax.paper_example(),
                                   RunSpec.make(t_final=t_final, sample_time=1e-3), cfg)
    fn, flat = search.grad_fn(problem), ravel_pytree(problem.z0)[0][None]
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(flat))
    compile_s = time.perf_counter() - t0
    times = []
    for i in range(repeats):
        z = flat * (1.0 + 0.01 * (i + 1))
        t0 = time.perf_counter()
        jax.block_until_ready(fn(z))
        times.append(time.perf_counter() - t0)
    print(json.dumps({"mode": type(problem.mode).__name__, "n": int(flat.size),
                      "compile_s": compile_s, "grad_s": median(times),
                      "grad": np.asarray(out["grad"][0]).tolist()}))
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if (code := child_call(argv, measure)) is not None:
        return code
    p = parser(__doc__, "timed calls per case")
    a = p.parse_args(argv)
    t_final, repeats = (2.0, 3) if a.quick else (20.0, a.repeats or 7)
    bench = Bench("ad_mode", "The tuner's AD mode for one plant", quick=a.quick)
    script = Path(__file__).resolve()
    for size in SIZES:
        out = {}
        for mode in ("forward", "reverse"):
            run, out[mode] = run_child(script, mode, size, t_final, repeats, env=cold_env())
            if out[mode] is None:
                raise SystemExit(run.stderr.strip().splitlines()[-1][:300])
        f, r = out["forward"], out["reverse"]
        g, g_ref = np.asarray(f["grad"]), np.asarray(r["grad"])
        bench.add(tuned_numbers=size, forward_grad_s=f["grad_s"], reverse_grad_s=r["grad_s"],
                  forward_over_reverse=f["grad_s"] / r["grad_s"],
                  forward_compile_s=f["compile_s"], reverse_compile_s=r["compile_s"],
                  gradients_differ_by=float(np.max(np.abs(g - g_ref)) / np.max(np.abs(g_ref))))
        print(f"  {size} tuned numbers: done", file=sys.stderr, flush=True)
    bench.note(f"T = {t_final:g} s; each mode's gradient in a fresh process (compile: the "
               "first call, cold, compilation included; grad: the median of "
               f"{repeats} calls); 'differ by': the largest difference of the two gradients "
               "relative to their largest component. `--gradient auto` takes forward mode for "
               "one plant up to tuning.optimize.FORWARD_MAX_PARAMS_ONE_PLANT tuned numbers.")
    bench.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
