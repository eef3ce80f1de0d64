"""`dscjax hysteresis`: the config's hysteresis model alone (hysteresis.kind: backlash, pi, gpi,
bouc_wen), driven open-loop by u(t) = A sin(omega t) with the closed loop's RK4 (and the play
operators' exact clamp).

Writes DIR/loop.npz (t (N+1,), u and w (K, N+1) on the step grid, one row per amplitude, and
`amplitude` (K,), `omega`, `kind`) and DIR/loop.png (w against u, one panel per amplitude, with
the lines w = lam u + d_1 limits). Without options: the paper's Fig. 1 (backlash-like model (4),
amplitudes 3.5 and 6.5, omega = 2.3, three periods).
"""

from __future__ import annotations

import math

import numpy as np

from dscjax import files, validation
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, start
from dscjax.hysteresis import sine_loops
from dscjax.reproduce.figures import loop_figure
from dscjax.reproduce.runs import FIG1_AMPLITUDES, FIG1_OMEGA
from dscjax.runspec import RunSpec

DEFAULT_DT = 1e-3
OUTPUTS = Outputs(("loop.npz", "loop.png"))


HELP = "a hysteresis model alone: w(t) and its loop for u = A sin(omega t)"


def add_options(p):
    p.add_argument("--config", metavar="FILE", help="TOML (or JSON) config: only its "
                   "[hysteresis] and simulation.t_final, dt, device (options win) are used")
    common.add_example_arg(p)
    p.add_argument("--amplitude", type=common.finite_float, action="append", metavar="A",
                   help="input amplitude; repeat for several loops (default "
                   f"{' and '.join(f'{a:g}' for a in FIG1_AMPLITUDES)})")
    p.add_argument("--omega", type=common.positive_float, default=FIG1_OMEGA, metavar="W",
                   help=f"input frequency [rad/s] (default {FIG1_OMEGA:g})")
    p.add_argument("--t-final", type=common.positive_float, metavar="T",
                   help="horizon [s] (default three periods 6 pi / omega, on the dt grid)")
    p.add_argument("--dt", type=common.positive_float, metavar="DT", help=f"RK4 step [s] "
                   f"(default {DEFAULT_DT:g})")
    common.add_run_args(p, ("device",))
    add_out_arg(p, "results/hysteresis")


def run(args) -> int:
    amplitudes = tuple(args.amplitude or FIG1_AMPLITUDES)
    setup, spec = common.config_setup(args)  # spec: [simulation] checked (t_final, dt, device)
    hyst = setup.hysteresis
    hyst.validate("hysteresis")
    validation.finite_tree(hyst, "hysteresis")
    sim = common.config_data(args).get("simulation", {})  # which keys the config gave
    # an option, else the config's key, else the default (named as the option)
    dt_field = "simulation.dt" if args.dt is None and "dt" in sim else "--dt"
    dt = sim["dt"] if dt_field == "simulation.dt" else args.dt or DEFAULT_DT
    t_field = "simulation.t_final" if args.t_final is None and "t_final" in sim else "--t-final"
    t_final = sim["t_final"] if t_field == "simulation.t_final" else args.t_final
    if t_final is None:  # three periods on the dt grid
        dt = validation.finite_positive(dt, dt_field)
        t_final = max(round(6 * math.pi / args.omega / dt), 1) * dt
    steps = validation.whole_steps(t_final, dt, t_field, dt_field)
    if args.print_config:
        return common.print_config(setup, RunSpec.make(float(t_final), float(dt)))
    k = len(amplitudes)
    validation.check_work(validation.Work(
        steps=steps, member_steps=k * steps, memory=8.0 * (2 * k + 1) * (steps + 1),
        memory_what=f"t, u and w at every step ({k} amplitude(s))"),
        what=common.horizon_text(t_final, dt, steps), fix=common.SHORTER)
    out = start(args, OUTPUTS, f"{hyst.kind}, u = A sin({args.omega:g} t), A = "
                f"{', '.join(f'{a:g}' for a in amplitudes)}, T = {t_final:g} s, dt = {dt:g} s",
                args.device or spec.device, k)
    t, u, w = sine_loops(hyst, amplitudes, args.omega, t_final, dt)
    files.write_npz(out / "loop.npz", dict(t=t, u=u, w=w, amplitude=np.asarray(amplitudes, float),
                                           omega=np.asarray(args.omega, float),
                                           kind=np.asarray(hyst.kind)))
    loop_figure(hyst, amplitudes, args.omega, u, w, hyst.title, out / "loop.png", 120)
    for a, wk in zip(amplitudes, w, strict=True):
        print(f"A = {a:g}: max|w| = {np.max(np.abs(wk)):.6g}, w(T) = {wk[-1]:.6g}")
    common.wrote(out, "loop.npz", "loop.png")
    return 0

