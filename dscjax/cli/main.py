"""Entry point of the `dscjax` command.

Errors a user can fix (bad settings, unreadable files) print one line and exit 2 without a
traceback; a diverged simulation prints when it diverged and exits 3; Ctrl-C exits 130 and
says what was kept and the command that continues (a subcommand's `interrupt_hint(args)`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# Subcommand name -> module under dscjax.cli exposing add_parser(subparsers) and run(args).
COMMANDS = {
    "simulate": "dscjax.cli.simulate",
    "reproduce": "dscjax.cli.reproduce",
    "tune": "dscjax.cli.tune",
    "sweep": "dscjax.cli.sweep",
    "stability": "dscjax.cli.stability",
    "worst-case": "dscjax.cli.worst_case",
    "hysteresis": "dscjax.cli.hysteresis",
}

EXIT_USAGE = 2
EXIT_DIVERGED = 3


class CLIError(Exception):
    """A user-fixable problem: printed as one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """argparse's own errors (an unknown choice, a missing or malformed value) as one line
    and exit 2, like every other bad input, instead of a usage block first; `--help` still
    gives the usage. Subcommands' parsers are of this class too (argparse's default)."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def _available_commands():
    out = {}
    for name, module in COMMANDS.items():
        try:
            out[name] = importlib.import_module(module)
        except ModuleNotFoundError as err:
            if err.name != module:
                raise
    return out


def build_parser(commands) -> argparse.ArgumentParser:
    from dscjax import __version__

    parser = _Parser(
        prog="dscjax",
        description="Differentiable simulator of adaptive dynamic surface control with hysteresis.",
        epilog="Results go to stdout; the start banner, progress, notes, warnings and errors to "
        "stderr. Exit codes: 0 ok, 2 bad input, 3 a simulation diverged, 130 interrupted.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("--no-compilation-cache", action="store_true",
                        help="do not keep compiled programs in JAX's persistent cache "
                        "($XDG_CACHE_HOME/dscjax/jax or ~/.cache/dscjax/jax; also "
                        "DSCJAX_NO_COMPILATION_CACHE=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in commands.values():
        module.add_parser(sub)
    parser.subcommands = sub.choices  # name -> its parser (`parse`)
    return parser


def parse(parser, argv):
    """The arguments, an unknown one reported by the subcommand it was given to
    (`dscjax hysteresis: error: unrecognized arguments: ...`, one line, exit 2)."""
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        parser.subcommands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    return args


def resume_command(argv) -> str:
    """The command line that continues an interrupted run: the same arguments, --resume
    instead of --overwrite."""
    import shlex

    args = [a for a in argv if a != "--overwrite"]
    if "--resume" not in args:
        args.append("--resume")
    return shlex.join(["dscjax", *args])


def rerun_command(argv) -> str:
    import shlex

    return shlex.join(["dscjax", *argv])


def main(argv=None) -> int:
    commands = _available_commands()
    parser = build_parser(commands)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse(parser, argv)
    args.argv = argv
    # Float64 is the default everywhere in the CLI; --float32 casts the setup instead.
    os.environ.setdefault("JAX_ENABLE_X64", "1")
    import jax

    jax.config.update("jax_enable_x64", True)
    from dscjax import compilation_cache

    if not (args.no_compilation_cache or compilation_cache.opted_out()):
        compilation_cache.enable()  # compiled programs survive the process (an entry point's
        # choice: the library never changes JAX's configuration by itself)
    from dscjax.simulate import DivergenceError
    from dscjax.validation import ConfigError

    try:
        return int(commands[args.command].run(args) or 0)
    except (ConfigError, CLIError) as err:
        print(f"dscjax {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except DivergenceError as err:
        print(f"dscjax {args.command}: simulation diverged: {err}", file=sys.stderr)
        return EXIT_DIVERGED
    except KeyboardInterrupt:
        hint = getattr(commands[args.command], "interrupt_hint", None)
        note = hint(args) if hint is not None else None
        print(f"\ndscjax {args.command}: interrupted" + (f"; {note}" if note else ""),
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
