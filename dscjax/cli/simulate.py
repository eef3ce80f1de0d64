"""`dscjax simulate`: run one closed loop, write trajectory.npz, metrics.json, trajectory.png."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from dscjax.cli.common import add_config_args, load_setup, write_json


def add_parser(sub):
    p = sub.add_parser(
        "simulate", help="simulate one closed loop (default: the paper's example)",
        description="Simulate the closed loop of a config (default: the paper's Section 4 "
        "example) by fixed-step RK4 and write DIR/trajectory.npz, DIR/metrics.json and "
        "DIR/trajectory.png. For the DSC, trajectory.npz also holds V, the Lyapunov function "
        "(44) of the paper's Theorem 1, and its terms V_surface, V_filter, V_theta, V_phi, "
        "V_zeta, V_d, V_y (the filter errors).")
    add_config_args(p)
    p.add_argument("--out", default="results/simulate", metavar="DIR",
                   help="output directory (default: results/simulate)")
    p.add_argument("--save-every", type=int, metavar="K", help="keep every K-th step")
    p.add_argument("--variant", choices=("full", "no_dhat", "no_dhat_no_zeta"),
                   help="DSC variant: full, or without hysteresis compensation (d_hat = 0; or "
                   "also zeta_hat = 1)")
    p.add_argument("--no-plot", action="store_true", help="skip trajectory.png")
    p.add_argument("--print-config", action="store_true",
                   help="print the effective config as TOML and exit")
    return p


def run(args) -> int:
    from dscjax import config
    from dscjax.simulate import DivergenceError, divergence_report, simulate

    if args.save_every is not None:
        from dscjax import validation

        validation.integer(args.save_every, "--save-every", 1)
    setup, options = load_setup(args)
    if args.save_every is not None:
        import dataclasses

        options = dataclasses.replace(options, save_every=args.save_every)
    if args.print_config:
        sys.stdout.write(config.dumps_toml(config.to_dict(setup, options)))
        return 0

    out = Path(args.out)
    n = setup.order
    print(f"dscjax simulate: order n={n}, {setup.controller.kind} "
          f"(variant {getattr(setup.controller, 'variant', '-')}), T={options.t_final:g} s, "
          f"dt={options.dt:g} s, {options.dtype}", file=sys.stderr)
    t0 = time.perf_counter()
    diverged = None
    try:
        traj = simulate(setup, options.t_final, options.dt, save_every=options.save_every,
                        window_start=options.window_start, state_bound=options.state_bound)
    except DivergenceError as err:
        traj, diverged = err.trajectory, err
    elapsed = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)

    arrays = {"t": traj.t, "x": traj.x, "u": traj.u, "w": traj.w, "yr": traj.yr, "e": traj.e,
              "S": traj.S, "u_dot": traj.u_dot}
    if hasattr(traj.ctrl, "_fields"):
        arrays |= {name: getattr(traj.ctrl, name) for name in traj.ctrl._fields}
    if setup.controller.kind == "dsc":
        from dscjax.theory import lyapunov

        lv = lyapunov(setup, traj)  # V of eq. (44) and its terms, true plant parameters
        arrays |= {"V": lv.V} | {f"V_{k}": v for k, v in lv.arrays().items()
                                 if k not in ("t", "V")}
    np.savez(out / "trajectory.npz", **{k: np.asarray(v) for k, v in arrays.items()})
    metrics = {k: float(v) for k, v in traj.metrics.items()}
    report = divergence_report(traj, options.state_bound)
    write_json(out / "metrics.json", {
        **metrics,
        "diverged": bool(traj.diverged),
        "t_diverged": float(traj.t_diverged) if bool(traj.diverged) else None,
        "divergence": report[0] if report else None,
        "t_final": options.t_final, "dt": options.dt, "dtype": options.dtype,
        "window_start": float(options.window_start if options.window_start is not None
                              else (1.0 if options.t_final > 1.0 else 0.0)),
        **({"V_max": float(np.max(arrays["V"])), "V_final": float(np.asarray(arrays["V"])[-1])}
           if "V" in arrays else {}),
        "wall_time_s": elapsed,
    })
    if not args.no_plot:
        from dscjax.plotting import plot_trajectory

        plot_trajectory(traj, out / "trajectory.png", title=_title(setup, options))
    print(f"  wrote {out}/trajectory.npz, metrics.json"
          + ("" if args.no_plot else ", trajectory.png") + f" ({elapsed:.2f} s)", file=sys.stderr)
    print(f"  L-inf error {metrics['linf_error']:.4g} "
          f"(after t0: {metrics['linf_error_window']:.4g}),"
          f" L2 error {metrics['l2_error']:.4g}, max|u| {metrics['max_abs_u']:.4g}",
          file=sys.stderr)
    if diverged is not None:
        raise diverged
    return 0


def _title(setup, options):
    c = setup.controller
    return (f"{c.kind.upper()} ({getattr(c, 'variant', '')}), n={setup.order}, "
            f"dt={options.dt:g} s, {options.dtype}")
