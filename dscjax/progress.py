"""Progress of long runs on stderr: one display for every command, drawn by tqdm.

    with Progress(total=n, desc="  sweep", unit="sample") as bar:
        for ...:
            bar.update_to(done, postfix="2.1e7 steps/s")

On a terminal tqdm redraws one line in place; elsewhere (a log, CI, a pipe) the same figures
are printed as plain lines, at most every `every_s` seconds and once at the end.

Under `handle_interrupts` (installed by the CLI) a Ctrl-C inside a `critical()` section (a
generation and its state update, a checkpoint write) is deferred to the section's end, so the
state saved on interrupt is whole; a second Ctrl-C then raises `Abort` at once.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

from tqdm import tqdm

# A plain line: "  sweep  40 % (4000/10000 samples) 00:12 elapsed, ETA 00:18; 2.1e7 steps/s"
LINE = "{desc} {percentage:3.0f} % ({n_fmt}/{total_fmt} {unit}) {elapsed} elapsed, ETA {remaining}"
# ... and without a total (work that stops on a time limit or a criterion, not a count)
OPEN_LINE = "{desc} {n_fmt} {unit}, {elapsed} elapsed"


class Progress:
    """A progress display of `total` units of work (see the module docstring).

    Args:
        total: units of work in all (None: unknown; no percentage or ETA).
        desc: the start of the line.
        unit: the unit's name ("sample", ...), pluralised with an s unless the count is 1.
        initial, elapsed: units done and seconds spent before (a resumed run).
        file: where to write (default stderr).
        every_s: the least time between two plain lines (not on a terminal).
        enabled: False shows nothing (--quiet).
    """

    def __init__(self, total: int | None, *, desc: str, unit: str, initial: int = 0,
                 elapsed: float = 0.0, file: TextIO | None = None, every_s: float = 5.0,
                 enabled: bool = True):
        self.file = file if file is not None else sys.stderr
        self.total, self.desc, self.unit = total, desc, unit
        self.enabled = enabled
        self.tty = enabled and hasattr(self.file, "isatty") and self.file.isatty()
        self.every_s = every_s
        self.n, self.initial = initial, initial
        self.postfix = ""
        self.start = time.perf_counter() - elapsed
        self.last = -float("inf")
        self.bar = None
        if self.tty:
            self.bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, file=self.file,
                            dynamic_ncols=True, leave=True)
            self.bar.start_t -= elapsed

    def restart_clock(self) -> None:
        """Count elapsed time (and so the rate and ETA) from now: call it when the work
        proper starts, e.g. after compilation."""
        self.start = time.perf_counter()
        if self.bar is not None:
            self.bar.reset(total=self.total)
            self.bar.update(self.n)

    def update_to(self, n: int, postfix: str = "") -> None:
        """n units are done now; `postfix` is shown after the figures."""
        self.n, self.postfix = n, postfix
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(postfix, refresh=False)
            self.bar.update(n - self.bar.n)
            return
        now = time.perf_counter()
        if (self.total is not None and n >= self.total) or now - self.last >= self.every_s:
            self._line(now)

    def _line(self, now: float) -> None:
        self.last = now
        elapsed = now - self.start
        done = self.n - self.initial
        rate = done / elapsed if elapsed > 0 and done > 0 else None
        count = self.total if self.total is not None else self.n
        unit = self.unit + ("" if count == 1 else "s")  # "1 generation", "2 generations"
        text = tqdm.format_meter(self.n, self.total, elapsed, prefix=self.desc, unit=unit,
                                 rate=rate, initial=self.initial,
                                 bar_format=LINE if self.total is not None else OPEN_LINE)
        print(text + (f"; {self.postfix}" if self.postfix else ""), file=self.file,
              flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- Ctrl-C ------------------------------------------------------------------------------------


class Abort(BaseException):
    """A second Ctrl-C while the first was deferred: stop at once, without saving. Not a
    KeyboardInterrupt, so that the handlers that save on Ctrl-C let it pass."""


class _Deferral:
    """The state of `handle_interrupts` (main thread only)."""

    installed = False
    depth = 0  # nested critical sections now open
    pending = False  # a Ctrl-C arrived inside one


_DEFERRAL = _Deferral()
DEFERRED = ("\n  Ctrl-C: finishing the current step to save a whole state (Ctrl-C again stops "
            "at once, without saving)\n")


def _on_sigint(signum, frame) -> None:
    if _DEFERRAL.depth == 0:
        raise KeyboardInterrupt
    if _DEFERRAL.pending:
        raise Abort
    _DEFERRAL.pending = True
    try:  # not through sys.stderr's buffer, which the interrupted code may be writing
        os.write(sys.stderr.fileno(), DEFERRED.encode())
    except (AttributeError, OSError, ValueError):
        sys.stderr.write(DEFERRED)


@contextmanager
def handle_interrupts() -> Iterator[None]:
    """Install the deferral of Ctrl-C for the block (see the module docstring): a command's
    entry point calls it, never a library. Outside the main thread it does nothing (only the
    main thread receives signals). The previous SIGINT handler is restored afterwards."""
    if threading.current_thread() is not threading.main_thread() or _DEFERRAL.installed:
        yield
        return
    previous = signal.signal(signal.SIGINT, _on_sigint)
    _DEFERRAL.installed, _DEFERRAL.depth, _DEFERRAL.pending = True, 0, False
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _DEFERRAL.installed, _DEFERRAL.depth, _DEFERRAL.pending = False, 0, False


class critical:
    """A section a Ctrl-C does not cut: under `handle_interrupts` (main thread), a Ctrl-C
    inside it raises KeyboardInterrupt when the outermost section ends (unless the section
    raised something else). Sections nest; elsewhere it changes nothing."""

    def __enter__(self) -> critical:
        self.active = (_DEFERRAL.installed
                       and threading.current_thread() is threading.main_thread())
        if self.active:
            _DEFERRAL.depth += 1
        return self

    def __exit__(self, kind, value, tb) -> bool:
        if not self.active:
            return False
        _DEFERRAL.depth -= 1
        if _DEFERRAL.depth == 0 and _DEFERRAL.pending:
            _DEFERRAL.pending = False
            if kind is None:
                raise KeyboardInterrupt
        return False


__all__ = ["Abort", "Progress", "critical", "handle_interrupts"]
