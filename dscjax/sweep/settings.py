"""What a sweep varies and how: the `[sweep]` table of a config file and its checks."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, Literal, get_args

import numpy as np

from dscjax import device, params, validation
from dscjax.params import Param, Range, default_ranges
from dscjax.validation import ConfigError

Parallel = Literal["per_device", "spmd"]
PARALLEL: tuple[str, ...] = get_args(Parallel)
Dtype = Literal["float32", "float64"]
DTYPES: tuple[str, ...] = get_args(Dtype)
AUTO_BLOCK = device.CPU_BLOCK  # about this many samples per block on the CPU (chunk = None)


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    """What to sweep and how; the `[sweep]` table of a config file (see `settings_from_dict`).

    Attributes:
        samples: number of sampled plants (not for a grid).
        method: "uniform", "lhs" or "grid" (full factorial, first range slowest).
        ranges: what varies; empty: `default_ranges(setup)` (each +-30 %).
        seed: seed of the samples (and of the random handful of traces).
        chunk: samples per block and device; None: `device.auto_chunk`.
        dtype: "float64" (default) or "float32" (faster; its metrics re-checked in float64,
            `float64_check`).
        worst, random: how many worst samples and random samples get full traces.
        heatmap: the two parameter names of the heatmap (default: the first two swept).
        threshold: windowed L-inf error above which tracking counts as degraded (default:
            2 x the nominal setup's).
        parallel: "per_device" (bitwise device-count independent) or "spmd" (shard_map).
    """

    samples: int = 10_000
    method: params.Method = "uniform"
    ranges: tuple[Range, ...] = ()
    seed: int = 0
    chunk: int | None = None
    dtype: Dtype = "float64"
    worst: int = 6
    random: int = 3
    heatmap: tuple[str, str] | None = None
    threshold: float | None = None
    parallel: Parallel = "per_device"

    def resolved_ranges(self, setup) -> tuple[Range, ...]:
        return tuple(r.resolve(setup) for r in (self.ranges or default_ranges(setup)))

    def n_samples(self) -> int:
        if self.method == "grid":
            return int(np.prod([r.num for r in self.ranges], dtype=np.int64))
        return int(self.samples)


SETTINGS_KEYS = ("samples", "method", "seed", "chunk", "dtype", "worst", "random", "heatmap",
                 "threshold", "parallel", "ranges", "grid")


def settings_from_dict(table: Mapping[str, Any], base: SweepSettings | None = None
                       ) -> SweepSettings:
    """The `[sweep]` table of a config file laid over `base`.

    Keys: `SweepSettings`' fields, and the sub-tables `[sweep.ranges]` (``"plant.g[1]" =
    [0.8, 1.2]``, ``"hysteresis.alpha" = "30%"``) or `[sweep.grid]` (``"hysteresis.alpha" =
    [0.7, 1.3, 41]``, method "grid").
    """
    s = base or SweepSettings()
    for key in table:
        if key not in SETTINGS_KEYS:
            raise ConfigError(f"unknown key 'sweep.{key}' (allowed: {', '.join(SETTINGS_KEYS)})")
    changes: dict[str, Any] = {}
    for key in ("samples", "seed", "chunk", "worst", "random"):
        if key in table:
            changes[key] = validation.integer(table[key], f"sweep.{key}")
    for key in ("method", "dtype", "parallel"):
        if key in table:
            changes[key] = validation.string(table[key], f"sweep.{key}")
    if "threshold" in table:
        changes["threshold"] = validation.number(table["threshold"], "sweep.threshold")
    if "heatmap" in table:
        v = table["heatmap"]
        if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, str) for x in v)):
            raise ConfigError(f"sweep.heatmap must be a list of two parameter names "
                              f"(got {v!r})")
        changes["heatmap"] = (Param.parse(v[0], "sweep.heatmap").name,
                              Param.parse(v[1], "sweep.heatmap").name)
    if "ranges" in table and "grid" in table:
        raise ConfigError("give either [sweep.ranges] or [sweep.grid], not both")
    for key, grid in (("ranges", False), ("grid", True)):
        if key in table:
            changes["ranges"] = params.from_table(table[key], f"sweep.{key}", grid)
    if "grid" in table:
        if "samples" in table:
            raise ConfigError("sweep.samples cannot be used with [sweep.grid] (a grid's size "
                              "is the product of its numbers of points)")
        if changes.get("method", "grid") != "grid":
            raise ConfigError(f"sweep.method must be 'grid' with [sweep.grid] "
                              f"(got {changes['method']!r})")
        changes["method"] = "grid"
    return dataclasses.replace(s, **changes)


def check_settings(settings: SweepSettings, setup, t_final: float, dt: float,
                   window_start: float | None = None) -> tuple[Range, ...]:
    """The resolved ranges, after checking the settings against the setup (ConfigError
    naming the field; the ranges as `params.check`)."""
    s = settings
    # the run settings first: a bad window or dt is not the fault of a range
    validation.validate_run(setup, t_final, dt, 1, window_start)
    validation.one_of(s.method, "sweep.method", params.METHODS)
    validation.one_of(s.dtype, "sweep.dtype", DTYPES)
    validation.one_of(s.parallel, "sweep.parallel", PARALLEL)
    if s.method != "grid":
        validation.integer(s.samples, "sweep.samples", 1)
    if s.chunk is not None:
        validation.integer(s.chunk, "sweep.chunk", 1)
    for key in ("worst", "random"):
        validation.integer(getattr(s, key), f"sweep.{key}", 0)
    if s.threshold is not None and not (s.threshold > 0 and math.isfinite(s.threshold)):
        raise ConfigError(f"sweep.threshold must be > 0 (got {s.threshold})")
    if s.method == "grid" and not s.ranges:
        raise ConfigError("a grid sweep needs at least one axis (--grid PATH=LOW:HIGH:NUM)")
    field = "sweep.grid" if s.method == "grid" else "sweep.ranges"
    ranges = params.check(s.ranges or default_ranges(setup), setup, field, grid=s.method == "grid",
                      t_final=t_final, dt=dt, window_start=window_start)
    if s.method != "grid" and len(ranges) == 0:
        raise ConfigError("sweep.ranges is empty")
    if s.heatmap is not None:
        names = [r.name for r in ranges]
        for h in s.heatmap:
            if h not in names:
                raise ConfigError(f"sweep.heatmap: {h!r} is not swept (swept: "
                                  f"{', '.join(names)})")
        if s.heatmap[0] == s.heatmap[1]:
            raise ConfigError("sweep.heatmap needs two different parameters")
    if s.n_samples() > 2**40:
        raise ConfigError(f"sweep size {s.n_samples()} is too large")
    return ranges

