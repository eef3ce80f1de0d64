"""`dscjax identify`: fit the free numbers of a config (--free) to a measured record (--data:
CSV with a header row, or NPZ, columns t, u and any of x1..xn, w) by Levenberg-Marquardt on
exact Jacobians through the simulator (`dscjax.identify`): the actuator alone where the record
measures w only, the plant with its actuator where it measures a state. Reports the fit (NRMSE,
MSE, FPE), each number's standard error and 95 % interval, which numbers the data cannot
identify, and a validation fit (docs/identification.md). Writes into DIR identified.toml (a
whole config, the numbers' 95 % intervals as the robust tuning box), report.md (which it also
prints), report.json, fit.png and residuals.png.
"""

from __future__ import annotations

from dscjax import settings
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, start
from dscjax.identify import read
from dscjax.identify import run as ident

OUTPUTS = Outputs(("identified.toml", "report.md", "report.json", "fit.png", "residuals.png"))


HELP = "identify plant and actuator numbers from a measured record"


def add_options(p):
    p.add_argument("--data", required=True, metavar="FILE", help="the measured record")
    common.add_config_args(p, run_keys=("dt",), float32=False, table="identify")
    settings.add_arguments(p, ident.IdentifySettings, "identify.")
    add_out_arg(p, "results/identify", plot="skip the figures")


def load(args):
    """(setup, spec, settings, source) from --config (its [identify] table), --example and the
    options."""
    setup, spec = common.load_setup(args, dtype="float64")
    s = common.own_settings(args, ident.IdentifySettings, "identify")[0]
    ident.check_free(setup, s.free)  # before the data and --out
    source = {"data": args.data, "model": args.config or f"--example {args.example}"}
    return setup, spec, s, source


def run(args) -> int:
    setup, spec, s, source = load(args)
    if args.print_config:
        return common.print_config(setup, spec, {"identify": settings.to_table(s)},
                                   groups={"identify": s})
    record = read(args.data, setup.order)
    val = None if s.validate is None else ident.validation_record(s.validate, record, setup.order)
    ident.check_free(setup, s.free, record.plant)  # the numbers this record can fix
    # the report (printed below) says which experiment, the segments and the starts
    out = start(args, OUTPUTS, f"{len(record)} samples of {', '.join(record.y)} over t = "
                f"{record.t[0]:g}..{record.t[-1]:g} s; free: {', '.join(s.free)}; fitting ...")
    res = ident.identify(setup, spec, record, s, val)
    written = ident.write(out, res, spec, source, plot=not args.no_plot)
    print((out / "report.md").read_text())
    common.wrote(out, *written)
    return 0
