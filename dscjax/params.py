"""Address the numbers of a Setup by dotted path, the same names the TOML config uses.

    get(setup, "hysteresis.alpha"); set(setup, "controller.k", jnp.array([5.0, 1.0]))
    Param.parse("plant.g[1]")             # one element of a vector leaf
    Param.parse("hysteresis.p*")          # one factor s scaling a whole vector leaf: p -> s p
    overrides(setup, columns, table)      # a (B, d) table of numbers -> {path: (B, ...)}

Every feature names numbers this way: tuning the parameters it differentiates, sweeps (and
the training and held-out batches of tuning) the ones they vary (`dscjax.ranges`).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax.validation import ConfigError


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
    def parse(cls, text: str, field: str = "parameter") -> Param:
        """`Param` from its name, e.g. "hysteresis.alpha", "plant.g[1]" or "hysteresis.p*"."""
        m = _PARAM_RE.match(str(text).strip())
        if not m:
            raise ConfigError(f"{field}: {text!r} is not a parameter path (e.g. "
                              f"'hysteresis.alpha', 'plant.g[1]' or 'hysteresis.p*')")
        return cls(m.group(1), None if m.group(2) is None else int(m.group(2)),
                   m.group(3) is not None)

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
        if self.scale:
            if len(shape) != 1:
                raise ConfigError(f"{field}: {self.name!r} scales a vector, but {self.path!r} "
                                  f"is a scalar; vary it directly (e.g. {self.path}=30%)")
            return self.value(setup)
        if self.index is None:
            return leaf
        if len(shape) != 1:
            raise ConfigError(f"{field}: {self.path!r} is a scalar; write it without an index")
        if not 0 <= self.index < shape[0]:
            raise ConfigError(f"{field}: index {self.index} of {self.path!r} is out of range (it "
                              f"has {shape[0]} elements, indices 0..{shape[0] - 1})")
        return leaf[self.index]


def check_columns(columns: Sequence[Param], field: str) -> None:
    """ConfigError naming `field` if a vector is both scaled and set (by leaf or element):
    which would win depends on the order of the columns."""
    scaled = {p.path for p in columns if p.scale}
    for p in columns:
        if p.path in scaled and not p.scale:
            raise ConfigError(f"{field}: {p.name!r} and {p.path + '*'!r} both change "
                              f"{p.path!r}; give one of them")


def overrides(setup, columns: Sequence[Param], table) -> dict[str, Any]:
    """{path: (B, ...)} for `simulate_batch`/`run` from a (B, d) table whose column j holds
    the values of columns[j]; the elements of a vector leaf that no column names keep their
    values in `setup`, a scale column s gives s * (the vector in `setup`), and every leaf
    keeps its dtype. NumPy in, NumPy out; traced in, traced out (the sweep builds its
    overrides inside its compiled block)."""
    host = isinstance(table, np.ndarray)
    xp = np if host else jnp
    b = table.shape[0]
    out: dict[str, Any] = {}
    for j, p in enumerate(columns):
        leaf = get(setup, p.path)
        dtype = leaf.dtype if hasattr(leaf, "dtype") else np.asarray(leaf).dtype
        col = table[:, j].astype(dtype)
        if p.scale:
            out[p.path] = col[:, None] * xp.asarray(leaf, dtype)[None, :]
            continue
        if p.index is None:
            out[p.path] = col
            continue
        if p.path not in out:
            leaf = xp.asarray(leaf, dtype)
            out[p.path] = xp.broadcast_to(leaf, (b, *leaf.shape))
        if host:
            out[p.path] = np.array(out[p.path])
            out[p.path][:, p.index] = col
        else:
            out[p.path] = out[p.path].at[:, p.index].set(col)
    return out


def set_row(setup, columns: Sequence[Param], row):
    """`setup` with the numbers of one row of such a table put in (host side)."""
    values = overrides(setup, columns, np.asarray(row, dtype=np.float64)[None, :])
    return set_many(setup, {path: v[0] for path, v in values.items()})


def _child(obj, name: str, path: str):
    if dataclasses.is_dataclass(obj) and name in {f.name for f in dataclasses.fields(obj)}:
        return getattr(obj, name)
    if isinstance(obj, Mapping) and name in obj:
        return obj[name]
    if dataclasses.is_dataclass(obj):
        allowed = [f.name for f in dataclasses.fields(obj)]
    elif isinstance(obj, Mapping):
        allowed = list(obj)
    else:
        allowed = []
    raise UnknownParameter(
        f"no parameter '{path}': '{name}' is not a field of {type(obj).__name__}"
        + (f" (allowed: {', '.join(allowed)})" if allowed else " (a number has no fields)"))


def get(setup, path: str) -> Any:
    """The value at a dotted path, e.g. "controller.k"."""
    obj = setup
    for name in path.split("."):
        obj = _child(obj, name, path)
    return obj


def _as_leaf(value):
    """Lists and tuples of numbers become one array leaf (not a pytree of scalars)."""
    if isinstance(value, list | tuple):
        try:
            return np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            return jnp.asarray(value)  # numbers mixed with tracers
    return value


def set(setup, path: str, value) -> Any:  # noqa: A001 - mirrors `get`
    """A copy of setup with the value at `path` replaced (shape and static fields untouched).

    Example:
        >>> import dscjax
        >>> s = set(dscjax.paper_example(), "controller.k", [12.0, 0.5])
        >>> get(s, "controller.k").tolist()
        [12.0, 0.5]
    """
    return _set(setup, path.split("."), _as_leaf(value), path)


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


def numeric_paths(obj, prefix: str = "") -> list[str]:
    """Every path to a traced leaf (array or float) below obj, in field order (an absent
    optional model, None, has none)."""
    out = []
    if obj is None:
        return out
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            if f.metadata.get("static"):
                continue
            out += numeric_paths(getattr(obj, f.name), f"{prefix}{f.name}.")
    elif isinstance(obj, Mapping):
        for k, v in obj.items():
            out += numeric_paths(v, f"{prefix}{k}.")
    else:
        out.append(prefix[:-1])
    return out


def cast(setup, dtype):
    """Every floating leaf of setup converted to `dtype` (e.g. jnp.float32 for sweeps).

    Concrete leaves become NumPy arrays (host data, exact whatever JAX's x64 setting; JAX
    converts them when a jitted function is called); traced leaves are cast with jnp.
    """

    def conv(x):
        if isinstance(x, jax.core.Tracer):
            return x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
        a = np.asarray(x)
        if np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer):
            return a.astype(dtype)
        return a

    return jax.tree.map(conv, setup)
