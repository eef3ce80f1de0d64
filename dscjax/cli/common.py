"""Helpers shared by the subcommands: config loading with command-line overrides, output."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import math
import sys

import jax
import numpy as np

from dscjax import config, device, settings
from dscjax.markdown import figure
from dscjax.metrics import CHATTER_RATIO, RunningMetrics, chatters
from dscjax.params import cast
from dscjax.rules import AtLeast, Number, Positive
from dscjax.runspec import RunSpec, Simulation
from dscjax.validation import ConfigError, Work

# Subcommand name -> module under dscjax.cli exposing HELP (its line in `dscjax --help`; its
# docstring, or DESCRIPTION, is its own --help's), add_options(parser) and run(args).
COMMANDS = {
    "simulate": "dscjax.cli.simulate",
    "reproduce": "dscjax.cli.reproduce",
    "tune": "dscjax.cli.tune",
    "sweep": "dscjax.cli.sweep",
    "stability": "dscjax.cli.stability",
    "worst-case": "dscjax.cli.worst_case",
    "hysteresis": "dscjax.cli.hysteresis",
    "export": "dscjax.cli.export",
    "sensitivity": "dscjax.cli.sensitivity",
    "identify": "dscjax.cli.identify",
}


def count(low: int = 0):
    """An argparse type: an integer >= low, also written as an integral float (1e5, 100000.0);
    anything else is refused with the allowed range and the value (`rules.AtLeast`)."""
    return settings.argtype(AtLeast(low))


# argparse types: a finite number (inf and nan are refused, naming the option), and one > 0
finite_float = settings.argtype(Number())
positive_float = settings.argtype(Positive())


def positive_numbers(text: str | None, option: str) -> list[float] | None:
    """"0.5,1,2" -> the positive numbers an option lists (None stays None); anything else is
    refused in one line naming the option."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or min(values) <= 0:
        raise ConfigError(f"{option} must be positive numbers like 0.5,1,2 (got {text!r})")
    return values


class Once(argparse._StoreAction):
    """argparse's "store", refusing an option given twice (one line, exit 2) instead of
    silently keeping the last value. The parsers of the `dscjax` command (`cli.main`) use it
    for every single-valued option; options that take several values say so (append)."""

    def __call__(self, parser, namespace, values, option_string=None):
        seen = namespace.__dict__.setdefault("_given_once", {})
        if self.dest in seen:
            first, then = (repr(v) if isinstance(v, str) else f"{v}"
                           for v in (seen[self.dest], values))
            raise argparse.ArgumentError(
                self, f"given twice (first {first}, then {then}); give it once")
        seen[self.dest] = values
        super().__call__(parser, namespace, values, option_string)


@contextlib.contextmanager
def blame_options(names: dict[str, str]):
    """A ConfigError raised in the block that names a config key given on the command line
    names the option the user typed instead: `names` maps such keys to their options, e.g.
    {"sweep.threshold": "--threshold"} ("sweep.threshold must be > 0" becomes "--threshold
    must be > 0"; "sweep.grid.hysteresis.alpha: ..." becomes "--grid hysteresis.alpha: ...").
    Keys the config gave keep their names."""
    try:
        yield
    except ConfigError as err:
        text = str(err)
        for key in sorted(names, key=len, reverse=True):
            rest = text[len(key):]
            if text.startswith(key) and not (rest[:1].isalnum() or rest[:1] in "_["):
                rest = " " + rest[1:] if rest.startswith(".") else rest
                raise ConfigError(names[key] + rest) from None
        raise


# the [simulation] keys of the sampled controller, an option on every command that simulates
SAMPLED_KEYS = ("sample_time", "delay", "noise", "noise_seed", "discretisation")


def add_run_args(p, keys=("t_final", "dt"), defaults: dict | None = None):
    """Options for the given [simulation] keys (`dscjax.runspec.Simulation`), each overriding
    the config's value; their help states the default (`defaults` may give a command's own)."""
    settings.add_arguments(p, Simulation, "simulation.", keys=keys, defaults=defaults)


def run_overrides(args) -> tuple[dict, dict]:
    """({key: value} of the [simulation] options given on the command line, {key: option
    typed})."""
    table, names = settings.given(args, Simulation, "")
    if getattr(args, "float32", False):
        table["dtype"], names["dtype"] = "float32", "--float32"
    return table, names


def apply_run_options(args, spec):
    """`spec` with the command line's [simulation] options laid over it (checked; a message
    names the option). For a command with --device, its device one that may run here: a config
    file's `simulation.device = "gpu"` on a machine without an accelerator is a preference of
    the run it was written for (a gains.json of `tune --device gpu`), not of the file, so it
    runs on the CPU ("auto") after a one-line note on stderr. A device typed on the command
    line is left to `choose_device`, which refuses one that is not here."""
    overrides, names = run_overrides(args)
    spec = spec.replace(names=names, **overrides) if overrides else spec
    if (not hasattr(args, "device") or args.device or spec.device != "gpu"
            or any(d.platform != "cpu" for d in device.visible())):
        return spec
    say(args, "note", f"simulation.device = 'gpu' in {args.config}: no GPU here; running on "
        f"the CPU")
    return spec.replace(device="auto")


