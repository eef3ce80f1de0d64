"""Sensitivities by reverse mode against central differences.

    python experiments/bench_sensitivity.py                  # 20 s horizon (docs)
    python experiments/bench_sensitivity.py --t-final 5      # a shorter horizon (docs)
    python experiments/bench_sensitivity.py --quick          # 2 s: JSON only

The paper's example at dt = 1e-3, d ln m / d ln p of the four metrics of `dscjax sensitivity`
to every number of the controller, plant and hysteresis model (d = 43), in the continuous loop
and the loop sampled at 1 ms. Each repeat times, in turn: one forward run, the jitted forward
and pull-backs of `dscjax.sensitivity` (one per metric) and central differences (2 d forward
runs of the same compiled program, each metric from the same runs). Compilation is timed apart.
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from harness import Bench, median, parser, positive  # noqa: E402

import dscjax  # noqa: E402
from dscjax.sensitivity import Problem  # noqa: E402

DT = 1e-3


def main() -> None:
    p = parser(__doc__, "timed calls of each case (default 5; --quick 2)")
    p.add_argument("--t-final", type=positive(float), default=None,
                   help="horizon [s] (default 20; --quick 2)")
    args = p.parse_args()
    t_final = args.t_final or (2.0 if args.quick else 20.0)
    repeats = args.repeats or (2 if args.quick else 5)
    bench = Bench("sensitivity", "Sensitivities: reverse mode against central differences",
                  quick=args.quick)
    for loop, sample_time in (("continuous", None), ("sampled at 1 ms", 1e-3)):
        spec = dscjax.RunSpec.make(t_final, DT, sample_time=sample_time, refine=0)
        problem = Problem.make(dscjax.paper_example(), spec)
        d = len(problem.columns)
        z0 = problem.z0()
        t0 = time.perf_counter()
        jax.block_until_ready(problem.metrics_at(z0))
        t1 = time.perf_counter()
        jax.block_until_ready(problem.jacobian())
        t2 = time.perf_counter()
        steps = np.eye(d) * 1e-7

        def central(problem=problem, steps=steps):
            return [problem.metrics_at(s * e)[0] for e in steps for s in (1.0, -1.0)]

        times = bench.interleaved({"forward": lambda p=problem, z=z0: p.metrics_at(z),
                                   "reverse": problem.jacobian, "central": central},
                                  repeats=repeats)
        fwd, rev, cen = (median(times[k]) for k in ("forward", "reverse", "central"))
        bench.add(loop=loop, T_s=t_final, parameters=d, metrics=len(problem.metrics),
                  forward_ms=1e3 * fwd, reverse_ms=1e3 * rev, central_ms=1e3 * cen,
                  reverse_over_forward=rev / fwd, reverse_over_central=rev / cen,
                  reverse_over_2d_forward=rev / (2 * d * fwd),
                  compile_forward_s=t1 - t0, compile_reverse_s=t2 - t1)
    bench.note("reverse: one forward run and one pull-back per metric (`dscjax.sensitivity`, "
               "the time-parallel gradient of the loop); central: 2 d forward runs of the "
               "same compiled forward program at h = 1e-7 in ln p, timed as such; 2d forward: "
               "the same from the forward run's median (what central differences cost "
               "without the overhead of 2 d calls). The reverse pass's cost does not depend "
               "on d; central differences grow as 2 d. Goal: reverse <= 1/4 of central.")
    bench.finish()


if __name__ == "__main__":
    main()
