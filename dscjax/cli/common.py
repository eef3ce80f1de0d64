"""Helpers shared by the subcommands: config loading with command-line overrides, output."""

from __future__ import annotations

import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np


def add_horizon_args(p):
    """--t-final and --dt, their help stating SimOptions' defaults (a config may change them)."""
    from dscjax.config import SimOptions

    d = SimOptions()
    p.add_argument("--t-final", type=float, metavar="S", help=f"horizon in seconds (default "
                   f"{d.t_final:g}, or the config's simulation.t_final)")
    p.add_argument("--dt", type=float, metavar="S", help=f"RK4 step in seconds (default "
                   f"{d.dt:g}, or the config's simulation.dt)")


def add_config_args(p, *, t_final=True):
    from dscjax.config import SimOptions

    p.add_argument("--config", metavar="FILE", help="TOML (or JSON) config laid over the paper's "
                   "example; see `dscjax simulate --print-config`")
    if t_final:
        add_horizon_args(p)
    p.add_argument("--float32", action="store_true",
                   help=f"run in float32 (default {SimOptions().dtype})")


def load_setup(args):
    """(Setup, SimOptions) from --config plus command-line overrides, cast to the dtype."""
    from dscjax import config
    from dscjax.params import cast

    if args.config:
        setup, options = config.load(args.config)
    else:
        setup, options = config.from_dict({})
    changes = {}
    for name in ("t_final", "dt"):
        value = getattr(args, name, None)
        if value is not None:
            changes[name] = value
    if getattr(args, "float32", False):
        changes["dtype"] = "float32"
    if getattr(args, "variant", None):
        setup = setup.replace(
            controller=dataclasses.replace(setup.controller, variant=args.variant))
    options = dataclasses.replace(options, **changes)
    options.validate()
    return cast(setup, np.dtype(options.dtype)), options


def prepare_out(path, option: str = "--out") -> Path:
    """Create the output directory and check that a file can be written in it, before any
    work is done; ConfigError (one line, exit 2) naming the option and the path if not."""
    from dscjax.validation import ConfigError

    out = Path(path)
    try:
        if out.exists() and not out.is_dir():
            raise NotADirectoryError(0, "it is a file, not a directory")
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=out, prefix=".dscjax-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise ConfigError(f"{option} {str(path)!r}: cannot write the output there "
                          f"({err.strerror or err}); give a writable directory") from None
    return out
