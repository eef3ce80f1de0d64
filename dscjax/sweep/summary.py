"""What a finished sweep says: quantiles, divergence and degradation rates, the worst samples,
full re-simulated traces of chosen rows, the float64 re-check of a float32 sweep (which metrics
float32 can be trusted with) and summary.md."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from dscjax import params
from dscjax.divergence import OUTCOMES, outcome_counts
from dscjax.markdown import escape, figure, number, table, window
from dscjax.metrics import CHATTER_RATIO
from dscjax.params import Param
from dscjax.runspec import RunSpec
from dscjax.simulate import simulate
from dscjax.sweep.device import METRICS
from dscjax.sweep.run import RUN_KEYS, SweepResult

# the metrics of summary.md's table of the worst samples: tracking and effort on the window
WORST_COLUMNS = ("linf_error_window", "rms_error_window", "tv_u_window", "chattering_index")
# the quantiles of summary.json and summary.md, by name
QUANTILES = {"min": 0.0, "p01": 0.01, "p05": 0.05, "p25": 0.25, "p50": 0.5, "p75": 0.75,
             "p95": 0.95, "p99": 0.99, "max": 1.0}
# A float32 metric is trusted when, on every re-checked row, it agrees with the same row run in
# float64 to this relative difference (`float64_check`).
FLOAT32_RTOL = 1e-3
MIN_CHECK_ROWS = 3  # a float32 sweep re-checks at least this many rows in float64


def rank_rows(columns: Mapping[str, np.ndarray], k: int, diverged: bool = False) -> np.ndarray:
    """Rows of the k worst samples that did not diverge, largest windowed L-inf error first;
    with `diverged`, of the first k samples to diverge (earliest divergence time first)."""
    rows = np.flatnonzero(np.asarray(columns["diverged"], bool) == diverged)
    key = (np.asarray(columns["t_diverged"], np.float64) if diverged else
           -np.nan_to_num(np.asarray(columns["linf_error_window"], np.float64), nan=np.inf))
    return rows[np.argsort(key[rows], kind="stable")][:k]


def trace_rows(columns: Mapping[str, np.ndarray], k: int) -> tuple[np.ndarray, list[str]]:
    """k rows worth a full trace: about a third the earliest diverged (if any), the rest
    the worst that track; either kind fills in for the other if there are too few."""
    want_div = min(int(np.sum(columns["diverged"])), -(-k // 3))
    worst = rank_rows(columns, k - want_div)
    div = rank_rows(columns, k - len(worst), diverged=True)
    return (np.concatenate([worst, div]).astype(np.int64),
            ["worst"] * len(worst) + ["diverged"] * len(div))


def summarize(result: SweepResult, nominal: Mapping[str, float] | None = None,
              threshold: float | None = None, worst: int = 6) -> dict[str, Any]:
    """Quantiles of every metric (over the samples that did not diverge), the divergence and
    degradation rates, the worst samples that track and the first to diverge, with their
    parameters."""
    c, n = result.columns, result.n
    ok, counts = outcome_counts(c["diverged"], c["refinements"])
    div = ~ok
    out = {
        "n_samples": n,
        **counts,
        "divergence_rate": float(div.mean()) if n else 0.0,
        "smallest_dt_tried": float(np.min(c["dt_used"][div])) if div.any() else None,
        "quantiles_over": "samples that did not diverge",
        "quantiles": {m: _quantiles(np.asarray(c[m], np.float64)[ok]) for m in METRICS},
    }
    if nominal is not None:
        out["nominal"] = {k: float(v) for k, v in nominal.items()}
    # the one chattering criterion (dscjax.metrics.chatters, row by row); NaN (diverged): no
    chatter = ok & (np.asarray(c["chattering_index"], np.float64) > CHATTER_RATIO)
    out["chattering"] = {"metric": "chattering_index", "above": CHATTER_RATIO,
                         "count": int(chatter.sum()),
                         "rate": float(chatter.mean()) if n else 0.0,
                         "definition": "docs/numerics.md"}
    if threshold is not None:
        degraded = div | (np.asarray(c["linf_error_window"], np.float64) > threshold)
        out["degraded"] = {"metric": "linf_error_window", "threshold": float(threshold),
                           "rate": float(degraded.mean()) if n else 0.0,
                           "count": int(degraded.sum())}
    for key, diverged in (("worst", False), ("first_diverged", True)):
        out[key] = [sample_record(c, result.param_names, i) for i in rank_rows(c, worst, diverged)]
    return out


def _quantiles(v: np.ndarray) -> dict[str, float] | None:
    """`QUANTILES` and the mean of the finite values of v; None if there are none."""
    v = v[np.isfinite(v)]
    if not v.size:
        return None
    qs = np.quantile(v, list(QUANTILES.values()))
    return {**{k: float(x) for k, x in zip(QUANTILES, qs, strict=True)}, "mean": float(np.mean(v))}


def sample_record(columns, param_names, i) -> dict[str, Any]:
    return {
        "sample": int(columns["sample"][i]),
        "params": {p: float(columns[p][i]) for p in param_names},
        "metrics": {m: float(columns[m][i]) for m in METRICS},
        "diverged": bool(columns["diverged"][i]),
        "t_diverged": (float(columns["t_diverged"][i]) if columns["diverged"][i] else None),
        "refinements": int(columns["refinements"][i]),
        "dt_used": float(columns["dt_used"][i]),
    }


def random_rows(n: int, k: int, seed: int, exclude: Iterable[int] = ()) -> np.ndarray:
    """k >= 0 distinct rows (fewer where fewer are left) drawn with the sweep's seed (a stream
    separate from the samples)."""
    pool = np.setdiff1d(np.arange(n, dtype=np.int64), np.asarray(list(exclude), np.int64))
    rng = np.random.default_rng([seed, 1])
    return np.sort(rng.choice(pool, size=min(k, pool.size), replace=False))


def simulate_rows(setup, result: SweepResult, rows: Sequence[int], *, save_every: int = 10,
                  dtype: str | None = None) -> list:
    """Full trajectories of chosen rows, re-simulated one at a time with `dscjax.simulate`
    with the sweep's run (solver, refinement, the sampled controller's Ts, delay and noise;
    throw=False: diverged ones come back frozen at their last good state), in `dtype`
    (default the sweep's)."""
    info = result.info
    setup = params.cast(setup, np.dtype(dtype or info["dtype"]))
    cols = [Param.parse(p) for p in result.param_names]
    spec = RunSpec.make(info["t_final"], info["dt"], **{k: info[k] for k in RUN_KEYS},
                        save_every=max(1, min(save_every, info["n_steps"])))
    index = np.asarray(rows, np.int64)
    table = np.stack([result.columns[p][index] for p in result.param_names], axis=1)
    return [simulate(params.set_row(setup, cols, row), spec=spec, throw=False) for row in table]


def check_rows(result: SweepResult, rows: Iterable[int], least: int = MIN_CHECK_ROWS
               ) -> np.ndarray:
    """The rows a float32 sweep re-checks in float64: `rows` (the traced ones) that did not
    diverge, topped up to at least `least` with the first other rows that did not diverge."""
    ok = ~np.asarray(result.columns["diverged"], bool)
    mine = [int(i) for i in rows if ok[i]]
    mine += np.setdiff1d(np.flatnonzero(ok), mine)[:max(least - len(mine), 0)].tolist()
    return np.asarray(sorted(set(mine)), np.int64)


def float64_check(setup, result: SweepResult, rows: Sequence[int]) -> dict[str, Any] | None:
    """Which metrics a float32 sweep can be trusted with: `rows` re-run in float64
    (`simulate_rows`), and per metric the largest relative difference of the swept float32
    value from the float64 one. A metric above `FLOAT32_RTOL` on any row is listed in
    "untrusted". None for a float64 sweep (nothing to check) or without rows.

    The float32 loop itself can differ from the float64 one (high gains amplify its rounding
    into chattering of u), so no float64 accumulation of the float32 run would repair it.
    """
    if result.info["dtype"] != "float32" or len(rows) == 0:
        return None
    runs = simulate_rows(setup, result, rows, save_every=result.info["n_steps"], dtype="float64")
    c = result.columns
    trust = float32_trust({m: [c[m][i] for i in rows] for m in METRICS},
                          {m: [tr.metrics[m] for tr in runs] for m in METRICS})
    return {"rows": [int(c["sample"][i]) for i in rows], "rtol": trust["rtol"],
            "max_rel_diff": trust["max_rel_diff"],
            "at_sample": {m: int(c["sample"][rows[j]]) for m, j in trust["at"].items()},
            "untrusted": trust["untrusted"]}


def float32_trust(got: Mapping[str, float | Sequence[float]],
                  reference: Mapping[str, float | Sequence[float]],
                  rtol: float | None = None) -> dict[str, Any]:
    """The one float32 check (sweeps, `simulate --float32`, `sensitivity --float32`): per
    name, the largest relative difference |a - r| / |r| of the float32 values `got` from
    their float64 `reference` (0 where both are NaN, no value: a diverged run, a null
    sensitivity; inf where only one is), the index where it is largest ("at"), and the names
    whose sign flips on some index (a r < 0). A name above `rtol` or whose sign flips is
    "untrusted"; the order is `got`'s; a single number counts as one value. `rtol` default:
    FLOAT32_RTOL."""
    rtol = FLOAT32_RTOL if rtol is None else rtol
    diff, at, flips = {}, {}, []
    for name, values in got.items():
        a = np.asarray(values, np.float64).reshape(-1)
        r = np.asarray(reference[name], np.float64).reshape(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(np.isfinite(a) & np.isfinite(r),
                         np.abs(a - r) / np.maximum(np.abs(r), 1e-30),
                         np.where(np.isnan(a) & np.isnan(r), 0.0, np.inf))
        j = int(np.argmax(d))  # the first of the largest
        diff[name], at[name] = float(d[j]), j
        if np.any(a * r < 0):
            flips.append(name)
    return {"rtol": rtol, "max_rel_diff": diff, "at": at, "sign_flips": flips,
            "untrusted": [n for n in got if not diff[n] <= rtol or n in flips]}


def _cell(x) -> str:
    """A cell of summary.md: yes or no, a count with thousands separators, a figure (`number`)
    or text."""
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    return number(x) if x is None or isinstance(x, float) else escape(x)


def scope_text(run: Mapping[str, Any]) -> str:
    """What a sweep runs, in words, from its "run" (`run_sweep`'s info, or the same keys
    before the run): "10,000 samples (uniform, seed 0) of hysteresis.alpha in [0.7, 1.3], ...;
    T = 20 s, float64, the continuous loop (RK4 at dt = 0.001 s)"."""
    what = "grid points" if run["method"] == "grid" else "samples"
    ranges = ", ".join(f"{k} in [{v[0]:.4g}, {v[1]:.4g}]" + (f" x{v[2]}" if len(v) > 2 else "")
                       for k, v in run["ranges"].items())
    return (f"{run['n_samples']:,} {what} ({run['method']}, seed {run['seed']}) of {ranges}; "
            f"T = {run['t_final']:g} s, {run['dtype']}, {run['loop']}")


def outcome(summary: Mapping[str, Any]) -> list[str]:
    """The outcome of a sweep in lines, summary.md's "Outcome" and the console's: the windowed
    error and effort of the samples that did not diverge, the three kinds of rows, the
    chattering and degraded counts, the nominal setup."""
    run, q, n = summary["run"], summary["quantiles"], summary["n_samples"]
    span = window(run["window_start"], run["t_final"])
    lines = []
    if (e := q["linf_error_window"]) is not None:
        lines.append(f"windowed L-inf error on {span} over the {n - summary['n_diverged']:,} "
                     f"samples that did not diverge: median {e['p50']:.4g}, p95 {e['p95']:.4g}, "
                     f"max {e['max']:.4g}")
    if (tv := q["tv_u_window"]) is not None:
        lines.append(f"effort on {span} over the same samples: TV(u) median "
                     f"{figure(tv['p50'])}, p95 {figure(tv['p95'])}, max {figure(tv['max'])}; "
                     f"max|u| max {figure(q['max_abs_u_window']['max'])}")
    smallest = summary["smallest_dt_tried"]
    chat = summary["chattering"]
    lines += [f"{OUTCOMES['n_tracked']}: {summary['n_tracked']:,}",
              f"{OUTCOMES['n_refined']} (a numerically stiff run re-done with ETDRK4 at a "
              f"smaller step): {summary['n_refined']:,}",
              f"{OUTCOMES['n_diverged']}: {summary['n_diverged']:,} of {n:,} "
              f"({100 * summary['divergence_rate']:.2f} %"
              + (f", down to dt = {smallest:.3g} s" if smallest is not None else "") + ")",
              f"chattering (chattering index above {chat['above']:g}, docs/numerics.md; "
              f"diverged samples not counted): {chat['count']:,} of {n:,} "
              f"({100 * chat['rate']:.2f} %)"]
    if deg := summary.get("degraded"):
        lines.append(f"degraded ({deg['metric']} above {deg['threshold']:.4g}"
                     + (f", {deg['rule']}" if deg.get("rule") else "")
                     + f"; diverged included): {deg['count']:,} ({100 * deg['rate']:.2f} %)")
    if nominal := summary.get("nominal"):
        shown = ("linf_error_window", "tv_u_window", "chattering_index")
        lines.append("nominal setup: " + ("diverged" if nominal.get("diverged") else
                     ", ".join(f"{m} {figure(nominal[m])}" for m in shown)))
    return lines


def markdown(summary: Mapping[str, Any]) -> str:
    """summary.md: what summary.json says, for a person: the run, its outcome, the float32
    trust flags, the quantiles, the worst and first diverged samples."""
    run = summary["run"]
    lines = ["# Robustness sweep", "",
             f"{scope_text(run)}; windowed metrics on t >= {run['window_start']:g} s. Wall "
             f"time {run['wall_s']:.1f} s on {run['devices']} device(s) ({run['platform']}).",
             ""]
    warnings = summary.get("warnings", [])
    lines += [f"**Warning:** {w}" for w in warnings] + ([""] if warnings else [])
    lines += ["## Outcome", "", *(f"- {line}" for line in outcome(summary))]
    check = summary.get("float32_check")
    lines += ["", "## float32 trust", ""]
    if check is None and run["dtype"] == "float32":
        lines.append("The sweep ran in float32 and was **not re-checked** in float64 "
                     "(`float64_check`): its metrics may be far from float64's.")
    elif check is None:
        lines.append(f"The sweep ran in {run['dtype']}: nothing to re-check.")
    else:
        bad = check["untrusted"]
        lines += [f"{len(check['rows'])} rows (samples {', '.join(map(str, check['rows']))}) "
                  f"were re-run in float64. A metric is trusted when every one agrees to a "
                  f"relative {check['rtol']:.3g}. "
                  + (f"**Not trusted in float32: {', '.join(bad)}**; rerun with --float64."
                     if bad else "Every metric agrees."), ""]
        lines += table(["metric", "max relative difference", "at sample", "trusted"],
                       [(m, check["max_rel_diff"][m], check["at_sample"][m], m not in bad)
                        for m in check["max_rel_diff"]], _cell)
    q = summary["quantiles"]
    lines += ["", f"## Quantiles over the {summary['quantiles_over']}", ""]
    keys = [*QUANTILES, "mean"]
    lines += table(["metric", *keys], [(m, *((q[m] or {}).get(k) for k in keys)) for m in q],
                   _cell)
    for title, key, columns in (
            ("Worst samples that track", "worst", [*WORST_COLUMNS, "refinements"]),
            ("First samples to diverge", "first_diverged", ["t_diverged", "dt_used"])):
        if recs := summary.get(key):
            # each column a field of the record (`sample_record`) or one of its metrics
            body = [(r["sample"], *r["params"].values(),
                     *(r[k] if k in r else r["metrics"][k] for k in columns)) for r in recs]
            head = ["sample", *recs[0]["params"], *columns]
            lines += ["", f"## {title}", ""] + table(head, body, _cell)
    return "\n".join(lines) + "\n"
