"""--out, the one rule of every command's output directory: what a command writes
(`Outputs`), the checks before any work (`check_out`), the directory made ready and locked
(`prepare_out`: refused when it holds another run's or another command's files, unless
--overwrite or --resume), a command's start in its order (`start`: the device, --out, the
start line), what an interrupted command keeps (`kept_text`), and the command that continues
it or runs it again (`resume_command`, `rerun_command`)."""

from __future__ import annotations

import dataclasses
import importlib
import os
import shlex
import shutil
import tempfile
from pathlib import Path

from dscjax import files
from dscjax.cli.common import COMMANDS, banner, listed, use_device
from dscjax.validation import ConfigError


def add_out_arg(p, default: str, *, later: bool = False, **rest):
    """--out DIR of a command (the one rule of --out, README), then `add_overwrite_arg(p,
    **rest)`, unless the command declares those `later` (after options of its own)."""
    p.add_argument("--out", default=default, metavar="DIR",
                   help=f"output directory (default: {default})")
    if not later:
        add_overwrite_arg(p, **rest)


def add_overwrite_arg(p, resume: str | None = None, overwrite: str | None = None, *,
                      plot: str | None = None, quiet: str | None = None):
    """--overwrite (the one rule of --out, README); for a command that continues an
    interrupted run, --resume (help `resume`) too, the two exclusive; then --no-plot (help
    `plot`) and --quiet (help `quiet`) where the command has them."""
    group = p.add_mutually_exclusive_group() if resume else p
    if resume:
        group.add_argument("--resume", action="store_true", help=resume)
    group.add_argument("--overwrite", action="store_true", help=overwrite or "replace the "
                       "files of an earlier run in DIR (only those this command writes); "
                       "without it such a DIR is refused")
    for flag, text in (("--no-plot", plot), ("--quiet", quiet)):
        if text:
            p.add_argument(flag, action="store_true", help=text)


@dataclasses.dataclass(frozen=True)
class Outputs:
    """What a command writes into its --out, declared once per command: file names or glob
    patterns, and folders. The one rule of an existing --out checks them and --overwrite
    deletes them, never anything else. `at_end`: they are written when the run ends, which an
    interrupted run says where it kept none (`kept_text`)."""

    files: tuple[str, ...]
    folders: tuple[str, ...] = ()
    at_end: bool = False

    def found(self, out: Path) -> list[str]:
        """The outputs present in `out` (folders with a trailing /), sorted."""
        names = {p.name for pattern in self.files for p in out.glob(pattern) if p.is_file()}
        names |= {f"{p.name}/" for pattern in self.folders for p in out.glob(pattern)
                  if p.is_dir()}
        return sorted(names)

    def remove(self, out: Path) -> None:
        for name in self.found(out):
            (shutil.rmtree if name.endswith("/") else Path.unlink)(out / name.rstrip("/"))


def check_out(args) -> None:
    """Refuse an --out the system cannot take as an output directory, before any work: an
    empty path, a name too long, a component that is a file, no permission, a read-only file
    system (`files.out_problem`); one line naming the path and the reason, exit 2."""
    if not str(args.out).strip():
        raise ConfigError(f"--out {str(args.out)!r}: an empty path; give a directory, e.g. "
                          f"--out results/run (or --out . for the current one)")
    problem = files.out_problem(args.out)
    if problem is not None:
        raise _unwritable(args, problem)


def _unwritable(args, why) -> ConfigError:
    return ConfigError(f"--out {str(args.out)!r}: cannot write the output there ({why}); give "
                       f"a writable directory")


def _other_commands(args, outputs: Outputs, out: Path) -> dict[str, list[str]]:
    """{command: its files in `out` that this command would replace}: for each other command
    whose own files are in `out` (those no other command writes, e.g. a sweep's sweep.json),
    the files of `outputs` found there that are among its outputs too (summary.json). A
    command may replace or delete only the files that it wrote itself."""
    ours = set(outputs.found(out))
    if not ours:
        return {}
    found = {name: set(importlib.import_module(module).OUTPUTS.found(out))
             for name, module in COMMANDS.items() if name != args.command}
    # its own files are there (named by neither this command nor another), and shared names
    return {name: sorted(theirs & ours) for name, theirs in found.items() if theirs & ours
            and theirs - ours.union(*(f for n, f in found.items() if n != name))}


