"""`dscjax hysteresis`: a hysteresis model alone, driven open-loop by u = A sin(omega t).

Writes DIR/loop.npz (t (N+1,), u and w (K, N+1) on the step grid, one row per amplitude, and
`amplitude` (K,), `omega`, `kind`) and DIR/loop.png (w against u, one panel per amplitude, with
the lines w = lam u + d_1 limits). Without options: the paper's Fig. 1 (backlash-like model (4),
amplitudes 3.5 and 6.5, omega = 2.3, three periods).
"""

from __future__ import annotations

import math
import sys

import numpy as np

from dscjax.cli.common import Outputs, add_example_arg, add_overwrite_arg, prepare_out

DEFAULT_AMPLITUDES = (3.5, 6.5)  # the paper's Fig. 1
DEFAULT_OMEGA = 2.3
OUTPUTS = Outputs(("loop.npz", "loop.png"))


def add_parser(sub):
    p = sub.add_parser(
        "hysteresis", help="a hysteresis model alone: w(t) and its loop for u = A sin(omega t)",
        description="Drive the config's hysteresis model (hysteresis.kind: backlash, pi, gpi, "
        "bouc_wen) open-loop by u(t) = amplitude sin(omega t) with the closed loop's RK4 (and "
        "the play operators' exact clamp); write DIR/loop.npz (t, u, w on the step grid) and "
        "DIR/loop.png (w against u). Default: the paper's Fig. 1.")
    p.add_argument("--config", metavar="FILE", help="TOML (or JSON) config; only its "
                   "[hysteresis] table is used (default: the --example's)")
    add_example_arg(p)
    p.add_argument("--amplitude", type=float, action="append", metavar="A",
                   help="input amplitude; repeat for several loops (default 3.5 and 6.5)")
    p.add_argument("--omega", type=float, default=DEFAULT_OMEGA, metavar="W",
                   help=f"input frequency [rad/s] (default {DEFAULT_OMEGA:g})")
    p.add_argument("--t-final", type=float, metavar="T",
                   help="horizon [s] (default three periods 6 pi / omega, on the dt grid)")
    p.add_argument("--dt", type=float, default=1e-3, metavar="DT", help="RK4 step [s] "
                   "(default 1e-3)")
    p.add_argument("--out", default="results/hysteresis", metavar="DIR",
                   help="output directory (default results/hysteresis)")
    add_overwrite_arg(p)
    return p


def run(args) -> int:
    from dscjax import config, validation
    from dscjax.cli.common import example_setup
    from dscjax.files import write_npz
    from dscjax.hysteresis import sine_loops

    amplitudes = tuple(args.amplitude or DEFAULT_AMPLITUDES)
    for a in amplitudes:
        validation.finite(a, "--amplitude")
    validation.finite(args.omega, "--omega")
    validation.positive(args.omega, "--omega")
    validation.finite(args.dt, "--dt")
    validation.positive(args.dt, "--dt")
    base = example_setup(args)
    setup = config.load(args.config, base=base)[0] if args.config else base
    hyst = setup.hysteresis
    hyst.validate("hysteresis")
    validation.finite_tree(hyst, "hysteresis")
    if args.t_final is None:
        t_final = max(round(6 * math.pi / args.omega / args.dt), 1) * args.dt
    else:
        validation.finite(args.t_final, "--t-final")
        t_final = args.t_final
        validation.whole_steps(t_final, args.dt, "--t-final", "--dt")
    out = prepare_out(args, OUTPUTS)
    print(f"dscjax hysteresis: {hyst.kind}, u = A sin({args.omega:g} t), A = "
          f"{', '.join(f'{a:g}' for a in amplitudes)}, T = {t_final:g} s, dt = {args.dt:g} s",
          file=sys.stderr)
    t, u, w = sine_loops(hyst, amplitudes, args.omega, t_final, args.dt)
    write_npz(out / "loop.npz", dict(t=t, u=u, w=w, amplitude=np.asarray(amplitudes, float),
                                     omega=np.asarray(args.omega, float),
                                     kind=np.asarray(hyst.kind)))
    _plot(hyst, amplitudes, args.omega, u, w, out / "loop.png")
    for a, wk in zip(amplitudes, w, strict=True):
        print(f"A = {a:g}: max|w| = {np.max(np.abs(wk)):.6g}, w(T) = {wk[-1]:.6g}")
    print(f"wrote {out}/loop.npz, loop.png")
    return 0


def _plot(hyst, amplitudes, omega, u, w, path):
    import matplotlib

    from dscjax import files
    from dscjax.plotting import hysteresis_loop, subplots
    from dscjax.reproduce import RC

    with matplotlib.rc_context(RC):
        fig, axes = subplots(1, len(amplitudes), figsize=(4.2 * len(amplitudes), 3.9),
                             sharey=True)
        axes = np.atleast_1d(axes)
        for ax, a, uk, wk in zip(axes, amplitudes, u, w, strict=True):
            hysteresis_loop(ax, hyst, uk, wk, f"$w(u)$, $u = {a:g}\\,\\sin({omega:g}t)$")
            ax.set_title(f"amplitude {a:g}")
            ax.legend(loc="upper left", framealpha=0.95, fontsize=8)
        axes[0].set_ylabel("hysteresis output $w$ [-]")
        fig.suptitle(hyst.title)
        files.save_figure(fig, path, dpi=120)