def choose_device(args, kind: str, rows: int = 1):
    """Where a command's work runs (`dscjax.device.choose` of `kind`, --device or
    simulation.device, for `rows` trajectories run together): a `Choice`, whose str is the
    banner's clause. "gpu" without one is refused (one line naming the option, exit 2), so
    call it before `prepare_out`."""
    field = "--device" if getattr(args, "device", None) else "simulation.device"
    return device.choose(kind, rows, field=field)


def use_device(args, kind: str, rows: int = 1):
    """`choose_device`, with its device made JAX's default (`jax.default_device`) for the
    rest of the command (held by `args.exit_stack`): for commands whose library calls take no
    device of their own."""
    choice = choose_device(args, kind, rows)
    args.exit_stack.enter_context(device.placed(choice))
    return choice


def say(args, kind: str, *texts) -> None:
    """Each text as one line on stderr, "dscjax COMMAND: KIND: TEXT" (KIND: warning, note)."""
    for text in texts:
        print(f"dscjax {args.command}: {kind}: {text}", file=sys.stderr)


def banner(args, text: str, warnings=()) -> None:
    """A command's start line on stderr, "dscjax COMMAND: TEXT", then its `warnings` (`say`)."""
    print(f"dscjax {args.command}: {text}", file=sys.stderr)
    say(args, "warning", *warnings)


def wrote(out, *names: str | None, took: str = "") -> None:
    """A command's line of the files it wrote into its --out `out`, on stdout with its
    results: "  wrote DIR/a, b, c (TOOK)"; a name that is None (a figure not drawn) is left
    out."""
    print(f"  wrote {out}/{', '.join(filter(None, names))}" + (f" ({took})" if took else ""))


def listed(names, most: int = 6) -> str:
    """names joined, at most `most` of them and how many more."""
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


# the fix of a horizon too long for the machine (`validation.check_work`)
SHORTER = "use a shorter --t-final or a larger --dt"


def horizon_text(t_final: float, dt: float, steps: int) -> str:
    return f"T = {t_final:g} s at dt = {dt:g} s ({steps:,} steps)"


def effort_text(metrics, window: str) -> str:
    """The effort part of a run's verdict, from its metrics: "effort on [t0, T] s: max|u| 6.29,
    TV(u) 19,408, CHATTERING (index 29.3 > 1.5; docs/numerics.md)" or "..., no chattering (index
    1.04 <= 1.5)" (`dscjax.metrics.chatters`; the definition is docs/numerics.md's)."""
    index = metrics["chattering_index"]
    verdict = (f"CHATTERING (index {figure(index)} > {CHATTER_RATIO:g}; docs/numerics.md)"
               if chatters(index) else
               f"no chattering (index {figure(index)} <= {CHATTER_RATIO:g})")
    return (f"effort on {window}: max|u| {figure(metrics['max_abs_u_window'])}, TV(u) "
            f"{figure(metrics['tv_u_window'])}, {verdict}")


def untrusted_text(untrusted, rel_diff: dict, rtol: float, fix: str, on: str = "") -> str:
    """The warning of a float32 re-check in float64 (`dscjax.sweep.float32_trust`) whose
    metrics `untrusted` differ by more than `rtol` (`rel_diff` {metric: relative difference};
    `on`: the rows re-checked)."""
    worst = max(rel_diff[m] for m in untrusted)
    return (f"float32 cannot be trusted with {', '.join(untrusted)}: they differ from float64 "
            f"by up to {100 * worst:.3g} %{on} (tolerance {100 * rtol:g} %); {fix}")


def loop_sizes(setup) -> tuple[int, int, int]:
    """(m, k, itemsize): the floats of the closed loop's state (what the time-parallel
    gradient's Jacobians are square in), of one saved point of a Trajectory (state and
    observations, k >= m), and the bytes of one float. Shapes only: nothing is run, and a
    setup of a structure already sized is not traced again."""
    leaves, tree = jax.tree.flatten(setup)
    return _loop_sizes(tree, tuple(map(jax.typeof, leaves)))


@functools.cache
def _loop_sizes(tree, leaves) -> tuple[int, int, int]:
    from dscjax.simulate import run

    spec = RunSpec.make(1e-3, 1e-3, save_every=1, window_start=0.0)
    setup = jax.tree.unflatten(tree, [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
                                      for a in leaves])
    shapes = jax.eval_shape(functools.partial(run, spec=spec), setup)

    def floats(tree):
        return sum(math.prod(a.shape[1:]) for a in jax.tree.leaves(tree))

    m = floats((shapes.x, shapes.h, shapes.ctrl))
    return m, m + floats((shapes.w, shapes.u, shapes.u_dot, shapes.yr, shapes.S)), \
        shapes.x.dtype.itemsize


def gradient_work(setup, steps: int, copies: int = 1):
    """The memory of `copies` time-parallel gradients of one trajectory of `steps` steps: the
    Jacobians of every step, of the state (m x k) and of the running metrics (r x r)
    (`integrate.gradients.time_parallel_jvp`)."""
    m, per_point, size = loop_sizes(setup)
    r = len(RunningMetrics._fields)
    return Work(memory=copies * steps * (m * per_point + r * r) * size,
                memory_what=f"the time-parallel gradient ({copies:,} x {steps:,} steps x "
                f"({m} x {per_point} + {r} x {r}) Jacobian entries)")


