"""Maximise a metric of the closed loop (default: the windowed L-inf of the tracking error)
over boxes of parameters (--range, as in sweeps) and a bounded disturbance waveform
(--disturbance), by projected gradient ascent from M starts advanced together, with random
sampling and CMA-ES given the same search time as baselines. A candidate that diverges is
re-simulated at smaller steps (ETDRK4) before it is reported; a divergence of the loop itself is
reported with its time. Settings may also come from a [worst] table of the config; the command
line wins.

Writes into DIR: worst.json, worst_config.toml, worst_trajectory.npz, report.md, the figures
worst_vs_nominal.png, worst_disturbance.png, search_progress.png, and each method's state
(state_<method>.npz, saved after every iteration; --resume continues from them).
"""

from __future__ import annotations

import sys
from pathlib import Path

from dscjax import files, settings, worst
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, kept_text, resume_text, start
from dscjax.params import from_table, parse_range
from dscjax.progress import Progress
from dscjax.validation import ConfigError, Work, check_work
from dscjax.worst.report import FIGURES, FILES, methods_table, searched, verdict, write

MANIFEST = "worst_case.json"
OUTPUTS = Outputs((MANIFEST, *FILES, "state_*.npz", *FIGURES))


HELP = "worst-case search over parameter boxes and disturbance waveforms"


def add_options(p):
    common.add_config_args(p, run_keys=("t_final", "dt", *common.SAMPLED_KEYS, "device"),
                           table="worst")
    p.add_argument("--range", action="append", dest="ranges", metavar="PATH=LOW:HIGH|PATH=P%",
                   help="a searched parameter (repeat), e.g. plant.g[1]=0.7:1.3 or "
                   "hysteresis.alpha=30%%")
    settings.add_arguments(p, worst.WorstSettings, "worst.")
    add_out_arg(p, "results/worst-case", resume="continue a search in DIR (each method from "
                "its last finished iteration)", overwrite="discard a search in DIR",
                plot="skip the figures", quiet="no progress display")


def run(args) -> int:
    setup, options = common.load_setup(args)
    s, ranges = worst_settings(args)
    requirements = requirement_table(args, s)
    if args.print_config:
        table = settings.to_table(s) | ({"ranges": {r.name: r.spec().split("=", 1)[1]
                                                    for r in ranges}} if ranges else {})
        tuning = {"tuning": {"requirements": requirements}} if requirements else {}
        return common.print_config(setup, options, {"worst": table} | tuning,
                                   groups={"worst": s})
    requirement = None
    if requirements:  # built as the tuner builds it
        from tuning.requirements import build_requirements

        requirement = build_requirements(setup, requirements)[0]
    problem = worst.make_problem(setup, ranges, s.disturbance, metric=s.metric,
                                 requirement=requirement, spec=options, period=s.period)
    methods = list(s.methods)
    search = {"starts": s.starts, "batch": s.batch, "time_limit": s.time_limit,
              "max_evals": s.max_evals, "coarsening": s.gradient_coarsening}
    worst.check_search(problem, methods, **search)
    what = common.horizon_text(problem.spec.t_final, float(problem.spec.dt),
                              problem.spec.n_steps)
    fix = ("use a shorter --t-final, a larger --dt, or fewer --starts or a smaller --batch "
           "(or a larger --time-limit)")
    each = iteration_work(problem, methods, s.starts, s.batch, s.gradient_coarsening)
    check_work(each, what=f"one search iteration of {what}", fix=fix,
               limit_s=s.time_limit, limit=f"--time-limit {s.time_limit:g} s")
    check_work(stored_work(problem), what=f"the worst case's re-simulation of {what}", fix=fix)
    fingerprint = {"problem": problem.fingerprint(), "seed": s.seed, "starts": s.starts,
                   "batch": s.batch, "methods": methods, "coarsening": s.gradient_coarsening}
    if args.resume:
        files.check_record(args.out, MANIFEST, fingerprint)
    out = start(args, OUTPUTS, f"{problem.metric} over {searched(problem)}; "
                f"{', '.join(methods)}, {s.time_limit:g} s each"
                + (f" (at most {s.max_evals} evaluations)" if s.max_evals else "")
                + f"; {what}", options.device, max(s.starts, s.batch),
                worst.assumption_warnings(problem), resumable=True)
    files.write_json(out / MANIFEST, {"fingerprint": fingerprint,
                                      "argv": getattr(args, "argv", [])})
    bars, compiled = {}, {}

    def say(text):
        for bar in bars.values():
            bar.close()
        if not args.quiet:
            print(f"  {text}", file=sys.stderr)

    say("each method compiles its programs first (not counted in --time-limit)")

    def progress(method, tr, limit):
        # the bar (and its ETA) counts search seconds: it starts after an iteration that
        # compiled nothing (the first of this process always compiles or loads its programs),
        # its clock at the search seconds so far; while a method compiles, `say` said so
        fresh = compiled.get(method) == tr.compile_seconds
        compiled[method] = tr.compile_seconds
        bar = bars.get(method)
        if bar is None and fresh:
            bar = bars[method] = Progress(int(round(limit)), desc=f"  {method:8s}", unit="second",
                                          elapsed=tr.seconds, enabled=not args.quiet)
        if bar is not None:
            bar.update_to(min(int(tr.seconds), int(round(limit))),
                          f"best {worst.best_value(tr):.5g}, {tr.evaluations} evaluations")

    try:
        result = worst.worst_case(problem, methods=methods, seed=s.seed, out_dir=out,
                                  resume=args.resume, progress=progress, say=say, **search)
    finally:
        for bar in bars.values():
            bar.close()
    if not args.no_plot:
        say("writing worst_trajectory.npz, report.md and the figures")
    names = write(result, out, plots=not args.no_plot)
    print(f"  worst {problem.metric}: {verdict(result)} by {result.method} (nominal "
          f"{result.nominal_value:.6g})")
    print("\n".join(f"  {line}" for line in methods_table(result)))
    common.wrote(out, *names)
    return 0


