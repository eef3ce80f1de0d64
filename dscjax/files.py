"""The files every feature writes: atomically, as strict JSON, and with a fingerprint that says
whether a directory holds the same run (so that `--resume` never mixes two runs).

    write_json(out / "summary.json", summary)        # arrays, NaN, Paths: all handled
    fp = {...}                                        # what determines a run's results
    check_record(out, "sweep.json", fp)               # --resume: the same run, or refused

Every write (figures too: `save_figure`) goes to a temporary file beside the target, fsynced
and renamed over it, so a killed run leaves the previous whole file; a failed write removes its
temporary file, one short of space raises `NoSpace`. `lock_out` keeps a second process out of
an output directory.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import hashlib
import io
import json
import math
import os
import shlex
import socket
import tempfile
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dscjax.validation import ConfigError


class NoSpace(OSError):
    """A write failed for want of space (errno ENOSPC, EDQUOT or EFBIG); `filename` is the
    file that was being written (its temporary file is removed)."""


def _no_space(err: OSError, path: str | Path) -> OSError:
    """`err` as NoSpace naming `path` if it failed for want of space (the device, the quota,
    the file size limit), else `err`."""
    if err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return NoSpace(err.errno, err.strerror, str(path))
    return err


def atomic_write(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically: a temporary file, fsync, then a rename over `path`.

    On any failure (an interrupt included) the temporary file is removed and `path` keeps its
    previous content; NoSpace if the disk, the quota or the file size limit is exhausted."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise _no_space(err, path) from None
        raise


def mkdir(path: str | Path) -> Path:
    """`path` and its parents created (NoSpace where the disk is full)."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise _no_space(err, path) from None
    return path


def save_figure(fig, path: str | Path, **kwargs) -> None:
    """A matplotlib figure saved atomically to `path` (its format from the suffix), as every
    other file: rendered into memory, then `atomic_write`."""
    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or None, **kwargs)
    atomic_write(path, buf.getvalue())


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


