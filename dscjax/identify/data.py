"""A measured record: time stamps, the input u and the measured columns, read from CSV (a header
row) or NPZ and checked before anything is fitted.

    rec = read("run.csv", order=2)      # columns t, u and any of x1, x2 and w
    rec.t, rec.u, rec.y["x1"]

Time stamps need not be uniform; they must increase. A problem is one `ConfigError` naming the
file, the column and the line (or the NPZ array and the index).
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np

from dscjax.validation import ConfigError

MIN_SAMPLES = 20  # fewer cannot fit and validate a model


@dataclasses.dataclass(frozen=True)
class Record:
    """A record: t (N,) increasing, u (N,), y {column: (N,)} (x1..xn: plant states, w: the
    actuator's output), and where it came from."""

    t: np.ndarray
    u: np.ndarray
    y: dict[str, np.ndarray]
    source: str = ""

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def plant(self) -> bool:
        """Whether it measures a plant state (the plant experiment), not w alone (the actuator
        alone)."""
        return any(c != "w" for c in self.y)

    def part(self, start: int, stop: int | None = None) -> Record:
        """The samples start..stop-1 (a validation tail, a segment)."""
        sl = slice(start, stop)
        return Record(self.t[sl], self.u[sl], {k: v[sl] for k, v in self.y.items()},
                      self.source)


def read(path: str | Path, order: int | None, option: str = "--data") -> Record:
    """The record in `path` (.csv with a header row, or .npz), checked: columns t and u, at
    least one measured column the model has, no other column, numbers
    only, no NaN, increasing times, at least MIN_SAMPLES samples. The columns a model of
    plant order n has: x1..xn and w (order None: the actuator alone, w only)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if path.is_dir():
        raise ConfigError(f"{option}: {path} is a directory (give a .csv or .npz file)")
    if suffix not in (".csv", ".npz"):
        raise ConfigError(f"{option}: {path}: a record is CSV (.csv, a header row) or NPZ "
                          f"(.npz) (got {suffix or 'no suffix'!r})")
    try:
        raw = _read_csv(path) if suffix == ".csv" else _read_npz(path)
    except OSError as err:
        raise ConfigError(f"{option}: cannot read {path}: {err.strerror}") from None
    # where a value sits: the line of a CSV (the first sample's after the header), or the index
    where, first = ("line", 2) if suffix == ".csv" else ("index", 0)

    def at(i: int, column: str) -> str:
        return f"{path}, {where} {first + i}, column {column!r}"

    allowed = ("w",) if order is None else (*(f"x{i + 1}" for i in range(order)), "w")
    for name in ("t", "u"):
        if name not in raw:
            raise ConfigError(f"{path}: no column {name!r} (the columns are: "
                              f"{', '.join(raw) or 'none'}; a record needs t, u and one of "
                              f"{', '.join(allowed)})")
    extra = [c for c in raw if c not in ("t", "u", *allowed)]
    if extra:
        states = "the actuator alone has none" if order is None else \
            f"order {order}: {', '.join(allowed[:-1])}"
        raise ConfigError(f"{path}: column {extra[0]!r}: the model has no such state ({states}; "
                          f"w: the actuator's output)")
    measured = [c for c in allowed if c in raw]
    if not measured:
        raise ConfigError(f"{path}: no measured column: give one of {', '.join(allowed)}")
    values = {}
    for name, column in raw.items():
        a = np.asarray(column, dtype=object).ravel()
        out = np.empty(a.size)
        for i, v in enumerate(a):
            try:
                out[i] = float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"{at(i, name)}: not a number ({str(v)!r})") from None
            if not math.isfinite(out[i]):
                raise ConfigError(f"{at(i, name)}: {v} (every value must be a finite number)")
        values[name] = out
    n = values["t"].size
    if n < MIN_SAMPLES:
        raise ConfigError(f"{path}: {n} samples; at least {MIN_SAMPLES} are needed")
    bad = np.flatnonzero(np.diff(values["t"]) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise ConfigError(f"{at(i, 't')}: {values['t'][i]:g} is not after the time before "
                          f"it, {values['t'][i - 1]:g} (times must increase)")
    return Record(values["t"], values["u"], {c: values[c] for c in measured}, str(path))


def _read_csv(path: Path) -> dict[str, list]:
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise ConfigError(f"{path}: empty (a record is a header row, then one row a sample)")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        twice = next(h for h in header if header.count(h) > 1)
        raise ConfigError(f"{path}, line 1: column {twice!r} is given twice")
    for line, row in enumerate(rows[1:], start=2):
        if row and len(row) != len(header):  # (an empty line is skipped, here and below)
            raise ConfigError(f"{path}, line {line}: {len(row)} values for {len(header)} "
                              f"columns ({', '.join(header)})")
    return {h: [row[j].strip() for row in rows[1:] if row] for j, h in enumerate(header)}


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except ValueError as err:
        raise ConfigError(f"{path}: not a plain NPZ of arrays ({err})") from None


__all__ = ["MIN_SAMPLES", "Record", "read"]
