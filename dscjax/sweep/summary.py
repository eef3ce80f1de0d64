"""What a finished sweep says: quantiles, divergence and degradation rates, the worst samples,
and full re-simulated traces of chosen rows."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from dscjax import params
from dscjax.params import Param
from dscjax.simulate import simulate
from dscjax.sweep.device import METRICS
from dscjax.sweep.run import SweepResult

QUANTILES = (0.0, 0.01, 0.05, 0.25, 0.5, 0.75, 0.95, 0.99, 1.0)


def rank_worst(columns: Mapping[str, np.ndarray], k: int) -> np.ndarray:
    """Rows of the k worst samples that did not diverge, largest windowed L-inf error first."""
    ok = ~np.asarray(columns["diverged"], bool)
    lw = np.nan_to_num(np.asarray(columns["linf_error_window"], np.float64), nan=np.inf)
    rows = np.flatnonzero(ok)
    return rows[np.argsort(-lw[rows], kind="stable")][:k]


def rank_diverged(columns: Mapping[str, np.ndarray], k: int) -> np.ndarray:
    """Rows of the first k samples to diverge (earliest divergence time first)."""
    rows = np.flatnonzero(np.asarray(columns["diverged"], bool))
    t = np.asarray(columns["t_diverged"], np.float64)[rows]
    return rows[np.argsort(t, kind="stable")][:k]


def trace_rows(columns: Mapping[str, np.ndarray], k: int) -> tuple[np.ndarray, list[str]]:
    """k rows worth a full trace: about a third the earliest diverged (if any), the rest
    the worst that track; either kind fills in for the other if there are too few."""
    n_div = int(np.sum(columns["diverged"]))
    want_div = min(n_div, -(-k // 3)) if n_div else 0
    worst = rank_worst(columns, k - want_div)
    div = rank_diverged(columns, k - len(worst))
    return (np.concatenate([worst, div]).astype(np.int64),
            ["worst"] * len(worst) + ["diverged"] * len(div))


def summarize(result: SweepResult, nominal: Mapping[str, float] | None = None,
              threshold: float | None = None, worst: int = 6) -> dict[str, Any]:
    """Quantiles of every metric (over the samples that did not diverge), the divergence and
    degradation rates, the worst samples that track and the first to diverge, with their
    parameters."""
    c = result.columns
    div = np.asarray(c["diverged"], bool)
    ok = ~div
    n = result.n
    quant = {}
    for m in METRICS:
        v = np.asarray(c[m], np.float64)[ok]
        v = v[np.isfinite(v)]
        if v.size:
            qs = np.quantile(v, QUANTILES)
            quant[m] = {f"p{round(q * 100):02d}" if 0 < q < 1 else ("min" if q == 0 else "max"):
                        float(x) for q, x in zip(QUANTILES, qs, strict=True)}
            quant[m]["mean"] = float(np.mean(v))
        else:
            quant[m] = None
    lw = np.asarray(c["linf_error_window"], np.float64)
    refined = np.asarray(c.get("refinements", np.zeros(n)), np.int64) > 0
    out = {
        "n_samples": n,
        "n_tracked": int((~div & ~refined).sum()),
        "n_refined": int((~div & refined).sum()),
        "n_diverged": int(div.sum()),
        "divergence_rate": float(div.mean()) if n else 0.0,
        "smallest_dt_tried": (float(np.min(c["dt_used"][div])) if div.any() and "dt_used" in c
                              else None),
        "quantiles_over": "samples that did not diverge",
        "quantiles": quant,
    }
    if nominal is not None:
        out["nominal"] = {k: float(v) for k, v in nominal.items()}
    if threshold is not None:
        degraded = div | (lw > threshold)
        out["degraded"] = {"metric": "linf_error_window", "threshold": float(threshold),
                           "rate": float(degraded.mean()) if n else 0.0,
                           "count": int(degraded.sum())}
    out["worst"] = [sample_record(c, result.param_names, i) for i in rank_worst(c, worst)]
    out["first_diverged"] = [sample_record(c, result.param_names, i)
                             for i in rank_diverged(c, worst)]
    return out


def sample_record(columns, param_names, i) -> dict[str, Any]:
    return {
        "sample": int(columns["sample"][i]),
        "params": {p: float(columns[p][i]) for p in param_names},
        "metrics": {m: float(columns[m][i]) for m in METRICS},
        "diverged": bool(columns["diverged"][i]),
        "t_diverged": (float(columns["t_diverged"][i]) if columns["diverged"][i] else None),
        "refinements": int(columns["refinements"][i]) if "refinements" in columns else 0,
        "dt_used": float(columns["dt_used"][i]) if "dt_used" in columns else None,
    }


def random_rows(n: int, k: int, seed: int, exclude: Iterable[int] = ()) -> np.ndarray:
    """k distinct rows drawn with the sweep's seed (a stream separate from the samples)."""
    pool = np.setdiff1d(np.arange(n, dtype=np.int64), np.asarray(list(exclude), np.int64))
    if k <= 0 or pool.size == 0:
        return np.zeros(0, dtype=np.int64)
    rng = np.random.default_rng([seed, 1])
    return np.sort(rng.choice(pool, size=min(k, pool.size), replace=False))


def simulate_rows(setup, result: SweepResult, rows: Sequence[int], *, save_every: int = 10,
                  ranges_params: Sequence[Param] | None = None) -> list:
    """Full trajectories of chosen rows, re-simulated one at a time with `dscjax.simulate`
    with the sweep's solver and refinement (throw=False: diverged ones come back frozen at
    their last good state)."""
    info = result.info
    setup = params.cast(setup, np.dtype(info["dtype"]))
    cols = ranges_params or [Param.parse(p) for p in result.param_names]
    n_steps = info["n_steps"]
    every = max(1, min(save_every, n_steps))
    out = []
    for i in rows:
        row = np.array([result.columns[p][i] for p in result.param_names])
        s = params.set_row(setup, cols, row)
        out.append(simulate(s, info["t_final"], info["dt"], save_every=every,
                            window_start=info["window_start"],
                            state_bound=info["state_bound"], throw=False,
                            solver=info.get("solver", "rk4"), refine=info.get("refine", 0),
                            sample_time=info.get("sample_time")))
    return out