def differences(old: Any, new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """The keys of the fingerprint `new` whose values differ in `old`, each as `key OLD (now
    NEW)` for single values (a key missing on one side reads None), `key` for lists; nested
    tables are compared key by key (`adversarial.search_evals None (now 8)`)."""
    new = json.loads(dumps(new))  # as it reads back from a JSON file, as `old` was
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


SAME_SETTINGS = "use the same settings, or --overwrite to start afresh"  # a resume's fix


def resume_file(out: str | Path, marker: str) -> Path:
    """out/marker, the record of a run that `--resume` continues; ConfigError where it is
    missing."""
    path = Path(out) / marker
    if not path.exists():
        raise ConfigError(f"--resume: nothing to resume in {out} ({marker} is missing); "
                          f"run without --resume to start afresh")
    return path


def check_record(out: str | Path, marker: str, new: Mapping[str, Any], *,
                 key: str = "fingerprint", where: str | None = None) -> dict:
    """The JSON record out/marker of the run that `--resume` continues: ConfigError where it
    is missing (`resume_file`), or (one line, the old and new values of what differs, `where`
    by default "--resume: PATH") unless its `key` is `new`."""
    path = resume_file(out, marker)
    meta = read_json(path)
    check_same(meta.get(key), new, where=where or f"--resume: {path}")
    return meta


def check_same(old: Any, new: Mapping[str, Any], *, where: str,
               fix: str = SAME_SETTINGS) -> None:
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


# -- the output directory ----------------------------------------------------------------------


def out_problem(path: str | Path) -> str | None:
    """Why the system would refuse `path` as an output directory, in its own words (strerror:
    "File name too long", "Not a directory", "Permission denied", "Read-only file system"),
    or None if it may be used. Asked of the system itself, without touching `path` (several
    processes may share it): in a fresh temporary directory made in its deepest existing
    directory, the missing directories are made and a file written; it is removed again."""
    path = Path(os.path.abspath(path))
    problem = _path_problem(path)
    if problem is not None:
        return problem
    base = next(p for p in (path, *path.parents) if os.path.lexists(p))
    try:
        with tempfile.TemporaryDirectory(dir=base, prefix=".dscjax-write-test-",
                                         ignore_cleanup_errors=True) as probe_dir:
            leaf = Path(probe_dir, path.relative_to(base))
            leaf.mkdir(parents=True, exist_ok=True)
            fd, _ = tempfile.mkstemp(dir=leaf)
            os.close(fd)
    except OSError as err:
        return err.strerror or str(err)
    return None


def _path_problem(path: Path) -> str | None:
    """`out_problem` from what the path's existing part says (nothing is created)."""
    for level in (path, *path.parents):
        try:
            os.stat(level)
        except FileNotFoundError:
            continue
        except OSError as err:  # too long, a loop of links, no permission to look
            return err.strerror or str(err)
        if not os.path.isdir(level):
            return ("it is a file, not a directory" if level == path else
                    f"{os.strerror(errno.ENOTDIR)}: {level} is a file")
        try:
            longest = os.pathconf(level, "PC_NAME_MAX")
        except (OSError, ValueError):
            longest = 255
        if any(len(os.fsencode(name)) > longest for name in path.relative_to(level).parts):
            return f"{os.strerror(errno.ENAMETOOLONG)}: a name longer than {longest} bytes"
        if os.access(level, os.W_OK | os.X_OK):
            return None
        with contextlib.suppress(OSError):
            if os.statvfs(level).f_flag & os.ST_RDONLY:
                return os.strerror(errno.EROFS) + (f": {level}" if level != path else "")
        return os.strerror(errno.EACCES) + (f": {level}" if level != path else "")
    return None


# -- one process per output directory ----------------------------------------------------------

LOCK = ".dscjax.lock"


@contextlib.contextmanager
def lock_out(out: str | Path, *, name: str = LOCK, argv: Sequence[str] = ()) -> Iterator[None]:
    """Hold an exclusive lock on the directory `out` (which must exist) while the block runs.

    An flock on `out/name`, a file naming the holder (pid, host, argv, start), removed on
    release; another process gets a ConfigError at once naming the holder. A dead holder never
    blocks (the kernel releases its lock)."""
    path = Path(out) / name
    fd = _acquire(path, out)
    try:
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": shlex.join(argv),
                "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
        except OSError as err:
            raise _no_space(err, path) from None
        yield
    finally:
        with contextlib.suppress(OSError):
            if _same_file(path, fd):
                os.unlink(path)  # before the lock is released: no one can hold this file
        os.close(fd)


def _acquire(path: Path, out) -> int:
    """A descriptor of `path` holding its flock; ConfigError naming the holder if another
    process has it."""
    for _ in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as err:
            raise ConfigError(f"--out {str(out)!r}: cannot create the lock file {path.name} "
                              f"({err.strerror or err}); give a writable directory") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise ConfigError(f"--out {str(out)!r} is in use by another dscjax process "
                              f"({holder}); wait for it to end, or give another --out") from None
        except OSError as err:
            if err.errno not in (errno.ENOLCK, errno.EOPNOTSUPP):
                os.close(fd)
                raise
            return fd  # a file system without locks: go on unlocked
        # the previous holder may have removed the file between our open and our lock
        if _same_file(path, fd):
            return fd
        os.close(fd)
    raise ConfigError(f"--out {str(out)!r}: cannot lock {path.name}; try again")


def _same_file(path: Path, fd: int) -> bool:
    try:
        a, b = os.stat(path), os.fstat(fd)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _holder(fd: int) -> str:
    """Who holds the lock, from its file: "pid P on host H, since T: COMMAND"."""
    try:
        info = json.loads(os.pread(fd, 1 << 16, 0).decode())
        return (f"pid {info['pid']} on host {info['host']}, since {info['started']}: "
                f"{info['command']}")
    except (OSError, ValueError, KeyError, TypeError):
        return "its details are not written yet"


__all__ = ["LOCK", "NoSpace", "SAME_SETTINGS", "atomic_write",
           "check_record", "check_same", "differences", "digest", "dumps", "jsonable",
           "lock_out", "mkdir", "out_problem", "read_json", "read_npz", "resume_file",
           "save_figure", "write_json", "write_npz", "write_text"]
