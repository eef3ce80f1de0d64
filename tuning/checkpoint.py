"""Checkpoint files of a tuning run: plain arrays (npz, no pickle) and JSON, written atomically.

    checkpoint.npz   every leaf of the TuneState, keys "leaf_0000", ...
    checkpoint.json  what the run is (fingerprint of the problem) and where it is
    best.json        the best point so far (values and z by name, its loss and iteration)
    gains.json       the best gains as a dscjax config (loadable by `dscjax simulate --config`)
    history.csv      one row per iteration

Every file is written atomically (`dscjax.files`): a run killed in the middle of a write
leaves the previous complete file behind.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from dscjax import files
from dscjax.validation import ConfigError

FORMAT_VERSION = 1
FILES = ("checkpoint.npz", "checkpoint.json", "best.json", "gains.json", "history.csv")


def fingerprint(desc) -> str:
    """Short digest of the problem's description (stored in checkpoint.json beside it)."""
    return files.digest(desc)[:16]


def drop_defaults(d: Mapping[str, Any], defaults: Mapping[str, Any]) -> dict:
    """`d` without the keys of `defaults` whose value equals the one given there.

    For the descriptions that fingerprint a run: an option added after runs were saved is
    left out at the value that does what those runs did, so their fingerprints stay as they
    were and they still resume; set to anything else, it is part of the fingerprint.

        >>> drop_defaults({"line_backoff": 0, "seed": 1}, {"line_backoff": 0})
        {'seed': 1}
    """
    return {k: v for k, v in d.items() if not (k in defaults and v == defaults[k])}


def save_state(path: Path, state) -> dict:
    """Write the state's leaves to an npz; return a description (for checkpoint.json)."""
    leaves, treedef = jax.tree.flatten(state)
    arrays = {f"leaf_{i:04d}": np.asarray(x) for i, x in enumerate(leaves)}
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    files.atomic_write(path, buf.getvalue())
    return {"n_leaves": len(leaves), "treedef": str(treedef),
            "shapes": [list(a.shape) for a in arrays.values()]}


def load_state(path: Path, template, desc: Mapping[str, Any]):
    """Leaves from the npz put into `template`'s structure (shapes and structure checked)."""
    leaves, treedef = jax.tree.flatten(template)
    if desc.get("treedef") != str(treedef) or desc.get("n_leaves") != len(leaves):
        raise ConfigError(f"{path} does not match this tuning problem (different parameters or "
                          f"optimiser); start afresh with --overwrite")
    with np.load(path, allow_pickle=False) as z:
        new = []
        for i, t in enumerate(leaves):
            a = z[f"leaf_{i:04d}"]
            if a.shape != np.shape(t):
                raise ConfigError(f"{path}: leaf {i} has shape {a.shape}, expected "
                                  f"{np.shape(t)}; start afresh with --overwrite")
            new.append(jax.numpy.asarray(a, dtype=np.asarray(t).dtype))
    return jax.tree.unflatten(treedef, new)


def write_history(path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _fmt(r.get(k)) for k in columns})
    files.write_text(path, buf.getvalue())


def read_history(path: Path) -> list[dict[str, Any]]:
    if not Path(path).exists():
        return []
    with open(path, newline="") as f:
        rows = []
        for r in csv.DictReader(f):
            rows.append({k: _parse(v) for k, v in r.items()})
        return rows


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
