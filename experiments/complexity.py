"""The explosion of complexity, measured: DSC against autodiff backstepping for n = 2..8.

    python experiments/complexity.py [--orders 2-8] [--repeats 3] [--out results/complexity]

A thin script over `dscjax.complexity` (the same code `dscjax reproduce --complexity` runs):
it measures each control law (jaxpr equations, XLA FLOPs, trace and compile time, time per
evaluation; medians of --repeats fresh builds), fits the growth per order and writes
complexity.json and complexity.png. Deterministic apart from the timings; the machine's load
shows in those, so run it on a quiet machine and report medians.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--orders", default="2-8", help="e.g. 2-8 or 2,4,6 (default 2-8)")
    p.add_argument("--repeats", type=int, default=3, help="fresh builds per law (default 3)")
    p.add_argument("--evals", type=int, default=2000, help="evaluations per timing loop")
    p.add_argument("--out", default="results/complexity", help="output directory")
    p.add_argument("--dpi", type=int, default=150)
    args = p.parse_args(argv)

    jax.config.update("jax_enable_x64", True)
    from dscjax import files
    from dscjax.cli.reproduce import parse_orders
    from dscjax.reproduce import STYLE, complexity

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = complexity.study(parse_orders(args.orders), repeats=args.repeats, evals=args.evals,
                              log=lambda msg: print(msg, file=sys.stderr, flush=True))
    files.write_json(out / "complexity.json", result)
    complexity.plot(result, out / "complexity.png", dpi=args.dpi,
                    colors={c: STYLE[c]["color"] for c in ("dsc", "backstepping")})
    for c, fits in result["fits"].items():
        for metric, fit in fits.items():
            print(f"{c:>12} {metric:>9}: x{fit['ratio_per_order']:.3f} per order "
                  f"(r2 {fit['r2_geometric']:.3f}), ~n^{fit['exponent']:.2f} "
                  f"(r2 {fit['r2_power']:.3f})")
    print(f"wrote {out}/complexity.json and complexity.png ({result['wall_time_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
