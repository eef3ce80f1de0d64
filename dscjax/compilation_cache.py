"""JAX's persistent compilation cache in a per-user directory, switched on by the CLI only.

Compilation is a large part of a short run: the exact gradient of the tuner took 15-55 s to
compile under load (docs/tuning.md), every time, in a new process. JAX can keep compiled
programs on disk and reuse them when the same program is compiled again (same code, shapes,
options, jax and XLA versions). `dscjax` (the command) calls `enable()` at start-up, so a
second `dscjax tune` of the same problem structure skips most of the compilation; a number
changed in a config does not change the program, a shape or a static setting does.

Nothing changes on `import dscjax`: the cache is JAX's global configuration, so the library
never touches it by itself. In Python, call `dscjax.compilation_cache.enable()` yourself.

    directory: $XDG_CACHE_HOME/dscjax/jax, else ~/.cache/dscjax/jax
    opt out:   DSCJAX_NO_COMPILATION_CACHE=1 or `dscjax --no-compilation-cache COMMAND`
    yours:     JAX_COMPILATION_CACHE_DIR (or jax_compilation_cache_dir) set beforehand wins
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

OPT_OUT = "DSCJAX_NO_COMPILATION_CACHE"
# programs that compile faster than this are not written (JAX's own default: 1 s)
MIN_COMPILE_TIME_S = 1.0


def default_dir(environ: Mapping[str, str] = os.environ) -> Path:
    """$XDG_CACHE_HOME/dscjax/jax, else ~/.cache/dscjax/jax."""
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "dscjax" / "jax"


def opted_out(environ: Mapping[str, str] = os.environ) -> bool:
    return environ.get(OPT_OUT, "").strip().lower() not in ("", "0", "false", "no")


def enable(directory: str | Path | None = None,
           min_compile_time_s: float = MIN_COMPILE_TIME_S) -> Path | None:
    """Turn on JAX's persistent compilation cache in `directory` (default `default_dir()`)
    and return it. A cache directory already configured (JAX_COMPILATION_CACHE_DIR) is kept
    and returned. None if the directory cannot be created (nothing is changed then).
    This sets JAX's global configuration for the whole process."""
    import jax

    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    path = Path(directory) if directory is not None else default_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    return path


__all__ = ["MIN_COMPILE_TIME_S", "OPT_OUT", "default_dir", "enable", "opted_out"]
