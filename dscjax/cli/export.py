"""`dscjax export`: the controller of a config (e.g. a tune's gains.json) sampled every TS
seconds, as C99 with no dependency beyond <math.h> (`dscjax.export`), in DIR/dsc_controller.h
and DIR/dsc_controller.c: exactly the initialisation and the update law of dscjax's sampled
loop (the law, its hysteresis compensation, the discretisation of its states, the input
delay). dsc_init starts it from the measured x(0), dsc_step runs one sample. The plant, the
actuator (and its limits: u is returned unbounded) and the measurement noise are not part of
it."""

from __future__ import annotations

from dscjax import export
from dscjax.cli import common
from dscjax.cli.out import Outputs, add_out_arg, start
from dscjax.export import PRECISIONS
from dscjax.files import write_text
from dscjax.params import cast
from dscjax.validation import ConfigError, validate_setup

OUTPUTS = Outputs(("dsc_controller.h", "dsc_controller.c"))


HELP = "the sampled controller of a config as C99 (dsc_controller.h, .c)"


def add_options(p):
    p.add_argument("--gains", metavar="FILE", help="a config laid over --config (e.g. the "
                   "gains.json of `dscjax tune`)")
    common.add_config_args(p, run_keys=("sample_time", "delay", "discretisation"), float32=False)
    p.add_argument("--precision", choices=PRECISIONS, default="double", help="the C's real "
                   "type: double (default; the simulated loop to round-off) or float")
    add_out_arg(p, "results/export")


def load(args):
    """(setup, spec, source) of --example, --config, --gains and the options, float64, the
    spec sampled (a config without a sample time and no --sample-time: one line)."""
    setup, spec = common.config_setup(args, gains=common.whole_config)
    source = " ".join(f"{flag} {value}" for flag, value in (
        ("--example", args.example), ("--config", args.config), ("--gains", args.gains)) if value)
    overrides, names = common.run_overrides(args)
    ts = overrides.get("sample_time", spec.sample_time)
    if ts is None:
        raise ConfigError("--sample-time is needed: the config has no simulation.sample_time "
                          "(a continuous controller); give --sample-time TS, a number > 0 "
                          "[s], e.g. 0.001")
    # The C is exact for `dscjax simulate` of the same config with --sample-time TS, so TS
    # is checked as simulate checks it (RunSpec.make), against the config's own step and
    # horizon: export has neither option, so the message names them as the config's.
    names |= {"dt": "the config's simulation.dt", "t_final": "the config's simulation.t_final"}
    spec = spec.replace(names=names, **overrides)
    validate_setup(setup)
    return cast(setup, "float64"), spec, source


def run(args) -> int:
    setup, spec, source = load(args)
    if args.print_config:
        return common.print_config(setup, spec)
    # every input checked before --out
    files = export.c_files(setup, spec, source=source, precision=args.precision)
    out = start(args, OUTPUTS, f"order n={setup.order}, {setup.controller.kind}, sampled "
                f"every {spec.sample_time:g} s, {spec.discretisation.name}, delay {spec.delay}, "
                f"{args.precision}; from {source}")
    for name, text in files.items():
        write_text(out / name, text)
    common.wrote(out, *files)
    return 0
