"""Where a program runs: the device of a run, the sweep's default block, what JAX sees.

    choice = device.choose("auto", rows=100_000)   # Choice(device, devices, reason)
    with device.placed(choice): ...                # jax.default_device, a context

`choose` and `auto_chunk` are pure functions of a device list and free memory (testable
without an accelerator). "auto" runs one trajectory, and batches below a crossover row count,
on the CPU (an accelerator pays a launch latency at every step) and larger batches on the
accelerator; the crossover is an estimate (docs/sweeps.md), not measured on the machine at
hand. A user's `jax.default_device` is honoured. Nothing here changes JAX's global state.
"""

from __future__ import annotations

import collections
import contextlib
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax

from dscjax.validation import ConfigError, cores, one_of

KINDS = ("auto", "cpu", "gpu")
# Estimates behind the crossover (docs/sweeps.md): batched rows x steps per second of one CPU
# core (float32), and the seconds an accelerator spends per integration step whatever the
# batch (kernel launches), so a batch of B rows runs at B / latency row-steps per second there.
CPU_ROW_STEPS_PER_S_CORE = 1.5e7
ACCELERATOR_STEP_LATENCY_S = 3.4e-5
# The sweep's block: on the CPU about CPU_BLOCK rows; on an
# accelerator the largest power of two whose program takes at most FILL of the free memory,
# within [MIN_BLOCK, MAX_BLOCK], or DEFAULT_ACCELERATOR_BLOCK where the memory is unknown.
CPU_BLOCK = 16_384
MAX_BLOCK = 2**19
MIN_BLOCK = 256
DEFAULT_ACCELERATOR_BLOCK = 2**17
FILL = 0.5


class Choice(NamedTuple):
    """Where a run goes. `device`: the device of a single program (one of this process's);
    `devices`: every device of its platform, over every host (a sweep's blocks);
    `reason`: why, one clause for a banner (`str(choice)`: "cpu (auto: ...)")."""

    device: Any
    devices: tuple
    reason: str

    @property
    def platform(self) -> str:
        return self.device.platform

    def __str__(self) -> str:
        n = len(self.devices)
        return f"{self.platform}{f' x{n}' if n > 1 else ''} ({self.reason})"


def visible() -> list:
    """The devices JAX sees: the default backend's (over every host), then the CPU's if the
    default is an accelerator."""
    devices = list(jax.devices())
    if devices[0].platform != "cpu":
        with contextlib.suppress(RuntimeError):
            devices += jax.devices("cpu")
    return devices


def crossover(n_cores: int | None = None) -> int:
    """The batch size (rows) above which an accelerator outruns `n_cores` CPU cores: where
    B / ACCELERATOR_STEP_LATENCY_S = n_cores x CPU_ROW_STEPS_PER_S_CORE (estimates)."""
    n = cores() if n_cores is None else n_cores
    return max(int(round(n * CPU_ROW_STEPS_PER_S_CORE * ACCELERATOR_STEP_LATENCY_S)), 1)


def _seen(devices: Sequence) -> str:
    count = collections.Counter(d.platform for d in devices)
    return ", ".join(f"{p} x{n}" for p, n in count.items()) or "none"


def choose(kind, rows: int = 1, devices: Sequence | None = None, *, preferred=None,
           n_cores: int | None = None, field: str = "simulation.device") -> Choice:
    """The device of a run of `rows` trajectories (one program's batch).

    Args:
        kind: "auto", "cpu" or "gpu" (`RunSpec.device`), or a jax Device (used as given).
        rows: trajectories run together (1: a single run).
        devices: the devices to choose from (default `visible()`).
        preferred: the caller's `jax.default_device`, which "auto" takes (read from JAX when
            `devices` is None).
        n_cores: the CPU cores (default: this process's), for the crossover.
        field: how a message names the setting.

    Raises ConfigError naming `field` for an unknown kind, or "gpu" with no accelerator.
    """
    process = 0
    if devices is None:
        devices = visible()
        preferred = _default_device() if preferred is None else preferred
        process = jax.process_index()
    devices = list(devices)

    def pick(platform: str, reason: str, first=None) -> Choice:
        same = [d for d in devices if d.platform == platform and d is not first]
        every = ([first] if first is not None else []) + same
        mine = [d for d in every if getattr(d, "process_index", 0) == process]
        return Choice((mine or every)[0], tuple(every), reason)

    if not isinstance(kind, str):  # a Device
        return pick(kind.platform, "as given", kind)
    one_of(kind, field, KINDS)
    accelerators = [d for d in devices if d.platform != "cpu"]
    has_cpu = any(d.platform == "cpu" for d in devices)
    if kind == "gpu":
        if not accelerators:
            raise ConfigError(
                f"{field} must be one of 'auto', 'cpu' on this machine (got 'gpu', but JAX "
                f"sees no GPU: {_seen(devices)}); on a GPU machine install JAX's CUDA wheels: "
                f"pip install -e \".[cuda]\"")
        return pick(accelerators[0].platform, "as asked")
    if kind == "cpu":
        if not has_cpu:
            raise ConfigError(f"{field} must not be 'cpu' here: JAX sees no CPU device "
                              f"({_seen(devices)}; JAX_PLATFORMS may exclude it)")
        return pick("cpu", "as asked")
    if preferred is not None:
        return pick(preferred.platform, "auto: the caller's jax.default_device", preferred)
    if not accelerators:
        return pick(devices[0].platform, "auto: JAX sees no GPU")
    what = "one trajectory" if rows <= 1 else f"{rows:,} trajectories"
    limit = crossover(n_cores)
    if has_cpu and rows < limit:
        return pick("cpu", f"auto: {what}, fewer than the ~{limit:,} a GPU needs to be "
                    f"faster")
    return pick(accelerators[0].platform, f"auto: {what}" + (
        f", at least the ~{limit:,} a GPU needs to be faster" if has_cpu else ""))


