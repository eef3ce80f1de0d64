"""The "explosion of complexity" (Introduction, Remarks 4 and 6; never measured by the paper):
size and cost of the DSC and backstepping control laws, built by the same code for
`order_n_example(n)`, against the order n, as compiled programs of (u, info) at the initial
state: eqns (jaxpr equations, sub-jaxprs inlined), flops (XLA's cost analysis, after its
simplification), trace_s, compile_s, build_s = trace + compile, eval_s (per evaluation inside
one compiled loop, as a simulation evaluates the law) and call_s (one call from Python).
Timings are medians over `repeats` fresh builds. Growth is fitted by least squares on log(v):
`ratio_per_order` (v ~ r^n) and `exponent` (v ~ n^p), each with its r2.
"""

from __future__ import annotations

import json
import statistics
import time
import timeit
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from dscjax import files
from dscjax.closed_loop import initial_state, prepared
from dscjax.config import order_n_example
from dscjax.controllers.backstepping import with_backstepping
from dscjax.plotting import LOG_GRID, saved
from dscjax.reproduce.runs import STYLE
from dscjax.validation import ConfigError

CONTROLLERS = ("dsc", "backstepping")


def count_eqns(jaxpr) -> int:
    """Equations of a jaxpr, with every sub-jaxpr (jit, custom derivatives, ...) inlined."""
    subs = (list(jax.extend.core.jaxprs_in_params(eqn.params)) for eqn in jaxpr.eqns)
    return sum(sum(map(count_eqns, s)) if s else 1 for s in subs)


def _eval_loop(law):
    """A jitted loop of k (traced) law evaluations at moving (x, t) -> a checksum of every
    output leaf behind an optimisation barrier, as in the closed loop: XLA drops nothing."""

    def run(state, x, t0, k):
        def body(i, acc):
            t = t0 + i * 1e-3
            out = jax.lax.optimization_barrier(law(state, x + 1e-3 * t, t))
            return acc + sum(jnp.sum(leaf) for leaf in jax.tree.leaves(out))

        return jax.lax.fori_loop(jnp.zeros((), k.dtype), k, body, jnp.zeros((), x.dtype))

    return jax.jit(run)


def _median_time(fn, runs: int) -> float:
    """The median of `runs` timings of fn() to its results' readiness."""
    return statistics.median(timeit.repeat(lambda: jax.block_until_ready(fn()), repeat=runs,
                                           number=1))


def measure(controller: str, n: int, repeats: int = 3, evals: int = 2000,
            eval_budget_s: float = 0.25, slow_build_s: float = 20.0) -> dict:
    """Size and cost of one control law (the module docstring's fields): `repeats` builds
    (fewer, counted in the result, after one slower than `slow_build_s`); `evals` evaluations
    per timing loop, fewer (at least 10) to keep a loop near `eval_budget_s`."""
    if controller not in CONTROLLERS:
        raise ValueError(f"controller must be one of {CONTROLLERS} (got {controller!r})")
    setup = order_n_example(n, dtype=jnp.float64)
    setup = prepared(with_backstepping(setup) if controller == "backstepping" else setup)
    # backstepping's law without its inner jit (`plain_law`), so tracing is measured in full
    impl = getattr(setup.controller, "plain_law", setup.controller.law)
    X = initial_state(setup)
    args = (X.ctrl, X.x, jnp.zeros((), X.x.dtype))
    trace_s, compile_s = [], []
    for _ in range(repeats):
        def law(state, x, t):  # a new function object for each build: nothing cached
            return impl(state, x, t, setup.plant, setup.reference)

        jitted = jax.jit(law)
        t0 = time.perf_counter()
        closed = jax.make_jaxpr(law)(*args)
        t1 = time.perf_counter()
        compiled = jitted.trace(*args).lower().compile()
        t2 = time.perf_counter()
        trace_s.append(t1 - t0)
        compile_s.append(t2 - t1)
        if t2 - t0 > slow_build_s:
            break
    jax.block_until_ready(compiled(*args))
    call_s = _median_time(lambda: compiled(*args), 21)
    loop = _eval_loop(jitted)  # the jitted law's trace is cached: the loop is only compiled
    count = jnp.asarray(10)
    jax.block_until_ready(loop(*args, count))
    per = _median_time(lambda: loop(*args, count), 3) / 10
    k = int(np.clip(eval_budget_s / max(per, 1e-12), 10, evals))
    count = jnp.asarray(k)
    eval_s = _median_time(lambda: loop(*args, count), max(repeats, 5)) / k
    build_s = [a + b for a, b in zip(trace_s, compile_s, strict=True)]
    # flops: XLA's count in its cost analysis of the compiled program (a dict), NaN if none
    return dict(controller=controller, n=n, eqns=count_eqns(closed.jaxpr),
                flops=float((compiled.cost_analysis() or {}).get("flops", float("nan"))),
                trace_s=statistics.median(trace_s), compile_s=statistics.median(compile_s),
                build_s=statistics.median(build_s), eval_s=eval_s, call_s=call_s,
                repeats=len(trace_s), evals=k)


def fit_growth(ns: Sequence[int], values: Sequence[float]) -> dict:
    """Least-squares growth of positive values against the order n (module docstring)."""
    n = np.asarray(ns, float)
    v = np.asarray(values, float)
    ok = np.isfinite(v) & (v > 0)
    n, logv = n[ok], np.log(v[ok])
    if n.size < 2:
        return dict(ratio_per_order=None, r2_geometric=None, exponent=None, r2_power=None)

    def fit(xs):
        slope, icept = np.polyfit(xs, logv, 1)
        resid = logv - (slope * xs + icept)
        ss = np.sum((logv - logv.mean()) ** 2)
        return float(slope), float(1.0 - np.sum(resid**2) / ss) if ss > 0 else 1.0

    slope_n, r2_n = fit(n)
    slope_log, r2_log = fit(np.log(n))
    return dict(ratio_per_order=float(np.exp(slope_n)), r2_geometric=r2_n,
                exponent=slope_log, r2_power=r2_log)


