"""`dscjax sweep`: Monte-Carlo or grid robustness sweep: many plants simulated with the gains
fixed, and how well they track. A [sweep] table of --config may hold the settings
(docs/sweeps.md); the command line wins.

Writes into DIR: sweep.json (what was run), chunks/chunk_*.npz (one per finished block),
results.npz (one row per sample: parameters and metrics), summary.json, summary.md (the same for a
person, with the float32 trust flags of a float32 sweep), hist_linf_window.png,
heatmap_linf_window.png (or scan_linf_window.png for one parameter), traces.npz and
traces.png (the worst samples and a random handful, re-simulated with full trajectories).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from dscjax import config, files, params, sweep
from dscjax import settings as schema
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, nothing_kept, prepare_out, resume_text
from dscjax.params import DEFAULT_PATHS, DEFAULT_REL, assumption_warnings, parse_range
from dscjax.progress import Progress
from dscjax.runspec import Simulation
from dscjax.validation import ConfigError, Work, check_work

# Default threshold of "degraded" tracking: this many times the nominal setup's windowed error.
DEGRADED_FACTOR = 2.0
# the [simulation] keys this command takes as options
SWEEP_KEYS = ("t_final", "dt", "window_start", "solver", "refine", *common.SAMPLED_KEYS, "device")
OUTPUTS = Outputs((sweep.MANIFEST, "results.npz", "summary.json", "summary.md", "traces.npz",
                   "hist_linf_window.png", "heatmap_linf_window.png", "scan_linf_window.png",
                   "traces.png"), folders=("chunks",))


HELP = "Monte-Carlo / grid robustness sweep over plant and hysteresis parameters"


def add_options(p):
    names = ", ".join(path.split(".")[-1] for path in DEFAULT_PATHS)
    common.add_config_args(p, run_keys=SWEEP_KEYS, float32=False, table="sweep")
    p.add_argument("--gains", metavar="FILE", help="a config (e.g. tune's gains.json) whose "
                   "[controller] and sampled-controller [simulation] keys (sample_time, delay, "
                   "noise, ...) are laid over --config; the rest is ignored")
    axes = p.add_mutually_exclusive_group()
    axes.add_argument("--grid", action="append", metavar="PATH=LOW:HIGH:NUM",
                      help="full-factorial grid axis (repeat for more axes), e.g. "
                      "hysteresis.alpha=0.7:1.3:41")
    axes.add_argument("--range", action="append", dest="ranges",
                      metavar="PATH=LOW:HIGH|PATH=P%", help=f"a sampled parameter (repeat; "
                      f"replaces the default: {names} each +-{100 * DEFAULT_REL:g}%%), e.g. "
                      "plant.g[1]=0.8:1.2 or hysteresis.alpha=30%%")
    schema.add_arguments(p, sweep.SweepSettings, "sweep.")
    prec = p.add_mutually_exclusive_group()
    for dtype in ("float64", "float32"):
        prec.add_argument(f"--{dtype}", action="store_true",
                          help=f"run in {dtype} (default {sweep.SweepSettings.dtype})")
    add_out_arg(p, "results/sweep",
                resume="continue a sweep in DIR: skip the blocks already written",
                overwrite="discard a sweep in DIR and start afresh", plot="skip the PNG figures",
                quiet="no progress line")
    dist = p.add_argument_group("several hosts (run the same command on every host)")
    dist.add_argument("--distributed", action="store_true", help="call "
                      "jax.distributed.initialize() first (SLURM, Open MPI, ... auto-detected)")
    dist.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0 "
                      "(implies --distributed)")
    dist.add_argument("--num-processes", type=common.count(1), metavar="N",
                      help="number of processes")
    dist.add_argument("--process-id", type=common.count(0), metavar="I",
                      help="this process's index")


def load(args):
    """(setup, options, settings) from --config, --gains and the command line."""
    setup, options = common.checked_setup(args, *common.config_setup(args, gains=_gains))
    settings = sweep.settings_from_dict(common.config_data(args).get("sweep", {}))
    if args.grid and args.samples is not None:
        raise ConfigError("--samples cannot be used with --grid (a grid's size is the product "
                          "of its numbers of points)")
    settings, given, _ = common.own_settings(args, sweep.SweepSettings, "sweep", settings)
    changes = {}
    if args.grid:
        changes |= dict(method=params.Grid(), ranges=tuple(parse_range(g, grid=True)
                                                    for g in args.grid))
    elif (args.samples is not None or args.ranges or args.method) and settings.method.grid \
            and "method" not in given:
        changes |= dict(method=params.Uniform(), ranges=())
    if args.ranges:
        changes["ranges"] = tuple(parse_range(r) for r in args.ranges)
    if args.float64 or args.float32:
        changes["dtype"] = "float64" if args.float64 else "float32"
    return setup, options, dataclasses.replace(settings, **changes)


def _gains(args, setup, options):
    """(setup, options) with the gains file's gains and the loop they were tuned as laid
    over the config's: a gains.json of `dscjax tune` is a whole config, of which the sweep
    takes the [controller] table and the sampled controller's [simulation] keys
    (`SAMPLED_KEYS`: Ts, delay, noise, discretisation; absent ones at their defaults, so
    gains tuned continuous are swept continuous); its plant, hysteresis and horizon are the
    sweep's to choose. The command line still wins (`apply_run_options` afterwards)."""
    gains = config.read(args.gains, "--gains")
    if not isinstance(gains.get("controller"), dict):
        raise ConfigError(f"{args.gains}: no [controller] table (the gains) in the gains file")
    setup, _ = config.from_dict({"controller": gains["controller"]}, base=setup,
                                base_spec=options)
    loop = gains.get("simulation")
    if loop is None:  # gains alone: the config's loop
        return setup, options
    if not isinstance(loop, dict):
        raise ConfigError(f"{args.gains}: 'simulation' must be a table ([simulation])")
    config_loop = common.config_data(args).get("simulation", {})
    continuous = {k: getattr(Simulation(), k) for k in common.SAMPLED_KEYS}
    given = {k: loop[k] for k in common.SAMPLED_KEYS if k in loop}
    tuned = continuous | given  # the loop the gains were tuned as
    for key, value in tuned.items():
        if key in config_loop and config_loop[key] != value:
            common.say(args, "note", f"simulation.{key} = {config_loop[key]!r} in "
                       f"{args.config} gives way to {args.gains}'s {value!r} (the loop the "
                       f"gains were tuned as; --{key.replace('_', '-')} overrides both)")
    # the config's run with the sampled controller's keys the gains file's (checked)
    return setup, options.replace(names={k: f"simulation.{k} of --gains {args.gains}"
                                         for k in given}, **tuned)


