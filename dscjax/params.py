"""Address the numbers of a Setup by dotted path, the same names the TOML config uses.

    get(setup, "hysteresis.alpha"); set(setup, "controller.k", jnp.array([5.0, 1.0]))

Tuning selects the parameters it differentiates by path, sweeps the ones they vmap over.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax.validation import ConfigError


class UnknownParameter(ConfigError, KeyError):
    """A path that names no parameter: a `ConfigError` (as bad settings are), and a `KeyError`
    for code that catches lookups."""

    __str__ = ConfigError.__str__  # KeyError would quote the message


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
    """Every path to a traced leaf (array or float) below obj, in field order."""
    out = []
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
