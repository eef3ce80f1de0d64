"""Sweep cost per plant of each hysteresis model against the backlash-like model (issue 15's
target: P-I plants within 2x the backlash sweep's time per plant).

The sweep's own block program (`dscjax.sweep.device.Runner`, metrics only, float32 as
`dscjax sweep` runs by default) on B plants of each built-in example (`--example paper | pi |
gpi | bouc_wen`), each model's default sweep ranges (+-30 %). Compilation is excluded: every
runner is called once, then the models are timed in turn, `--repeats` rounds, so that load
from other processes on the machine hits them alike; medians are reported.

    python experiments/bench_hysteresis_sweep.py [--plants 4096] [--t-final 2] [--repeats 3]
        [--examples paper,pi]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from dscjax import params
from dscjax.config import example
from dscjax.metrics import default_window
from dscjax.sweep.device import Runner

DT = 1e-3


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", type=int, default=4096)
    ap.add_argument("--t-final", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None, help="write the figures here")
    ap.add_argument("--examples", default="paper,pi,gpi,bouc_wen",
                    help="comma-separated examples to time (the first one is the baseline)")
    args = ap.parse_args()
    n = int(round(args.t_final / DT))
    runners = {}
    names = args.examples.split(",")
    for name in names:
        setup = example(name, dtype=np.float32)
        ranges = [r.resolve(setup) for r in params.default_ranges(setup)]
        table = params.sample_table(ranges, "uniform", args.plants, 0)
        runner = Runner(setup, [r.param for r in ranges], n, DT,
                        default_window(args.t_final, None), 1e6, args.plants,
                        devices=jax.devices()[:1])
        t0 = time.perf_counter()
        runner(table, 1)
        print(f"{name:9s} compiled and ran once in {time.perf_counter() - t0:.1f} s", flush=True)
        runners[name] = (runner, table)
    times = {name: [] for name in runners}
    for _ in range(args.repeats):
        for name, (runner, table) in runners.items():
            t0 = time.perf_counter()
            runner(table, 1)
            times[name].append(time.perf_counter() - t0)
    base = min(times[names[0]]) / args.plants
    base_med = float(np.median(times[names[0]])) / args.plants
    rows = {}
    for name, ts in times.items():
        per_plant, med = min(ts) / args.plants, float(np.median(ts)) / args.plants
        rows[name] = {"seconds_per_plant": per_plant, "ratio_to_backlash": per_plant / base,
                      "median_ratio": med / base_med, "plant_steps_per_s": n / per_plant,
                      "times": ts}
        print(f"{name:9s} {per_plant * 1e3:8.3f} ms per plant ({args.t_final:g} s, "
              f"{n:,} steps)  {per_plant / base:5.2f} x backlash (medians: "
              f"{med / base_med:5.2f} x)  {n / per_plant:9.3g} plant-steps/s", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"plants": args.plants, "t_final": args.t_final, "rows": rows,
                       "loadavg": os.getloadavg()}, f, indent=1)


if __name__ == "__main__":
    main()
