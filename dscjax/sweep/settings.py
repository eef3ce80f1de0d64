"""What a sweep varies and how: the `[sweep]` table of a config file and its checks."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Literal, get_args

import numpy as np

from dscjax import device, params, validation
from dscjax import settings as schema
from dscjax.params import Param, Range, default_ranges
from dscjax.rules import AtLeast, Choice, Maybe, Positive, Strings
from dscjax.runspec import RunSpec
from dscjax.settings import setting
from dscjax.validation import ConfigError

Dtype = Literal["float32", "float64"]
DTYPES: tuple[str, ...] = get_args(Dtype)


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    """What to sweep and how: the `[sweep]` table of a config file, each key declared once
    (`dscjax.settings`: its default, meaning, rule and option), and `ranges` from the
    sub-table `[sweep.ranges]` (sampled) or `[sweep.grid]` (full factorial), read by
    `settings_from_dict`; empty: `default_ranges(setup)` (each +-30 %)."""

    samples: int = setting(10_000, "number of sampled plants (not for a grid)", AtLeast(1),
                           flag="--samples")
    method: params.Uniform | params.LatinHypercube | params.Grid = setting(
        params.Uniform(), "sampling: uniform (i.i.d.), lhs (Latin hypercube) or grid (full "
        "factorial, first range slowest; [sweep.grid] or --grid)", Choice(params.METHODS),
        flag="--method")
    ranges: tuple[Range, ...] = ()
    seed: int = setting(0, "seed of the samples (and of the random handful of traces)",
                        AtLeast(0), flag="--seed")
    chunk: int | None = setting(
        None, f"samples per block and device; none: about {device.CPU_BLOCK} on the CPU, on a "
        f"GPU from its free memory up to {device.MAX_BLOCK:,} (a --resume keeps the sweep's own)",
        Maybe(AtLeast(1)), flag="--chunk")
    dtype: Dtype = setting("float64", "float64, or float32 (faster; its metrics re-checked in "
                           "float64 on a few rows)", Choice(DTYPES))
    worst: int = setting(6, "full traces of the K worst samples", AtLeast(0), flag="--worst")
    random: int = setting(3, "full traces of R random samples", AtLeast(0), flag="--random")
    heatmap: tuple[str, str] | None = setting(
        None, "the two parameters of the heatmap, e.g. hysteresis.alpha,plant.g[1]; none: the "
        "first two swept", Maybe(Strings()), flag="--heatmap")
    threshold: float | None = setting(
        None, "windowed L-inf error above which tracking counts as degraded; none: 2 x the "
        "nominal setup's", Maybe(Positive()), flag="--threshold")

    def validate(self, prefix: str = "sweep") -> None:
        if self.heatmap is not None and len(self.heatmap) != 2:
            raise ConfigError(f"{prefix}.heatmap must be two parameter names (got "
                              f"{list(self.heatmap)!r})")

    def n_samples(self) -> int:
        if self.method.grid:
            return int(np.prod([r.num for r in self.ranges], dtype=np.int64))
        return int(self.samples)


def settings_from_dict(table: Mapping[str, Any], base: SweepSettings | None = None
                       ) -> SweepSettings:
    """The `[sweep]` table of a config file laid over `base`: `SweepSettings`' keys, and the
    sub-tables `[sweep.ranges]` (``"plant.g[1]" = [0.8, 1.2]``, ``"hysteresis.alpha" =
    "30%"``) or `[sweep.grid]` (``"hysteresis.alpha" = [0.7, 1.3, 41]``, method "grid")."""
    s = schema.from_table(SweepSettings, table, "sweep.", base, skip=("ranges", "grid"))
    if s.heatmap is not None:
        s = dataclasses.replace(s, heatmap=tuple(Param.parse(h, "sweep.heatmap").name
                                                 for h in s.heatmap))
    if "ranges" in table and "grid" in table:
        raise ConfigError("give either [sweep.ranges] or [sweep.grid], not both")
    if "ranges" in table:
        s = dataclasses.replace(s, ranges=params.from_table(table["ranges"], "sweep.ranges"))
    if "grid" in table:
        if "samples" in table:
            raise ConfigError("sweep.samples cannot be used with [sweep.grid] (a grid's size "
                              "is the product of its numbers of points)")
        if table.get("method", "grid") != "grid":
            raise ConfigError(f"sweep.method must be 'grid' with [sweep.grid] "
                              f"(got {table['method']!r})")
        s = dataclasses.replace(s, method=params.Grid(),
                                ranges=params.from_table(table["grid"], "sweep.grid", True))
    return s


def to_table(s: SweepSettings, setup) -> dict[str, Any]:
    """The effective [sweep] table (ranges resolved to absolute bounds, each the shortest
    decimal that gives the bound in the sweep's dtype), as data for the TOML writer."""
    table = {k: v for k, v in schema.to_table(s).items() if v != "none"
             and not (k == "samples" and s.method.grid)}
    resolved = (r.resolve(setup) for r in s.ranges or default_ranges(setup))
    table["grid" if s.method.grid else "ranges"] = {
        r.name: [validation.shortest(r.low, s.dtype), validation.shortest(r.high, s.dtype)]
        + ([r.num] if r.num is not None else []) for r in resolved}
    return table


def check_settings(settings: SweepSettings, setup, spec: RunSpec) -> tuple[Range, ...]:
    """The resolved ranges, after checking the settings against the setup and the run of
    `spec` (ConfigError naming the field; the ranges as `params.check`)."""
    # the run settings first: a bad window or dt is not the fault of a range
    validation.validate_run(setup, spec.t_final, float(spec.dt), float(spec.window_start))
    s = schema.checked(settings, lambda key: f"sweep.{key}")  # (built in code: read by rules)
    if s.method.grid and not s.ranges:
        raise ConfigError("a grid sweep needs at least one axis (--grid PATH=LOW:HIGH:NUM)")
    field = "sweep.grid" if s.method.grid else "sweep.ranges"
    ranges = params.check(s.ranges or default_ranges(setup), setup, field, grid=s.method.grid,
                          spec=spec)
    if not s.method.grid and len(ranges) == 0:
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

