"""Issue 33's targets for the gains.json of `dscjax tune` runs, in the sampled loop at 1 ms:

    python experiments/check_tuned_gains.py results/tune-seed0 results/tune-seed1 ...

For each run directory, with the controller's states by exponential Euler and by forward Euler:
the windowed L-inf on [1, 20] s of the paper's and the tuned gains on the nominal plant and
their ratio, max|u| and TV(u) against the tuner's default bounds (the paper's gains' max|u|
and 1.5 x their TV(u) with exponential Euler, the loop tuned), and the held-out plants (32,
the default held-out box, seed 777) that diverge at Ts = 1 ms and 0.5 ms (one refinement).
One JSON line per run on stdout.
"""

from __future__ import annotations

import json
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import dscjax  # noqa: E402
from dscjax import config, params  # noqa: E402
from dscjax.runspec import RunSpec  # noqa: E402
from tuning.config import DSC_GAINS  # noqa: E402
from tuning.runner import heldout_ranges  # noqa: E402

PLANTS, SEED = 32, 777


def check(run_dir: str, paper) -> dict:
    tuned = params.cast(config.from_dict(config.read(f"{run_dir}/gains.json"), base=paper)[0],
                        np.float64)
    rep = json.load(open(f"{run_dir}/report.json"))
    row = {"generations": rep["run"]["iterations"]}
    ov = {p: np.stack([np.asarray(params.get(s, p)) for s in (paper, tuned)])
          for p in DSC_GAINS}
    ranges = params.check(heldout_ranges(paper), paper, "heldout")
    held = params.sample_overrides(tuned, ranges, PLANTS, SEED)
    bounds = None
    for disc in ("exponential-euler", "euler"):
        spec = RunSpec.make(20.0, 1e-3, sample_time=1e-3, discretisation=disc, refine=0)
        m = {k: np.asarray(v) for k, v in dscjax.simulate_batch(paper, ov, spec=spec)
             .metrics.items()}
        (lp, lt), (up, ut), (tp, tt) = m["linf_error_window"], m["max_abs_u"], m["tv_u"]
        bounds = bounds or (float(up), 1.5 * float(tp))
        out = {"paper": float(lp), "tuned": float(lt), "ratio": float(lp / lt),
               "max_abs_u": [float(up), float(ut)], "tv_u": [float(tp), float(tt)],
               "bounds": list(bounds), "u_bound_met": bool(ut <= bounds[0] * (1 + 1e-9)),
               "tv_bound_met": bool(tt <= bounds[1] * (1 + 1e-9))}
        for ts in (1e-3, 5e-4):
            sp = RunSpec.make(20.0, ts, sample_time=ts, discretisation=disc, refine=1)
            div = np.asarray(dscjax.simulate_batch(tuned, held, spec=sp).diverged)
            out[f"heldout_diverged_{1e3 * ts:g}ms"] = int(div.sum())
        row[disc] = out
    return row


if __name__ == "__main__":
    paper = params.cast(dscjax.paper_example(), np.float64)
    for d in sys.argv[1:]:
        print(json.dumps({"run": d} | check(d, paper)), flush=True)
