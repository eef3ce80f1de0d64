"""Results go to stdout; the banner, progress, notes, warnings and errors to stderr. Exit
codes: 0 ok; 2 bad input (one line, no traceback) or --out in use; 3 diverged; 4 disk full
(naming the file and the command that continues); 128 + the signal's number if interrupted (130
Ctrl-C, 143 SIGTERM, 129 SIGHUP), saying what was kept and how to continue."""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import os
import signal
import sys

from dscjax.cli.common import COMMANDS, Once
from dscjax.cli.out import check_out, kept_text, rerun_command, resume_command

EXIT_USAGE = 2
EXIT_DIVERGED = 3
EXIT_NO_SPACE = 4


class _Parser(argparse.ArgumentParser):
    """argparse's own errors (an unknown choice, a missing or malformed value) as one line
    and exit 2, like every other bad input, instead of a usage block first; `--help` still
    gives the usage. Subcommands' parsers are of this class too (argparse's default). A
    single-valued option given twice is refused (`cli.common.Once`)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register("action", None, Once)  # groups share the registry
        self.register("action", "store", Once)

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


class _Version(argparse.Action):
    """--version: the version, then what JAX sees (`dscjax.device.describe`), one line each."""

    def __call__(self, parser, namespace, values, option_string=None):
        from dscjax import __version__, device

        print("\n".join([f"{parser.prog} {__version__}", *device.describe()]))
        parser.exit(0)


def _available_commands():
    return {name: importlib.import_module(module) for name, module in COMMANDS.items()}


def build_parser(commands) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dscjax",
        description="Differentiable simulator of adaptive dynamic surface control with hysteresis.",
        epilog=__doc__,
    )
    parser.add_argument("--version", action=_Version, nargs=0, default=argparse.SUPPRESS,
                        help="show the version, then the JAX backends and devices, and exit")
    parser.add_argument("--no-compilation-cache", action="store_true",
                        help="do not keep compiled programs in JAX's persistent cache "
                        "($XDG_CACHE_HOME/dscjax/jax or ~/.cache/dscjax/jax; also "
                        "DSCJAX_NO_COMPILATION_CACHE=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in commands.items():
        description = getattr(module, "DESCRIPTION", module.__doc__)
        module.add_options(sub.add_parser(name, help=module.HELP, description=description))
    parser.subcommands = sub.choices  # name -> its parser (`main`)
    return parser


def typed_program() -> list[str]:
    """The program as the user typed it: `sys.argv[0]` (e.g. .venv/bin/dscjax), or `python -m
    dscjax.cli.main` with the interpreter that runs it."""
    prog = sys.argv[0] if sys.argv else ""
    if prog and os.path.abspath(prog) == os.path.abspath(__file__):
        return [sys.executable, "-m", "dscjax.cli.main"]
    return [prog if prog not in ("", "-c") else "dscjax"]


def main(argv=None) -> int:
    commands = _available_commands()
    parser = build_parser(commands)
    # the program as typed (hints repeat it); "dscjax" when called with arguments (tests)
    prog = typed_program() if argv is None else ["dscjax"]
    argv = list(sys.argv[1:] if argv is None else argv)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # reported by the subcommand it was given to ("dscjax hysteresis: error: ...")
        parser.subcommands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    args.argv, args.prog = argv, prog
    # Float64 is the default everywhere in the CLI; --float32 casts the setup instead.
    os.environ.setdefault("JAX_ENABLE_X64", "1")
    import jax

    jax.config.update("jax_enable_x64", True)
    from dscjax import xla

    if not (args.no_compilation_cache or xla.cache_opted_out()):
        xla.enable_compilation_cache()  # compiled programs survive the process (an entry
        # point's choice: the library never changes JAX's configuration by itself)
    from dscjax.files import NoSpace
    from dscjax.progress import Abort, handle_interrupts, signal_name
    from dscjax.simulate import DivergenceError
    from dscjax.validation import ConfigError

    module = commands[args.command]
    try:
        # the lock on --out and the clean-up of an --out left empty (cli.out.prepare_out)
        # last as long as the command
        with handle_interrupts(), contextlib.ExitStack() as args.exit_stack:
            if not getattr(args, "print_config", False):
                check_out(args)  # an --out the system refuses: one line, before any work
            return int(module.run(args) or 0)
    except ConfigError as err:
        print(f"dscjax {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except DivergenceError as err:
        print(f"dscjax {args.command}: simulation diverged: {err}", file=sys.stderr)
        return EXIT_DIVERGED
    except NoSpace as err:
        why = "" if err.errno == errno.ENOSPC else f" ({err.strerror})"
        # the command that continues (--resume, where something is kept) or runs it again
        resumable = getattr(module, "resumable", None)
        how = (f"rerun with: {resume_command(args)}" if resumable and resumable(args) else
               f"run the same command again: {rerun_command(args)}")
        print(f"dscjax {args.command}: error: no space left on the device writing "
              f"{err.filename}{why}; free space and {how}", file=sys.stderr)
        return EXIT_NO_SPACE
    except (KeyboardInterrupt, Abort) as stop:
        # a command without its own hint: the files it finished (or nothing), and the
        # command that runs it again
        hint = getattr(module, "interrupt_hint", None)
        note = hint(args) if hint is not None else kept_text(args, module.OUTPUTS)
        signum = int(getattr(stop, "signum", signal.SIGINT))  # SIGINT: a plain KeyboardInterrupt
        by = "" if signum == signal.SIGINT else f" by {signal_name(signum)}"
        what = (f"interrupted again{by}: stopped at once without saving the step under way"
                if isinstance(stop, Abort) else f"interrupted{by}")
        print(f"\ndscjax {args.command}: {what}" + (f"; {note}" if note else ""),
              file=sys.stderr)
        return 128 + signum  # 130 for Ctrl-C, 143 SIGTERM, 129 SIGHUP


if __name__ == "__main__":
    sys.exit(main())
