"""How dscjax's programs are compiled: fusion emitters, vector width, fusion barriers, the
persistent cache.

- `compiler_options()`: 512-bit vectors for the batched programs on CPUs with AVX-512.
- `lean_options()`: XLA:CPU's loop fusion emitters instead of its MLIR ones (where jaxlib
  still offers the choice: `emitter_choice`), for the programs
  that run once or a few times (one trajectory, a gradient, a report's check, a batch of at
  most `LEAN_ROWS` rows): they compile in about half the time and run as fast; a larger
  batch runs faster with the MLIR emitters (docs/benchmarks.md, "Compilation"). A batched
  program whose whole work is known and small (`lean_work`: a sweep, a search with an
  iteration limit) compiles lean too: the compile time it saves exceeds its slower run.
- Both are given per compiled function (`jax.jit(f, compiler_options=...)`), never through the
  environment; an option the user sets in `XLA_FLAGS` wins. `jit` carries them at the top
  level.
- `tiles`: rows in tiles of a compiled width, the last padded with copies of a valid row, so
  that a batch of any size runs one program (a sweep's blocks, a refinement level's rows, a
  search's single point, the points of a trajectory's checks).
- `barrier` / `barriers`: optimisation barriers, active only while the batched layout is
  traced, so that XLA:CPU computes a shared intermediate once instead of re-fusing it into
  every consumer (docs/architecture.md).
- `enable_compilation_cache()`: JAX's persistent cache in $XDG_CACHE_HOME/dscjax/jax (else
  ~/.cache/dscjax/jax), at most `CACHE_MAX_BYTES`, its reads and writes locked; the `dscjax`
  command calls it, the library never does (opt out: DSCJAX_NO_COMPILATION_CACHE=1,
  --no-compilation-cache; JAX_COMPILATION_CACHE_DIR wins, as configured).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import os
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

import jax
import numpy as np

OPTION = "xla_cpu_prefer_vector_width"
WIDE = {OPTION: 512}
EMITTERS = "xla_cpu_use_fusion_emitters"
LEAN = {EMITTERS: False}
LEAN_ROWS = 8  # a batch of at most this many rows compiles lean
# A batched program whose runs add up to at most this many member-steps (rows x RK4 steps over
# all its calls) compiles lean: its run is slower by less than the compile time lean saves
# (half the break-even of docs/benchmarks.md, "Compilation").
LEAN_WORK = 5e6


def cpu_has_avx512(cpuinfo: str = "/proc/cpuinfo") -> bool:
    """True if the CPU reports AVX-512 (Linux `/proc/cpuinfo`); False elsewhere or unknown."""
    if not sys.platform.startswith("linux"):
        return False
    with contextlib.suppress(OSError), open(cpuinfo) as f:
        for line in f:
            if line.startswith("flags"):
                return "avx512f" in line.split()
    return False


def compiler_options(environ: Mapping[str, str] = os.environ,
                     has_avx512: bool | None = None) -> dict[str, int]:
    """The compiler options of dscjax's batched programs: `WIDE` on a CPU with AVX-512,
    unless `XLA_FLAGS` already sets the vector width (the user's choice wins); else {}.
    Other backends ignore the option."""
    wide = cpu_has_avx512() if has_avx512 is None else has_avx512
    return dict(WIDE) if wide and OPTION not in environ.get("XLA_FLAGS", "") else {}


def emitter_choice(jaxlib_version: str = jax.lib.__version__) -> bool:
    """True if this jaxlib's XLA:CPU offers a choice of fusion emitters: jaxlib 0.11 has the
    MLIR ones only and refuses the option that chose them."""
    return tuple(int(p) for p in jaxlib_version.split(".")[:2]) < (0, 11)


def lean_options(environ: Mapping[str, str] = os.environ) -> dict[str, bool]:
    """The compiler options of dscjax's run-once programs: `LEAN`, unless `XLA_FLAGS` already
    chooses the fusion emitters (the user's choice wins) or this jaxlib has no choice of them
    (`emitter_choice`). Other backends ignore the option."""
    return dict(LEAN) if emitter_choice() and EMITTERS not in environ.get("XLA_FLAGS", "") else {}


def lean_work(member_steps: float | None) -> bool:
    """True if a batched program whose runs add up to `member_steps` (None: unknown, e.g. a
    search limited by time alone) compiles lean (`LEAN_WORK`)."""
    return member_steps is not None and member_steps <= LEAN_WORK


def jit(fn: Callable, lean: bool = False, **kwargs) -> Callable:
    """`jax.jit(fn, **kwargs)` carrying `lean_options()` (lean) or `compiler_options()` when
    called at the top level.

    JAX refuses compiler options on a jit nested in a trace (a user's jit, grad or vmap), so
    there the plain jit is traced into the caller's program instead. `.top` is the top-level
    compiled function (its cache, e.g. for tests; `.lower` is its)."""
    top = jax.jit(fn, compiler_options=lean_options() if lean else compiler_options(), **kwargs)
    nested = jax.jit(fn, **kwargs)

    @functools.wraps(fn)
    def call(*args, **kw):
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((args, kw))):
            return nested(*args, **kw)
        try:
            return top(*args, **kw)
        except ValueError as e:  # concrete arguments, but inside a trace all the same
            if "compiler_options" not in str(e):
                raise
            return nested(*args, **kw)

    call.top, call.lower = top, top.lower
    return call


def tiles(rows: np.ndarray, width: int) -> list[np.ndarray]:
    """`rows` split into tiles of `width` rows, the last padded with copies of its own first
    row (a valid sample)."""
    out = [rows[lo:lo + width] for lo in range(0, max(rows.shape[0], 1), width)]
    last = out[-1]  # the only tile that can be short
    out[-1] = np.concatenate([last, np.repeat(last[:1], width - last.shape[0], axis=0)])
    return out


# -- fusion barriers ------------------------------------------------------------------------------

_BARRIERS = contextvars.ContextVar("dscjax_fusion_barriers", default=False)


def barrier(tree):
    """Materialise `tree` (computed once, not re-fused into consumers) in batched traces."""
    return jax.lax.optimization_barrier(tree) if _BARRIERS.get() else tree


@contextlib.contextmanager
def barriers():
    """Within this block (a trace-time context), `barrier` is active."""
    token = _BARRIERS.set(True)
    try:
        yield
    finally:
        _BARRIERS.reset(token)


# -- the persistent compilation cache -------------------------------------------------------------

CACHE_OPT_OUT = "DSCJAX_NO_COMPILATION_CACHE"
# programs that compile faster than this are not written (JAX's own default, 1 s, would leave
# out the lean programs, which compile in a fraction of a second to a few seconds)
MIN_COMPILE_TIME_S = 0.3
# the cache's size: JAX drops the least recently used programs beyond it, and a cache with a
# size is one whose reads and writes JAX locks (filelock), so that processes sharing it (a
# sweep's, the tests' workers) never read a program another is still writing
CACHE_MAX_BYTES = 1 << 30
# JAX's files of a sized cache: each program (NAME-cache) beside its last use (NAME-atime, 8
# bytes); a program without its last use (written before the cache had a size, or cut off
# between the two files) makes JAX fail every later write
_PROGRAM, _LAST_USE = "-cache", "-atime"


def cache_opted_out(environ: Mapping[str, str] = os.environ) -> bool:
    """True if DSCJAX_NO_COMPILATION_CACHE is set to anything but "", 0, false or no."""
    return environ.get(CACHE_OPT_OUT, "").strip().lower() not in ("", "0", "false", "no")


def enable_compilation_cache(directory: str | Path | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in `directory` (default
    $XDG_CACHE_HOME/dscjax/jax, else ~/.cache/dscjax/jax), at most `CACHE_MAX_BYTES` unless a
    size is configured (JAX_COMPILATION_CACHE_MAX_SIZE), and return it; a program there
    without its last use is given the oldest. A cache directory already configured
    (JAX_COMPILATION_CACHE_DIR) is kept as it is, sized and locked only if configured so, and
    returned. None if the directory cannot be created (nothing is changed then). This sets
    JAX's global configuration for the whole process."""
    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = Path(directory) if directory is not None else Path(base) / "dscjax" / "jax"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    if "JAX_COMPILATION_CACHE_MAX_SIZE" not in os.environ:
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
    with contextlib.suppress(OSError):  # (a cache that cannot be mended is still read)
        for program in path.glob(f"*{_PROGRAM}"):
            last_use = program.with_name(program.name.removesuffix(_PROGRAM) + _LAST_USE)
            if not last_use.exists():
                last_use.write_bytes(bytes(8))
    return path


__all__ = ["CACHE_MAX_BYTES", "CACHE_OPT_OUT", "EMITTERS", "LEAN", "LEAN_ROWS", "LEAN_WORK",
           "MIN_COMPILE_TIME_S", "OPTION", "WIDE", "barrier", "barriers", "cache_opted_out",
           "compiler_options", "cpu_has_avx512", "emitter_choice", "enable_compilation_cache",
           "jit", "lean_options", "lean_work"]
