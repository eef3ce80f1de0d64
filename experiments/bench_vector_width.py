"""Batched throughput with and without XLA:CPU's 512-bit vectors (`dscjax/xla.py`).

    python experiments/bench_vector_width.py [--horizon 3] [--repeats 5] [--rounds 2]

Each configuration runs in a fresh process: the batched simulation compiled with
`compiler_options=dscjax.xla.WIDE` (what `simulate_batch` and sweeps use on AVX-512 CPUs)
against the same program compiled without it, interleaved for --rounds rounds. Paper's
example, batch-last `simulate_batch` over alpha, lam, psi (+-30 %), metrics only; float32
and float64. Prints a table of steps/s and the ratio, checks that both modes give bitwise
equal metrics, and writes results/bench_vector_width.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SIZES = (512, 4096, 16384)


def child(mode: str, horizon: float, repeats: int) -> dict:
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import dscjax
    from dscjax import xla
    from dscjax.simulate import _run_reported

    batch = jax.jit(_run_reported, static_argnames=("n_steps", "save_every", "checkpoint_every"),
                    compiler_options=xla.WIDE if mode == "wide" else None)
    dt = 1e-3
    n = int(round(horizon / dt))
    res = {}
    for dtype in (np.float32, np.float64):
        setup = dscjax.canonical(dscjax.paper_example(dtype=dtype))
        for b in SIZES:
            rng = np.random.default_rng(0)
            over = {"hysteresis.alpha": jnp.asarray(rng.uniform(0.7, 1.3, b), dtype),
                    "hysteresis.lam": jnp.asarray(rng.uniform(1.0, 1.86, b), dtype),
                    "hysteresis.psi": jnp.asarray(rng.uniform(0.0735, 0.1365, b), dtype)}

            def run(over=over, setup=setup, dtype=dtype):
                return batch(setup, jnp.asarray(dt, dtype), jnp.asarray(1.0, dtype),
                             jnp.asarray(1e6, dtype), n_steps=n, save_every=n,
                             overrides=over).metrics

            m = jax.block_until_ready(run())
            ts = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(run())
                ts.append(time.perf_counter() - t0)
            key = f"{np.dtype(dtype).name}/{b}"
            res[key] = {"steps_per_s": b * n / float(np.median(ts)),
                        "metrics": {k: np.asarray(v, np.float64).tolist() for k, v in m.items()}}
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--horizon", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--out", default=str(ROOT / "results" / "bench_vector_width.json"))
    p.add_argument("--child", choices=("wide", "narrow"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child, a.horizon, a.repeats)))
        return 0
    runs = {"wide": [], "narrow": []}
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    for r in range(a.rounds):
        for mode in ("narrow", "wide"):
            print(f"  round {r + 1}/{a.rounds}: {mode} ...", file=sys.stderr, flush=True)
            out = subprocess.run([sys.executable, __file__, "--child", mode, "--horizon",
                                  str(a.horizon), "--repeats", str(a.repeats)], env=env,
                                 capture_output=True, text=True, check=True)
            runs[mode].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"paper's example, {a.horizon:g} s at dt = 1e-3, median of {a.repeats} per process, "
          f"median over {a.rounds} process(es) per mode; load average {os.getloadavg()[0]:.2f}")
    print(f"{'dtype':8} {'batch':>6} {'256-bit [steps/s]':>18} {'512-bit [steps/s]':>18} "
          f"{'ratio':>6} {'same results':>13}")
    table = []
    for key in [k for k in runs["wide"][0] if "/" in k]:
        narrow = float(np.median([r[key]["steps_per_s"] for r in runs["narrow"]]))
        wide = float(np.median([r[key]["steps_per_s"] for r in runs["wide"]]))
        same = all(r[key]["metrics"] == runs["narrow"][0][key]["metrics"]
                   for r in runs["wide"] + runs["narrow"])
        dtype, b = key.split("/")
        print(f"{dtype:8} {int(b):>6} {narrow:>18.3g} {wide:>18.3g} {wide / narrow:>6.2f} "
              f"{'bitwise' if same else 'NO':>13}")
        table.append(dict(dtype=dtype, batch=int(b), narrow_steps_per_s=narrow,
                          wide_steps_per_s=wide, ratio=wide / narrow, bitwise_equal=same))
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(horizon=a.horizon, repeats=a.repeats, rounds=a.rounds,
                                   table=table),
                              indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
