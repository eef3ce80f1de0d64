"""Checkpoint files of a tuning run: plain arrays (npz, no pickle) and JSON, written atomically.

    search.npz       the search's state (`dscjax.search`'s one format), saved every iteration
    checkpoint.json  what the run is (fingerprint of the problem) and where it is
    best.json        the best point so far (values and z by name, its loss and iteration)
    gains.json       the best gains as a dscjax config (loadable by `dscjax simulate --config`)
    history.csv      one row per iteration

Each is written atomically (`dscjax.files`): a run killed mid-write leaves the previous file.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dscjax import files

FORMAT_VERSION = 2
FILES = ("search.npz", "checkpoint.json", "best.json", "gains.json", "history.csv")


def fingerprint(desc) -> str:
    """Short digest of the problem's description (stored in checkpoint.json beside it)."""
    return files.digest(desc)[:16]


def write_history(path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _fmt(r.get(k)) for k in columns})
    files.write_text(path, buf.getvalue())


def read_history(path: Path) -> list[dict[str, Any]]:
    """history.csv's rows, numbers parsed ([] if there is no file)."""
    if not Path(path).exists():
        return []
    with open(path, newline="") as f:
        return [{k: _parse(v) for k, v in r.items()} for r in csv.DictReader(f)]


def _fmt(v):
    if v is None:
        return ""
    if isinstance(v, bool | np.bool_):
        return int(v)
    if isinstance(v, float | np.floating):
        return repr(float(v))
    return v


def _parse(v: str):
    if v == "":
        return None
    try:
        f = float(v)
    except ValueError:
        return v
    return int(f) if f.is_integer() and "." not in v and "e" not in v.lower() else f
