"""Progress of long runs on stderr: one display for every command, drawn by tqdm.

    with Progress(total=n, desc="  sweep", unit="sample") as bar:
        for ...:
            bar.update_to(done, postfix="2.1e7 steps/s")

On a terminal tqdm redraws one line in place (rate, elapsed time, ETA). Anywhere else (a log
file, CI, a pipe) the same figures are printed as a plain line of their own, at most every
`every_s` seconds and once at the end, so that a log holds readable lines instead of carriage
returns. The numbers (rate, ETA) are tqdm's in both cases.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm

# A plain line: "  sweep  40 % (4000/10000 samples) 00:12 elapsed, ETA 00:18; 2.1e7 steps/s"
LINE = "{desc} {percentage:3.0f} % ({n_fmt}/{total_fmt} {unit}) {elapsed} elapsed, ETA {remaining}"
# ... and without a total (work that stops on a time limit or a criterion, not a count)
OPEN_LINE = "{desc} {n_fmt} {unit}, {elapsed} elapsed"


class Progress:
    """A progress display of `total` units of work (see the module docstring).

    Args:
        total: units of work in all (None: not known in advance; no percentage or ETA).
        desc: what is being done, the start of the line.
        unit: the unit's name ("sample", "step", "iteration"), pluralised with an s unless
            the count is 1.
        initial: units done before this display started (a resumed run).
        elapsed: seconds of this run already spent when the display starts.
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


__all__ = ["Progress"]