METRICS = ("eqns", "flops", "trace_s", "compile_s", "build_s", "eval_s", "call_s")


def _load_rows(path: Path, settings: dict, log) -> dict:
    """The saved measurements; ConfigError if missing, unreadable or made with other
    settings (resuming them would mix two studies)."""
    files.resume_file(path.parent, path.name)
    try:
        saved = json.loads(path.read_text())
        old = saved.get("settings")
        rows = {(r["controller"], int(r["n"])): r for r in saved["rows"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        raise ConfigError(f"--resume: {path} is unreadable; run without --resume to measure "
                          f"afresh") from None
    files.check_same(old, settings, where=f"--resume: {path}",
                     fix="use the same ones, or run without --resume to measure afresh")
    if log:
        log(f"  resumed: {len(rows)} measurement(s) kept from {path}")
    return rows


def study(orders: Sequence[int] = tuple(range(2, 9)), repeats: int = 3, evals: int = 2000,
          log: Callable[[str], None] | None = print, rows_path=None,
          resume: bool = False) -> dict:
    """Rows, fits and the machine context of every controller at every order. Each finished
    measurement is saved at once to `rows_path` (atomically); `resume=True` reuses those made
    with the same repeats, evals, jax version and backend."""
    # what a saved measurement must have been made with to be reused by a resumed study
    settings = dict(repeats=repeats, evals=evals, jax_version=jax.__version__,
                    backend=jax.default_backend())
    path = None if rows_path is None else Path(rows_path)
    saved = _load_rows(path, settings, log) if (resume and path) else {}
    rows = []
    t_start = time.perf_counter()
    for n in orders:
        for c in CONTROLLERS:
            kept = (c, int(n)) in saved
            row = saved[(c, int(n))] if kept else measure(c, n, repeats=repeats, evals=evals)
            rows.append(row)
            if path is not None and not kept:
                saved[(c, int(n))] = row
                files.write_json(path, dict(settings=settings, rows=list(saved.values())))
            if log:  # every figure is in complexity.json
                log(f"  complexity n={n} {c:>12}: {row['eqns']:>7} eqns, build "
                    f"{row['build_s']:.3g} s, eval {row['eval_s'] * 1e6:.3g} us  " + (
                        "[kept]" if kept else f"[{time.perf_counter() - t_start:.0f} s]"))
    mine = {c: [r for r in rows if r["controller"] == c] for c in CONTROLLERS}
    fits = {c: {m: fit_growth([r["n"] for r in mine[c]], [r[m] for r in mine[c]]) for m in METRICS}
            for c in CONTROLLERS}
    return dict(rows=rows, fits=fits, orders=list(orders), repeats=repeats, evals=evals,
                plant="dscjax.order_n_example(n): f_i = 0.2 x_i^2 + 0.2 sin x_i + 0.05 x_(i-1) "
                      "x_i, rho_i = 0.05 + 0.02 (x_1^2 + ... + x_i^2)",
                jax_version=jax.__version__, backend=jax.default_backend(),
                wall_time_s=time.perf_counter() - t_start)


def growth_text(fit: dict, power: str = "~ n^{:.2f}") -> str:
    """"x3.10 per order" or "~ n^1.00" (the exponent in `power`), whichever model fits
    log(value) better."""
    if fit["r2_geometric"] >= fit["r2_power"]:
        return f"x{fit['ratio_per_order']:.2f} per order"
    return power.format(fit["exponent"])


# the panels of `plot` and their axis labels
LABELS = {"eqns": "equations in the jaxpr", "flops": "FLOPs (XLA cost analysis)",
          "build_s": "JIT time: trace + compile [s]", "eval_s": "time per evaluation [s]"}


def plot(result: dict, path, dpi: int = 150) -> None:
    """Log-scale panels of the metrics against n, one line per controller (growth in legend),
    in the colours of its run (`runs.STYLE`)."""
    names = {"dsc": "DSC", "backstepping": "backstepping (autodiff)"}
    with saved(path, dpi, 2, 2, rc=LOG_GRID, figsize=(9, 6.4)) as (fig, axes):
        for ax, (metric, ylabel) in zip(axes.ravel(), LABELS.items(), strict=True):
            for c, fits in result["fits"].items():
                rows = [r for r in result["rows"] if r["controller"] == c]
                ns = [r["n"] for r in rows]
                name, fit, color = names.get(c, c), fits[metric], STYLE[c]["color"]
                label = name + (", in a compiled loop" if metric == "eval_s" else
                                ": " + growth_text(fit, "~ $n^{{{:.2f}}}$")
                                if fit.get("ratio_per_order") else "")
                ax.semilogy(ns, [r[metric] for r in rows], "o-", color=color, lw=1.5, ms=4,
                            label=label)
                if metric == "eval_s":
                    ax.semilogy(ns, [r["call_s"] for r in rows], "s--", color=color, lw=1.0,
                                ms=3, alpha=0.6, label=name + ", one call from Python")
            ax.set_xlabel("plant order $n$")
            ax.set_ylabel(ylabel)
            ax.set_xticks(result["orders"])
            # headroom above the data so that the legend never hides a point
            lo, hi = ax.get_ylim()
            share = 0.45 if metric == "eval_s" else 0.3
            ax.set_ylim(lo, hi * 10 ** (np.log10(hi / lo) * share / (1 - share)))
            ax.legend(fontsize=8, loc="upper left")
        fig.suptitle("Size and cost of the control law against the plant order", fontsize=11)
