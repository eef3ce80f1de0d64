"""The README's grid sweep with and without refinement, against an independent fine-step run.

    .venv/bin/python experiments/stiff_grid.py [--out results/stiff_grid] [--repeats 3]

The grid hysteresis.alpha = 0.1..10 (21) x hysteresis.lam = 0.15..3 (21), 20 s, default
settings (float32, dt = 1e-3). Prints and writes stiff_grid.json:

- the time of the sweep with classical RK4 only (`--refine 0`, what the tool did before
  refinement) and with the default refinement (rows that diverge re-run with ETDRK4 at dt,
  dt/2, ...), each a fresh process (compilation included), medians of `--repeats` runs,
  interleaved; the machine's load beside them;
- the three kinds of rows (tracked, tracked after refinement, diverged);
- at the grid's four corners, the windowed L-inf error of the sweep against the independent
  plain-Python implementation of the paper's loop (tests/reference_paper.py, sharing no code
  with dscjax) by classical RK4 at dt = 1e-4 (which is stable there).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GRID = ["--grid", "hysteresis.alpha=0.1:10:21", "--grid", "hysteresis.lam=0.15:3:21"]
CORNERS = [(0.1, 0.15), (0.1, 3.0), (10.0, 0.15), (10.0, 3.0)]


def sweep_once(refine: int, out: Path) -> float:
    cmd = [sys.executable, "-m", "dscjax.cli.main", "sweep", *GRID, "--refine", str(refine),
           "--out", str(out), "--no-plot", "--quiet", "--overwrite"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - t0


def reference_linf(alpha: float, lam: float, dt: float = 1e-4, t_final: float = 20.0,
                   t0: float = 1.0) -> float:
    sys.path.insert(0, str(ROOT / "tests"))
    import reference_paper as ref

    p = dict(ref.P, alpha=alpha, lam=lam)
    n = int(round(t_final / dt))
    X = ref.rk4(ref.initial_state(p), dt, n, p)
    t = np.arange(n + 1) * dt
    keep = t >= t0 - 1e-12
    return float(np.max(np.abs(X[keep, 0] - np.sin(t[keep]))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/stiff_grid")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times = {0: [], 6: []}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            for refine in times:
                times[refine].append(sweep_once(refine, Path(tmp) / f"r{refine}"))
                load.append(os.getloadavg()[0])
        rows = {r: dict(np.load(Path(tmp) / f"r{r}" / "results.npz")) for r in times}
    d = rows[6]
    kinds = dict(tracked=int(np.sum(~d["diverged"] & (d["refinements"] == 0))),
                 refined=int(np.sum(~d["diverged"] & (d["refinements"] > 0))),
                 diverged=int(np.sum(d["diverged"])),
                 diverged_without_refinement=int(np.sum(rows[0]["diverged"])))
    corners = []
    for a, lam in CORNERS:
        i = int(np.flatnonzero(np.isclose(d["hysteresis.alpha"], a)
                               & np.isclose(d["hysteresis.lam"], lam))[0])
        r = reference_linf(a, lam)
        corners.append(dict(alpha=a, lam=lam, sweep=float(d["linf_error_window"][i]),
                            refinements=int(d["refinements"][i]), reference_dt_1e4=r,
                            abs_diff=abs(float(d["linf_error_window"][i]) - r)))
    med = {r: float(np.median(v)) for r, v in times.items()}
    result = dict(times_s={str(k): v for k, v in times.items()}, median_s=med,
                  ratio=med[6] / med[0], load=load, kinds=kinds, corners=corners,
                  cpus=os.cpu_count())
    print(f"grid 21 x 21, 20 s, dt = 1e-3, float32; load {min(load):.1f}-{max(load):.1f} on "
          f"{os.cpu_count()} CPUs")
    print(f"  sweep time, median of {args.repeats}: RK4 only {med[0]:.1f} s, with refinement "
          f"{med[6]:.1f} s (x{result['ratio']:.2f})")
    print(f"  rows: {kinds}")
    print(f"  {'alpha':>6} {'lam':>5} {'sweep':>10} {'ref dt=1e-4':>12} {'|diff|':>9} level")
    for c in corners:
        print(f"  {c['alpha']:6g} {c['lam']:5g} {c['sweep']:10.6f} {c['reference_dt_1e4']:12.6f}"
              f" {c['abs_diff']:9.2e} {c['refinements']}")
    (out / "stiff_grid.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}/stiff_grid.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