def _default_device():
    """The caller's `jax.default_device` (a Device; a platform name gives its first device),
    or None."""
    value = jax.config.jax_default_device
    if not isinstance(value, str):  # a Device, or None
        return value
    try:
        return jax.devices(value)[0]
    except RuntimeError:
        return None


def placed(choice: Choice):
    """A context that makes `choice.device` JAX's default device (`jax.default_device`);
    nothing where it already is the default (JAX's first device, no caller's default)."""
    if jax.config.jax_default_device is None and choice.device == jax.devices()[0]:
        return contextlib.nullcontext()
    return jax.default_device(choice.device)


def free_bytes(device) -> int | None:
    """Bytes free on `device` for new buffers (its allocator's limit less what is in use);
    None where JAX does not say (the CPU)."""
    try:
        stats = device.memory_stats()
    except (AttributeError, NotImplementedError, RuntimeError):
        return None
    if not stats or "bytes_limit" not in stats:
        return None
    return max(int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)), 0)


def per_row_bytes(compiled, rows: int) -> float | None:
    """Bytes per batch row of a compiled program (`jax.stages.Compiled`) of `rows` rows: its
    arguments, outputs and temporaries (`memory_analysis()`) over `rows`, the fixed part
    included (an overestimate). None where JAX gives no memory analysis."""
    try:
        stats = compiled.memory_analysis()
    except (AttributeError, NotImplementedError, RuntimeError):
        return None
    if stats is None:
        return None
    total = (stats.argument_size_in_bytes + stats.output_size_in_bytes
             + stats.temp_size_in_bytes - stats.alias_size_in_bytes)
    return total / rows if total > 0 and rows > 0 else None


def auto_chunk(n: int, device=None, free: int | None = None, per_row: float | None = None,
               n_devices: int = 1) -> int:
    """Rows per block of a sweep of `n` rows on `device` (None: the CPU).

    CPU: about CPU_BLOCK, the blocks evenly filled (rounded up to 256). Accelerator: at most
    the largest power of two of rows whose program takes FILL of the `free` bytes at
    `per_row` bytes a row (DEFAULT_ACCELERATOR_BLOCK where either is unknown), within
    [MIN_BLOCK, MAX_BLOCK], and at most n spread over `n_devices`; the blocks evenly filled.
    """
    if device is None or device.platform == "cpu":
        return _even(n, CPU_BLOCK)
    if free is None or not per_row:
        cap = DEFAULT_ACCELERATOR_BLOCK
    else:
        fits = max(int(FILL * free / per_row), 1)
        cap = min(max(1 << (fits.bit_length() - 1), MIN_BLOCK), MAX_BLOCK)
    return _even(n, min(cap, max(-(-n // max(n_devices, 1)), 1)))


def _even(n: int, cap: int) -> int:
    """Rows per block: at most about `cap`, the ceil(n / cap) blocks evenly filled (rounded
    up to 256, or to 8 for blocks of at most 256)."""
    blocks = -(-n // cap)
    per = -(-n // blocks)
    align = 256 if per > 256 else 8
    return -(-per // align) * align


def describe() -> list[str]:
    """What JAX sees, one line per backend: "cpu: 1 device (TFRT_CPU_0)", "gpu: none (...)"."""
    lines = [f"jax {jax.__version__}, default backend {jax.default_backend()}"]
    for platform in ("cpu", "gpu", "tpu"):
        try:
            devices = jax.devices(platform)
        except RuntimeError:
            if platform == "gpu":
                lines.append("gpu: none (on a GPU machine: pip install -e \".[cuda]\")")
            continue
        kinds = sorted({getattr(d, "device_kind", platform) for d in devices})
        lines.append(f"{platform}: {len(devices)} device{'s' if len(devices) > 1 else ''} "
                     f"({', '.join(kinds)})")
    return lines


__all__ = ["ACCELERATOR_STEP_LATENCY_S", "CPU_BLOCK", "CPU_ROW_STEPS_PER_S_CORE",
           "DEFAULT_ACCELERATOR_BLOCK", "FILL", "KINDS", "MAX_BLOCK", "MIN_BLOCK", "Choice",
           "auto_chunk", "choose", "cores", "crossover", "describe", "free_bytes",
           "per_row_bytes", "placed", "visible"]