def add_example_arg(p):
    """--example, and --print-config, which prints the whole effective config (`print_config`)."""
    p.add_argument("--example", default="paper", metavar="NAME",
                   help="the built-in loop under --config (--print-config shows it whole): "
                   "paper (default), backstepping, order-N (N >= 2), or the paper's loop with "
                   "pi, gpi or bouc_wen hysteresis")
    p.add_argument("--print-config", action="store_true", help="print the whole effective "
                   "config as TOML (--config loads it back) and exit")


def print_config(setup, spec, extra: dict | None = None, groups: dict | None = None) -> int:
    """`--print-config`: [simulation] and the model tables of (setup, spec), then a command's
    own tables ({name: table}), as TOML on stdout, each key with its meaning (`groups`:
    {name: the settings group declaring a table}). Returns 0, the command's exit status."""
    docs = dict(config.DOCS)
    for name, group in (groups or {}).items():
        docs |= settings.meanings(group, f"{name}.")
    sys.stdout.write(config.to_toml(setup, spec, extra=extra, docs=docs))
    return 0


def add_config_args(p, *, run_keys=("t_final", "dt"), float32=True, defaults=None, table=None):
    """--config (which may hold the command's own `table`), --example and --print-config, the
    given [simulation] options (`defaults`: a command's own), --float32."""
    own = f"; may hold a [{table}] table" if table else ""
    p.add_argument("--config", metavar="FILE", help="TOML (or JSON) config laid over the "
                   f"--example{own}; see --print-config")
    add_example_arg(p)
    add_run_args(p, run_keys, defaults)
    if float32:
        p.add_argument("--float32", action="store_true", help="run in float32 (default "
                       "float64, or the config's simulation.dtype)")


def config_data(args) -> dict:
    """The tables of --config ({} without one), read once for the command (`args.config_data`):
    the model's, and the commands' own ([tuning], [sweep], ...; `config.COMMAND_TABLES`)."""
    if "config_data" not in vars(args):
        args.config_data = config.read(args.config, "--config") if args.config else {}
    return args.config_data


def config_setup(args, base_spec=None, gains=None):
    """(Setup, RunSpec) of --config laid over --example (float64; and `base_spec`), then the
    file of --gains, where one is given, laid over that by `gains` (a command's way: e.g.
    `whole_config`), before the command line's options."""
    base = config.example(args.example or "paper", dtype=np.float64)
    setup, spec = config.from_dict(config_data(args), base=base, base_spec=base_spec)
    if gains and args.gains:
        return gains(args, setup, spec)
    return setup, spec


def whole_config(args, setup, spec):
    """--gains of `export` and `tune`: the whole config of the file (e.g. the gains.json of
    `dscjax tune`: the gains, the plant and the loop they were tuned on) laid over (setup,
    spec)."""
    return config.from_dict(config.read(args.gains, "--gains"), base=setup, base_spec=spec)


def own_settings(args, group, name: str, base=None, skip: tuple[str, ...] = ()):
    """(settings, given, names): a command's settings group `group`, `base` (by default the
    [NAME] table of --config laid over the group's defaults, `skip` its keys the command reads
    itself) with the group's options given on the command line laid over it, a refusal naming
    the option typed (`blame_options`); `given` and `names` as `dscjax.settings.given`'s."""
    prefix = f"{name}."
    if base is None:
        base = settings.from_table(group, config_data(args).get(name, {}), prefix, skip=skip)
    given, names = settings.given(args, group, prefix)
    with blame_options(names):
        return settings.from_table(group, given, prefix, base), given, names


def checked_setup(args, setup, spec):
    """(setup, spec): the command line's [simulation] options laid over `spec`
    (`apply_run_options`), then the setup validated and simulation.noise (--noise) checked as
    one number or one per state of the plant (n), each refused in one line naming how it was
    given, before anything traces the loop (a shape mismatch would otherwise surface as a JAX
    broadcasting error from inside an eval_shape)."""
    from dscjax.simulate import check

    spec = apply_run_options(args, spec)
    given = getattr(args, "noise", None) is not None
    with blame_options({"simulation.noise": "--noise"} if given else {}):
        check(setup, spec, batched=True)  # batched: the setup and the noise, not the filters
    return setup, spec


def load_setup(args, base_spec=None, gains=None, dtype=None):
    """(Setup, RunSpec) from --config (and --gains: `config_setup`) plus command-line options
    (`checked_setup`), the setup cast to `dtype` (default the spec's; a command's own table
    in the file, e.g. [tuning], is left to that command)."""
    setup, spec = config_setup(args, base_spec, gains)
    if getattr(args, "variant", None):
        setup = setup.replace(
            controller=dataclasses.replace(setup.controller, variant=args.variant))
    setup, spec = checked_setup(args, setup, spec)
    return cast(setup, np.dtype(dtype or spec.dtype)), spec
