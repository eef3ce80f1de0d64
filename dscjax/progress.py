"""Progress of long runs on stderr: one display for every command, drawn by tqdm.

    with Progress(total=n, desc="  sweep", unit="sample") as bar:
        for ...:
            bar.update_to(done, postfix="2.1e7 steps/s")

On a terminal tqdm redraws one line in place; elsewhere (a log, CI, a pipe) the same figures
are printed as plain lines, at most every `every_s` seconds and once at the end. The ETA is
shown once a unit of work was timed (never from compilation alone).

Work without a count (a compilation, a held-out check) is a `Phase`, shown only if it lasts:

    with Phase("  the held-out check (256 plants)"):
        ...

Under `handle_interrupts` (installed by the CLI) a Ctrl-C inside a `critical()` section (a
generation and its state update, a checkpoint write) is deferred to the section's end, so the
state saved on interrupt is whole; a second Ctrl-C then raises `Abort` at once. SIGTERM and
SIGHUP (`timeout`, batch schedulers, `docker stop`, a closed terminal) are handled alike, as
`Terminated`, a KeyboardInterrupt that carries the signal's number.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from types import SimpleNamespace
from typing import TextIO

from tqdm import tqdm

# A plain line: "  sweep  40 % (4000/10000 samples) 00:12 elapsed, ETA 00:18; 2.1e7 steps/s",
# without the ETA before a unit was timed (no rate yet)
START_LINE = "{desc} {percentage:3.0f} % ({n_fmt}/{total_fmt} {unit}) {elapsed} elapsed"
LINE = START_LINE + ", ETA {remaining}"
# ... and without a total (work that stops on a time limit or a criterion, not a count)
OPEN_LINE = "{desc} {n_fmt} {unit}, {elapsed} elapsed"


class Progress(AbstractContextManager):
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
        self.enabled, self.every_s = enabled, every_s
        self.n, self.initial = initial, initial
        self.start = time.perf_counter() - elapsed
        self.last = -float("inf")
        self.bar = None
        if enabled and self.file.isatty():
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
        self.n = n
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(postfix, refresh=False)
            self.bar.update(n - self.bar.n)
            return
        now = time.perf_counter()
        if (self.total is None or n < self.total) and now - self.last < self.every_s:
            return  # a plain line at most every every_s seconds, and the last
        self.last, elapsed = now, now - self.start
        done = n - self.initial
        rate = done / elapsed if elapsed > 0 and done > 0 else None
        count = self.total if self.total is not None else n
        unit = self.unit + ("" if count == 1 else "s")  # "1 generation", "2 generations"
        form = OPEN_LINE if self.total is None else LINE if rate is not None else START_LINE
        text = tqdm.format_meter(n, self.total, elapsed, prefix=self.desc, unit=unit,
                                 rate=rate, initial=self.initial, bar_format=form)
        print(text + (f"; {postfix}" if postfix else ""), file=self.file, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __exit__(self, *exc) -> None:
        self.close()


class Phase:
    """A phase of work without a count, on stderr: if it still runs after `after_s` seconds,
    "DESC ..." (on a terminal, redrawn with the time elapsed every second; elsewhere again
    every `every_s` seconds), and at its end "DESC: done in 12.3 s". A phase shorter than
    `after_s` shows nothing. Use it as a context manager, or `start()` and `stop()`."""

    def __init__(self, desc: str, *, after_s: float = 2.0, every_s: float = 30.0,
                 file: TextIO | None = None, enabled: bool = True):
        self.desc, self.after_s, self.every_s, self.enabled = desc, after_s, every_s, enabled
        self.file = file if file is not None else sys.stderr
        self.tty = enabled and self.file.isatty()
        self.shown = False
        self._stop = threading.Event()
        self._thread = None

    def start(self) -> Phase:
        self.t0 = time.perf_counter()
        if self.enabled:
            self._thread = threading.Thread(target=self._show, daemon=True)
            self._thread.start()
        return self

    def _show(self) -> None:
        if self._stop.wait(self.after_s):
            return
        self.shown = True
        while True:
            elapsed = tqdm.format_interval(time.perf_counter() - self.t0)
            self.file.write(f"\r{self.desc} ... {elapsed} elapsed" if self.tty
                            else f"{self.desc} ... ({elapsed} elapsed)\n")
            self.file.flush()
            if self._stop.wait(1.0 if self.tty else self.every_s):
                return

    def stop(self) -> None:
        """End the phase (again: nothing)."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        if self.shown:
            start, end = ("\r", "\033[K") if self.tty else ("", "")  # (erase the rest)
            self.file.write(f"{start}{self.desc}: done in "
                            f"{time.perf_counter() - self.t0:.1f} s{end}\n")
            self.file.flush()

    def __enter__(self) -> Phase:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


