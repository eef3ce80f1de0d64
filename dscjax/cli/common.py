"""Helpers shared by the subcommands: config loading with command-line overrides, output."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import tempfile
from pathlib import Path

import numpy as np


def count(low: int = 0):
    """An argparse type: an integer >= low, also written as an integral float (1e5, 100000.0);
    anything else is refused with the allowed range and the value."""

    def parse(text: str) -> int:
        value = None
        try:
            value = int(text)
        except ValueError:
            try:
                x = float(text)
            except ValueError:
                x = math.nan
            if math.isfinite(x) and x == int(x):
                value = int(x)
        if value is None or value < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low} (got {text!r})")
        return value

    parse.__name__ = "count"
    return parse


def finite_float(text: str) -> float:
    """An argparse type: a finite number (inf and nan are refused, naming the option)."""
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"must be a finite number (got {text!r})")
    return x


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0 (got {text!r})")
    return x


# The [simulation] keys the commands take as options, and their argparse types.
RUN_TYPES = {"t_final": positive_float, "dt": positive_float, "save_every": count(1),
             "window_start": finite_float, "state_bound": positive_float, "refine": count(0),
             "sample_time": positive_float, "delay": count(0), "noise": finite_float,
             "noise_seed": count(0)}


def flag(key: str) -> str:
    """The command-line option of a [simulation] key: --key-with-dashes."""
    return "--" + key.replace("_", "-")


# the [simulation] keys of the sampled controller, an option on every command that simulates
SAMPLED_KEYS = ("sample_time", "delay", "noise", "noise_seed", "discretisation")


def add_run_args(p, keys=("t_final", "dt"), defaults: dict | None = None):
    """Options for the given [simulation] keys (`dscjax.runspec.OPTIONS`), each overriding the
    config's value; their help states the default (`defaults` may give a command's own)."""
    from dscjax.integrate import SOLVERS
    from dscjax.runspec import DEVICES, OPTIONS

    for key in keys:
        default, doc = OPTIONS[key]
        default = (defaults or {}).get(key, default)
        shown = "omitted" if default is None else f"{default:g}" if isinstance(
            default, float) else f"{default}"
        text = f"{doc} (default {shown}, or the config's simulation.{key})"
        if key == "solver":
            p.add_argument(flag(key), choices=tuple(SOLVERS), help=text)
        elif key == "device":
            p.add_argument(flag(key), choices=DEVICES, help=text)
        elif key == "discretisation":
            p.add_argument(flag(key), type=str, metavar="SCHEME", help=text)
        else:
            p.add_argument(flag(key), type=RUN_TYPES[key], metavar=key.upper().replace(
                "_", "-") if key != "t_final" else "S", help=text.replace("%", "%%"))


def run_overrides(args) -> dict:
    """{key: value} of the [simulation] options given on the command line."""
    from dscjax.runspec import OPTIONS

    out = {k: getattr(args, k) for k in OPTIONS if getattr(args, k, None) is not None}
    if getattr(args, "float32", False):
        out["dtype"] = "float32"
    return out


def apply_run_options(args, spec):
    """`spec` with the command line's [simulation] options laid over it (checked; a message
    names the option)."""
    overrides = run_overrides(args)
    if not overrides:
        return spec
    return spec.replace(names={k: flag(k) if k != "dtype" else "--float32" for k in overrides},
                        **overrides)


def choose_device(args, kind: str, rows: int = 1):
    """Where a command's work runs (`dscjax.device.choose` of `kind`, --device or
    simulation.device, for `rows` trajectories run together): a `Choice`, whose str is the
    banner's clause. "gpu" without one is refused (one line naming the option, exit 2), so
    call it before `prepare_out`."""
    from dscjax import device

    field = "--device" if getattr(args, "device", None) else "simulation.device"
    return device.choose(kind, rows, field=field)


def use_device(args, kind: str, rows: int = 1):
    """`choose_device`, with its device made JAX's default (`jax.default_device`) for the
    rest of the command (held by `args.exit_stack`): for commands whose library calls take no
    device of their own."""
    from dscjax import device

    choice = choose_device(args, kind, rows)
    args.exit_stack.enter_context(device.placed(choice))
    return choice


def horizon_text(t_final: float, dt: float, steps: int) -> str:
    return f"T = {t_final:g} s at dt = {dt:g} s ({steps:,} steps)"


def loop_sizes(setup) -> tuple[int, int, int]:
    """(m, k, itemsize): the floats of the closed loop's state (what the time-parallel
    gradient's Jacobians are square in), of one saved point of a Trajectory (state and
    observations, k >= m), and the bytes of one float. Shapes only: nothing is run."""
    import functools

    import jax

    from dscjax.runspec import RunSpec
    from dscjax.simulate import run

    spec = RunSpec.make(1e-3, 1e-3, save_every=1, window_start=0.0)
    shapes = jax.eval_shape(functools.partial(run, spec=spec), setup)
    def floats(tree):
        return sum(math.prod(a.shape[1:]) for a in jax.tree.leaves(tree))

    m = floats((shapes.x, shapes.h, shapes.ctrl))
    return m, m + floats((shapes.w, shapes.u, shapes.u_dot, shapes.yr, shapes.S)), \
        shapes.x.dtype.itemsize


def gradient_work(setup, steps: int, copies: int = 1):
    """The memory of `copies` time-parallel gradients of one trajectory of `steps` steps: the
    Jacobians of every step, O(N m^2) (`integrate._time_parallel_jvp`)."""
    from dscjax.validation import Work

    m, per_point, size = loop_sizes(setup)
    return Work(memory=copies * steps * m * per_point * size,
                memory_what=f"the time-parallel gradient ({copies:,} x {steps:,} steps x "
                f"{m} x {per_point} Jacobian entries)")


def add_example_arg(p):
    """--example, and --print-config, which prints the whole effective config (`print_config`)."""
    p.add_argument("--example", default="paper", metavar="NAME",
                   help="the built-in closed loop a --config is laid over: paper (default), "
                   "backstepping (the paper's plant, backstepping baseline), order-N (the "
                   "order-n family, N >= 2, e.g. order-4), or pi, gpi, bouc_wen (the paper's "
                   "loop behind that hysteresis model); --print-config shows it whole")
    p.add_argument("--print-config", action="store_true",
                   help="print the whole effective config as TOML ([simulation], the model "
                   "tables and this command's own settings) and exit; --config loads it back")


def print_config(setup, spec, *tables: str) -> None:
    """`--print-config`: [simulation] and the model tables of (setup, spec), then a command's
    own tables (TOML text), on stdout."""
    import sys

    from dscjax import config

    sys.stdout.write("\n".join([config.to_toml(setup, spec).rstrip("\n"),
                                *(t.rstrip("\n") for t in tables)]) + "\n")


def example_setup(args):
    """The Setup of --example (float64), the base every config is laid over."""
    from dscjax.config import example

    return example(getattr(args, "example", "paper") or "paper", dtype=np.float64)


def add_config_args(p, *, run_keys=("t_final", "dt"), float32=True):
    """--config, --example and --print-config, the given [simulation] options, --float32."""
    p.add_argument("--config", metavar="FILE", help="TOML (or JSON) config laid over the "
                   "--example (default: the paper's); see `dscjax simulate --print-config`")
    add_example_arg(p)
    add_run_args(p, run_keys)
    if float32:
        p.add_argument("--float32", action="store_true", help="run in float32 (default "
                       "float64, or the config's simulation.dtype)")


def load_setup(args, ignore: tuple[str, ...] = ()):
    """(Setup, RunSpec) from --config plus command-line options, the setup cast to the dtype.

    `ignore`: tables of the file that belong to another command (e.g. "tuning"), skipped."""
    from dscjax import config
    from dscjax.params import cast
    from dscjax.validation import validate_setup

    base = example_setup(args)
    raw = config.read(args.config) if args.config else {}
    for name in ignore:
        raw.pop(name, None)
    setup, spec = config.from_dict(raw, base=base)
    spec = apply_run_options(args, spec)
    if getattr(args, "variant", None):
        setup = setup.replace(
            controller=dataclasses.replace(setup.controller, variant=args.variant))
    # before anything traces the setup (a shape mismatch would otherwise surface as a JAX
    # broadcasting error from inside an eval_shape)
    validate_setup(setup)
    return cast(setup, np.dtype(spec.dtype)), spec


def add_overwrite_arg(p):
    """--overwrite of the commands without --resume (the one rule of --out, README)."""
    p.add_argument("--overwrite", action="store_true", help="replace the files of an earlier "
                   "run in DIR (only those this command writes); without it such a DIR is "
                   "refused")


@dataclasses.dataclass(frozen=True)
class Outputs:
    """What a command writes into its --out, declared once per command: file names or glob
    patterns, and folders. The one rule of an existing --out checks them and --overwrite
    deletes them, never anything else."""

    files: tuple[str, ...]
    folders: tuple[str, ...] = ()

    def found(self, out: Path) -> list[str]:
        """The outputs present in `out` (folders with a trailing /), sorted."""
        names = {p.name for pattern in self.files for p in out.glob(pattern) if p.is_file()}
        names |= {f"{p.name}/" for pattern in self.folders for p in out.glob(pattern)
                  if p.is_dir()}
        return sorted(names)

    def remove(self, out: Path) -> None:
        import shutil

        for name in self.found(out):
            path = out / name.rstrip("/")
            if name.endswith("/"):
                shutil.rmtree(path)
            else:
                path.unlink()


def prepare_out(args, outputs: Outputs, *, resumable: bool = False, lock: str | None = None,
                check: bool = True, option: str = "--out") -> Path:
    """Make `args.out` ready, after every input has been validated: refuse a DIR that is a
    file, cannot be written or is held by another process (one line, exit 2); create it if new
    (removed again if the command leaves it empty); lock it (`files.lock_out`, file `lock`) for
    the command (`args.exit_stack`); refuse a DIR holding `outputs` unless --resume
    (`resumable`) or --overwrite (deletes them, nothing else)."""
    from dscjax import files
    from dscjax.validation import ConfigError

    out = Path(args.out)
    new = [p for p in (out, *out.parents) if not p.exists()]  # created here, leaf first
    args.exit_stack.callback(_remove_if_empty, new)
    try:
        if out.exists() and not out.is_dir():
            raise NotADirectoryError(0, "it is a file, not a directory")
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=out, prefix=".dscjax-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise ConfigError(f"{option} {str(args.out)!r}: cannot write the output there "
                          f"({err.strerror or err}); give a writable directory") from None
    args.exit_stack.enter_context(files.lock_out(
        out, name=lock or files.LOCK, argv=[*args.prog, *args.argv], option=option))
    if check:
        found = outputs.found(out)
        if found and not (getattr(args, "overwrite", False) or getattr(args, "resume", False)):
            shown = ", ".join(found[:4]) + (", ..." if len(found) > 4 else "")
            how = ("--resume to continue them, --overwrite to start afresh (deleting only "
                   "them)" if resumable else "--overwrite to replace them")
            raise ConfigError(f"{option} {str(args.out)!r} already holds files this command "
                              f"writes ({shown}); {how}, or give another {option}")
        if getattr(args, "overwrite", False):
            outputs.remove(out)
    return out


def _remove_if_empty(created: list[Path]) -> None:
    """The directories a command created for its --out (leaf first), removed if it left
    nothing in them."""
    for path in created:
        try:
            path.rmdir()
        except OSError:
            return