def typed_settings(args) -> dict[str, str]:
    """{sweep.KEY: the option typed}, for the [sweep] keys given on the command line."""
    names = schema.given(args, sweep.SweepSettings, "sweep.")[1]
    return names | {f"sweep.{key}": option for dest, key, option in (
        ("grid", "grid", "--grid"), ("ranges", "ranges", "--range"),
        ("float32", "dtype", "--float32"), ("float64", "dtype", "--float64"))
        if getattr(args, dest, None)}


def work(settings, steps: int, ranges):
    """The sweep's work (`validation.check_work`): every sample over the horizon, the
    nominal setup and the re-simulated traces; its largest allocation, the results table."""
    # the sample's number, its parameters, metrics and status
    n = settings.n_samples()
    columns = 1 + len(ranges) + len(sweep.METRICS) + len(sweep.run.STATUS_COLUMNS)
    traces = 1 + settings.worst + settings.random  # re-simulated one after another
    return Work(steps=(1 + traces) * steps, member_steps=(n + traces) * steps,
                memory=8.0 * n * columns,
                memory_what=f"the results table ({n:,} samples x {columns} columns)")


def run(args) -> int:
    import jax

    if args.distributed or args.coordinator:
        # before anything touches a JAX backend
        jax.distributed.initialize(coordinator_address=args.coordinator,
                                   num_processes=args.num_processes, process_id=args.process_id)
    from dscjax.simulate import check, simulate

    setup, options, settings = load(args)
    n = settings.n_samples()
    printed = setup
    setup = params.cast(setup, settings.dtype)
    with common.blame_options(typed_settings(args)):
        ranges = sweep.check_settings(settings, setup, options)
    if args.print_config:
        return common.print_config(printed, options,
                                   {"sweep": sweep.settings.to_table(settings, setup)},
                                   groups={"sweep": settings})
    check(setup, options)
    check_work(work(settings, options.n_steps, ranges),
               what=f"{n:,} samples of "
               f"{common.horizon_text(options.t_final, float(options.dt), options.n_steps)}",
               fix="use fewer --samples, a shorter --t-final or a larger --dt")
    if args.resume:
        # a changed config: refused before anything is printed or run
        sweep.check_resumable(args.out, setup, settings, options)
    choice = common.choose_device(args, options.device, n)  # run_sweep places the blocks alike
    main = jax.process_index() == 0
    # several processes share --out: process 0 (which writes every file) takes the lock of
    # the directory and applies the rule of --out; process i > 0 takes a lock of its own
    out = prepare_out(args, OUTPUTS, resumable=True, check=main,
                      lock=files.LOCK if main else f"{files.LOCK}.{jax.process_index()}")
    warnings = assumption_warnings(setup, ranges, "sweep.grid" if settings.method.grid
                                   else "sweep.ranges")
    if main:
        scope = {"n_samples": n} | sweep.run.scope(settings, options, ranges)
        common.banner(args, f"{sweep.scope_text(scope)}; on {len(choice.devices)} device(s) "
                      f"({choice.platform}), {jax.process_count()} process(es) "
                      f"({choice.reason})", warnings)
    bar = None

    def progress(p):
        nonlocal bar
        if bar is None:  # after the first round, which compiled: the rate and the ETA are
            # timed from here on, so no ETA is shown before a round was timed alone
            bar = Progress(p["total"], desc="  sweep", unit="sample", initial=p["done"],
                           enabled=main and not args.quiet)
        bar.update_to(p["done"], f"{p['steps_per_s']:.3g} steps/s")

    try:
        result = sweep.run_sweep(setup, settings, options, out_dir=out, resume=args.resume,
                                 overwrite=args.overwrite, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    if not main:
        return 0
    info = result.info
    if info["samples_resumed"]:
        print(f"  resumed: {info['samples_resumed']:,} samples were already done",
              file=sys.stderr)
    c = result.columns
    every = max(1, -(-info["n_steps"] // 2000))  # at most 2001 saved points per trace
    nominal = simulate(setup, spec=options.replace(save_every=every), throw=False)
    nominal_metrics = {k: float(v) for k, v in nominal.metrics.items()}
    threshold, rule = settings.threshold, "given"
    if threshold is None:
        threshold, rule = default_threshold(bool(nominal.diverged),
                                            nominal_metrics["linf_error_window"], c)
    summary = sweep.summarize(result, nominal_metrics, threshold, worst=max(settings.worst, 1))
    summary["degraded"]["rule"] = rule
    summary["nominal"]["diverged"] = bool(nominal.diverged)
    summary |= {"nominal_params": {r.name: r.param.nominal(setup) for r in ranges},
                "run": info, "warnings": warnings}

    rows, kinds = sweep.trace_rows(c, settings.worst)
    rand_rows = sweep.random_rows(result.n, settings.random, settings.seed, exclude=rows)
    rows, kinds = [*rows, *rand_rows], kinds + ["random"] * len(rand_rows)
    trajs = sweep.simulate_rows(setup, result, rows, save_every=every)
    records = [sweep.sample_record(c, result.param_names, i) for i in rows]
    summary["traces"] = {"rows": [int(c["sample"][i]) for i in rows], "kinds": kinds,
                         "max_rel_diff_resimulated_vs_sweep": _recheck(trajs, records)}
    _write_traces(out / "traces.npz", trajs, records, kinds, nominal)
    f32 = None
    if settings.dtype == "float32":
        rechecked = sweep.check_rows(result, rows)
        print(f"  re-checking {len(rechecked)} rows in float64 (which metrics float32 can be "
              f"trusted with) ...", file=sys.stderr)
        f32 = sweep.float64_check(setup, result, rechecked)
    summary["float32_check"] = f32

    figures = [] if args.no_plot else _plots(out, result, settings, summary, trajs, records,
                                             kinds, nominal)
    files.write_json(out / "summary.json", summary)
    files.write_text(out / "summary.md", sweep.markdown(summary))

    took = (f"{info['steps_per_s']:.3g} steps/s incl. compilation" if info["steps_per_s"]
            else "nothing left to run")
    common.wrote(out, "results.npz", "summary.json", "summary.md", "traces.npz", *figures,
                 took=f"{info['wall_s']:.1f} s, {took}")
    for line in sweep.outcome(summary):
        print(f"  {line}")
    if f32 is not None and f32["untrusted"]:
        common.say(args, "warning", common.untrusted_text(
            f32["untrusted"], f32["max_rel_diff"], f32["rtol"], "rerun with --float64",
            on=f" on {len(f32['rows'])} re-checked rows"))
    return 0


def resumable(args) -> bool:
    """Does --out hold a sweep that `--resume` continues (its sweep.json)?"""
    return (Path(args.out) / sweep.MANIFEST).exists()


def interrupt_hint(args) -> str | None:
    import jax

    if jax.process_index() != 0:
        return None
    out = Path(args.out)
    if not resumable(args):
        return nothing_kept(args)
    n_done = len(list((out / "chunks").glob("chunk_*.npz")))
    return resume_text(args, f"{n_done} finished block(s) are kept in {out}/chunks")


def _recheck(trajs, records) -> dict[str, float] | None:
    """Per metric, the largest relative difference between the re-simulated and the swept
    values (float64: round-off; float32: a few sensitive plants amplify rounding):
    `float32_trust`'s, over the pairs where both are finite (the others count as NaN in both,
    a difference of 0, where `float32_trust` would give inf for one non-finite value)."""
    if not trajs:
        return None
    again = np.array([[float(tr.metrics[m]) for m in sweep.METRICS] for tr in trajs])
    swept = np.array([[rec["metrics"][m] for m in sweep.METRICS] for rec in records], float)
    both = np.isfinite(again) & np.isfinite(swept)
    pair = [dict(zip(sweep.METRICS, np.where(both, v, np.nan).T, strict=True))
            for v in (again, swept)]
    return sweep.float32_trust(*pair)["max_rel_diff"]


def default_threshold(nominal_diverged: bool, nominal_error: float,
                      columns) -> tuple[float, str]:
    """The threshold of "degraded" tracking when none is given, and its rule in words:
    DEGRADED_FACTOR x the nominal setup's windowed L-inf error; where the nominal setup
    diverged or its windowed error is 0, DEGRADED_FACTOR x the median over the samples that
    did not diverge (1 where none did)."""
    if not nominal_diverged and nominal_error > 0:
        return DEGRADED_FACTOR * nominal_error, f"{DEGRADED_FACTOR:g} x nominal"
    why = ("the nominal setup diverged" if nominal_diverged
           else "the nominal setup's windowed error is 0")
    ok = ~np.asarray(columns["diverged"], bool)
    if not ok.any():
        return 1.0, f"1 ({why}; every sample diverged)"
    median = float(np.median(columns["linf_error_window"][ok]))
    return DEGRADED_FACTOR * median, f"{DEGRADED_FACTOR:g} x median ({why})"


def _write_traces(path, trajs, records, kinds, nominal):
    arrays = {"nominal_t": nominal.t, "nominal_e": nominal.e, "nominal_u": nominal.u}
    if trajs:
        arrays |= {"sample": np.array([r["sample"] for r in records], dtype=np.int64),
                   "kind": np.array(kinds)}
        arrays |= {k: np.stack([np.asarray(getattr(t, k)) for t in trajs]) for k in "txeuw"}
        arrays["diverged"] = np.array([bool(t.diverged) for t in trajs])
    files.write_npz(path, arrays)


def _plots(out, result, settings, summary, trajs, records, kinds, nominal) -> list[str]:
    """The sweep's figures (their file names); the heatmap's cell statistics into `summary`."""
    from dscjax.sweep import plots as sp

    c, run, at = result.columns, summary["run"], summary["nominal_params"]
    err, div, refined = c["linf_error_window"], c["diverged"], c["refinements"] > 0
    shared = dict(t0=run["window_start"], t_final=run["t_final"],
                  threshold=summary["degraded"]["threshold"],
                  title=f"{result.n:,} {'grid points' if settings.method.grid else 'samples'}, "
                  f"T = {run['t_final']:g} s, dt = {run['dt']:g} s, {settings.dtype}")
    figures = ["hist_linf_window.png"]
    sp.plot_histogram(err, div, out / figures[0], nominal=summary["nominal"]["linf_error_window"],
                      refined=refined, **shared)
    names = result.param_names
    if len(names) >= 2:
        x, y = settings.heatmap or names[:2]
        grid = dict(grid_x=c[x], grid_y=c[y]) if settings.method.grid else {}
        figures.append("heatmap_linf_window.png")
        summary["heatmap"] = sp.plot_heatmap(c[x], c[y], err, div, out / figures[-1],
                                             names=(x, y), nominal_xy=(at[x], at[y]),
                                             refined=refined, **grid, **shared)
    else:
        figures.append("scan_linf_window.png")
        sp.plot_scan(c[names[0]], err, div, out / figures[-1], name=names[0],
                     nominal_x=at[names[0]], **shared)
    if trajs:
        figures.append("traces.png")
        labels = [sp.trace_label(r, names, k) for r, k in zip(records, kinds, strict=True)]
        counts = [f"{kinds.count(k)} {name}" for k, name in (
            ("worst", "worst tracking"), ("diverged", "first diverged"), ("random", "random"))
            if k in kinds]
        sp.plot_traces(trajs, labels, kinds, out / figures[-1], nominal=nominal,
                       t0=shared["t0"], title=", ".join(counts)
                       + f" samples of the sweep, re-simulated ({settings.dtype})")
    return figures
