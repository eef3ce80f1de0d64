"""`dscjax sensitivity`: the normalised sensitivity d ln m / d ln p = (p / m) dm/dp of each
metric m to every number p of the controller, the plant and the hysteresis model (or those given
by --param), on the nominal plant or as the mean over --batch plants, by one reverse pass per
metric (`dscjax.sensitivity`). lp_error_window is the windowed L_p norm of e, p =
`dscjax.sensitivity.LP_ORDER` = 16 (a smooth L-inf). The loop is piecewise smooth: these are
exact local derivatives (docs/sensitivity.md).

Writes DIR/sensitivity.json ({metric: {path: value}}, null where the number is 0 and has no
d ln p; with --float32 also "float32_check", the float64 re-check) and DIR/sensitivity.png (a
tornado chart per metric), and prints the table sorted by magnitude.
"""

from __future__ import annotations

import dataclasses
import sys
import time

import numpy as np

from dscjax import files, params, validation
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, start
from dscjax.markdown import number, table
from dscjax.plotting import saved
from dscjax.progress import Progress
from dscjax.runspec import loop_words
from dscjax.sensitivity import METRICS, Problem, check_metrics
from dscjax.simulate import DivergenceError
from dscjax.sweep.summary import float32_trust

OUTPUTS = Outputs(("sensitivity.json", "sensitivity.png"), at_end=True)
RUN_KEYS = ("t_final", "dt", "window_start", "solver", *common.SAMPLED_KEYS, "device")
TOP = 15  # bars per metric in the tornado chart


HELP = "d ln(metric) / d ln(p) for every number of the loop, by reverse mode"


def add_options(p):
    common.add_config_args(p, run_keys=RUN_KEYS)
    p.add_argument("--metric", action="append", dest="metrics", metavar="NAME",
                   help=f"a metric (repeat for several): {', '.join(METRICS)} (default all)")
    p.add_argument("--param", action="append", dest="paths", metavar="PATH",
                   help="a number by its config path, a vector (controller.k) or an element "
                   "(plant.g[1]) (repeat; default every number of controller, plant, hysteresis)")
    p.add_argument("--batch", type=common.count(0), default=0, metavar="B",
                   help="the mean over B plants drawn uniformly from --range, as tune's "
                   "training batch (default 0: the nominal plant)")
    p.add_argument("--range", action="append", dest="ranges", metavar="PATH=LOW:HIGH|PATH=P%",
                   help="a range the --batch plants are drawn from (repeat; default the "
                   "hysteresis model's numbers within +-30%%, as sweep's)")
    p.add_argument("--seed", type=common.count(0), default=0, help="seed of the --batch plants "
                   "(default 0)")
    add_out_arg(p, "results/sensitivity", plot="skip sensitivity.png")


def run(args) -> int:
    setup, spec = common.load_setup(args)
    metrics = check_metrics(args.metrics or METRICS)
    if args.ranges and not args.batch:
        raise validation.ConfigError("--range draws the --batch plants: give --batch B >= 1 too")
    overrides = None
    if args.batch:
        ranges = (tuple(params.parse_range(r) for r in args.ranges) if args.ranges
                  else params.default_ranges(setup))
        ranges = params.check(ranges, setup, "--range", spec=spec)
        overrides = params.sample_overrides(setup, ranges, args.batch, args.seed)
    problem = Problem.make(setup, spec, args.paths, metrics, overrides)
    if args.print_config:
        return common.print_config(setup, spec)
    # a number that is 0 has no d ln p (null): known before anything compiles
    zero = [p.name for p, z in zip(problem.columns, problem.zero, strict=True) if z]
    if len(zero) == len(problem.columns):
        raise validation.ConfigError(
            f"{'--param' if args.paths else 'the loop'}: every number to differentiate is 0, "
            f"so none has a d ln p (got {common.listed(zero)} = 0); give numbers that are not 0")
    steps, rows = spec.n_steps, max(args.batch, 1)
    what = common.horizon_text(spec.t_final, float(spec.dt), steps)
    work = validation.Work(steps=2 * steps, member_steps=2 * steps * rows)
    if not args.batch:
        work = work + common.gradient_work(setup, steps)
    validation.check_work(work, what=what, fix=common.SHORTER)
    d = len(problem.columns)
    plants = (f"mean over {args.batch} plants (seed {args.seed})" if args.batch
              else "the nominal plant")
    out = start(args, OUTPUTS, f"{len(metrics)} metric(s) x {d} numbers, {plants}, {what}, "
                f"{loop_words(spec)}", spec.device, rows, validation.assumption_warnings(setup))
    if zero:
        are = "is 0 and has" if len(zero) == 1 else "are 0 and have"
        common.say(args, "note", f"{len(zero)} of the {d} numbers {are} no d ln p (null in "
                   f"sensitivity.json): {common.listed(zero)}")
    t0 = time.perf_counter()
    with Progress(2, desc="  sensitivity", unit="stage", every_s=0.0) as bar:
        bar.update_to(0, "compiling the loop and its reverse pass")
        jacobian = problem.compile()
    t1 = time.perf_counter()
    # the run is timed on its own: the compilation's time says nothing of it (no ETA from it)
    with Progress(2, desc="  sensitivity", unit="stage", initial=1, elapsed=t1 - t0,
                  every_s=0.0) as bar:
        bar.update_to(1, f"compiled in {t1 - t0:.1f} s; running")
        result = problem.result(jacobian())
        t2 = time.perf_counter()
        bar.update_to(2, f"forward and {len(metrics)} reverse pass(es) in {t2 - t1:.2f} s")
    values, untrusted = result.values, None  # (a new dict)
    if spec.dtype == "float32":
        print("  re-checking in float64 (which values float32 can be trusted with) ...",
              file=sys.stderr)
        values["float32_check"], untrusted = _float64_check(problem, result, args.paths)
    files.write_json(out / "sensitivity.json", values)
    _print_table(result)
    if not args.no_plot:
        sampled = f", sampled every {spec.sample_time:g} s" if spec.sampled else ""
        _plot(result, out / "sensitivity.png", f"sensitivity of "
              f"{setup.controller.kind.upper()}, n={setup.order}, {what}{sampled}, {plants}")
    common.wrote(out, "sensitivity.json", None if args.no_plot else "sensitivity.png",
                 took=f"{t2 - t0:.1f} s, compilation {t1 - t0:.1f} s")
    if untrusted:
        common.say(args, "warning", untrusted)
    return 0


