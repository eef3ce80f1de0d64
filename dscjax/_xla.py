"""XLA:CPU code generation: ask for 512-bit vectors on CPUs that have AVX-512.

XLA:CPU vectorises elementwise kernels for 256-bit registers by default. The batch-last rows
layout of `simulate_batch` and of sweeps is exactly such kernels, and on an AVX-512 CPU (the
project's AMD EPYC) `--xla_cpu_prefer_vector_width=512` makes it 1.3-1.5x faster in float32
and float64 with bitwise identical results (measured in `experiments/bench_core.py`; a test
compares the results). Single runs are bound by kernel dispatch and do not change.

`prefer_wide_vectors()` runs when this module is imported, which `dscjax/__init__.py` does
first. It appends the flag to `XLA_FLAGS` only if the CPU has AVX-512 (Linux `/proc/cpuinfo`),
the user has not set the flag, JAX has not yet created its backends (XLA reads the flags then),
and `DSCJAX_NO_XLA_FLAGS` is not set. Other backends ignore the flag.
"""

from __future__ import annotations

import os
import sys

FLAG = "--xla_cpu_prefer_vector_width=512"
OPT_OUT = "DSCJAX_NO_XLA_FLAGS"


def cpu_has_avx512(cpuinfo: str = "/proc/cpuinfo") -> bool:
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


def _backends_initialized() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover - layout of a future jax
        return False
    check = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(check()) if check is not None else False


def prefer_wide_vectors(environ=os.environ, has_avx512=None) -> bool:
    """Append FLAG to environ["XLA_FLAGS"] when it can help and is wanted; True if it did."""
    flags = environ.get("XLA_FLAGS", "")
    if environ.get(OPT_OUT) or "xla_cpu_prefer_vector_width" in flags:
        return False
    if not (cpu_has_avx512() if has_avx512 is None else has_avx512):
        return False
    if environ is os.environ and _backends_initialized():
        return False
    environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True


prefer_wide_vectors()
