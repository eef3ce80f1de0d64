"""Ranges of parameters and the tables of values drawn from them.

    r = parse_range("plant.g[1]=0.8:1.2")             # or "hysteresis.alpha=30%" (+-30 %)
    r = parse_range("hysteresis.p*=0.7:1.3")          # the whole vector p times s in [0.7, 1.3]
    r = from_value(Param.parse("hysteresis.alpha"), "30%", grid=False, field="...")   # TOML
    ranges = check([r], setup, "sweep.ranges")         # resolved, validated against the setup
    table = sample_table(ranges, "lhs", n=1000, seed=0)   # (n, d), row i = sample i
    overrides = params.overrides(setup, [r.param for r in ranges], table)

The one home of the range syntax (command line and TOML), of its checks (a range whose ends
make a model invalid is refused before anything runs) and of sampling. Sweeps use it for the
plants they simulate, tuning for its training and held-out batches; a new feature that varies
parameters (a worst-case search) starts here too.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal, get_args

import numpy as np

from dscjax import params, validation
from dscjax.params import Param
from dscjax.validation import ConfigError

Method = Literal["uniform", "lhs", "grid"]
METHODS: tuple[str, ...] = get_args(Method)
DEFAULT_PATHS = ("hysteresis.alpha", "hysteresis.lam", "hysteresis.psi")
DEFAULT_REL = 0.30


@dataclasses.dataclass(frozen=True)
class Range:
    """Bounds of one varied parameter.

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


def default_ranges(setup=None) -> tuple[Range, ...]:
    """The hysteresis model's `default_sweep` numbers (alpha, lam and psi for the backlash-like
    model (4), the default without a setup) each within +-30 % of the setup's values."""
    paths = (DEFAULT_PATHS if setup is None else
             tuple(f"hysteresis.{name}" for name in type(setup.hysteresis).default_sweep))
    return tuple(Range(Param.parse(p), rel=DEFAULT_REL) for p in paths)


# -- the syntax ---------------------------------------------------------------------------------


def parse_range(text: str, grid: bool = False, field: str | None = None) -> Range:
    """A range from the command line: ``PATH=LOW:HIGH``, ``PATH=30%`` (+-30 % of the nominal
    value) or, for a grid, ``PATH=LOW:HIGH:NUM``."""
    field = field or ("--grid" if grid else "--range")
    form = "PATH=LOW:HIGH:NUM" if grid else "PATH=LOW:HIGH or PATH=P%"
    path, eq, body = text.partition("=")
    if not eq:
        raise ConfigError(f"{field} must be {form} (got {text!r})")
    param = Param.parse(path, field)
    body = body.strip()
    value = body if body.endswith("%") else body.split(":")
    return from_value(param, value, grid, f"{field} {param.name}", form, got=repr(text))


