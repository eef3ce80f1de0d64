"""Which numbers of a Setup are tuned, and in which coordinates.

A tuned parameter is a leaf of the Setup by its config path (``controller.k``), one element
(``controller.gamma_g[0]``) or one factor scaling a vector (``hysteresis.p*``); everything else
is frozen. The search works on coordinates z: "log" (the default for gains: value = exp(z), a
step is a relative change whatever the scale, positivity never lost) or "linear" (signed
numbers such as theta_hat0: value = z). Box bounds on values are a box on z.

    sel = Selection.build(setup, ["controller.k", "controller.tau"],
                          bounds={"controller.tau": (1e-3, 0.1)})
    z = sel.init(setup)                 # {"controller.k": log k, "controller.tau": log tau}
    setup2 = sel.apply(setup, z)        # traced: differentiate through it
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal, get_args

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import params, validation
from dscjax.params import Param
from dscjax.validation import ConfigError

Transform = Literal["log", "linear"]
TRANSFORMS: tuple[str, ...] = get_args(Transform)

# the design parameters of the DSC (Section 2 of the paper), tuned by default
DSC_GAINS = ("controller.k", "controller.tau", "controller.gamma_g", "controller.gamma_phi",
             "controller.gamma_zeta", "controller.gamma_d", "controller.eta", "controller.sigma",
             "controller.eta_zeta", "controller.eta_d", "controller.eps", "controller.sat_width")
# Initial estimates: optional ("and optionally the initial estimates"). theta_hat0 is signed.
DSC_INITIAL_ESTIMATES = ("controller.theta_hat0", "controller.phi_hat0",
                         "controller.zeta_hat0", "controller.d_hat0")
SIGNED = ("controller.theta_hat0", "controller.c", "plant.x0", "hysteresis.w0")


@dataclasses.dataclass(frozen=True)
class Tuned:
    """One tuned number or leaf."""

    path: str  # config path of the leaf, e.g. "controller.k"
    index: int | None = None  # an element of a vector leaf (None: the whole leaf)
    transform: Transform = "log"
    lower: float | None = None  # box bounds on the VALUE, not on z (None: none)
    upper: float | None = None
    scale: bool = False  # one factor (start 1) multiplying the whole vector leaf ("path*")

    @property
    def param(self) -> Param:
        return Param(self.path, self.index, self.scale)

    @property
    def name(self) -> str:
        return self.param.name

    def to_z(self, value):
        return jnp.log(value) if self.transform == "log" else value

    def from_z(self, z):
        return jnp.exp(z) if self.transform == "log" else z

    def z_bounds(self) -> tuple[float, float]:
        lo = -math.inf if self.lower is None else self.lower
        hi = math.inf if self.upper is None else self.upper
        if self.transform == "log":
            return (math.log(lo) if lo > 0 else -math.inf, math.log(hi) if hi < math.inf
                    else math.inf)
        return lo, hi


@dataclasses.dataclass(frozen=True)
class Selection:
    """An ordered set of tuned parameters (hashable: it is static in the jitted step)."""

    items: tuple[Tuned, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.items)

    def size(self, setup) -> int:
        """Number of scalars tuned."""
        return sum(int(np.size(t.param.value(setup))) for t in self.items)

    @classmethod
    def build(cls, setup, tune: Sequence[str], freeze: Sequence[str] = (),
              bounds: Mapping[str, Sequence[float]] | None = None,
              transforms: Mapping[str, str] | None = None, field: str = "tuning") -> Selection:
        """The selection of the paths `tune` less `freeze` (paths or elements), validated
        against the setup (ConfigError naming the field). `bounds`: {name: (lower, upper)} on
        values, either end None, a whole leaf's for each of its elements; `transforms`: {name:
        "log" | "linear"}, default "log" except for the signed numbers of `SIGNED`."""
        bounds = dict(bounds or {})
        transforms = dict(transforms or {})
        order: list[tuple[str, int | str | None]] = []  # index "*": a scale of the vector
        for text in tune:
            p = Param.parse(text, f"{field}.params")
            p.check(setup, f"{field}.params")
            key = (p.path, "*" if p.scale else p.index)
            if key in order:
                raise ConfigError(f"{field}.params lists {text!r} twice")
            order.append(key)
        params.check_columns([_param(p, i) for p, i in order], f"{field}.params")
        frozen = set()
        for text in freeze:
            p = Param.parse(text, f"{field}.freeze")
            p.check(setup, f"{field}.freeze")
            frozen.add((p.path, p.index))
        expanded: list[tuple[str, int | None]] = []
        for path, index in order:
            value = np.asarray(params.get(setup, path), dtype=float)
            if index == "*":
                if any(p == path for p, _ in frozen):
                    raise ConfigError(f"{field}.freeze: {path + '*'!r} is one number; it "
                                      f"cannot be frozen in part")
                expanded.append((path, index))
            elif index is None and (path, None) not in frozen:
                idx = [i for i in range(value.size) if (path, i) in frozen] if value.ndim else []
                if idx:
                    expanded += [(path, i) for i in range(value.size) if (path, i) not in frozen]
                else:
                    expanded.append((path, None))
            elif index is not None and (path, index) not in frozen and (path, None) not in frozen:
                expanded.append((path, index))
        for key in frozen:
            if not any(p == key[0] for p, _ in order):
                name = key[0] if key[1] is None else f"{key[0]}[{key[1]}]"
                raise ConfigError(f"{field}.freeze: {name!r} is not among the tuned parameters "
                                  f"({', '.join(_param(p, i).name for p, i in order)})")
        if not expanded:
            raise ConfigError(f"{field}: nothing left to tune (every parameter is frozen)")
        names_tuned = {p for p, _ in order}
        for text in list(bounds) + list(transforms):
            path = Param.parse(text, f"{field}.bounds").path
            if path not in names_tuned:
                raise ConfigError(f"{field}: {text!r} has a bound or transform but is not tuned "
                                  f"(add it to {field}.params)")
        items = []
        for path, index in expanded:
            p = _param(path, index)
            name = p.name
            default = "linear" if path in SIGNED and not p.scale else "log"
            # a scale reads only its own entries: the leaf's bound is on values, not factors
            leaf = None if p.scale else path
            transform = transforms.get(name, transforms.get(leaf, default))
            validation.one_of(transform, f"{field}.transform.{name}", TRANSFORMS)
            lo, hi = _bound_pair(bounds.get(name, bounds.get(leaf)), f"{field}.bounds.{name}")
            item = Tuned(p.path, p.index, transform, lo, hi, p.scale)
            _check_item(item, setup, field)
            items.append(item)
        return cls(tuple(items))

    def init(self, setup) -> dict[str, jax.Array]:
        """Unconstrained coordinates z of the setup's current values."""
        return {t.name: t.to_z(jnp.asarray(t.param.value(setup))) for t in self.items}

    def values(self, z: Mapping[str, Any]) -> dict[str, Any]:
        """Constrained values by name."""
        return {t.name: t.from_z(z[t.name]) for t in self.items}

    def apply(self, setup, z: Mapping[str, Any]):
        """The setup with the tuned numbers taken from z (traceable)."""
        new: dict[str, Any] = {}
        for t in self.items:
            v = t.from_z(z[t.name])
            if t.scale:
                new[t.path] = v * jnp.asarray(params.get(setup, t.path))
            elif t.index is None:
                new[t.path] = v
            else:
                leaf = new.get(t.path)
                if leaf is None:
                    leaf = jnp.asarray(params.get(setup, t.path))
                new[t.path] = leaf.at[t.index].set(v.astype(leaf.dtype))
        dtype = jnp.result_type(setup.plant.x0)
        return params.set_many(setup, {p: jnp.asarray(v, dtype) for p, v in new.items()})

    def columns(self, setup) -> tuple[Param, ...]:
        """One `Param` per tuned number, in the order of `row` (whole vector leaves by
        element): the columns of a table of candidates for `dscjax.params.overrides`."""
        out: list[Param] = []
        for t in self.items:
            shape = np.shape(params.get(setup, t.path))
            if t.index is None and shape and not t.scale:
                out += [Param(t.path, i) for i in range(shape[0])]
            else:
                out.append(t.param)
        return tuple(out)

    def row(self, z: Mapping[str, Any]) -> jax.Array:
        """The tuned values at z as one vector, in the order of `columns` (traceable)."""
        return jnp.concatenate([jnp.ravel(t.from_z(z[t.name])) for t in self.items])

    def z_box(self, z: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) of the flat `ravel_pytree(z)[0]` element by element (the pytree's
        order, names sorted, not `items`'s: the box is raveled as z is)."""
        box = [{t.name: np.full(np.shape(z[t.name]), t.z_bounds()[k], dtype=float)
                for t in self.items} for k in (0, 1)]
        return tuple(np.asarray(ravel_pytree(b)[0], dtype=float) for b in box)

    def describe(self, setup) -> list[str]:
        rows = []
        for t in self.items:
            v = np.asarray(t.param.value(setup), dtype=float)
            b = "" if t.lower is None and t.upper is None else (
                f" in [{'-inf' if t.lower is None else f'{t.lower:g}'}, "
                f"{'inf' if t.upper is None else f'{t.upper:g}'}]")
            rows.append(f"{t.name} = {np.array2string(v, precision=4)} ({t.transform}{b})")
        return rows


def _param(path: str, index) -> Param:
    """The Param of an entry of `Selection.build`'s list: index "*" is a scale."""
    return Param(path, scale=True) if index == "*" else Param(path, index)


def _bound_pair(b, field) -> tuple[float | None, float | None]:
    if b is None:
        return None, None
    if not isinstance(b, list | tuple) or len(b) != 2:
        raise ConfigError(f"{field} must be [lower, upper] (got {b!r})")
    out = []
    for i, x in enumerate(b):
        if x is None or (isinstance(x, str) and x.lower() in ("none", "")):
            out.append(None)
            continue
        if isinstance(x, bool):
            raise ConfigError(f"{field}[{i}] must be a number, not a boolean (got "
                              f"{'true' if x else 'false'})")
        if not isinstance(x, int | float):
            raise ConfigError(f"{field} must be [lower, upper] with numbers (got {b!r})")
        out.append(float(x))
    lo, hi = out
    if lo is not None and hi is not None and not lo < hi:
        raise ConfigError(f"{field}: lower must be < upper (got [{lo:g}, {hi:g}])")
    return lo, hi


def _check_item(t: Tuned, setup, field):
    v = np.asarray(t.param.value(setup), dtype=float)
    where = f"{field}.bounds.{t.name}"
    if t.transform == "log":
        if not np.all(v > 0):
            raise ConfigError(f"{field}: {t.name} is tuned in log-space and must start > 0 "
                              f"(got {np.array2string(v, precision=6)}); give it a positive "
                              f"start or transform = \"linear\"")
        for side, b in (("lower", t.lower), ("upper", t.upper)):
            if b is not None and not b > 0:
                raise ConfigError(f"{where}: the {side} bound of a log-space (positive) "
                                  f"parameter must be > 0 (got {b:g})")
    for side, b, bad in (("lower", t.lower, lambda b: np.any(v < b)),
                         ("upper", t.upper, lambda b: np.any(v > b))):
        if b is not None and bad(b):
            raise ConfigError(f"{where}: the start value {np.array2string(v, precision=6)} is "
                              f"outside the bounds ({side} bound {b:g})")
