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
from dscjax.cli.out import Outputs, add_out_arg, nothing_kept, prepare_out
from dscjax.identify import run as ident
from dscjax.params import cast
from dscjax.validation import ConfigError, validate_setup

OUTPUTS = Outputs(("identified.toml", "report.md", "report.json", "fit.png", "residuals.png"))
interrupt_hint = nothing_kept


def add_parser(sub):
    p = sub.add_parser(
        "identify", help="identify plant and actuator numbers from a measured record",
        description=__doc__)
    p.add_argument("--data", required=True, metavar="FILE", help="the measured record")
    common.add_config_args(p, run_keys=("dt",), float32=False)
    settings.add_arguments(p, ident.IdentifySettings, "identify.")
    add_out_arg(p, "results/identify", plot="skip the figures")
    return p


def load(args):
    """(setup, spec, settings, source) from --config (its [identify] table), --example and the
    options."""
    setup, spec = common.config_setup(args)
    table = common.config_data(args).get("identify", {})
    s = settings.from_table(ident.IdentifySettings, table, "identify.")
    s = common.own_settings(args, ident.IdentifySettings, "identify.", s)[0]
    if not s.free:
        raise ConfigError("--free: give the numbers to fit, e.g. --free "
                          "plant.g,hysteresis.alpha (or [identify] free in the config)")
    spec = common.apply_run_options(args, spec)
    validate_setup(setup)
    source = {"data": args.data, "model": args.config or f"--example {args.example}"}
    return cast(setup, "float64"), spec, s, source


def run(args) -> int:
    setup, spec, s, source = load(args)
    if args.print_config:
        common.print_config(setup, spec, {"identify": settings.to_table(s)}, groups={"identify": s})
        return 0
    record, val = ident.read_records(s, args.data, setup.order)
    out = prepare_out(args, OUTPUTS)
    kind = "the plant with its actuator" if any(c != "w" for c in record.y) else \
        "the actuator alone"
    common.banner(args, f"{len(record)} samples of {', '.join(record.y)} over "
                  f"t = {record.t[0]:g}..{record.t[-1]:g} s, {kind}; free: {', '.join(s.free)}; "
                  f"{s.segments} segment(s), {s.starts} start(s); fitting ...")
    res = ident.identify(setup, spec, record, s, val)
    written = ident.write(out, res, spec, source, plot=not args.no_plot)
    print((out / "report.md").read_text())
    print(f"  wrote {out}: {', '.join(written)}; tune for it: dscjax tune --config "
          f"{out}/identified.toml --batch 8")
    return 0
