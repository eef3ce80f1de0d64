"""Run the shell examples of README.md and docs/*.md with small sizes.

    python tests/doc_examples.py WORKDIR          # all of them, in order, in one directory
    python tests/doc_examples.py WORKDIR GROUP    # one group of `plan()`: shared, README.md, ...

prints a JSON report; exit 1 if any failed. tests/test_docs.py runs each group through
`run_group` in its own process. Every `dscjax ...` line of a shell block (```, ```bash) of
README.md, then of docs/*.md, runs through `dscjax.cli.main.main`, as a user who follows the
documents in order would type it (so the docs may use what the README's examples wrote:
`my.toml`, `results/tune/gains.json`), with these changes only:

- sizes: 200 RK4 steps (--t-final 200 dt: at dt = 1 ms the 0.2 s of the suite's other
  command-line tests, whose compiled programs the worker then shares), --samples
  8, grid axes of 2 points, --steps 1 (2 to resume), --batch 2, --heldout 0, --adversarial 1
  with searches by random sampling for 0.2 s, --complexity for n = 2..3 with 1
  build, --theory-orders without the orders above 3 and the alpha_0 study at alpha_0 = 1 only
  (--alpha0 1),
  sweeps re-simulate 1 worst sample, worst-case searches by random sampling only for 0.2 s
  (--methods random, --batch 2), no figures for tune, sweep, worst-case and reproduce
  (--no-plot; their figures are tested in test_tuning_loop.py, test_sweep.py,
  test_reproduce.py and by the benchmark) but where a --format is asked for (--dpi 30);
- export (no horizon) as printed; identify on the whole record, with 3 Marquardt steps and no
  figures (--max-steps 3 --no-plot);
- `> FILE` redirects stdout to FILE; the example records dscjax/data/*.csv are where they are
  in a clone;
- a ```toml block whose first line is `# file: NAME` is written to NAME where it stands (a
  config the commands after it read);
- a command printed twice (the docs repeat the README) runs once, in the first document
  that prints it, or in the document of HOME that reads its outputs;
- multi-host lines (--coordinator, --distributed) are skipped: they need several processes
  (tests/test_sweep.py runs two).

The groups of `plan()` are independent: the commands whose outputs other documents read
(SHARED: `my.toml`, the README's tune run) form the group "shared"; each document's group is
the rest of its commands, run in a copy of the shared group's directory when it reads them
(READS_SHARED).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shlex
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHELL = ("", "bash", "sh", "shell", "console")
SKIP = ("--coordinator", "--distributed")
N_STEPS = 200


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


FILE = "# file: "


def commands(text: str) -> list[list[str]]:
    """The argv (after `dscjax`) of every dscjax command in the shell blocks, in order; a
    redirect stays in the list as '>' FILE; a TOML block that names a file is the entry
    [FILE, NAME, its text]."""
    out, block, lang, toml = [], False, "", None
    for line in text.splitlines():
        if line.startswith("```"):
            if toml is not None:
                out.append([FILE, toml[0], "\n".join(toml[1:]) + "\n"])
                toml = None
            block, lang = not block, line[3:].strip()
            continue
        if block and lang == "toml" and (toml is not None or line.startswith(FILE)):
            toml = [line[len(FILE):].strip()] if toml is None else [*toml, line]
            continue
        if not block or lang not in SHELL:
            continue
        for part in line.split("&&"):
            if part.split()[:1] not in (["dscjax"], [".venv/bin/dscjax"]):
                continue  # not a command (a plain ``` block may hold a diagram)
            words = shlex.split(part, comments=True)
            if words and words[0] in (".venv/bin/dscjax", "dscjax"):
                out.append(words[1:])
    return out


def _set(argv: list[str], option: str, value: str, add: bool = True) -> None:
    if option in argv:
        argv[argv.index(option) + 1] = value
    elif add:
        argv += [option, value]


def shrink(argv: list[str]) -> list[str]:
    """The same command with small sizes (see the module docstring)."""
    a = list(argv)
    command = a[0]
    if (("--print-config" not in a or command == "simulate")
            and command not in ("export", "identify")):
        # the same number of steps whatever dt: one compiled program serves every command
        dt = float(a[a.index("--dt") + 1]) if "--dt" in a else 1e-3
        _set(a, "--t-final", f"{N_STEPS * dt:g}")
    if command == "sweep":
        if "--grid" in a:
            a = [f"{w.rsplit(':', 1)[0]}:2" if i and a[i - 1] == "--grid" else w
                 for i, w in enumerate(a)]
        else:
            _set(a, "--samples", "8")
        _set(a, "--worst", "1")
        _set(a, "--random", "0")
        a.append("--no-plot")
    elif command == "tune":
        _set(a, "--steps", "2" if "--steps" in a else "1")
        _set(a, "--batch", "2", add=False)
        _set(a, "--heldout", "0")
        if "--adversarial" in a:  # one round, searches by random sampling for 0.2 s
            _set(a, "--adversarial", "1")
            _set(a, "--search-time", "0.2")
            _set(a, "--search-method", "random")
        a.append("--no-plot")
    elif command == "identify":  # the record's own length: a few Marquardt steps
        _set(a, "--max-steps", "3")
        a.append("--no-plot")
    elif command == "sensitivity":
        _set(a, "--batch", "2", add=False)
    elif command == "worst-case":
        _set(a, "--time-limit", "0.2")
        _set(a, "--methods", "random")
        _set(a, "--batch", "2")
        a.append("--no-plot")
    elif command == "reproduce":
        if "--format" in a:  # the figures in that format, small
            _set(a, "--dpi", "30")
        else:
            a.append("--no-plot")
        if "--complexity" in a:
            _set(a, "--orders", "2-3")
            _set(a, "--repeats", "1")
        if "--theory-orders" in a:  # n = 4 compiles ~40 s (its V: test_lyapunov)
            orders = [o for o in a[a.index("--theory-orders") + 1].split(",") if int(o) <= 3]
            _set(a, "--theory-orders", ",".join(orders) or "2")
        if "--theory" in a:  # each alpha_0 picks its own step: one program per value
            _set(a, "--alpha0", "1")
    return a


def redirect(argv: list[str]) -> tuple[list[str], str | None]:
    """(the command, the file after '>' or None)."""
    if ">" in argv:
        i = argv.index(">")
        return argv[:i], argv[i + 1]
    return argv, None


def run_one(argv: list[str], target: str | None) -> tuple[int, str]:
    """(exit code, the last lines of stderr) of one command; its stdout to `target`."""
    from commands import exit_code

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = exit_code(argv)
    if target is not None:
        Path(target).write_text(out.getvalue())
    return int(code or 0), "\n".join(err.getvalue().strip().splitlines()[-3:])


def _join(words: list[str]) -> str:
    """The command line as a shell would take it (a redirect stays unquoted)."""
    return " ".join(w if w == ">" else shlex.quote(w) for w in words)


# The commands (as printed) whose outputs other documents read, and the documents that read
# them (my.toml, results/tune/: the README's `tune`, resumed by tuning.md's `tune --resume`).
SHARED = ("dscjax simulate --print-config > my.toml", "dscjax tune")
READS_SHARED = ("README.md", "hysteresis.md", "sweeps.md", "tuning.md")
# A command the README prints whose outputs one other document reads runs in that document's
# group (identification.md replays, tunes and exports what `identify` wrote).
HOME = {"dscjax identify --data dscjax/data/record.csv --free 'plant.g[0],plant.theta[0],"
        "hysteresis.alpha,hysteresis.lam,hysteresis.psi' --segments 4 --out results/identify":
        "identification.md"}


def plan() -> dict[str, list[tuple]]:
    """{group: its steps in order}: the group "shared" (the commands of SHARED), then one
    group per document. A step is ("file", NAME, TEXT) or ("run", printed, small argv,
    redirect target or None); each command (after `shrink`) runs in one group only."""
    groups, done = {"shared": []}, set()
    for doc in documents():
        steps = groups.setdefault(doc.name, [])
        for argv in commands(doc.read_text()):
            if argv[0] == FILE:
                steps.append(("file", argv[1], argv[2]))
                continue
            if any(s in argv for s in SKIP):
                continue
            command, target = redirect(argv)
            small = shrink(command)
            ran = _join(["dscjax", *small] + ([">", target] if target else []))
            if ran in done:
                continue
            done.add(ran)
            printed = _join(["dscjax", *argv])
            home = ("shared" if printed in SHARED else HOME.get(printed, doc.name))
            groups.setdefault(home, []).append(("run", printed, small, target))
    return groups


def run_group(work: Path, group: str, steps: list[tuple]) -> list[dict]:
    """Run `steps` in `work` (the current directory meanwhile): one report entry a command."""
    report = []
    work.mkdir(parents=True, exist_ok=True)
    data = work / "dscjax" / "data"  # the example records, where a clone has them
    if not data.exists():
        data.parent.mkdir(exist_ok=True)
        data.symlink_to(ROOT / "dscjax" / "data")
    os.chdir(work)
    for step in steps:
        if step[0] == "file":
            Path(step[1]).write_text(step[2])
            continue
        _, printed, small, target = step
        t0 = time.perf_counter()
        code, err = run_one(small, target)
        report.append(dict(doc=group, printed=printed,
                           ran=_join(["dscjax", *small] + ([">", target] if target else [])),
                           code=code, seconds=round(time.perf_counter() - t0, 1),
                           stderr=err if code else ""))
    return report


def main(work: Path, group: str | None = None) -> int:
    groups = plan()
    names = list(groups) if group is None else [group]
    if group is not None and group not in groups:
        print(f"doc_examples.py: GROUP must be one of {', '.join(groups)} (got {group!r})",
              file=sys.stderr)
        return 2
    report = [r for name in names for r in run_group(work, name, groups[name])]
    print(json.dumps(report, indent=1))
    return 1 if any(r["code"] for r in report) else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]).resolve(), *sys.argv[2:3]))
