"""`dscjax simulate`: simulate the closed loop of a config (default: the paper's Section 4
example) by fixed-step RK4 and write DIR/trajectory.npz, DIR/metrics.json and
DIR/trajectory.png. For the DSC, trajectory.npz also holds V, the Lyapunov function (44) of the
paper's Theorem 1, and its terms V_surface, V_filter, V_theta, V_phi, V_zeta, V_d, V_y (the
filter errors)."""

from __future__ import annotations

import sys
import time

import numpy as np

from dscjax import markdown, validation
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, add_overwrite_arg, prepare_out
from dscjax.controllers.dsc import DSC, VARIANTS
from dscjax.files import write_json, write_npz
from dscjax.params import cast
from dscjax.plotting import plot_trajectory
from dscjax.progress import Progress
from dscjax.reproduce.theory import lyapunov
from dscjax.runspec import MAX_SAVED_POINTS, loop_words
from dscjax.simulate import DivergenceError, check, divergence_report, refinement_level
from dscjax.sweep.summary import float32_trust
from dscjax.validation import fmt_bytes

OUTPUTS = Outputs(("trajectory.npz", "metrics.json", "trajectory.png"), at_end=True)
# the [simulation] keys this command takes as options
SIMULATE_KEYS = ("t_final", "dt", "save_every", "window_start", "solver", "refine",
                 *common.SAMPLED_KEYS, "device")


HELP = "simulate one closed loop (default: the paper's example)"


def add_options(p):
    common.add_config_args(p, run_keys=SIMULATE_KEYS)
    add_out_arg(p, "results/simulate", later=True)
    p.add_argument("--variant", choices=VARIANTS,
                   help="DSC variant: full, or without hysteresis compensation (d_hat = 0, or "
                   f"also zeta_hat = 1) (default controller.variant, {DSC.variant})")
    add_overwrite_arg(p, plot="skip trajectory.png")


