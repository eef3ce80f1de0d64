"""Theorem 1's L-inf bound (72) against the measured ||S_1||_inf, for alpha_0 over a range.

    python experiments/alpha0_study.py [--orders 2,3,4] [--alpha0 0.1,1,10] [--mu 0.1]
                                       [--t-final 20] [--out results/alpha0]

A thin script over `dscjax.alpha0_study` (the code `dscjax reproduce --theory` runs): for each
order n and alpha_0, the gains of (55), tau of (60) with M_(i+1) estimated along the run (a
fixed point, so the bound is a data-driven estimate), the L-inf initialisation (67)-(68), and
every statement of the theorem checked. Prints one markdown table per order and writes
alpha0_n{n}.json and fig_alpha0.png. Deterministic (no randomness); the wall times depend on
the machine's load.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--orders", default="2", help="orders n, e.g. 2,3,4 (default 2)")
    p.add_argument("--alpha0", help="alpha_0 values, e.g. 0.1,1,10 (default per order)")
    p.add_argument("--mu", type=float, help="mu of (59)-(60) (default 0.1 for n = 2, 10 above)")
    p.add_argument("--t-final", type=float, help="horizon [s] (default 20 for n = 2, 10 above)")
    p.add_argument("--out", default="results/alpha0", help="output directory")
    p.add_argument("--dpi", type=int, default=150)
    args = p.parse_args(argv)

    jax.config.update("jax_enable_x64", True)
    from dscjax import files
    from dscjax.cli.reproduce import parse_alpha0, parse_orders
    from dscjax.reproduce import alpha0 as alpha0_study

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    results = []
    for n in parse_orders(args.orders):
        opts = alpha0_study.default_options(n, alpha0=parse_alpha0(args.alpha0), mu=args.mu,
                                            t_final=args.t_final)
        res = alpha0_study.study(alpha0_study.base_setup(n), opts, log=log)
        files.write_json(out / f"alpha0_n{n}.json", res)
        print(f"\n## n = {n}, mu = {opts.mu:g}, T = {opts.t_final:g} s "
              f"({res['wall_s']:.1f} s)\n\n{alpha0_study.table_markdown(res)}")
        results.append(res)
    alpha0_study.plot(results, out / "fig_alpha0.png", dpi=args.dpi)
    print(f"\nwrote {out}/ ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