# -- Ctrl-C, SIGTERM, SIGHUP -------------------------------------------------------------------


class _Signalled:
    """An exception raised by a signal: `signum` is the signal's number, its name the text."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class Terminated(_Signalled, KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled as Ctrl-C is: `signum` is the signal's number (the CLI exits
    128 + signum, as a shell reports a process the signal ended)."""


class Abort(_Signalled, BaseException):
    """A second Ctrl-C (or SIGTERM, SIGHUP) while the first was deferred: stop at once, without
    saving. Not a KeyboardInterrupt, so that the handlers that save on Ctrl-C let it pass.
    `signum`: the signal that asked to stop."""


def signal_name(signum: int) -> str:
    """"Ctrl-C" for SIGINT, else the signal's name ("SIGTERM")."""
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


# the state of `handle_interrupts` (main thread only): the critical sections now open (depth)
# and the signal number of an interrupt that arrived inside one (pending, or None)
_DEFERRAL = SimpleNamespace(installed=False, depth=0, pending=None)
DEFERRED = ("\n  {name}: finishing the current step to save a whole state ({again} stops "
            "at once, without saving)\n")


def _interrupt(signum: int) -> KeyboardInterrupt:
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


def _on_signal(signum, frame) -> None:
    if _DEFERRAL.depth == 0:
        raise _interrupt(signum)
    if _DEFERRAL.pending is not None:
        raise Abort(signum)
    _DEFERRAL.pending = signum
    name = signal_name(signum)
    text = DEFERRED.format(name=name, again="Ctrl-C again" if name == "Ctrl-C"
                           else f"{name} or Ctrl-C")
    try:  # not through sys.stderr's buffer, which the interrupted code may be writing
        os.write(sys.stderr.fileno(), text.encode())
    except (AttributeError, OSError, ValueError):
        sys.stderr.write(text)


@contextmanager
def handle_interrupts() -> Iterator[None]:
    """Install the deferral of Ctrl-C, SIGTERM and SIGHUP for the block (see the module
    docstring): a command's entry point calls it, never a library. Outside the main thread it
    does nothing (only the main thread receives signals); a signal the process ignores (SIGHUP
    under `nohup`) stays ignored. The previous handlers are restored afterwards."""
    if threading.current_thread() is not threading.main_thread() or _DEFERRAL.installed:
        yield
        return
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # where not ignored (nohup)
        if signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, _on_signal)
    _DEFERRAL.installed, _DEFERRAL.depth, _DEFERRAL.pending = True, 0, None
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _DEFERRAL.installed, _DEFERRAL.depth, _DEFERRAL.pending = False, 0, None


class critical:
    """A section a Ctrl-C (SIGTERM, SIGHUP) does not cut: under `handle_interrupts` (main
    thread), one inside it raises KeyboardInterrupt (`Terminated`) when the outermost section
    ends (unless the section raised something else). Sections nest; elsewhere it changes
    nothing."""

    def __enter__(self) -> critical:
        self.active = _DEFERRAL.installed and threading.current_thread() is threading.main_thread()
        if self.active:
            _DEFERRAL.depth += 1
        return self

    def __exit__(self, kind, value, tb) -> bool:
        if not self.active:
            return False
        _DEFERRAL.depth -= 1
        if _DEFERRAL.depth == 0 and _DEFERRAL.pending is not None:
            signum, _DEFERRAL.pending = _DEFERRAL.pending, None
            if kind is None:
                raise _interrupt(signum)
        return False


__all__ = ["Abort", "Phase", "Progress", "Terminated", "critical", "handle_interrupts",
           "signal_name"]
