"""The DSC at the paper's gains on each built-in hysteresis example (`--example paper | pi |
gpi | bouc_wen`): 20 s at dt = 1e-3 (classical RK4, and ETDRK4), tracking errors and max |u|,
with each model's large-amplitude slope and d_1 limits. The table of docs/hysteresis.md.

Usage: python experiments/hysteresis_examples.py   (about a minute)
"""

from __future__ import annotations

import jax
import numpy as np

from dscjax.config import example
from dscjax.simulate import simulate


def main():
    jax.config.update("jax_enable_x64", True)
    print("| example | slope | d_1 limits | solver | L-inf e | L-inf e, t >= 1 s | RMS e | "
          "max abs u | diverged |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in ("paper", "pi", "gpi", "bouc_wen"):
        setup = example(name, dtype=np.float64)
        h = setup.hysteresis
        lo, hi = (float(x) for x in h.d1_limits())
        for solver in ("rk4", "etdrk4"):
            tr = simulate(setup, t_final=20.0, dt=1e-3, solver=solver, refine=0)
            m = {k: float(v) for k, v in tr.metrics.items()}
            print(f"| {name} ({h.kind}) | {float(h.effective_slope()):.3f} | {lo:+.3f}, "
                  f"{hi:+.3f} | {solver} | {m['linf_error']:.4f} | "
                  f"{m['linf_error_window']:.4f} | {m['rms_error']:.4f} | "
                  f"{m['max_abs_u']:.3f} | {bool(tr.diverged)} |")


if __name__ == "__main__":
    main()
