"""`dscjax stability`: which dt does classical RK4 need for a config, before a run.

Runs the loop at steps dt * 2^k (k = -4..4) for filter constants tau * scale, reports where
classical RK4 stays finite, bisects the largest stable dt at the config's tau, and compares it
with the linear guide 2.785 / max spectral radius of the closed loop's Jacobian along the
nominal run. Writes DIR/stability.json and DIR/stability.png (the (tau, dt) region, the
config's point, both steps) and prints the table.
"""

from __future__ import annotations

import sys

import numpy as np

from dscjax import files, validation
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, start

OUTPUTS = Outputs(("stability.json", "stability.png"))


HELP = "the largest stable RK4 step of a config and its (tau, dt) region"


def add_options(p):
    common.add_config_args(p, run_keys=("t_final", "dt", "device"))
    p.add_argument("--tau-scales", default="0.25,0.5,1,2,4", metavar="A,B,...",
                   help="factors applied to every filter constant tau_i, separated by commas "
                   "(default %(default)s)")
    add_out_arg(p, "results/stability", plot="skip stability.png")


def run(args) -> int:
    from dscjax.step_size import DT_FACTORS, map_steps, stability_map

    setup, options = common.load_setup(args)
    scales = sorted(common.positive_numbers(args.tau_scales, "--tau-scales"))
    validation.check_filters(setup, float(options.dt))
    if args.print_config:
        return common.print_config(setup, options)
    what = common.horizon_text(options.t_final, options.dt, options.n_steps)
    # one batch over the tau scales per step size (`map_steps`)
    counts = map_steps(options.t_final, float(options.dt),
                       [float(options.dt) * f for f in DT_FACTORS])
    if max(counts) > validation.MAX_STEPS:
        raise validation.ConfigError(
            f"{what}: the map's finest step, dt * {min(DT_FACTORS):g}, needs {max(counts):,} "
            f"steps, more than the {validation.MAX_STEPS:,} the integrator's step counter "
            f"holds; {common.SHORTER}")
    validation.check_work(validation.Work(steps=sum(counts), member_steps=len(scales)
                                          * sum(counts)), what=what, fix=common.SHORTER)
    out = start(args, OUTPUTS, f"{options.t_final:g} s, dt = {options.dt:g} s, tau x "
                f"{', '.join(f'{s:g}' for s in scales)}", options.device, len(scales))
    m = stability_map(setup, options.t_final, float(options.dt), tau_scales=scales,
                      log=lambda s: print(s, file=sys.stderr))
    bound, tried = (">= ", " (every step tried was stable)") if m.beyond_grid else ("", "")
    verdict = "stable" if m.requested_dt <= m.largest_stable_dt else "UNSTABLE"
    print(f"largest stable dt for classical RK4 at this config's tau: {bound}"
          f"{m.largest_stable_dt:.4g} s{tried} (requested {m.requested_dt:g} s: {verdict})")
    print(f"linear guide 2.785 / max spectral radius along the nominal run: {m.linear_dt:.4g} s "
          f"(the radius peaks at t = {m.t_peak:.4g} s; conservative: short bursts beyond it "
          f"are often survived)")
    head = "tau_min \\ dt" if np.isfinite(m.tau).any() else "dt"
    print(f"{head:>14} " + " ".join(f"{d:>9.3g}" for d in m.dt))
    for i in range(len(m.tau_scale)):
        label = f"{m.tau[i]:.4g}" if np.isfinite(m.tau[i]) else "-"
        print(f"{label:>14} " + " ".join(f"{'ok' if ok else 'div':>9}" for ok in m.stable[i]))
    data = m._asdict()
    data["tau_min"] = data.pop("tau")
    files.write_json(out / "stability.json", {"t_final": options.t_final, **data})
    if not args.no_plot:
        _plot(m, out / "stability.png")
    common.wrote(out, "stability.json", None if args.no_plot else "stability.png")
    return 0


def _plot(m, path):
    from dscjax.plotting import legend_below, saved

    has_tau = np.isfinite(m.tau).any()
    y = m.tau if has_tau else np.ones(1)
    dts, ys = np.meshgrid(m.dt, y)
    own = y[int(np.argmin(np.abs(m.tau_scale - 1.0)))]
    with saved(path, 120, figsize=(6.4, 5.0)) as (fig, ax):
        ax.scatter(dts[m.stable], ys[m.stable], marker="o", color="tab:green",
                   label="RK4 stays finite")
        ax.scatter(dts[~m.stable], ys[~m.stable], marker="x", color="tab:red", label="RK4 diverges")
        ax.scatter([m.requested_dt], [own], s=140, facecolors="none", edgecolors="k",
                   label=f"this config (dt = {m.requested_dt:g} s)")
        if np.isfinite(m.largest_stable_dt):
            ax.axvline(m.largest_stable_dt, color="tab:green", ls="--", lw=1,
                       label=f"largest stable dt {'>= ' if m.beyond_grid else ''}"
                       f"{m.largest_stable_dt:.3g} s" + ("" if m.beyond_grid else " (bisected)"))
        if np.isfinite(m.linear_dt):
            ax.axvline(m.linear_dt, color="tab:blue", ls=":", lw=1,
                       label=f"linear guide 2.785/max rho = {m.linear_dt:.3g} s")
        ax.set_xscale("log")
        if has_tau:
            ax.set_yscale("log")
            ax.set_ylabel("smallest filter constant tau [s]")
        else:
            ax.set_yticks([])
        ax.set_xlabel("RK4 step dt [s]")
        ax.set_title("Where classical RK4 stays finite over the horizon")
        legend_below(fig, ax, 2, fontsize=7)
