"""The benchmark suite's one harness: interleaved timings, the machine and its load, a printed
table, a JSON file and the benchmark's section of docs/benchmarks.md.

    bench = Bench("core", "The simulator core", quick=args.quick)
    times = bench.interleaved({"dscjax": run_a, "scipy": run_b}, repeats=5)  # A B A B ...
    bench.add(case="one trajectory", dscjax_ms=1e3 * median(times["dscjax"]), ...)
    bench.finish()      # table on stdout, results/bench/core.json, docs/benchmarks.md

Cases are run in turn (A B C A B C ...) after one warm-up call each (compilation), so a drift
of the shared machine's speed hits every case alike; ratios against a baseline are taken from
medians measured in the same run. The load average is read before and after and written beside
every figure. `quick` (the suite's CI mode) marks the results as a smoke run: they are printed
and written to JSON but never to docs/benchmarks.md. `child` runs a command in a fresh process
and measures its wall time and peak RSS (start-up, compilation and memory of a whole command).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
RESULTS = ROOT / "results" / "bench"
# New sections go above this heading of docs/benchmarks.md (the deleted studies stay last).
STUDIES = "## Studies that left the suite"


def parser(doc: str, repeats: str | None = None, default: int | None = None
           ) -> argparse.ArgumentParser:
    """A benchmark's argument parser (its description the first line of `doc`), with --quick,
    and with `repeats` (what is repeated) --repeats N (N > 0, default `default`)."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--quick", action="store_true",
                   help="small sizes, a minute or two; results to JSON only, not to the docs")
    if repeats is not None:
        p.add_argument("--repeats", type=positive(), default=default, help=repeats)
    return p


def positive(kind=int):
    """An argparse type: an integer (kind=int) or a finite number > 0, else the option's one-line
    error naming the range and the value (exit 2)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not value > 0 or value != value or value == float("inf"):
            what = "an integer" if kind is int else "a finite number"
            raise argparse.ArgumentTypeError(f"must be {what} > 0 (got {text!r})")
        return value

    return parse


def reference_loop():
    """The independent plain-Python loop of the paper's example (tests/reference_paper.py),
    the baseline of scipy's solve_ivp, loaded by its path (sys.path is left alone)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "reference_paper", ROOT / "tests" / "reference_paper.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def diffrax_rk4():
    """(diffrax, an instance of its solver with the classical RK4 tableau), or None without
    diffrax (`pip install -e ".[bench]"`): the peer both diffrax comparisons use."""
    try:
        import diffrax
    except ImportError:
        return None
    import numpy as np

    class RK4(diffrax.AbstractERK):
        tableau = diffrax.ButcherTableau(
            c=np.array([0.5, 0.5, 1.0]), b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
            b_error=np.zeros(4),
            a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])))
        interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

        def order(self, terms):
            return 4

    return diffrax, RK4()


def median(values) -> float:
    return float(statistics.median(values))


def _block(result):
    """Wait for JAX's asynchronous results (any pytree; other values pass through)."""
    try:
        import jax

        return jax.block_until_ready(result)
    except (ImportError, TypeError):
        return result


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """What the figures were measured on."""
    import jax

    devices = jax.devices()
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "backend": jax.default_backend(),
            "devices": f"{len(devices)} x {devices[0].device_kind}"}


def load() -> float:
    return os.getloadavg()[0]


@dataclasses.dataclass
class Child:
    """A command run in a fresh process (`child`)."""

    returncode: int
    wall_s: float
    peak_rss_mib: float  # its own high-water mark, also when it was killed
    stdout: str
    stderr: str
    killed: bool  # stopped because its resident memory passed the limit


# A small process that forks the command, kills it past a resident memory of argv[1] MiB and
# reports its peak RSS from wait4. A command forked by the benchmark itself would report the
# benchmark's own peak: Linux carries the high-water mark of the forking process into exec.
_LAUNCHER = """
import os, sys, time
limit, argv = float(sys.argv[1]), sys.argv[2:]
pid = os.fork()
if pid == 0:
    os.execvp(argv[0], argv)
killed = False
while True:
    done, status, usage = os.wait4(pid, os.WNOHANG)
    if done:
        break
    try:
        with open(f"/proc/{pid}/status") as f:
            rss = [float(x.split()[1]) / 1024 for x in f if x.startswith("VmRSS:")]
    except OSError:
        rss = []
    if limit > 0 and not killed and rss and rss[0] > limit:
        os.kill(pid, 9)
        killed = True
    time.sleep(0.05)
sys.stderr.write(f"\\nharness: peak {usage.ru_maxrss / 1024} killed {int(killed)}\\n")
sys.exit(os.waitstatus_to_exitcode(status))
"""