def run(args) -> int:
    from dscjax.simulate import simulate

    # another command's own table (a printed config of tune or sweep) is that command's
    setup, options = common.load_setup(args)
    if args.print_config:
        return common.print_config(setup, options)

    check(setup, options)
    n_steps, every, n_points = options.n_steps, options.save_every, options.n_saved
    _, per_point, itemsize = common.loop_sizes(setup)
    nbytes = n_points * per_point * itemsize
    validation.check_work(validation.Work(
        steps=n_steps, member_steps=n_steps, memory=MEMORY_FACTOR * nbytes,
        memory_what=f"the saved trajectory (simulation.save_every = {every} keeps "
        f"{n_points:,} points, {fmt_bytes(nbytes)}; {MEMORY_FACTOR}x that while written)"),
        what=common.horizon_text(options.t_final, options.dt, n_steps),
        fix="use a larger --save-every (or omit it: the automatic stride), or a shorter --t-final")
    warnings = validation.assumption_warnings(setup)
    choice = common.choose_device(args, options.device)  # simulate() places the run alike

    out = prepare_out(args, OUTPUTS)
    c = setup.controller
    loop = (f"{c.kind.upper()} ({getattr(c, 'variant', '-')}), n={setup.order}, "
            f"dt={options.dt:g} s, {options.dtype}")
    common.banner(args, f"{loop}, T={options.t_final:g} s ({n_steps:,} steps), "
                  f"{loop_words(options)}; on {choice}", warnings)
    if "save_every" in options.rules and every > 1:
        print(f"  saving one step in {every:,} and the last: {n_points:,} points (the automatic "
              f"stride, at most {MAX_SAVED_POINTS:,}); the metrics use every step", file=sys.stderr)
    if nbytes > BIG_FILE:
        print(f"  trajectory.npz will take about {fmt_bytes(nbytes)} ({n_points:,} points)",
              file=sys.stderr)
    bar = Progress(n_steps, desc="  simulated", unit="step",
                   enabled=n_steps >= PROGRESS_MIN_STEPS)

    def progress(frac: float) -> None:
        if frac == 0.0:
            bar.restart_clock()  # the loop starts now: compilation is over
        bar.update_to(round(frac * n_steps),
                      f"t = {frac * options.t_final:.4g} of {options.t_final:g} s")

    t0 = time.perf_counter()
    diverged = None
    with bar:  # progress (a callback from the loop) for a long run only
        try:
            traj = simulate(setup, spec=options, progress=progress if bar.enabled else None)
        except DivergenceError as err:
            traj, diverged = err.trajectory, err
    elapsed = time.perf_counter() - t0

    arrays = {k: getattr(traj, k) for k in ("t", "x", "u", "w", "yr", "e", "S", "u_dot")}
    arrays |= traj.ctrl._asdict() if hasattr(traj.ctrl, "_fields") else {}
    if setup.controller.kind == "dsc":
        lv = lyapunov(setup, traj)  # V of eq. (44) and its terms, true plant parameters
        arrays |= {"V": lv.V} | {f"V_{k}": v for k, v in lv.arrays().items()
                                 if k not in ("t", "V")}
    write_npz(out / "trajectory.npz", arrays)
    metrics = {k: float(v) for k, v in traj.metrics.items()}
    f32 = None
    if options.dtype == "float32" and diverged is None:
        print("  re-checking in float64 (which metrics float32 can be trusted with) ...",
              file=sys.stderr)
        f32 = _float64_check(setup, options, metrics)
        if f32["untrusted"]:
            warnings = [*warnings, common.untrusted_text(
                f32["untrusted"], f32["rel_diff"], f32["rtol"], "rerun without --float32")]
    report = divergence_report(traj, float(options.state_bound))
    used = refinement_level(int(traj.refinements), options.solver)[0].name
    write_json(out / "metrics.json", {
        **metrics,
        "diverged": bool(traj.diverged),
        "t_diverged": float(traj.t_diverged) if bool(traj.diverged) else None,
        "divergence": report[0] if report else None,
        "t_final": options.t_final, "dt": float(options.dt), "dtype": options.dtype,
        "save_every": every, "sample_time": options.sample_time, "solver": options.solver.name,
        "refinements": int(traj.refinements), "solver_used": used, "dt_used": float(traj.dt),
        "window_start": float(options.window_start),
        **({"V_max": float(np.max(arrays["V"])), "V_final": float(np.asarray(arrays["V"])[-1])}
           if "V" in arrays else {}),
        "wall_time_s": elapsed, "warnings": warnings, "float32_check": f32,
    })
    if not args.no_plot:
        sampled = f", sampled every {options.sample_time:g} s" if options.sampled else ""
        plot_trajectory(traj, out / "trajectory.png", title=loop + sampled)
    common.wrote(out, "trajectory.npz", "metrics.json",
                 None if args.no_plot else "trajectory.png", took=f"{elapsed:.2f} s")
    if int(traj.refinements) and not (options.sampled and diverged is not None):
        # (a sampled loop refined and still diverged: the error's line says why)
        what = "diverged at every level down to" if diverged else "the reported run is"
        print(f"  {options.solver.name} at dt = {options.dt:g} s diverged (a stiff loop: the "
              f"hysteresis rate alpha |u'| or the filters 1/tau); refined: {what} {used} at "
              f"dt = {float(traj.dt):g} s", file=sys.stderr)
    if diverged is None:
        window = markdown.window(options.window_start, options.t_final)
        print(f"  L-inf error on {window} {metrics['linf_error_window']:.4g} (over the whole "
              f"run {metrics['linf_error']:.4g}, from the initial error), L2 error "
              f"{metrics['l2_error']:.4g}, max|u| {metrics['max_abs_u']:.4g}; "
              + common.effort_text(metrics, window))
    else:
        print(f"  no metrics: the run diverged at t = {float(traj.t_diverged):.6g} s, so they "
              f"were not measured (null in metrics.json)")
    if f32 is not None and f32["untrusted"]:
        common.say(args, "warning", warnings[-1])
    if diverged is not None:
        raise diverged
    return 0


def _float64_check(setup, options, metrics: dict[str, float]) -> dict:
    """The float32 run's metrics against the same loop in float64 (the float32 numbers, the
    arithmetic in float64): `dscjax.sweep.float32_trust`, the check of a float32 sweep, with
    the float64 values."""
    from dscjax.simulate import simulate

    ref = simulate(cast(setup, np.float64), throw=False,
                   spec=options.replace(dtype="float64", save_every=options.n_steps))
    float64 = {m: float(ref.metrics[m]) for m in metrics}
    trust = float32_trust(metrics, float64)
    return {"rtol": trust["rtol"], "float64": float64, "rel_diff": trust["max_rel_diff"],
            "untrusted": trust["untrusted"]}


PROGRESS_MIN_STEPS = 1_000_000  # a run of at least this many steps shows progress
BIG_FILE = 256 * 2**20  # a trajectory.npz above this size is announced before the run
# Peak memory of a saved trajectory in multiples of its size: the result, its host copy and the
# npz being written
MEMORY_FACTOR = 3
