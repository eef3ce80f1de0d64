"""Address the numbers of a Setup by dotted path, the same names the TOML config uses.

    get(setup, "hysteresis.alpha"); set(setup, "controller.k", jnp.array([5.0, 1.0]))
    Param.parse("plant.g[1]")             # one element of a vector leaf
    Param.parse("hysteresis.p*")          # one factor s scaling a whole vector leaf: p -> s p
    overrides(setup, columns, table)      # a (B, d) table of numbers -> {path: (B, ...)}

Tuning, sweeps and the worst-case search all name the numbers they vary this way.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import validation
from dscjax.validation import ConfigError, numeric_paths


class UnknownParameter(ConfigError, KeyError):
    """A path that names no parameter: a `ConfigError` (as bad settings are), and a `KeyError`
    for code that catches lookups."""

    __str__ = ConfigError.__str__  # KeyError would quote the message


# A dotted path of identifiers, optionally with one element index ("plant.g[1]") or a star
# ("hysteresis.p*": a scale of the whole vector).
_PARAM_RE = re.compile(
    r"^([A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*)(?:\[(\d+)\]|(\*))?$")


@dataclasses.dataclass(frozen=True)
class Param:
    """One number or leaf of a Setup: the leaf at `path`, its element `index`, or (`scale`)
    one factor s that multiplies the whole vector leaf: its value is s, nominal 1, and the
    setup gets s * (the vector in the setup)."""

    path: str
    index: int | None = None
    scale: bool = False

    @property
    def name(self) -> str:
        if self.scale:
            return f"{self.path}*"
        return self.path if self.index is None else f"{self.path}[{self.index}]"

    @classmethod
    def parse(cls, text: str, field: str = "parameter", setup=None) -> Param:
        """`Param` from its name, e.g. "hysteresis.alpha", "plant.g[1]" or "hysteresis.p*";
        with a `setup`, `check`ed against it."""
        m = _PARAM_RE.match(str(text).strip())
        if not m:
            raise ConfigError(f"{field}: {text!r} is not a parameter path (e.g. "
                              f"'hysteresis.alpha', 'plant.g[1]' or 'hysteresis.p*')")
        p = cls(m.group(1), None if m.group(2) is None else int(m.group(2)),
                m.group(3) is not None)
        if setup is not None:
            p.check(setup, field)
        return p

    def value(self, setup):
        """The leaf, its element, or the scale (1 in the leaf's dtype: the setup as it is)."""
        leaf = get(setup, self.path)
        if self.scale:
            return np.ones((), jnp.result_type(leaf))  # result_type: also of a tracer
        return leaf if self.index is None else leaf[self.index]

    def nominal(self, setup) -> float:
        """The (scalar) value in `setup`, as a float."""
        return float(np.asarray(self.value(setup), dtype=float))

    def check(self, setup, field: str):
        """The value named, after checking that the path names a number or a vector of
        numbers of `setup` and that the index exists; ConfigError naming `field` if not."""
        try:
            leaf = get(setup, self.path)
        except KeyError:
            raise ConfigError(f"{field}: unknown parameter {self.path!r} (the numbers of the "
                              f"setup are: {', '.join(numeric_paths(setup))})") from None
        leaves = jax.tree.leaves(leaf)
        if len(leaves) != 1 or not np.issubdtype(np.asarray(leaves[0]).dtype, np.floating):
            raise ConfigError(f"{field}: {self.path!r} is not a number or vector of numbers")
        shape = np.shape(leaf)
        if self.scale and len(shape) != 1:
            raise ConfigError(f"{field}: {self.name!r} scales a vector, but {self.path!r} "
                              f"is a scalar; vary it directly (e.g. {self.path}=30%)")
        if self.index is not None and len(shape) != 1:
            raise ConfigError(f"{field}: {self.path!r} is a scalar; write it without an index")
        if self.index is not None and not 0 <= self.index < shape[0]:
            raise ConfigError(f"{field}: index {self.index} of {self.path!r} is out of range (it "
                              f"has {shape[0]} elements, indices 0..{shape[0] - 1})")
        return self.value(setup)


def check_columns(columns: Sequence[Param], field: str) -> None:
    """ConfigError naming `field` if a number is given twice, or a vector is both scaled and
    set (by leaf or element): which would win depends on the order of the columns."""
    scaled = {p.path for p in columns if p.scale}
    for i, p in enumerate(columns):
        if p in columns[:i]:
            raise ConfigError(f"{field}: {p.name!r} is given twice")
        if p.path in scaled and not p.scale:
            raise ConfigError(f"{field}: {p.name!r} and {p.path + '*'!r} both change "
                              f"{p.path!r}; give one of them")


def overrides(setup, columns: Sequence[Param], table) -> dict[str, Any]:
    """{path: (B, ...)} for `simulate_batch`/`run` from a (B, d) table, column j the values of
    columns[j]; unnamed elements of a vector leaf keep `setup`'s values, a scale column s gives
    s * the vector, dtypes are kept. NumPy in, NumPy out; traced in, traced out."""
    xp = np if isinstance(table, np.ndarray) else jnp
    out: dict[str, Any] = {}
    for j, p in enumerate(columns):
        leaf = get(setup, p.path)
        dtype = leaf.dtype if hasattr(leaf, "dtype") else np.asarray(leaf).dtype
        col = table[:, j].astype(dtype)
        if p.scale:  # s times the whole vector
            out[p.path] = col[:, None] * xp.asarray(leaf, dtype)[None, :]
        elif p.index is None:  # the whole leaf
            out[p.path] = col
        else:  # one element: the others keep the setup's values (or an earlier column's)
            rows = out.get(p.path, xp.asarray(leaf, dtype)[None, :])
            out[p.path] = xp.where(xp.arange(rows.shape[-1]) == p.index, col[:, None], rows)
    return out


def set_row(setup, columns: Sequence[Param], row):
    """`setup` with the numbers of one row of such a table put in (host side)."""
    values = overrides(setup, columns, np.asarray(row, dtype=np.float64)[None, :])
    return set_many(setup, {path: v[0] for path, v in values.items()})


def _child(obj, name: str, path: str):
    children = ({f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
                if dataclasses.is_dataclass(obj) else obj if isinstance(obj, Mapping) else {})
    if name in children:
        return children[name]
    raise UnknownParameter(
        f"no parameter '{path}': '{name}' is not a field of {type(obj).__name__}"
        + (f" (allowed: {', '.join(children)})" if children else " (a number has no fields)"))


def get(setup, path: str) -> Any:
    """The value at a dotted path, e.g. "controller.k"."""
    obj = setup
    for name in path.split("."):
        obj = _child(obj, name, path)
    return obj


def set(setup, path: str, value) -> Any:  # noqa: A001 - mirrors `get`
    """A copy of setup with the value at `path` replaced (shape and static fields untouched).

    Example:
        >>> import dscjax
        >>> s = set(dscjax.paper_example(), "controller.k", [12.0, 0.5])
        >>> get(s, "controller.k").tolist()
        [12.0, 0.5]
    """
    if isinstance(value, list | tuple):  # numbers: one array leaf, not a pytree of scalars
        try:
            value = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            value = jnp.asarray(value)  # numbers mixed with tracers
    return _set(setup, path.split("."), value, path)


def _set(obj, names, value, path):
    old = _child(obj, names[0], path)
    new = value if len(names) == 1 else _set(old, names[1:], value, path)
    if dataclasses.is_dataclass(obj):
        return dataclasses.replace(obj, **{names[0]: new})
    return {**obj, names[0]: new}


def set_many(setup, values: Mapping[str, Any]):
    for path, value in values.items():
        setup = set(setup, path, value)
    return setup


def cast(setup, dtype):
    """Every floating leaf of setup in `dtype`: concrete leaves as NumPy arrays (exact whatever
    JAX's x64 setting), traced ones cast with jnp."""

    def conv(x):
        if isinstance(x, jax.core.Tracer):
            return x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
        a = np.asarray(x)
        return a.astype(dtype) if a.dtype.kind in "fiu" else a  # floats and integers

    return jax.tree.map(conv, setup)


# -- ranges of parameters and the tables drawn from them ----------------------------------------


DEFAULT_PATHS = ("hysteresis.alpha", "hysteresis.lam", "hysteresis.psi")
DEFAULT_REL = 0.30


@dataclasses.dataclass(frozen=True)
class Range:
    """Bounds of one varied parameter: absolute (`low`, `high`) or relative (`rel`: nominal
    * (1 -+ rel), `resolve`d against the setup); `num` grid points (grid sweeps only)."""

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


def parse_range(text: str, grid: bool = False) -> Range:
    """A range from the command line: ``PATH=LOW:HIGH``, ``PATH=30%`` (+-30 % of the nominal
    value) or, for a grid, ``PATH=LOW:HIGH:NUM``."""
    field = "--grid" if grid else "--range"
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
    if isinstance(value, str) and not grid:  # (a grid's text is refused below)
        text, rel = value.strip().lstrip("±+"), math.nan
        with contextlib.suppress(ValueError):
            rel = float(text[:-1]) / 100.0 if text.endswith("%") else math.nan
        if not math.isfinite(rel):
            raise ConfigError(f"{field} must be {form} (got {got})")
        if rel <= 0:
            raise ConfigError(f"{field} is an empty range ({got}); give a percentage > 0")
        return Range(param, rel=rel)
    if not isinstance(value, list | tuple) or len(value) != (3 if grid else 2):
        raise ConfigError(f"{field} must be {form} (got {got})")
    for i, v in enumerate(value[:2]):
        validation.not_boolean(v, f"{field}[{i}]")
    try:
        low, high = (float(v) for v in value[:2])
    except (TypeError, ValueError):
        raise ConfigError(f"{field} must be {form} with numbers (got {got})") from None
    num = None
    if grid:
        num = value[2]
        with contextlib.suppress(ValueError):  # split CLI text: "LOW:HIGH:NUM"
            num = int(num) if isinstance(num, str) else num
        if isinstance(num, bool) or not isinstance(num, int):
            raise ConfigError(f"{field}: the number of grid points must be an integer "
                              f"(got {value[2]!r})")
    return Range(param, low=low, high=high, num=num)


def from_table(table: Mapping[str, Any], field: str, grid: bool = False) -> tuple[Range, ...]:
    """The ranges of a TOML table such as [sweep.ranges] or [tuning.robust.ranges]:
    ``"plant.g[1]" = [0.8, 1.2]``, ``"hysteresis.alpha" = "30%"``, or dotted keys
    (``hysteresis.alpha = [..]``, which TOML reads as nested tables)."""
    return tuple(from_value(Param.parse(name, field), value, grid, f"{field}.{name}")
                 for name, value in flatten(validation.table(table, field)).items())


def flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"hysteresis": {"alpha": [..]}} -> {"hysteresis.alpha": [..]} (TOML dotted keys)."""
    out = {}
    for k, v in table.items():
        out |= flatten(v, f"{prefix}{k}.") if isinstance(v, Mapping) else {f"{prefix}{k}": v}
    return out


# -- the checks against a setup -----------------------------------------------------------------


def check(ranges: Sequence[Range], setup, field: str, *, grid: bool = False,
          spec=None) -> tuple[Range, ...]:
    """The ranges resolved (absolute bounds), or a ConfigError naming `field`: a parameter
    given twice, an unknown path or index, a grid axis with < 2 points (a sampled one with
    any), bounds not finite or reversed, lam <= psi allowed, or either end outside a model's
    range (or, with a `RunSpec`, outside what RK4 can integrate at its step)."""
    check_columns([r.param for r in ranges], field)
    for r in ranges:
        f = f"{field}.{r.name}"
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
            one = set_row(setup, [r.param], [end])
            try:
                validation.validate_setup(one)
                if spec is not None:
                    validation.check_filters(one, float(spec.dt))
            except ConfigError as err:
                raise ConfigError(f"{field}.{r.name} = [{r.low:g}, {r.high:g}]: {err}") from None
    return resolved


def check_box(ranges: Sequence[Range], setup, field: str) -> None:
    """lam > psi must hold on the whole box: lam's lower end above psi's upper end (the
    ends of a single range are checked by `check`; this is the one check of two)."""
    by = {r.name: r for r in ranges if r.param.index is None and not r.param.scale}
    paths = ("hysteresis.lam", "hysteresis.psi")
    if not any(p in by for p in paths):
        return
    # a number not varied is the range [nominal, nominal]; lam and psi are both the
    # backlash model's, whose other one `check` has found
    lam, psi = (by.get(p) or Range(Param(p), rel=0.0).resolve(setup) for p in paths)
    if not lam.low > psi.high:
        lam_txt, psi_txt = (f"[{r.low:g}, {r.high:g}]" if r.name in by else f"{r.low:g} (fixed)"
                            for r in (lam, psi))
        raise ConfigError(
            f"{field}: hysteresis.lam must stay > hysteresis.psi over the ranges (got lam in "
            f"{lam_txt}, psi in {psi_txt}); make lam's lower bound exceed psi's upper bound")


def assumption_warnings(setup, ranges: Sequence[Range], field: str) -> list[str]:
    """`validation.assumption_warnings` of the setup and of every end of every (resolved)
    range: a violation only some samples see is reported with the range that reaches it."""
    out = list(validation.assumption_warnings(setup))
    for r in ranges:
        for end in (r.low, r.high):
            for w in validation.assumption_warnings(set_row(setup, [r.param], [end])):
                w = w.split(";")[0] + (f" for part of {field}.{r.name} = [{r.low:.6g}, "
                                       f"{r.high:.6g}]; the design's guarantees (Theorem 1) "
                                       f"do not apply there")
                if not any(o.split(":")[0] == w.split(":")[0] for o in out):
                    out.append(w)
    return out


# -- sampling -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Uniform:
    """Samples i.i.d. uniform in the box."""

    name: ClassVar[str] = "uniform"
    grid: ClassVar[bool] = False  # the ranges are axes of a full factorial (each with a num)

    def draw(self, ranges: Sequence[Range], n: int, seed: int) -> np.ndarray:
        """(n, d) float64 values, column j = ranges[j] (resolved), a function of (ranges, n,
        seed) only."""
        return self.scaled(ranges, np.random.default_rng(seed).random((n, len(ranges))))

    @staticmethod
    def scaled(ranges: Sequence[Range], u: np.ndarray) -> np.ndarray:
        low = np.array([r.low for r in ranges], dtype=np.float64)
        return low + u * (np.array([r.high for r in ranges], dtype=np.float64) - low)


@dataclasses.dataclass(frozen=True)
class LatinHypercube(Uniform):
    """A Latin hypercube: each column visits each of its n strata once."""

    name: ClassVar[str] = "lhs"

    def draw(self, ranges: Sequence[Range], n: int, seed: int) -> np.ndarray:
        rng, u = np.random.default_rng(seed), np.empty((n, len(ranges)))
        for j in range(len(ranges)):
            u[:, j] = (rng.permutation(n) + rng.random(n)) / n
        return self.scaled(ranges, u)


@dataclasses.dataclass(frozen=True)
class Grid:
    """The full factorial of linspace(low, high, num), C order (the first range slowest; n and
    the seed unused)."""

    name: ClassVar[str] = "grid"
    grid: ClassVar[bool] = True

    def draw(self, ranges: Sequence[Range], n: int, seed: int) -> np.ndarray:
        mesh = np.meshgrid(*[np.linspace(r.low, r.high, r.num) for r in ranges], indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)


METHODS = {c.name: c() for c in (Uniform, LatinHypercube, Grid)}  # by the name a config gives


def sample_overrides(setup, ranges: Sequence[Range], n: int, seed: int,
                     method: Uniform | LatinHypercube = Uniform()) -> dict[str, np.ndarray]:
    """{path: (n, ...)} plants drawn from `ranges` with a seed by `method` (`Uniform`,
    `LatinHypercube`), put into the setup's leaves by `params.overrides` (other elements of a
    vector leaf keep their values)."""
    ranges = [r.resolve(setup) for r in ranges]
    return overrides(setup, [r.param for r in ranges], method.draw(ranges, n, seed))


__all__ = [
    "assumption_warnings", "check", "check_box", "DEFAULT_PATHS", "default_ranges", "DEFAULT_REL",
    "flatten", "from_table", "from_value", "Grid", "LatinHypercube", "METHODS", "Param",
    "parse_range", "Range", "sample_overrides", "Uniform"
]
