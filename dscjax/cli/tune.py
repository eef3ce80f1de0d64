"""`dscjax tune`: tune controller gains through the closed loop (CMA-ES by default, or
exact gradients). Writes into DIR gains.json (the tuned gains as a config; report.md's last
line and the console's give the `dscjax simulate` command that runs the loop tuned from it),
history.csv, report.md, report.json, the figures and the checkpoint files `--resume` reads.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from dscjax import config, files
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, add_overwrite_arg, kept_text, prepare_out
from dscjax.progress import Phase, Progress
from dscjax.runspec import RunSpec
from dscjax.settings import add_arguments
from dscjax.validation import TIME_LIMIT_S, ConfigError, Work, check_work, fmt_seconds
from tuning.config import SIMULATION, TuningConfig, to_table
from tuning.config import from_dict as tuning_from_dict

OUTPUTS = Outputs(("gains.json", "history.csv", "report.md", "report.json", "loss_curve.png",
                   "before_after.png", "heldout.png", "sampling.png", "checkpoint.npz",
                   "search.npz", "checkpoint.json", "best.json", "adversarial.json"),
                  folders=("round_*", "fresh_*"))


HELP = "tune the controller gains (CMA-ES by default; exact-gradient methods)"
# --help's description, shorter than the module's docstring
DESCRIPTION = ("Tune the DSC gains of a config (default: the paper's example sampled at 1 kHz) "
               "to minimise the windowed L-inf error, max|u| and TV(u) bounded by the start "
               "gains' (TV(u) x 1.5). Settings: [tuning] (docs/tuning.md); the command line "
               "wins.")


def add_options(p):
    common.add_config_args(p, run_keys=("t_final", "dt", *common.SAMPLED_KEYS, "device"),
                           float32=False, defaults=SIMULATION, table="tuning")
    p.add_argument("--tuning", metavar="FILE", help="TOML (or JSON) file with a [tuning] table "
                   "(laid over the one in --config)")
    p.add_argument("--gains", metavar="FILE", help="start from the gains of this config, e.g. "
                   "the gains.json of an earlier run (laid over --config, its plant and loop too)")
    add_out_arg(p, "results/tune", later=True)
    add_arguments(p, TuningConfig, "tuning.")
    add_overwrite_arg(p, resume="continue the run in DIR from its checkpoint (iteration "
                      "count, optimiser state and best point)",
                      overwrite="discard a run in DIR and start afresh",
                      plot="skip the PNG figures", quiet="no progress line")


def resumable(args) -> bool:
    """Does --out hold a run that `--resume` continues (its checkpoint, or the record of the
    adversarial rounds)?"""
    from tuning.runner import RECORDS

    return any((Path(args.out) / name).exists() for name in RECORDS)


def interrupt_hint(args) -> str:
    from dscjax.cli.out import resume_text
    from tuning.checkpoint import RECORD
    from tuning.runner import MANIFEST

    if (Path(args.out) / MANIFEST).exists():
        return resume_text(args, f"the finished rounds and searches are kept in {args.out}")
    try:
        meta = files.read_json(Path(args.out) / RECORD)
    except ValueError:  # missing or unreadable (a ConfigError)
        return kept_text(args, OUTPUTS)
    return resume_text(args, f"the checkpoint (iteration {meta.get('iteration')}, best loss "
                       f"{meta.get('best_loss', float('nan')):.4g}) is kept in {args.out}")


def load(args):
    """(setup, options, TuningConfig) from --config, --tuning, --gains and the command line."""
    setup, options = common.load_setup(args, RunSpec.make(**SIMULATION), common.whole_config)
    if options.dtype != "float64":
        raise ConfigError("dscjax tune runs in float64 (simulation.dtype = \"float32\" is for "
                          "sweeps)")
    cfg = tuning_from_dict(common.config_data(args).get("tuning", {}))
    if args.tuning:
        extra = config.read(args.tuning, "--tuning")
        unknown = set(extra) - {"tuning"}
        if unknown:
            raise ConfigError(f"{args.tuning}: a --tuning file holds only a [tuning] table "
                              f"(got {', '.join(sorted(unknown))})")
        cfg = tuning_from_dict(extra.get("tuning", {}), cfg)
    cfg, given, names = common.own_settings(args, TuningConfig, "tuning", cfg)
    search = [names[f"tuning.adversarial.{k}"] for k in given.get("adversarial", {})
              if k != "rounds"]
    if search and not cfg.adversarial.rounds:
        raise ConfigError(f"{search[0]} applies to adversarial tuning: give --adversarial R "
                          f"with R >= 1 (or [tuning.adversarial] rounds)")
    return setup, options, cfg


def run(args) -> int:
    t_start = time.perf_counter()
    from tuning import elasticity, margins, report, report_md
    from tuning.checkpoint import format_progress
    from tuning.runner import build_problem, check_resume, model_default_ranges, simulate_command
    from tuning.runner import run as run_tuning

    setup, options, cfg = load(args)
    if args.print_config:
        return common.print_config(setup, options,
                                   {"tuning": to_table(model_default_ranges(cfg, setup), setup)},
                                   groups={"tuning": cfg})
    # the trajectories of one generation (its first population) or iteration, run together
    rows = check_work_of(args, setup, options, cfg)
    out = Path(args.out)
    adv = cfg.adversarial
    if adv.rounds:
        from tuning import adversarial

        # the zero waveform the training plants' disturbances replace (one compiled structure)
        searched = adversarial.search_problem(setup, options, cfg)
        setup = searched.setup
    if args.resume:  # nothing to resume or a changed config: refused before anything runs
        (adversarial.check_resume if adv.rounds else check_resume)(out, setup, options, cfg)
    # before build_problem, whose start scales run the loop; a refusal writes nothing
    oc, plants = cfg.optimizer, max(cfg.robust.batch, 1)
    choice = common.use_device(args, options.device, rows)
    # --out once every setting is validated, before the start scales compile and run the loop
    with Phase(f"  compiling the closed loop and measuring the start gains ({plants} "
               f"plant{'s' if plants > 1 else ''})", enabled=not args.quiet):
        problem = build_problem(setup, options, cfg,
                                ready=lambda: prepare_out(args, OUTPUTS, resumable=True))
    unit = "generation" if oc.name.generations else "iteration"
    limits = [f"{oc.max_steps} {unit}(s)"] if oc.max_steps is not None else []
    limits += [f"{oc.time_limit:g} s"] if oc.time_limit else []
    # (the loop tuned is one of the notes below)
    common.banner(args, f"{report.problem_sentence(problem)} {report_md.method_text(problem)} "
                  + ("At most " + " or ".join(limits) if limits else "No iteration or time limit")
                  + (f" per round; {adv.rounds} adversarial rounds over "
                     + ", ".join(r.spec() for r in searched.ranges)
                     + (f" and {adv.disturbance}" if adv.disturbance else "")
                     + f" ({adv.method} search, {adv.search_time:g} s each)" if adv.rounds
                     else "") + f"; on {choice}")
    parts = ([f"the held-out check ({cfg.heldout.batch} plants, start and tuned gains)",
              "the margins", "the constraints' sensitivities"] if cfg.heldout.batch else [])
    parts += [] if args.no_plot else ["the figures"]
    after = " and ".join([", ".join(parts[:-1]), parts[-1]] if len(parts) > 1 else parts)
    if after:
        print(f"  {after} come after the search"
              + (f"; the time limit ({oc.time_limit:g} s) bounds the search only"
                 if oc.time_limit else ""), file=sys.stderr)
    for note in problem.notes:
        print(f"  note: {note}", file=sys.stderr)
    common.say(args, "warning", *report.assumption_warnings(problem))
    start = problem.scales.start
    shown = [k for k in ("linf_error_window", "user_linf_error_window", "max_abs_u", "tv_u",
                         "max_abs_u_window", "tv_u_window") if k in start]
    # labelled as report.md's nominal table labels them
    shifted = {"shifted_reference": "user_linf_error_window" in start}
    print("  start gains: " + ", ".join(f"{report_md.label(k, shifted)} {start[k]:.4g}"
                                        for k in shown), file=sys.stderr)
    bar, bar_round = None, None
    # until the first generation (or iteration) ends: its compilation and run
    first = Phase(f"  compiling the {'search' if oc.name.generations else 'gradient'} and "
                  f"running its first {unit}", enabled=not args.quiet).start()

    def close():  # the first unit's phase, then the bar of the round done
        nonlocal bar
        first.stop()
        if bar is not None:
            bar.close()
            bar = None

    def progress(row):
        nonlocal bar, bar_round
        if bar is None or row.get("round") != bar_round:
            close()
            bar_round = row.get("round")
            # the unit just done counts as done before the clock (its time was compilation)
            bar = Progress(row["steps"], desc="  tune" if bar_round is None else
                           f"  round {bar_round} tune", unit=unit,
                           initial=row["iteration"] + 1, enabled=not args.quiet)
        bar.update_to(row["iteration"] + 1, format_progress(
            row, "sigma" if oc.name.generations else "lr"))

    def say(text):
        close()  # a round's search says what it does itself
        print(f"  {text}", file=sys.stderr)

    outcome = None
    try:
        if adv.rounds:
            outcome = adversarial.run(setup, options, cfg, out, resume=args.resume,
                                      overwrite=args.overwrite, progress=progress, say=say)
            result = outcome.result
        else:
            result = run_tuning(problem, out, resume=args.resume, overwrite=args.overwrite,
                                progress=progress)
    finally:
        close()
    print(f"  {report_md.run_sentence(report.run_record(result))}")
    with Phase(f"  {after}" if after else "  the report", enabled=not args.quiet):
        summary = report.write(out, result, plots=not args.no_plot, t_start=t_start)
    if outcome is not None:
        adversarial.add_to_report(out, summary, outcome)
        print(f"  {adversarial.fresh_sentence(summary['adversarial'])}")
    # the headlines of report.md, which has every figure
    n0, n1 = summary["nominal"]["start"], summary["nominal"]["tuned"]
    for key in [k for k in ("linf_error_window", "user_linf_error_window") if k in n0]:
        a, b = n0[key], n1[key]
        print(f"  nominal plant, {report_md.label(key, summary)}: {a:.4g} -> {b:.4g} "
              f"({a / max(b, 1e-300):.3g}x lower)")
    sens = {r["name"]: r for r in (summary.get("sensitivity") or {}).get("rows", [])}
    for c in summary["constraints"]["tuned"]:
        top = sens.get(c["name"], {}).get("largest")
        print(f"  constraint {c['name']} <= {c['bound']:.6g}: {'met' if c['met'] else 'VIOLATED'}"
              f" (tuned {c['value']:.6g}, margin {c['margin']:.4g}, "
              f"{100 * c['relative_margin']:.3g} %)"
              + ("" if top is None else f"; most sensitive to {top['number']} (elasticity "
                 f"{elasticity.text(top['elasticity'])})"))
    if "heldout" in summary:
        print(f"  {report_md.batch_counts(summary)}")
    for line in margins.verdicts(summary["margins"]) if summary["margins"] else []:
        print(f"  {line}")
    common.say(args, "WARNING", *report_md.warnings(summary))
    print(f"  run the loop tuned: {simulate_command(result.problem, str(out / 'gains.json'))}")
    rounds = ("adversarial.json", "round_*/ (each round's tuning run and search)", "fresh_*/")
    common.wrote(out, "gains.json", *(rounds if outcome is not None else ["history.csv"]),
                 "report.md", "report.json", *summary["figures"],
                 took=f"{time.perf_counter() - t_start:.1f} s in all")
    return 0


# consecutive steps of the margins in units of the tuning's steps, at most: the Ts sweep's
# continuous run and three sample times at dt/10 and two at dt, the long run of 10 x T, the
# delays (tuning.margins.DELAY_MAX runs)
MARGIN_STEPS = 4 * 10 + 2 + 10 + 4


def check_work_of(args, setup, options, cfg) -> int:
    """`validation.check_work` for a tuning run, before any of it: one generation (or
    iteration) within the time limit, and what follows the search (the held-out check, the
    figures) within the rest of a day. Lower bounds: a default population of at least 4.
    Returns the trajectories one generation (its first population) or iteration runs."""
    from tuning.optimize import Plants

    steps = options.n_steps
    oc, plants = cfg.optimizer, max(cfg.robust.batch, 1)
    what = common.horizon_text(options.t_final, options.dt, steps)
    if oc.name.generations:
        width = oc.population(plants, 1)
        rows = width * plants
        one = Work(steps=steps, member_steps=rows * steps)
        unit = f"generation ({width} candidates x {plants} plant(s))"
    else:
        rows = plants
        one = Work(steps=2 * steps, member_steps=2 * plants * steps)
        unit = f"iteration ({plants} plant(s), a value and a gradient)"
        if plants == 1 or isinstance(oc.gradient.chosen(0, plants, cfg.robust.over), Plants):
            one = one + common.gradient_work(setup, steps)  # time-parallel
    fix, limit = common.SHORTER, {}
    if oc.time_limit:
        name = "--time-limit" if args.time_limit is not None else "tuning.optimizer.time_limit"
        fix += f", or a larger {name}"
        limit = {"limit_s": oc.time_limit, "limit": f"{name} {oc.time_limit:g} s"}
    check_work(one, what=f"one {unit} of {what}", fix=fix, **limit)
    # after the search: start and tuned gains on the training and held-out batches, figures
    after = Work(steps=6 * steps, member_steps=2 * (plants + cfg.heldout.batch + 2) * steps)
    if cfg.heldout.batch:  # the margins (tuning.margins), each a batch of the two gain sets
        after = after + Work(steps=MARGIN_STEPS * steps, member_steps=2 * MARGIN_STEPS * steps)
        # the held-out batch with both gain sets at 2 x Ts
        after = after + Work(steps=steps, member_steps=2 * cfg.heldout.batch * steps)
        # the constraints' elasticities: a time-parallel gradient of each loop (the loop tuned
        # and the other discretisation's)
        after = after + common.gradient_work(setup, steps, copies=2)
    left = TIME_LIMIT_S - (oc.time_limit or 0.0)
    check_work(after, what=f"the held-out check and figures after the search ({what})",
               fix=common.SHORTER, limit_s=left,
               limit=f"the {fmt_seconds(left)} a day leaves after the search")
    return rows
