"""Monte-Carlo and grid robustness sweeps: many plants, fixed gains, metrics only.

    settings = SweepSettings(samples=100_000)                  # alpha, lam, psi within +-30 %
    result = run_sweep(paper_example(np.float32), settings, t_final=20.0, dt=1e-3,
                       out_dir="results/sweep")                 # chunk files, resumable
    result.columns["linf_error_window"]                         # one row per sample

What a sweep does:

- **Samples** (seeded; i.i.d. uniform or Latin hypercube) or a full-factorial **grid** over any
  numeric leaves of the Setup, addressed by their config paths, with an element index for
  vector leaves: ``hysteresis.alpha``, ``plant.g[1]``, ``plant.x0[0]``, ``plant.dbar_amp``.
  The whole table of parameters is drawn up front from the seed, so it does not depend on the
  chunk size or the device count.
- **Blocks.** Samples are processed in blocks of `chunk` rows (the last one padded with its own
  first row). Every block has the same shape, so one compiled program serves all of them. Per
  sample only the metrics come back (running reductions over every RK4 step, see `metrics.py`),
  with the divergence status and time; memory is O(chunk) on the device.
- **Devices.** The blocks of a round are laid out over a `jax.sharding.Mesh` of every device
  (all hosts after `jax.distributed.initialize()`) as one global array with a `NamedSharding`
  along the batch axis; each device then runs the SAME single-device program on its own block.
  This is deliberate: XLA compiles a partitioned (shard_map / GSPMD) program through a
  different pass pipeline from the single-device one, which on XLA:CPU changed float64 results
  by ~1e-11 and doubled the sines per step (measured; see docs/sweeps.md). With a fixed block
  shape per device, results are bitwise independent of the device count. `parallel="spmd"`
  runs one shard_map program instead (one compilation for all devices; results agree to
  round-off but not bitwise).
- **Disk.** With `out_dir`, every finished block is written at once as
  ``chunks/chunk_000123.npz`` (atomically); `resume=True` skips the blocks already there and
  the final ``results.npz`` is byte-identical to that of an uninterrupted run.

Nothing here raises for a bad sample: a diverged trajectory is a row with `diverged = True`,
the time it left the state bound or went non-finite, and NaN for every metric (they were not
measured over the horizon they name; `dscjax.simulate.nan_if_diverged`).
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import files, params, validation
from dscjax.validation import ConfigError

METHODS = ("uniform", "lhs", "grid")
PARALLEL = ("per_device", "spmd")
DEFAULT_PATHS = ("hysteresis.alpha", "hysteresis.lam", "hysteresis.psi")
DEFAULT_REL = 0.30
AUTO_BLOCK = 16384  # samples per block and device when chunk = None (best measured on CPU)
FORMAT_VERSION = 2  # 2: the metrics of diverged rows are NaN (were the frozen values)
METRICS = ("linf_error", "linf_error_window", "l2_error", "l2_error_window", "rms_error",
           "rms_error_window", "max_abs_u", "l2_u", "tv_u", "max_abs_w")
STATUS_COLUMNS = ("diverged", "t_diverged", "status")


# -- parameters and ranges ----------------------------------------------------------------------

_PARAM_RE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*)(?:\[(\d+)\])?$")


@dataclasses.dataclass(frozen=True)
class Param:
    """One swept number: the leaf at `path`, or its element `index` for a vector leaf."""

    path: str
    index: int | None = None

    @property
    def name(self) -> str:
        return self.path if self.index is None else f"{self.path}[{self.index}]"

    @classmethod
    def parse(cls, text: str, field: str = "sweep.ranges") -> Param:
        m = _PARAM_RE.match(text.strip())
        if not m:
            raise ConfigError(f"{field}: {text!r} is not a parameter path (e.g. "
                              f"'hysteresis.alpha' or 'plant.g[1]')")
        return cls(m.group(1), None if m.group(2) is None else int(m.group(2)))

    def nominal(self, setup) -> float:
        value = np.asarray(params.get(setup, self.path), dtype=float)
        return float(value if self.index is None else value[self.index])


@dataclasses.dataclass(frozen=True)
class Range:
    """Bounds of one swept parameter.

    Either absolute (`low`, `high`) or relative (`rel`: nominal * (1 -+ rel), resolved against
    the setup by `resolve`). `num` is the number of grid points (grid sweeps only).
    """

    param: Param
    low: float | None = None
    high: float | None = None
    rel: float | None = None
    num: int | None = None

    @property
    def name(self) -> str:
        return self.param.name

    def resolve(self, setup) -> Range:
        if self.rel is None:
            return self
        nominal = self.param.nominal(setup)
        lo, hi = sorted((nominal * (1.0 - self.rel), nominal * (1.0 + self.rel)))
        return dataclasses.replace(self, low=lo, high=hi, rel=None)

    def spec(self) -> str:
        """The range as written on the command line."""
        body = (f"{self.rel * 100:g}%" if self.rel is not None
                else f"{self.low:.10g}:{self.high:.10g}")
        return f"{self.name}={body}" + (f":{self.num}" if self.num is not None else "")


def parse_range(text: str, grid: bool = False, field: str | None = None) -> Range:
    """A range from the command line: ``PATH=LOW:HIGH``, ``PATH=30%`` (+-30 % of the nominal
    value) or, for a grid, ``PATH=LOW:HIGH:NUM``."""
    field = field or ("--grid" if grid else "--range")
    form = "PATH=LOW:HIGH:NUM" if grid else "PATH=LOW:HIGH or PATH=P%"
    path, eq, body = text.partition("=")
    if not eq:
        raise ConfigError(f"{field} must be {form} (got {text!r})")
    param = Param.parse(path, field)
    return _range_from_value(param, _split_body(body), grid, f"{field} {param.name}", form,
                             got=repr(text))


def _split_body(body: str):
    body = body.strip()
    if body.endswith("%"):
        return body
    return body.split(":")


def _range_from_value(param: Param, value, grid: bool, field: str, form: str | None = None,
                      got: str | None = None) -> Range:
    """Range from a TOML value ([low, high], [low, high, num] or "30%") or split CLI text
    (then `got` is the text as the user wrote it, which messages quote)."""
    form = form or ("[low, high, num]" if grid else "[low, high] or \"P%\"")
    got = got or repr(value)
    if isinstance(value, str):
        if grid:
            raise ConfigError(f"{field} must be {form} (got {got})")
        text = value.strip().lstrip("±+")
        try:
            rel = float(text[:-1]) / 100.0 if text.endswith("%") else math.nan
        except ValueError:
            rel = math.nan
        if not math.isfinite(rel):
            raise ConfigError(f"{field} must be {form} (got {got})")
        if rel <= 0:
            raise ConfigError(f"{field} is an empty range ({got}); give a percentage > 0")
        return Range(param, rel=rel)
    if not isinstance(value, list | tuple) or len(value) != (3 if grid else 2):
        raise ConfigError(f"{field} must be {form} (got {got})")
    for i, v in enumerate(value[:2]):
        if isinstance(v, bool):
            raise ConfigError(f"{field}[{i}] must be a number, not a boolean (got "
                              f"{'true' if v else 'false'})")
    try:
        low, high = (float(v) for v in value[:2])
    except (TypeError, ValueError):
        raise ConfigError(f"{field} must be {form} with numbers (got {got})") from None
    num = None
    if grid:
        num = value[2]
        if isinstance(num, str):
            try:
                num = int(num)
            except ValueError:
                pass
        if isinstance(num, bool) or not isinstance(num, int):
            raise ConfigError(f"{field}: the number of grid points must be an integer "
                              f"(got {value[2]!r})")
    return Range(param, low=low, high=high, num=num)


def default_ranges() -> tuple[Range, ...]:
    """alpha, lam and psi each within +-30 % of the setup's values."""
    return tuple(Range(Param(p), rel=DEFAULT_REL) for p in DEFAULT_PATHS)