def from_value(param: Param, value, grid: bool, field: str, form: str | None = None,
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


def from_table(table: Mapping[str, Any], field: str, grid: bool = False) -> tuple[Range, ...]:
    """The ranges of a TOML table such as [sweep.ranges] or [tuning.robust.ranges]:
    ``"plant.g[1]" = [0.8, 1.2]``, ``"hysteresis.alpha" = "30%"``, or dotted keys
    (``hysteresis.alpha = [..]``, which TOML reads as nested tables)."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"{field} must be a table ([{field}])")
    return tuple(from_value(Param.parse(name, field), value, grid, f"{field}.{name}")
                 for name, value in flatten(table).items())


def flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"hysteresis": {"alpha": [..]}} -> {"hysteresis.alpha": [..]} (TOML dotted keys)."""
    out = {}
    for k, v in table.items():
        if isinstance(v, Mapping):
            out |= flatten(v, f"{prefix}{k}.")
        else:
            out[f"{prefix}{k}"] = v
    return out


# -- the checks against a setup -----------------------------------------------------------------


def check(ranges: Sequence[Range], setup, field: str, *, grid: bool = False, t_final=None,
          dt=None, window_start=None) -> tuple[Range, ...]:
    """Validate ranges against the setup; return them resolved (absolute bounds).

    ConfigError naming `field` for: a parameter given twice, an unknown path, a vector leaf
    without an index, an index out of range, a grid axis without (or with fewer than 2) points
    or a sampled range with some, non-finite or empty bounds, lower > upper, ranges that allow
    lam <= psi, and values outside a model's allowed range (or, with t_final and dt, outside
    what RK4 can integrate) at either end.
    """
    params.check_columns([r.param for r in ranges], field)
    seen = set()
    for r in ranges:
        f = f"{field}.{r.name}"
        if r.name in seen:
            raise ConfigError(f"{f} is given twice")
        seen.add(r.name)
        value = r.param.check(setup, field)
        if r.param.index is None and np.shape(value) != ():
            raise ConfigError(f"{f}: {r.param.path} has shape {np.shape(value)}; vary one "
                              f"element, e.g. {r.param.path}[0]")
        if grid and r.num is None:
            raise ConfigError(f"{f} needs a number of grid points (LOW:HIGH:NUM)")
        if grid and r.num < 2:
            raise ConfigError(f"{f}: the number of grid points must be >= 2 (got {r.num})")
        if not grid and r.num is not None:
            raise ConfigError(f"{f}: a number of points is only meaningful for a grid")
        q = r.resolve(setup)
        if not (math.isfinite(q.low) and math.isfinite(q.high)):
            raise ConfigError(f"{f} must have finite bounds (got [{q.low:g}, {q.high:g}])")
        if q.low == q.high:
            raise ConfigError(f"{f} is an empty range (low = high = {q.low:g}); to fix a "
                              f"parameter, set it in its config section instead")
        if q.low > q.high:
            raise ConfigError(f"{f}: lower bound > upper bound (got [{q.low:g}, {q.high:g}])")
    resolved = tuple(r.resolve(setup) for r in ranges)
    check_box(resolved, setup, field)
    for r in resolved:  # every model check is a bound on one number: both ends suffice
        for end in (r.low, r.high):
            one = params.set_row(setup, [r.param], [end])
            try:
                validation.validate_setup(one)
                if t_final is not None and dt is not None:
                    validation.validate_run(one, t_final, dt, 1, window_start)
            except ConfigError as err:
                raise ConfigError(f"{field}.{r.name} = [{r.low:g}, {r.high:g}]: {err}") from None
    return resolved


def check_box(ranges: Sequence[Range], setup, field: str) -> None:
    """lam > psi must hold on the whole box: lam's lower end above psi's upper end (the
    ends of a single range are checked by `check`; this is the one check of two)."""
    by = {r.param.path: r for r in ranges if r.param.index is None and not r.param.scale}
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


def assumption_warnings(setup, ranges: Sequence[Range] = (), field: str = "sweep.ranges"
                        ) -> list[str]:
    """`validation.assumption_warnings` of the setup and of every end of every (resolved)
    range: a violation only some samples see is reported with the range that reaches it."""
    out = list(validation.assumption_warnings(setup))
    for r in ranges:
        for end in (r.low, r.high):
            for w in validation.assumption_warnings(params.set_row(setup, [r.param], [end])):
                w = w.split(";")[0] + (f" for part of {field}.{r.name} = [{r.low:.6g}, "
                                       f"{r.high:.6g}]; the design's guarantees (Theorem 1) "
                                       f"do not apply there")
                if not any(o.split(":")[0] == w.split(":")[0] for o in out) and w not in out:
                    out.append(w)
    return out


# -- sampling -----------------------------------------------------------------------------------


def sample_table(ranges: Sequence[Range], method: str, n: int, seed: int) -> np.ndarray:
    """(N, d) float64 parameter values, row i = sample i, column j = ranges[j] (resolved).

    "uniform": i.i.d. uniform in the box. "lhs": Latin hypercube (each column visits each of
    N equal strata exactly once, uniformly within it). "grid": the full factorial of
    linspace(low, high, num) per range, C order (the last range varies fastest; n is unused).
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
        validation.one_of(method, "method", METHODS)
    return low + u * (high - low)


def sample_overrides(setup, ranges: Sequence[Range], n: int, seed: int,
                     method: str = "uniform") -> dict[str, np.ndarray]:
    """{path: (n, ...)} plants drawn from `ranges` with a seed: `sample_table` put into the
    setup's leaves by `params.overrides` (other elements of a vector leaf keep their values)."""
    ranges = [r.resolve(setup) for r in ranges]
    table = sample_table(ranges, method, n, seed)
    return params.overrides(setup, [r.param for r in ranges], table)


__all__ = ["DEFAULT_PATHS", "DEFAULT_REL", "METHODS", "Method", "Param", "Range",
           "assumption_warnings", "check", "check_box", "default_ranges", "flatten",
           "from_table", "from_value", "parse_range", "sample_overrides", "sample_table"]