def child(argv, *, env=None, limit_mib: float | None = None) -> Child:
    """Run `argv` in a fresh process: its wall time (start-up included) and peak RSS; it is
    killed once its resident memory passes `limit_mib` (checked every 50 ms)."""
    cmd = [sys.executable, "-c", _LAUNCHER, str(limit_mib or 0), *map(str, argv)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    head, _, tail = proc.stderr.rpartition("\nharness: peak ")
    peak, killed = tail.split()[0], tail.split()[2] == "1"
    return Child(proc.returncode, wall, float(peak), proc.stdout, head, killed)


def cold_env(*drop: str) -> dict[str, str]:
    """The environment of a cold measurement: this one without a persistent compilation cache
    (JAX_COMPILATION_CACHE_DIR) and without the variables `drop`."""
    return {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", *drop)}


def run_child(script, *args, env=None, limit_mib: float | None = None
              ) -> tuple[Child, dict | None]:
    """A benchmark's own measurement `script --child ARGS` in a fresh process (`child`): the
    run, and the JSON object its last line of stdout holds (None if it failed or was killed).
    The script's main answers the call with `child_call`."""
    run = child([sys.executable, script, "--child", *args], env=env, limit_mib=limit_mib)
    ok = run.returncode == 0 and not run.killed
    return run, json.loads(run.stdout.strip().splitlines()[-1]) if ok else None


def child_call(argv, measure: Callable[[list[str]], int]) -> int | None:
    """`measure(ARGS)`'s exit code where argv is `--child ARGS` (`run_child`), else None."""
    return measure(argv[1:]) if argv[:1] == ["--child"] else None


class Bench:
    """One benchmark's results (see the module docstring)."""

    def __init__(self, name: str, title: str, *, quick: bool = False,
                 command: str | None = None):
        self.name, self.title, self.quick = name, title, quick
        self.command = command or "python " + " ".join(
            [f"experiments/{Path(sys.argv[0]).name}", *sys.argv[1:]])
        self.rows: list[dict] = []
        self.notes: list[str] = []
        self.loads = [load()]
        self.started = datetime.datetime.now().astimezone()

    def interleaved(self, cases: Mapping[str, Callable[[], object]], repeats: int = 5,
                    warmup: int = 1) -> dict[str, list[float]]:
        """{case: seconds of each of `repeats` calls}, the cases called in turn after `warmup`
        calls each that are not counted."""
        for fn in cases.values():
            for _ in range(warmup):
                _block(fn())
        times: dict[str, list[float]] = {k: [] for k in cases}
        for _ in range(repeats):
            for k, fn in cases.items():
                t0 = time.perf_counter()
                _block(fn())
                times[k].append(time.perf_counter() - t0)
        self.loads.append(load())
        return times

    def read_load(self) -> None:
        """Read the load average now (beside the reads of `interleaved` and `finish`)."""
        self.loads.append(load())

    def add(self, **row) -> None:
        """One row of the table (its keys are the columns, in order)."""
        self.rows.append(row)

    def note(self, text: str) -> None:
        """A sentence printed and written under the table."""
        self.notes.append(text)

    def table(self) -> str:
        """The rows as a Markdown table."""
        if not self.rows:
            return ""
        cols = list(dict.fromkeys(k for r in self.rows for k in r))
        lines = ["| " + " | ".join(c.replace("_", " ") for c in cols) + " |",
                 "|" + "---|" * len(cols)]
        for r in self.rows:
            lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
        return "\n".join(lines)

    def header(self) -> str:
        m = machine()
        loads = f"{min(self.loads):.1f}-{max(self.loads):.1f}"
        return (f"Measured {self.started:%Y-%m-%d} on {m['cpu']} ({m['cores']} cores, "
                f"{m['backend']}: {m['devices']}), load average {loads}, jax "
                f"{m['jax']}: `{self.command}`")

    def finish(self, extra: dict | None = None) -> dict:
        """Print the table, write results/bench/NAME.json (with `extra`'s keys) and (unless
        quick) the section of docs/benchmarks.md. Returns the JSON record."""
        self.loads.append(load())
        record = {"name": self.name, "title": self.title, "date": self.started.isoformat(),
                  "machine": machine(), "load": self.loads, "command": self.command,
                  "quick": self.quick, "rows": self.rows, "notes": self.notes, **(extra or {})}
        text = "\n\n".join(x for x in (self.header(), self.table(), "\n".join(
            f"- {n}" for n in self.notes)) if x)
        print(f"\n## {self.title}" + (" (quick: not written to docs)" if self.quick else ""))
        print(text)
        RESULTS.mkdir(parents=True, exist_ok=True)
        path = RESULTS / f"{self.name}{'-quick' if self.quick else ''}.json"
        path.write_text(json.dumps(record, indent=2, default=str) + "\n")
        print(f"wrote {path.relative_to(ROOT)}")
        if not self.quick:
            write_section(self.name, self.title, text)
            print(f"updated {DOC.relative_to(ROOT)}")
        return record


def write_section(name: str, title: str, text: str, doc: Path = DOC) -> None:
    """Replace the benchmark's section of docs/benchmarks.md, between its markers; a new one
    goes above the deleted studies' section (or at the end)."""
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    body = f"{begin}\n## {title}\n\n{text}\n{end}"
    old = doc.read_text() if doc.exists() else "# Benchmarks\n"
    if begin in old and end in old:
        new = old[:old.index(begin)] + body + old[old.index(end) + len(end):]
    elif f"\n{STUDIES}" in old:
        i = old.index(f"\n{STUDIES}") + 1
        new = old[:i] + body + "\n\n" + old[i:]
    else:
        new = old.rstrip("\n") + "\n\n" + body + "\n"
    doc.write_text(new)


def _fmt(v) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)
