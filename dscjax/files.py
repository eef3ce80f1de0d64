"""The files every feature writes: atomically, as strict JSON, and with a fingerprint that says
whether a directory holds the same run (so that `--resume` never mixes two runs).

    write_json(out / "summary.json", summary)        # arrays, NaN, Paths: all handled
    fp = {...}                                        # what determines a run's results
    check_same(read_json(manifest)["fingerprint"], fp, where=f"--resume: {manifest}",
               fix="use the same settings, or --overwrite to start afresh")

Every write goes to a temporary file in the same directory, is flushed to disk (fsync) and
renamed over the target, so a run killed in the middle of a write leaves the previous complete
file behind, never half a file. Sweeps (chunk files, results.npz), tuning (checkpoints, the
best point) and the paper's reproduction (summaries, the complexity study's measurements) all
write through here.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from dscjax.validation import ConfigError


def atomic_write(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically: a temporary file, fsync, then a rename over `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_text(path: str | Path, text: str) -> None:
    """`atomic_write` of a text (UTF-8)."""
    atomic_write(path, text.encode())


def jsonable(obj: Any) -> Any:
    """`obj` as plain JSON data: arrays and NumPy scalars as Python numbers and lists,
    non-finite floats as None (strict JSON has no NaN), tuples as lists, paths as strings, and
    functions or classes (the static callables of a `CustomPlant`) by qualified name, so that
    a fingerprint does not depend on where they sit in memory."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if obj is None or isinstance(obj, str | bool):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    if callable(obj) and hasattr(obj, "__qualname__"):
        return obj.__qualname__
    a = np.asarray(obj)
    if a.dtype == object:
        return repr(obj)
    if a.ndim:
        return jsonable(a.tolist())
    v = a.item()
    return None if isinstance(v, float) and not math.isfinite(v) else v


def dumps(obj: Any, **kwargs) -> str:
    """Strict JSON text of `jsonable(obj)`."""
    return json.dumps(jsonable(obj), allow_nan=False, **kwargs)


def write_json(path: str | Path, obj: Any) -> None:
    """`obj` as indented strict JSON, written atomically."""
    write_text(path, dumps(obj, indent=2) + "\n")


def read_json(path: str | Path) -> Any:
    """The JSON in `path`; ConfigError naming the file if it is missing or unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"cannot read {path}: {err}") from None


def digest(obj: Any) -> str:
    """sha256 (hex) of the canonical JSON of `obj` (sorted keys): equal data, equal digest."""
    return hashlib.sha256(dumps(obj, sort_keys=True).encode()).hexdigest()


def canonical(obj: Any) -> Any:
    """`obj` as it reads back from a JSON file (what a stored fingerprint is compared with)."""
    return json.loads(dumps(obj))


def differences(old: Any, new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """The keys of the fingerprint `new` whose values differ in `old`, each as `key OLD (now
    NEW)` for single values (a key missing on one side reads None), `key` for lists; nested
    tables are compared key by key (`adversarial.search_evals None (now 8)`)."""
    new = canonical(new)
    old = old if isinstance(old, Mapping) else {}
    out = []
    for k in sorted(set(new) | set(old)):
        a, b = old.get(k), new.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, f"{prefix}{k}.")
            continue
        simple = not isinstance(a, dict | list) and not isinstance(b, dict | list)
        out.append(f"{prefix}{k} {a!r} (now {b!r})" if simple else f"{prefix}{k}")
    return out


def check_same(old: Any, new: Mapping[str, Any], *, where: str, fix: str) -> None:
    """The one resume-by-fingerprint check: ConfigError unless the stored fingerprint `old`
    (as read back from a file) equals `new`, naming what differs, e.g.
    ``--resume: DIR/sweep.json was made with other settings (seed 0 (now 1)); FIX``."""
    diff = differences(old, new)
    if diff:
        raise ConfigError(f"{where} was made with other settings ({', '.join(diff)}); {fix}")


def write_npz(path: str | Path, arrays: Mapping[str, Any]) -> None:
    """An uncompressed .npz (`np.load` reads it) with fixed zip timestamps, so that equal
    arrays give equal bytes, written atomically."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asarray(a), allow_pickle=False)
    atomic_write(path, buf.getvalue())


def read_npz(path: str | Path) -> dict[str, np.ndarray] | None:
    """Every array of an .npz, or None if it is missing or unreadable (a partial file)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError):
        return None


__all__ = ["atomic_write", "canonical", "check_same", "differences", "digest", "dumps",
           "jsonable", "read_json", "read_npz", "write_json", "write_npz", "write_text"]