# -- settings -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    """What to sweep and how; the `[sweep]` table of a config file (see `settings_from_dict`).

    Attributes:
        samples: number of sampled plants (ignored for a grid, whose size is the product).
        method: "uniform" (i.i.d.), "lhs" (Latin hypercube) or "grid" (full factorial over
            the ranges' `num` points, first range slowest).
        ranges: what varies; empty means `default_ranges()` (alpha, lam, psi +-30 %).
        seed: seed of the samples (and of the random handful of traces).
        chunk: samples per block and device; None picks about 16384, evenly split.
        dtype: "float32" (default for sweeps) or "float64".
        worst, random: how many worst samples and random samples get full traces.
        heatmap: the two parameter names of the heatmap (default: the first two swept).
        threshold: windowed L-inf error above which tracking counts as degraded (default:
            2 x the nominal setup's).
        parallel: "per_device" (bitwise device-count independent) or "spmd" (shard_map).
    """

    samples: int = 10_000
    method: str = "uniform"
    ranges: tuple[Range, ...] = ()
    seed: int = 0
    chunk: int | None = None
    dtype: str = "float32"
    worst: int = 6
    random: int = 3
    heatmap: tuple[str, str] | None = None
    threshold: float | None = None
    parallel: str = "per_device"

    def resolved_ranges(self, setup) -> tuple[Range, ...]:
        return tuple(r.resolve(setup) for r in (self.ranges or default_ranges()))

    def n_samples(self) -> int:
        if self.method == "grid":
            return int(np.prod([r.num for r in self.ranges], dtype=np.int64))
        return int(self.samples)


SETTINGS_KEYS = ("samples", "method", "seed", "chunk", "dtype", "worst", "random", "heatmap",
                 "threshold", "parallel", "ranges", "grid")


def settings_from_dict(table: Mapping[str, Any], base: SweepSettings | None = None
                       ) -> SweepSettings:
    """The `[sweep]` table of a config file laid over `base`.

    Keys: samples, method, seed, chunk, dtype, worst, random, heatmap (a list of two names),
    threshold, parallel, and the sub-tables `[sweep.ranges]` (``"plant.g[1]" = [0.8, 1.2]``,
    ``"hysteresis.alpha" = "30%"``; dotted keys such as ``hysteresis.alpha = [..]`` work too)
    or `[sweep.grid]` (``"hysteresis.alpha" = [0.7, 1.3, 41]``, which selects method "grid").
    """
    s = base or SweepSettings()
    for key in table:
        if key not in SETTINGS_KEYS:
            raise ConfigError(f"unknown key 'sweep.{key}' (allowed: {', '.join(SETTINGS_KEYS)})")
    changes: dict[str, Any] = {}
    for key in ("samples", "seed", "chunk", "worst", "random"):
        if key in table:
            changes[key] = _int(table[key], f"sweep.{key}")
    for key in ("method", "dtype", "parallel"):
        if key in table:
            if not isinstance(table[key], str):
                raise ConfigError(f"sweep.{key} must be a string (got {table[key]!r})")
            changes[key] = table[key]
    if "threshold" in table:
        v = table["threshold"]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ConfigError(f"sweep.threshold must be a number (got {v!r})")
        changes["threshold"] = float(v)
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
            sub = table[key]
            if not isinstance(sub, Mapping):
                raise ConfigError(f"sweep.{key} must be a table ([sweep.{key}])")
            changes["ranges"] = tuple(
                _range_from_value(Param.parse(name, f"sweep.{key}"), value, grid,
                                  f"sweep.{key}.{name}")
                for name, value in _flatten(sub).items())
    if "grid" in table:
        if "samples" in table:
            raise ConfigError("sweep.samples cannot be used with [sweep.grid] (a grid's size "
                              "is the product of its numbers of points)")
        if changes.get("method", "grid") != "grid":
            raise ConfigError(f"sweep.method must be 'grid' with [sweep.grid] "
                              f"(got {changes['method']!r})")
        changes["method"] = "grid"
    return dataclasses.replace(s, **changes)


def _flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"hysteresis": {"alpha": [..]}} -> {"hysteresis.alpha": [..]} (TOML dotted keys)."""
    out = {}
    for k, v in table.items():
        if isinstance(v, Mapping):
            out |= _flatten(v, f"{prefix}{k}.")
        else:
            out[f"{prefix}{k}"] = v
    return out


def _int(value, field: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ConfigError(f"{field} must be an integer (got {value!r})")
    return int(value)


def check_settings(settings: SweepSettings, setup, t_final: float, dt: float,
                   window_start: float | None = None) -> tuple[Range, ...]:
    """Validate the settings against the setup; return the resolved ranges.

    Raises ConfigError naming the field for: N <= 0, chunk <= 0, an unknown method or dtype,
    an unknown parameter path, a vector leaf without an index, an empty range or lower > upper,
    ranges that allow lam <= psi, and values outside a model's allowed range at either end.
    """
    s = settings
    # the run settings first: a bad window or dt is not the fault of a range
    validation.validate_run(setup, t_final, dt, 1, window_start)
    validation.one_of(s.method, "sweep.method", METHODS)
    validation.one_of(s.dtype, "sweep.dtype", ("float32", "float64"))
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
    numeric = params.numeric_paths(setup)
    seen = set()
    field = "sweep.grid" if s.method == "grid" else "sweep.ranges"
    for r in s.ranges or default_ranges():
        f = f"{field}.{r.name}"
        if r.name in seen:
            raise ConfigError(f"{f} is given twice")
        seen.add(r.name)
        if r.param.path not in numeric:
            raise ConfigError(f"{field}: no parameter '{r.param.path}' in this setup (allowed: "
                              f"{', '.join(numeric)})")
        shape = np.shape(params.get(setup, r.param.path))
        if r.param.index is None and shape != ():
            raise ConfigError(f"{f}: {r.param.path} has shape {shape}; sweep one element, "
                              f"e.g. {r.param.path}[0]")
        if r.param.index is not None and (len(shape) != 1 or r.param.index >= shape[0]):
            raise ConfigError(f"{f}: index {r.param.index} is out of range for "
                              f"{r.param.path} of shape {shape}")
        if s.method == "grid" and r.num is None:
            raise ConfigError(f"{f} needs a number of grid points (LOW:HIGH:NUM)")
        if s.method == "grid" and r.num < 2:
            raise ConfigError(f"{f}: the number of grid points must be >= 2 (got {r.num})")
        if s.method != "grid" and r.num is not None:
            raise ConfigError(f"{f}: a number of points is only meaningful for a grid")
        q = r.resolve(setup)
        if not (math.isfinite(q.low) and math.isfinite(q.high)):
            raise ConfigError(f"{f} must have finite bounds (got [{q.low:g}, {q.high:g}])")
        if q.low == q.high:
            raise ConfigError(f"{f} is an empty range (low = high = {q.low:g}); to fix a "
                              f"parameter, set it in its config section instead")
        if q.low > q.high:
            raise ConfigError(f"{f}: lower bound > upper bound (got [{q.low:g}, {q.high:g}])")
    ranges = s.resolved_ranges(setup)
    if s.method != "grid" and len(ranges) == 0:
        raise ConfigError("sweep.ranges is empty")
    _check_lam_psi(ranges, setup, field)
    for r in ranges:  # every model check is a bound on one number: both ends suffice
        for end in (r.low, r.high):
            one = _set_values(setup, [r.param], np.array([end]))
            try:
                validation.validate_setup(one)
                validation.validate_run(one, t_final, dt, 1, window_start)
            except ConfigError as err:
                raise ConfigError(f"{field}.{r.name} = [{r.low:g}, {r.high:g}]: {err}") from None
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


def assumption_warnings(setup, ranges: Sequence[Range] = (), field: str = "sweep.ranges"
                        ) -> list[str]:
    """`validation.assumption_warnings` of the setup and of every end of every (resolved)
    range: a violation only some samples see is reported with the range that reaches it."""
    out = list(validation.assumption_warnings(setup))
    for r in ranges:
        for end in (r.low, r.high):
            for w in validation.assumption_warnings(_set_values(setup, [r.param],
                                                                np.array([end]))):
                w = w.split(";")[0] + (f" for part of {field}.{r.name} = [{r.low:.6g}, "
                                       f"{r.high:.6g}]; the design's guarantees (Theorem 1) "
                                       f"do not apply there")
                if not any(o.split(":")[0] == w.split(":")[0] for o in out) and w not in out:
                    out.append(w)
    return out


def _check_lam_psi(ranges, setup, field):
    """lam > psi must hold on the whole box: lam's lower end above psi's upper end."""
    by = {r.param.path: r for r in ranges if r.param.index is None}
    if "hysteresis.lam" not in by and "hysteresis.psi" not in by:
        return
    try:
        lam_nom = Param("hysteresis.lam").nominal(setup)
        psi_nom = Param("hysteresis.psi").nominal(setup)
    except KeyError:
        return
    lam = by.get("hysteresis.lam")
    psi = by.get("hysteresis.psi")
    lam_lo = lam.low if lam else lam_nom
    psi_hi = psi.high if psi else psi_nom
    if not lam_lo > psi_hi:
        lam_txt = f"[{lam.low:g}, {lam.high:g}]" if lam else f"{lam_nom:g} (fixed)"
        psi_txt = f"[{psi.low:g}, {psi.high:g}]" if psi else f"{psi_nom:g} (fixed)"
        raise ConfigError(
            f"{field}: hysteresis.lam must stay > hysteresis.psi over the ranges (got lam in "
            f"{lam_txt}, psi in {psi_txt}); make lam's lower bound exceed psi's upper bound")


# -- the table of samples -----------------------------------------------------------------------


def sample_table(ranges: Sequence[Range], method: str, n: int, seed: int) -> np.ndarray:
    """(N, d) float64 parameter values, row i = sample i, column j = ranges[j].

    "uniform": i.i.d. uniform in the box. "lhs": Latin hypercube (each column visits each of
    N equal strata exactly once, uniformly within it). "grid": the full factorial of
    linspace(low, high, num) per range, C order (the last range varies fastest).
    The table is a function of (ranges, method, n, seed) only.
    """
    low = np.array([r.low for r in ranges], dtype=np.float64)
    high = np.array([r.high for r in ranges], dtype=np.float64)
    if method == "grid":
        axes = [np.linspace(r.low, r.high, r.num) for r in ranges]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)
    rng = np.random.default_rng(seed)
    d = len(ranges)
    if method == "uniform":
        u = rng.random((n, d))
    elif method == "lhs":
        u = np.empty((n, d))
        for j in range(d):
            u[:, j] = (rng.permutation(n) + rng.random(n)) / n
    else:
        raise ConfigError(f"sweep.method must be one of {', '.join(map(repr, METHODS))} "
                          f"(got {method!r})")
    return low + u * (high - low)


def auto_chunk(n: int) -> int:
    """Samples per block: about AUTO_BLOCK, the blocks evenly filled (rounded to 256)."""
    blocks = -(-n // AUTO_BLOCK)
    per = -(-n // blocks)
    align = 256 if per > 256 else 8
    return -(-per // align) * align


# -- running one block ----------------------------------------------------------------------------


def _set_values(setup, columns: Sequence[Param], row):
    """setup with the numbers of one row of the table put in (host side, for `simulate`)."""
    values: dict[str, Any] = {}
    for j, p in enumerate(columns):
        if p.index is None:
            values[p.path] = np.asarray(row[j], dtype=np.asarray(params.get(setup, p.path)).dtype)
        else:
            leaf = np.array(values.get(p.path, params.get(setup, p.path)), copy=True)
            leaf[p.index] = row[j]
            values[p.path] = leaf
    return params.set_many(setup, values)


def _overrides(setup, columns: Sequence[Param], table):
    """{path: (B, ...)} overrides from the (B, d) table, inside the traced block function."""
    b = table.shape[0]
    out: dict[str, Any] = {}
    for j, p in enumerate(columns):
        col = table[:, j]
        if p.index is None:
            out[p.path] = col
        else:
            if p.path not in out:
                leaf = jnp.asarray(params.get(setup, p.path), table.dtype)
                out[p.path] = jnp.broadcast_to(leaf, (b, *leaf.shape))
            out[p.path] = out[p.path].at[:, p.index].set(col)
    return out


def _block_body(setup, table, dt, window_start, state_bound, *, columns, n_steps):
    from dscjax.simulate import nan_if_diverged, run

    traj = run(setup, dt, window_start, state_bound, n_steps=n_steps, save_every=n_steps,
                overrides=_overrides(setup, columns, table))
    metrics = nan_if_diverged(traj.metrics, traj.diverged)
    return {**{k: metrics[k] for k in METRICS}, "status": traj.status.code,
            "bad_step": traj.status.step}


_block = jax.jit(_block_body, static_argnames=("columns", "n_steps"))


class _Runner:
    """Runs rounds of blocks, one block per device of the mesh, and returns host arrays."""

    AXIS = "batch"

    def __init__(self, setup, columns, n_steps, dt, window_start, state_bound, chunk,
                 parallel="per_device", devices=None):
        from jax.sharding import Mesh, NamedSharding
        from jax.sharding import PartitionSpec as P

        self.devices = list(devices if devices is not None else jax.devices())
        self.mesh = Mesh(np.array(self.devices), (self.AXIS,))
        self.n_dev = len(self.devices)
        self.chunk = chunk
        self.columns = tuple(columns)
        self.n_steps = n_steps
        self.dtype = np.dtype(np.asarray(setup.plant.x0).dtype)
        self.scalars = tuple(np.asarray(v, self.dtype) for v in (dt, window_start, state_bound))
        self.in_sharding = NamedSharding(self.mesh, P(self.AXIS, None))
        self.out_sharding = NamedSharding(self.mesh, P(self.AXIS))
        self.parallel = parallel
        self._compiled = False
        me = jax.process_index()
        self.local = [d for d in self.devices if d.process_index == me]
        if parallel == "spmd":
            body = jax.shard_map(
                lambda s, t, *a: _block_body(s, t, *a, columns=self.columns, n_steps=n_steps),
                mesh=self.mesh, in_specs=(P(), P(self.AXIS, None), P(), P(), P()),
                out_specs=P(self.AXIS), check_vma=False)
            self._spmd = jax.jit(body)
            self.setup = jax.device_put(setup, NamedSharding(self.mesh, P()))
        else:
            self.setup_on = {d: jax.device_put(setup, d) for d in self.local}

    @property
    def round_size(self) -> int:
        return self.n_dev * self.chunk

    def __call__(self, table: np.ndarray, n_real: int) -> dict[str, np.ndarray]:
        """table: (n_dev * chunk, d) host array, identical on every process; its first
        `n_real` blocks are real (the others pad the round and their rows are garbage)."""
        table = np.asarray(table, self.dtype)
        arr = jax.make_array_from_callback(table.shape, self.in_sharding, lambda i: table[i])
        if self.parallel == "spmd":
            out = self._spmd(self.setup, arr, *self.scalars)
            return {k: _to_host(v) for k, v in out.items()}
        single = jax.process_count() == 1
        jobs = {}
        for shard in arr.addressable_shards:
            block = (shard.index[0].start or 0) // self.chunk
            if not (single and block >= n_real):  # one process: padding blocks need not run
                jobs[block] = shard

        def dispatch(shard):
            return shard.device, _block(self.setup_on[shard.device], shard.data, *self.scalars,
                                        columns=self.columns, n_steps=self.n_steps)

        if self._compiled or len(jobs) == 1:
            per_dev = {b: dispatch(sh) for b, sh in jobs.items()}  # asynchronous: devices overlap
        else:
            # The first call compiles the program once per device: do that concurrently.
            with ThreadPoolExecutor(len(jobs)) as pool:
                per_dev = dict(zip(jobs, pool.map(dispatch, jobs.values()), strict=True))
        self._compiled = True
        if single:
            keys = per_dev[0][1].keys()
            return {k: np.concatenate([np.asarray(per_dev[b][1][k]) for b in sorted(per_dev)]
                                      + [np.zeros(self.chunk * (self.n_dev - len(per_dev)),
                                                  per_dev[0][1][k].dtype)])
                    for k in keys}
        by_device = {dev: res for dev, res in per_dev.values()}
        keys = next(iter(by_device.values())).keys()
        out = {k: jax.make_array_from_single_device_arrays(
            (table.shape[0],), self.out_sharding, [by_device[d][k] for d in self.local])
            for k in keys}
        return {k: _to_host(v) for k, v in out.items()}


def _to_host(a) -> np.ndarray:
    if a.is_fully_addressable:
        return np.asarray(a)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(a, tiled=True))


# -- files ---------------------------------------------------------------------------------------


def _read_chunk(path: Path, fingerprint: str) -> dict[str, np.ndarray] | None:
    """A finished chunk file, or None if missing, unreadable or from another sweep."""
    data = files.read_npz(path)
    if data is None or str(data.pop("_fingerprint", "")) != fingerprint:
        return None
    return data


def _chunk_path(out_dir: Path, b: int) -> Path:
    return out_dir / "chunks" / f"chunk_{b:06d}.npz"


# -- the sweep -----------------------------------------------------------------------------------


@dataclasses.dataclass
class SweepResult:
    """A finished sweep.

    columns: one array per column, one row per sample (in sample order): "sample", the
        parameter columns (names as `Range.name`), the metrics (`METRICS`), "diverged",
        "t_diverged" (+inf if not) and "status" (0 ok, 1 non-finite, 2 state bound).
    param_names: the parameter columns, in table order.
    info: sizes, timing and settings (what `summary.json` reports under "run").
    """

    columns: dict[str, np.ndarray]
    param_names: tuple[str, ...]
    info: dict[str, Any]

    @property
    def n(self) -> int:
        return int(self.columns["sample"].shape[0])


def fingerprint(setup, settings: SweepSettings, ranges, t_final, dt, window_start,
                state_bound, chunk) -> dict[str, Any]:
    """Everything that determines the rows of a sweep (and how they are split into files)."""
    from dscjax import config

    setup_dict = config.to_dict(setup)
    setup_dict.pop("simulation", None)
    return {
        "format": FORMAT_VERSION, "setup": setup_dict,
        "ranges": [[r.name, r.low, r.high, r.num] for r in ranges],
        "method": settings.method, "samples": settings.n_samples(), "seed": settings.seed,
        "dtype": settings.dtype, "t_final": float(t_final), "dt": float(dt),
        "window_start": float(window_start), "state_bound": float(state_bound),
        "chunk": int(chunk),
    }


def run_sweep(
    setup,
    settings: SweepSettings = SweepSettings(),
    t_final: float = 20.0,
    dt: float = 1e-3,
    *,
    window_start: float | None = None,
    state_bound: float = 1e6,
    out_dir: str | Path | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: Callable[[dict[str, Any]], None] | None = None,
    devices=None,
) -> SweepResult:
    """Run a sweep of `setup` (gains fixed) over `settings`; see the module docstring.

    Args:
        setup: the nominal Setup; it is cast to `settings.dtype`.
        settings: what to sample and how (validated here; ConfigError names the field).
        t_final, dt, window_start, state_bound: as in `simulate` (window default 1 s).
        out_dir: write chunk files and results.npz there (None: keep everything in memory).
        resume: skip the blocks already in out_dir (written by the same settings).
        overwrite: start afresh even if out_dir holds chunk files of a sweep.
        progress: called after every round with a dict (done, total, elapsed_s,
            steps_per_s, eta_s, ...).
        devices: the devices to use (default: all, over every host).

    Returns:
        SweepResult; nothing is raised for diverged samples.

    Example:
        >>> import dscjax, numpy as np
        >>> from dscjax.sweep import SweepSettings, run_sweep
        >>> res = run_sweep(dscjax.paper_example(dtype=np.float32), SweepSettings(samples=8),
        ...                 t_final=0.5, dt=1e-3)
        >>> res.columns["linf_error_window"].shape
        (8,)
    """
    from dscjax.simulate import default_window

    window_start = default_window(t_final, window_start)
    validation.one_of(settings.dtype, "sweep.dtype", ("float32", "float64"))
    dtype = np.dtype(settings.dtype)
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise ConfigError("sweep.dtype = 'float64' needs JAX's x64 mode: "
                          "jax.config.update('jax_enable_x64', True) before anything else")
    setup = params.cast(setup, dtype)
    ranges = check_settings(settings, setup, t_final, dt, window_start)
    n_steps = validation.validate_run(setup, t_final, dt, 1, window_start)
    validation.validate_setup(setup)
    if not (state_bound > 0):
        raise ConfigError(f"simulation.state_bound must be > 0 (got {state_bound})")
    n = settings.n_samples()
    chunk = settings.chunk or auto_chunk(n)
    columns = tuple(r.param for r in ranges)
    names = tuple(r.name for r in ranges)
    table = sample_table(ranges, settings.method, n, settings.seed)
    # the values actually simulated: rounded to the sweep's dtype
    table = table.astype(dtype).astype(np.float64)
    n_blocks = -(-n // chunk)
    fp = fingerprint(setup, settings, ranges, t_final, dt, window_start, state_bound, chunk)
    digest = files.digest(fp)

    out = Path(out_dir) if out_dir is not None else None
    main = jax.process_index() == 0
    done = np.zeros(n_blocks, dtype=bool)
    if out is not None:
        done = _prepare_dir(out, fp, digest, n_blocks, resume, overwrite, main)
    kept: dict[int, dict[str, np.ndarray]] = {}

    runner = _Runner(setup, columns, n_steps, dt, window_start, state_bound, chunk,
                     settings.parallel, devices)
    todo = [b for b in range(n_blocks) if not done[b]]
    t_start = time.perf_counter()
    n_done_before = int(sum(_block_len(b, chunk, n) for b in range(n_blocks) if done[b]))
    n_run, t_first_round = 0, None
    for r in range(0, len(todo), runner.n_dev):
        group = todo[r:r + runner.n_dev]
        padded = group + [group[-1]] * (runner.n_dev - len(group))
        rows = np.concatenate([_block_rows(table, b, chunk) for b in padded])
        host = runner(rows, len(group))
        for k, b in enumerate(group):
            lo = b * chunk
            m = _block_len(b, chunk, n)
            part = {key: v[k * chunk:k * chunk + m] for key, v in host.items()}
            data = _columns(np.arange(lo, lo + m, dtype=np.int64), names,
                            table[lo:lo + m], part, dt)
            if out is not None:
                if main:
                    files.write_npz(_chunk_path(out, b), {**data, "_fingerprint": np.array(digest)})
            else:
                kept[b] = data
            n_run += m
        now = time.perf_counter()
        if t_first_round is None:
            t_first_round = (now, n_run)
        if progress is not None:
            progress(_progress(n_done_before + n_run, n, n_run, now - t_start, t_first_round,
                               t_start, n_steps, r // runner.n_dev + 1,
                               -(-len(todo) // runner.n_dev)))
    elapsed = time.perf_counter() - t_start

    if out is not None:
        parts = []
        for b in range(n_blocks):
            data = _read_chunk(_chunk_path(out, b), digest) if main else None
            if main and data is None:
                raise ConfigError(f"{_chunk_path(out, b)} is missing or unreadable after the "
                                  f"sweep; run again with --resume")
            parts.append(data)
    else:
        parts = [kept[b] for b in range(n_blocks)]
    columns_out = ({k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
                   if parts and parts[0] is not None else {})
    if out is not None and main:
        files.write_npz(out / "results.npz", columns_out)
    info = dict(n_samples=n, n_params=len(names), n_blocks=n_blocks, chunk=chunk,
                devices=runner.n_dev, processes=jax.process_count(),
                platform=runner.devices[0].platform, parallel=settings.parallel,
                n_steps=n_steps, dtype=settings.dtype, t_final=float(t_final), dt=float(dt),
                window_start=float(window_start), state_bound=float(state_bound),
                method=settings.method, seed=settings.seed,
                ranges={r.name: [r.low, r.high] + ([r.num] if r.num else []) for r in ranges},
                samples_run=n_run, samples_resumed=n_done_before, wall_s=elapsed,
                steps_per_s=(n_run * n_steps / elapsed) if n_run and elapsed > 0 else None)
    return SweepResult(columns=columns_out, param_names=names, info=info)


def check_resumable(out: str | Path) -> None:
    """ConfigError unless `out` holds a sweep to resume (its sweep.json)."""
    if not (Path(out) / "sweep.json").exists():
        raise ConfigError(f"--resume: nothing to resume in {out} (sweep.json is missing); run "
                          f"without --resume to start afresh")


def _prepare_dir(out: Path, fp, digest, n_blocks, resume, overwrite, main) -> np.ndarray:
    manifest = out / "sweep.json"
    done = np.zeros(n_blocks, dtype=bool)
    if resume:
        check_resumable(out)
    if main:
        (out / "chunks").mkdir(parents=True, exist_ok=True)
        existing = sorted((out / "chunks").glob("chunk_*.npz"))
        if resume:
            files.check_same(files.read_json(manifest).get("fingerprint"), fp,
                             where=f"--resume: {manifest}",
                             fix="use the same settings, or --overwrite to start afresh")
            for b in range(n_blocks):
                done[b] = _read_chunk(_chunk_path(out, b), digest) is not None
        elif existing and not overwrite:
            raise ConfigError(f"{out} already holds a sweep ({len(existing)} chunk files); "
                              f"use --resume to continue it or --overwrite to start afresh")
        else:
            for f in existing:
                f.unlink()
            (out / "results.npz").unlink(missing_ok=True)
        files.write_text(manifest, files.dumps({"fingerprint": fp, "digest": digest}) + "\n")
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        done = np.asarray(multihost_utils.broadcast_one_to_all(done))
    return done


def _block_len(b, chunk, n):
    return min(chunk, n - b * chunk)


def _block_rows(table, b, chunk):
    rows = table[b * chunk:(b + 1) * chunk]
    if rows.shape[0] < chunk:  # pad the last block with its first row (a valid sample)
        rows = np.concatenate([rows, np.repeat(rows[:1], chunk - rows.shape[0], axis=0)])
    return rows


def _columns(sample, names, values, part, dt) -> dict[str, np.ndarray]:
    code = part["status"].astype(np.int8)
    step = part["bad_step"].astype(np.int64)
    out = {"sample": sample}
    out |= {name: values[:, j] for j, name in enumerate(names)}
    out |= {k: part[k] for k in METRICS}
    out["diverged"] = code != 0
    out["t_diverged"] = np.where(step >= 0, step * float(dt), np.inf)
    out["status"] = code
    return out


def _progress(done, total, n_run, elapsed, first, t_start, n_steps, round_i, rounds):
    # The rate after the first round excludes compilation; the ETA uses it once known.
    t_first, n_first = first
    if n_run > n_first and (t_start + elapsed) > t_first:
        rate = (n_run - n_first) / (t_start + elapsed - t_first)
    else:
        rate = n_run / elapsed if elapsed > 0 else 0.0
    eta = (total - done) / rate if rate > 0 else math.inf
    return dict(done=done, total=total, elapsed_s=elapsed, samples_per_s=rate,
                steps_per_s=rate * n_steps, eta_s=eta, round=round_i, rounds=rounds)


def format_progress(p: Mapping[str, Any]) -> str:
    """One line: samples done, throughput and ETA."""
    frac = p["done"] / p["total"] if p["total"] else 1.0
    return (f"  {p['done']:,}/{p['total']:,} samples ({100 * frac:5.1f} %)  "
            f"{p['steps_per_s']:.3g} steps/s  elapsed {_hms(p['elapsed_s'])}  "
            f"ETA {_hms(p['eta_s'])}")


def _hms(s: float) -> str:
    if not math.isfinite(s):
        return "--"
    s = int(round(s))
    return f"{s // 3600}h{s // 60 % 60:02d}m{s % 60:02d}s" if s >= 3600 else (
        f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s")


# -- summaries and traces ------------------------------------------------------------------------

QUANTILES = (0.0, 0.01, 0.05, 0.25, 0.5, 0.75, 0.95, 0.99, 1.0)


def rank_worst(columns: Mapping[str, np.ndarray], k: int) -> np.ndarray:
    """Rows of the k worst samples that did not diverge, largest windowed L-inf error first."""
    ok = ~np.asarray(columns["diverged"], bool)
    lw = np.nan_to_num(np.asarray(columns["linf_error_window"], np.float64), nan=np.inf)
    rows = np.flatnonzero(ok)
    return rows[np.argsort(-lw[rows], kind="stable")][:k]


def rank_diverged(columns: Mapping[str, np.ndarray], k: int) -> np.ndarray:
    """Rows of the first k samples to diverge (earliest divergence time first)."""
    rows = np.flatnonzero(np.asarray(columns["diverged"], bool))
    t = np.asarray(columns["t_diverged"], np.float64)[rows]
    return rows[np.argsort(t, kind="stable")][:k]


def trace_rows(columns: Mapping[str, np.ndarray], k: int) -> tuple[np.ndarray, list[str]]:
    """k rows worth a full trace: about a third the earliest diverged (if any), the rest
    the worst that track; either kind fills in for the other if there are too few."""
    n_div = int(np.sum(columns["diverged"]))
    want_div = min(n_div, -(-k // 3)) if n_div else 0
    worst = rank_worst(columns, k - want_div)
    div = rank_diverged(columns, k - len(worst))
    return (np.concatenate([worst, div]).astype(np.int64),
            ["worst"] * len(worst) + ["diverged"] * len(div))


def summarize(result: SweepResult, nominal: Mapping[str, float] | None = None,
              threshold: float | None = None, worst: int = 6) -> dict[str, Any]:
    """Quantiles of every metric (over the samples that did not diverge), the divergence and
    degradation rates, the worst samples that track and the first to diverge, with their
    parameters."""
    c = result.columns
    div = np.asarray(c["diverged"], bool)
    ok = ~div
    n = result.n
    quant = {}
    for m in METRICS:
        v = np.asarray(c[m], np.float64)[ok]
        v = v[np.isfinite(v)]
        if v.size:
            qs = np.quantile(v, QUANTILES)
            quant[m] = {f"p{round(q * 100):02d}" if 0 < q < 1 else ("min" if q == 0 else "max"):
                        float(x) for q, x in zip(QUANTILES, qs, strict=True)}
            quant[m]["mean"] = float(np.mean(v))
        else:
            quant[m] = None
    lw = np.asarray(c["linf_error_window"], np.float64)
    out = {
        "n_samples": n,
        "n_diverged": int(div.sum()),
        "divergence_rate": float(div.mean()) if n else 0.0,
        "quantiles_over": "samples that did not diverge",
        "quantiles": quant,
    }
    if nominal is not None:
        out["nominal"] = {k: float(v) for k, v in nominal.items()}
    if threshold is not None:
        degraded = div | (lw > threshold)
        out["degraded"] = {"metric": "linf_error_window", "threshold": float(threshold),
                           "rate": float(degraded.mean()) if n else 0.0,
                           "count": int(degraded.sum())}
    out["worst"] = [sample_record(c, result.param_names, i) for i in rank_worst(c, worst)]
    out["first_diverged"] = [sample_record(c, result.param_names, i)
                             for i in rank_diverged(c, worst)]
    return out


def sample_record(columns, param_names, i) -> dict[str, Any]:
    return {
        "sample": int(columns["sample"][i]),
        "params": {p: float(columns[p][i]) for p in param_names},
        "metrics": {m: float(columns[m][i]) for m in METRICS},
        "diverged": bool(columns["diverged"][i]),
        "t_diverged": (float(columns["t_diverged"][i]) if columns["diverged"][i] else None),
    }


def random_rows(n: int, k: int, seed: int, exclude: Iterable[int] = ()) -> np.ndarray:
    """k distinct rows drawn with the sweep's seed (a stream separate from the samples)."""
    pool = np.setdiff1d(np.arange(n, dtype=np.int64), np.asarray(list(exclude), np.int64))
    if k <= 0 or pool.size == 0:
        return np.zeros(0, dtype=np.int64)
    rng = np.random.default_rng([seed, 1])
    return np.sort(rng.choice(pool, size=min(k, pool.size), replace=False))


def simulate_rows(setup, result: SweepResult, rows: Sequence[int], *, save_every: int = 10,
                  ranges_params: Sequence[Param] | None = None) -> list:
    """Full trajectories of chosen rows, re-simulated one at a time with `dscjax.simulate`
    (throw=False: diverged ones come back frozen at their last good state)."""
    from dscjax.simulate import simulate

    info = result.info
    setup = params.cast(setup, np.dtype(info["dtype"]))
    cols = ranges_params or [Param.parse(p) for p in result.param_names]
    n_steps = info["n_steps"]
    every = max(1, min(save_every, n_steps))
    while n_steps % every:
        every -= 1
    out = []
    for i in rows:
        row = np.array([result.columns[p][i] for p in result.param_names])
        s = _set_values(setup, cols, row)
        out.append(simulate(s, info["t_final"], info["dt"], save_every=every,
                            window_start=info["window_start"],
                            state_bound=info["state_bound"], throw=False))
    return out


__all__ = ["DEFAULT_PATHS", "METRICS", "Param", "Range", "SweepResult", "SweepSettings",
           "auto_chunk", "check_resumable", "check_settings", "default_ranges",
           "format_progress", "parse_range", "rank_diverged", "rank_worst", "run_sweep",
           "sample_table", "settings_from_dict", "simulate_rows", "summarize", "trace_rows"]