def iteration_work(problem, methods, starts: int, batch: int, coarsening: int):
    """One iteration of the slowest of `methods` (`validation.Work`): the gradient method
    simulates its M starts and differentiates them on the loop at F dt; random sampling and
    CMA-ES simulate one batch."""
    n = problem.spec.n_steps
    works = [Work(steps=n + n // coarsening, member_steps=starts * (n + n // coarsening))
             if m == "gradient" else Work(steps=n, member_steps=batch * n) for m in methods]
    slowest = max(works, key=lambda w: w.seconds())
    if "gradient" in methods:
        slowest = slowest + common.gradient_work(problem.setup, n // coarsening, copies=starts)
    return slowest


def stored_work(problem):
    """What the search keeps besides its iterations: the waveform's basis on the half-step
    grid, and the worst case re-simulated at every step (worst_trajectory.npz, figures)."""
    n = problem.spec.n_steps
    _, per_point, size = common.loop_sizes(problem.setup)
    saved = Work(steps=2 * n, member_steps=2 * n, memory=3.0 * (n + 1) * per_point * size,
                 memory_what=f"the worst case's trajectory at every step ({n + 1:,} points)")
    basis = Work(memory=8.0 * (2 * n + 1) * problem.m, memory_what=f"the waveform's basis on "
                 f"the half-step grid ({2 * n + 1:,} x {problem.m})")
    return saved + basis


def worst_settings(args):
    """(WorstSettings, ranges): the config's [worst] table (and [worst.ranges]) laid over the
    defaults, then the options given (a refusal names the option)."""
    s = common.own_settings(args, worst.WorstSettings, "worst", skip=("ranges",))[0]
    table = common.config_data(args).get("worst", {})
    ranges = tuple(from_table(table["ranges"], "worst.ranges")) if "ranges" in table else ()
    if args.ranges:
        ranges = tuple(parse_range(text) for text in args.ranges)
    return s, ranges


def requirement_table(args, s) -> dict:
    """{NAME: [tuning.requirements.NAME] of --config, read and checked as the tuner reads it}
    of `--metric requirement:NAME` ({} for any other metric); ConfigError where --config has
    no such table (also under --print-config: the run could not start)."""
    if not s.metric.startswith(worst.REQUIREMENT):
        return {}
    from tuning.config import from_dict

    name = s.metric[len(worst.REQUIREMENT):]
    tables = from_dict(common.config_data(args).get("tuning", {})).requirements
    if name not in tables:
        raise ConfigError(f"--metric {s.metric}: --config has no [tuning.requirements."
                          f"{name}] table (has: {', '.join(tables) or 'none'})")
    return {name: tables[name]}


def resumable(args) -> bool:
    """Does --out hold a search that `--resume` continues (its manifest)?"""
    return (Path(args.out) / MANIFEST).exists()


def interrupt_hint(args) -> str | None:
    out = Path(args.out)
    states = sorted(out.glob("state_*.npz"))
    if not states or not resumable(args):
        return kept_text(args, OUTPUTS)
    return resume_text(args, f"the finished iterations are kept in {out} "
                             f"({', '.join(s.name for s in states)})")