def _float64_check(problem, result, paths) -> tuple[dict, str | None]:
    """The float32 sensitivities against the same problem (the float32 numbers) in float64:
    `dscjax.sweep.float32_trust`, the check of a float32 sweep, on the metrics' values
    ("tv_u") and every d ln m / d ln p ("tv_u / controller.tau[0]"). Returns what
    sensitivity.json records and the warning (None if every value is trusted)."""
    f64 = Problem.make(params.cast(problem.setup, np.float64),
                       problem.spec.replace(dtype="float64"), paths, problem.metrics,
                       problem.overrides, problem.lp_order)
    try:
        ref = f64.result(f64.jacobian())
    except DivergenceError:  # no float64 reference: nothing of float32's can be trusted
        ref = dataclasses.replace(result, value=np.full_like(result.value, np.nan),
                                  gradient=np.full_like(result.gradient, np.nan))

    def named(res):
        n = res.normalised
        return {m: float(v) for m, v in zip(res.metrics, res.value, strict=True)} | {
            f"{m} / {p}": float(n[i, j]) for i, m in enumerate(res.metrics)
            for j, p in enumerate(res.names)}

    got, want = named(result), named(ref)
    trust = float32_trust(got, want)
    # (a float64 value that is NaN is written null by `files.write_json`)
    check = {"rtol": trust["rtol"], "float64": want, "rel_diff": trust["max_rel_diff"],
             "sign_flips": trust["sign_flips"], "untrusted": trust["untrusted"]}
    if not trust["untrusted"]:
        return check, None

    def why(name):  # the other sign, or one has no value (nan): both values
        pair = (got[name], want[name])
        if name in trust["sign_flips"] or np.isnan(pair).any():
            return " against ".join(number(x, "+.3g", "n/a") for x in pair)
        return f"off by {100 * trust['max_rel_diff'][name]:.3g} %"

    # sign flips first, then the largest differences
    bad = sorted(trust["untrusted"], key=lambda n: (n not in trust["sign_flips"],
                                                    -trust["max_rel_diff"][n]))
    shown = [f"{n} ({why(n)})" for n in bad]
    return check, (f"float32 cannot be trusted with {len(bad)} of the {len(got)} values "
                   f"(float64 differs by more than {100 * trust['rtol']:g} % or has the other "
                   f"sign): {common.listed(shown, 8)} (sensitivity.json: float32_check); rerun "
                   f"without --float32")


def _print_table(result) -> None:
    n = result.normalised
    # by the largest |d ln m / d ln p| over the metrics, those without one (p = 0) last
    largest = np.max(np.where(np.isnan(n), -1.0, np.abs(n)), axis=0)
    rows = [("value of m", *(f"{v:.4g}" for v in result.value))]
    rows += [(result.names[j], *(number(x, "+.3e") for x in n[:, j]))
             for j in np.argsort(-largest, kind="stable")]
    print("d ln m / d ln p (sorted by the largest magnitude; '-': p = 0, no d ln p)")
    print("\n".join(table(("parameter", *result.metrics), rows)))


def _plot(result, path, title: str) -> None:
    k = len(result.metrics)
    n = result.normalised
    shown = min(TOP, len(result.names))
    with saved(path, 120, 1, k, figsize=(3.6 * k + 1.6, 0.28 * shown + 1.6),
               squeeze=False) as (fig, axes):
        for i, ax in enumerate(axes[0]):
            row = np.where(np.isnan(n[i]), 0.0, n[i])
            order = np.argsort(-np.abs(row), kind="stable")[:shown][::-1]
            ax.barh(np.arange(shown), row[order],
                    color=["#d62728" if v > 0 else "#1f77b4" for v in row[order]])
            ax.set_yticks(np.arange(shown), [result.names[j] for j in order], fontsize=7)
            ax.axvline(0.0, color="k", lw=0.6)
            ax.set_title(f"{result.metrics[i]} = {result.value[i]:.3g}", fontsize=9)
            ax.set_xlabel("d ln m / d ln p")
        fig.suptitle(title, fontsize=9)