def prepare_out(args, outputs: Outputs, *, resumable: bool = False, lock: str | None = None,
                check: bool = True) -> Path:
    """Make `args.out` ready, after every input has been validated: refuse a DIR that is a
    file, cannot be written or is held by another process (one line, exit 2); create it if new
    (removed again if the command leaves it empty); lock it (`files.lock_out`, file `lock`) for
    the command (`args.exit_stack`); refuse a DIR holding `outputs` unless --resume
    (`resumable`) or --overwrite (deletes them, nothing else). `cli.main` ran `check_out`
    before the command: what the system refuses here all the same is refused below."""
    out = Path(args.out)
    try:
        new = [p for p in (out, *out.parents) if not p.exists()]  # created here, leaf first
        args.exit_stack.callback(_remove_if_empty, new)
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=out, prefix=".dscjax-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise _unwritable(args, err.strerror or err) from None
    args.exit_stack.enter_context(files.lock_out(out, name=lock or files.LOCK,
                                                 argv=[*args.prog, *args.argv]))
    if check:
        clash = _other_commands(args, outputs, out)
        if clash:
            shown = "; ".join(f"`dscjax {name}`: {', '.join(names)}"
                              for name, names in clash.items())
            raise ConfigError(f"--out {str(args.out)!r} holds the results of another "
                              f"command, which this one would replace ({shown}); give another "
                              f"--out")
        found = outputs.found(out)
        if found and not (getattr(args, "overwrite", False) or getattr(args, "resume", False)):
            how = ("--resume to continue them, --overwrite to start afresh (deleting only "
                   "them)" if resumable else "--overwrite to replace them")
            raise ConfigError(f"--out {str(args.out)!r} already holds files this command "
                              f"writes ({listed(found, 4)}); {how}, or give another --out")
        if getattr(args, "overwrite", False):
            outputs.remove(out)
    return out


def start(args, outputs: Outputs, text: str, device: str | None = None, rows: int = 1,
          warnings=(), **prepare) -> Path:
    """A command's work begins, in this order: its device (`common.use_device` of `device`
    for `rows` trajectories run together, named at the end of the start line, "; on ...", or
    alone where `text` is empty), so that one not here is refused before --out is touched;
    --out made ready for `outputs` (`prepare_out`, with `prepare`); the start line `text` and
    its `warnings` (`common.banner`). Returns --out."""
    if device is not None:
        text = "; ".join(filter(None, [text, f"on {use_device(args, device, rows)}"]))
    out = prepare_out(args, outputs, **prepare)
    banner(args, text, warnings)
    return out


def nothing_kept(args, why: str = "") -> str:
    """The hint of an interrupted command that keeps nothing (`why`, e.g. that it writes its
    files when it ends), and the command that runs it again (`rerun_command`)."""
    return f"nothing is kept{why}; run the same command again: {rerun_command(args)}"


def kept_text(args, outputs: Outputs) -> str:
    """What an interrupted command that cannot resume says it keeps: the files it finished
    (`outputs` found in --out: the rule of --out let it start only where none was), or
    nothing (`nothing_kept`, saying why where `outputs.at_end`); then the command that makes
    them all."""
    out = Path(args.out)
    found = outputs.found(out)  # none where --out is not a directory
    if not found:
        return nothing_kept(args, " (the files are written when the run ends)"
                            if outputs.at_end else "")
    return (f"the {len(found)} file(s) finished before it are kept in {out} "
            f"({listed(found, 4)}), the rest is not written; run the same command again: "
            f"{rerun_command(args)}")


def resume_command(args) -> str:
    """The command line that continues an interrupted run: the program as typed, the same
    arguments, --resume instead of --overwrite."""
    return _typed_again(args, "--overwrite", "--resume")


def resume_text(args, kept: str) -> str:
    """What an interrupted command that can resume keeps (`kept`), and the command that
    continues it (`resume_command`)."""
    return f"{kept}; continue with: {resume_command(args)}"


def rerun_command(args) -> str:
    """The command line that runs a command again from the start: the program as typed, the
    same arguments without --resume, and --overwrite where --out holds files the command
    writes (the one rule of --out would refuse the run otherwise)."""
    outputs = importlib.import_module(COMMANDS[args.command]).OUTPUTS
    return _typed_again(args, "--resume", "--overwrite", outputs.found(Path(args.out)))


def _typed_again(args, drop: str, add: str, needed=True) -> str:
    """The command line as typed (the program, the same arguments) without the flag `drop`,
    with the flag `add` where `needed` and not already there."""
    argv = [a for a in args.argv if a != drop]
    return shlex.join([*args.prog, *argv, *([add] if needed and add not in argv else [])])


def _remove_if_empty(created: list[Path]) -> None:
    """The directories a command created for its --out (leaf first), removed if it left
    nothing in them."""
    for path in created:
        try:
            path.rmdir()
        except OSError:
            return
