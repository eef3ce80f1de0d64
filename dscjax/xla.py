"""XLA:CPU code generation for the batched programs: 512-bit vectors on CPUs with AVX-512.

XLA:CPU vectorises elementwise kernels for 256-bit registers by default. The batch-last rows
layout of `simulate_batch` and of sweeps is exactly such kernels, and on an AVX-512 CPU (the
project's AMD EPYC) XLA's `xla_cpu_prefer_vector_width = 512` makes it 1.1-1.5x faster in
float32 and float64 with bitwise identical results (`experiments/bench_vector_width.py`; a test
compares the results). Single runs are bound by kernel dispatch and do not change.

The option is given per compiled function (`jax.jit(..., compiler_options=...)`), never
through the environment: dscjax's batched programs carry it, and nothing global changes on
`import dscjax` or when they run (no `XLA_FLAGS`, no other program affected). It produces the
same machine code as `XLA_FLAGS=--xla_cpu_prefer_vector_width=512` (compared byte for byte in
XLA's dumps of the batched simulation). Opt out, or choose another width, by setting that flag
in `XLA_FLAGS` yourself: the user's choice wins. To give your own jitted batched functions the
same preference:

    jax.jit(f, compiler_options=dscjax.xla.compiler_options())
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable, Mapping

import jax

OPTION = "xla_cpu_prefer_vector_width"
WIDE = {OPTION: 512}


def cpu_has_avx512(cpuinfo: str = "/proc/cpuinfo") -> bool:
    """True if the CPU reports AVX-512 (Linux `/proc/cpuinfo`); False elsewhere or unknown."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        with open(cpuinfo) as f:
            for line in f:
                if line.startswith("flags"):
                    return "avx512f" in line.split()
    except OSError:
        return False
    return False


def compiler_options(environ: Mapping[str, str] = os.environ,
                     has_avx512: bool | None = None) -> dict[str, int]:
    """The compiler options of dscjax's batched programs: `WIDE` on a CPU with AVX-512,
    unless `XLA_FLAGS` already sets the vector width (the user's choice wins); else {}.
    Other backends ignore the option."""
    if OPTION in environ.get("XLA_FLAGS", ""):
        return {}
    if not (cpu_has_avx512() if has_avx512 is None else has_avx512):
        return {}
    return dict(WIDE)


def jit(fn: Callable, **kwargs) -> Callable:
    """`jax.jit(fn, **kwargs)` carrying `compiler_options()` when called at the top level.

    JAX refuses compiler options on a jit nested in a trace (a user's jit, grad or vmap), so
    there the plain jit is traced into the caller's program instead. `.top` is the top-level
    compiled function (its cache, e.g. for tests)."""
    top = jax.jit(fn, compiler_options=compiler_options(), **kwargs)
    nested = jax.jit(fn, **kwargs)

    @functools.wraps(fn)
    def call(*args, **kw):
        traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((args, kw)))
        return (nested if traced else top)(*args, **kw)

    call.top = top
    return call


__all__ = ["OPTION", "WIDE", "compiler_options", "cpu_has_avx512", "jit"]
