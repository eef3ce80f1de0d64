"""Numbers of a Setup at paths, in coordinates z, and the one run at z that `dscjax.objective`,
`dscjax.sensitivity` and the tuner share (`run_at`).

    sel = Selection.build(setup, ["controller.k", "controller.tau"],
                          bounds={"controller.tau": (1e-3, 0.1)})
    z = sel.init(setup)                           # {"controller.k": log k, "controller.tau": ...}
    traj = run_at(sel, setup, z, spec.program())  # traced: differentiate through it

A number is a `dscjax.params.Param`: a leaf (``controller.k``), one element
(``controller.gamma_g[0]``) or one factor scaling a vector (``hysteresis.p*``). Its transform
maps z to its value: `Log` (exp z: a step is a relative change, positivity never lost),
`Linear` (z), `Relative` (p exp z, p the number where it is moved: z = 0 is the setup, d/dz is
d/d ln p) or `Shift` (p + z, for a number that is 0). Box bounds on values are a box on z.
`run_at`'s metrics are NaN where the run diverged, beside its status: the one divergence
convention (a caller that needs a finite figure, the tuner's penalty, maps it explicitly).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import params, validation
from dscjax.params import Param
from dscjax.simulate import Trajectory, run_reported
from dscjax.validation import ConfigError


@dataclasses.dataclass(frozen=True)
class Log:
    """value = exp(z): positive numbers."""

    name: ClassVar[str] = "log"

    def value(self, z, p):
        return jnp.exp(z)

    def z(self, value):
        return jnp.log(value)

    def z_bound(self, b: float) -> float:
        return math.log(b) if 0 < b < math.inf else -math.inf if b <= 0 else math.inf


@dataclasses.dataclass(frozen=True)
class Linear:
    """value = z: signed numbers."""

    name: ClassVar[str] = "linear"

    def value(self, z, p):
        return z

    def z(self, value):
        return value

    def z_bound(self, b: float) -> float:
        return b


@dataclasses.dataclass(frozen=True)
class Relative:
    """value = p exp(z), p the number as it is (each plant's own in a batch): z = 0 there
    (`dscjax.sensitivity`'s, which starts from z = 0 and bounds nothing)."""

    name: ClassVar[str] = "relative"

    def value(self, z, p):
        return p * jnp.exp(z).astype(p.dtype)


@dataclasses.dataclass(frozen=True)
class Shift(Relative):
    """value = p + z: a number that is 0, which has no relative move."""

    name: ClassVar[str] = "shift"

    def value(self, z, p):
        return p + z


# the transforms a config names
TRANSFORMS = {"log": Log(), "linear": Linear()}


@dataclasses.dataclass(frozen=True)
class Tuned:
    """One number of a `Selection`: its `Param`, transform and bounds on its VALUE."""

    param: Param
    transform: Log | Linear | Relative = Log()
    lower: float | None = None  # None: none
    upper: float | None = None

    @property
    def name(self) -> str:
        return self.param.name

    def z_bounds(self) -> tuple[float, float]:
        return (-math.inf if self.lower is None else self.transform.z_bound(self.lower),
                math.inf if self.upper is None else self.transform.z_bound(self.upper))

    def describe(self) -> dict[str, Any]:
        """The fingerprint's record: path, index, scale, transform (its name), bounds."""
        return dataclasses.asdict(self.param) | {"transform": self.transform.name,
                                                 "lower": self.lower, "upper": self.upper}


def _moved(leaf, t: Tuned, z, batched: bool):
    """`leaf` (one plant's, or a batch's (B, ...)) with t's number at z: a scale multiplies the
    vector by its factor, an element or a whole leaf takes its value."""
    leaf = jnp.asarray(leaf)
    if t.param.scale:
        return (t.transform.value(z, jnp.ones((), leaf.dtype)) * leaf).astype(leaf.dtype)
    at = (slice(None),) * batched + (() if t.param.index is None else (t.param.index,))
    return leaf.at[at].set(jnp.broadcast_to(t.transform.value(z, leaf[at]), leaf[at].shape)
                           .astype(leaf.dtype))


@dataclasses.dataclass(frozen=True)
class Selection:
    """An ordered set of `Tuned` numbers (hashable: static in a jitted program)."""

    items: tuple[Tuned, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.items)

    def size(self, setup) -> int:
        """Number of scalars selected."""
        return sum(int(np.size(t.param.value(setup))) for t in self.items)

    @classmethod
    def of(cls, paths: Sequence[str | Param], transform=Linear()) -> Selection:
        """The numbers at `paths`, each through `transform` (unchecked: `build` checks)."""
        return cls(tuple(Tuned(p if isinstance(p, Param) else Param.parse(p), transform)
                         for p in paths))

    @classmethod
    def build(cls, setup, tune: Sequence[str], freeze: Sequence[str] = (),
              bounds: Mapping[str, Sequence[float]] | None = None,
              transforms: Mapping[str, str] | None = None, field: str = "tuning",
              signed: Sequence[str] = ()) -> Selection:
        """The selection of the paths `tune` less `freeze` (paths or elements), validated
        against the setup (ConfigError naming the field). `bounds`: {name: (lower, upper)} on
        values, either end None, a whole leaf's for each of its elements; `transforms`: {name:
        "log" | "linear"}, default "log" except for the leaves `signed` (a scale is a factor:
        "log")."""
        bounds, transforms = dict(bounds or {}), dict(transforms or {})
        order = [Param.parse(text, f"{field}.params", setup) for text in tune]
        params.check_columns(order, f"{field}.params")
        frozen = {(p.path, p.index) for p in
                  (Param.parse(text, f"{field}.freeze", setup) for text in freeze)}
        expanded: list[Param] = []
        for p in order:
            if p.scale and any(q == p.path for q, _ in frozen):
                raise ConfigError(f"{field}.freeze: {p.name!r} is one number; it cannot be "
                                  f"frozen in part")
            if p.scale or p.index is not None:
                if (p.path, p.index) not in frozen and (p.path, None) not in frozen:
                    expanded.append(p)
            elif (p.path, None) not in frozen:
                leaf = np.asarray(params.get(setup, p.path))
                kept = [Param(p.path, i) for i in range(leaf.size) if (p.path, i) not in frozen]
                expanded += kept if leaf.ndim and len(kept) < leaf.size else [p]
        tuned = {p.path for p in order}
        for path, index in frozen:
            if path not in tuned:
                raise ConfigError(f"{field}.freeze: {Param(path, index).name!r} is not among the "
                                  f"tuned parameters ({', '.join(p.name for p in order)})")
        if not expanded:
            raise ConfigError(f"{field}: nothing left to tune (every parameter is frozen)")
        for text in list(bounds) + list(transforms):
            if Param.parse(text, f"{field}.bounds").path not in tuned:
                raise ConfigError(f"{field}: {text!r} has a bound or transform but is not tuned "
                                  f"(add it to {field}.params)")
        items = []
        for p in expanded:
            # a scale reads only its own entries: the leaf's bound is on values, not factors
            leaf = None if p.scale else p.path
            name = transforms.get(p.name, transforms.get(leaf, "linear" if leaf in signed
                                                          else "log"))
            validation.one_of(name, f"{field}.transform.{p.name}", tuple(TRANSFORMS))
            lo, hi = _bound_pair(bounds.get(p.name, bounds.get(leaf)), f"{field}.bounds.{p.name}")
            item = Tuned(p, TRANSFORMS[name], lo, hi)
            _check_item(item, setup, field)
            items.append(item)
        return cls(tuple(items))

    def init(self, setup) -> dict[str, jax.Array]:
        """Coordinates z of the setup's current values."""
        return {t.name: t.transform.z(jnp.asarray(t.param.value(setup))) for t in self.items}

    def values(self, z: Mapping[str, Any]) -> dict[str, Any]:
        """The values by name (a factor for a scale; `Log` and `Linear` only)."""
        return {t.name: t.transform.value(z[t.name], None) for t in self.items}

    def apply(self, setup, z: Mapping[str, Any]):
        """The setup with the selected numbers at z (traceable): its own leaves `move`d."""
        leaves = {t.param.path: params.get(setup, t.param.path) for t in self.items}
        return params.set_many(setup, self.move(leaves, z, batched=False))

    def move(self, overrides: Mapping[str, Any], z: Mapping[str, Any],
             batched: bool = True) -> dict[str, Any]:
        """A batch of plants ({path: (B, ...)}; with `batched=False`, one plant's leaves
        {path: leaf}) with the selected numbers it overrides moved alike, each plant from its
        own value (traceable)."""
        out = dict(overrides)
        for t in self.items:
            if t.param.path in out:
                out[t.param.path] = _moved(out[t.param.path], t, z[t.name], batched)
        return out

    def overrides(self, setup, zs: Mapping[str, Any]) -> dict[str, Any]:
        """{path: (B, ...)}: the selected leaves at B points (every leaf of zs with a leading
        axis), the overrides of a batch whose rows are the points (traceable)."""
        moved = jax.vmap(lambda z: self.apply(setup, z))(zs)
        return {t.param.path: params.get(moved, t.param.path) for t in self.items}

    def columns(self, setup) -> tuple[Param, ...]:
        """One `Param` per selected scalar (whole vector leaves by element)."""
        out: list[Param] = []
        for t in self.items:
            p = t.param
            shape = np.shape(params.get(setup, p.path))
            out += [Param(p.path, i) for i in range(shape[0])] if (
                p.index is None and shape and not p.scale) else [p]
        return tuple(out)

    def z_box(self, z: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) of the flat `ravel_pytree(z)[0]` element by element (the pytree's
        order, names sorted, not `items`'s: the box is raveled as z is)."""
        box = [{t.name: np.full(np.shape(z[t.name]), t.z_bounds()[k], dtype=float)
                for t in self.items} for k in (0, 1)]
        return tuple(np.asarray(ravel_pytree(b)[0], dtype=float) for b in box)


def run_at(selection: Selection, setup, z: Mapping[str, Any], spec, *, overrides=None,
           extra=None, points: bool = False) -> Trajectory:
    """`simulate.run` of `setup` with the selected numbers at z, a batch `overrides` moved
    alike (`Selection.move`); with `points`, z holds B points (a leading axis on every leaf)
    run as the rows of one batch beside the B rows of `overrides`. The metrics are NaN where
    the run diverged (`nan_if_diverged`: the time before it froze is not the horizon they
    name; their gradient 0), beside its status. Pure: no check, no refinement."""
    if points:
        ov = dict(overrides or {}) | selection.overrides(setup, z)
    else:
        setup, ov = selection.apply(setup, z), overrides and selection.move(overrides, z)
    return run_reported(setup, spec, overrides=ov or None, extra=extra)


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
        validation.not_boolean(x, f"{field}[{i}]")
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
    if isinstance(t.transform, Log):
        if not np.all(v > 0):
            raise ConfigError(f"{field}: {t.name} is tuned in log-space and must start > 0 "
                              f"(got {np.array2string(v, precision=6)}); give it a positive "
                              f"start or transform = \"linear\"")
        for side, b in (("lower", t.lower), ("upper", t.upper)):
            if b is not None and not b > 0:
                raise ConfigError(f"{where}: the {side} bound of a log-space (positive) "
                                  f"parameter must be > 0 (got {b:g})")
    for side, b, outside in (("lower", t.lower, np.less), ("upper", t.upper, np.greater)):
        if b is not None and np.any(outside(v, b)):
            raise ConfigError(f"{where}: the start value {np.array2string(v, precision=6)} is "
                              f"outside the bounds ({side} bound {b:g})")


__all__ = ["Linear", "Log", "Relative", "Selection", "Shift", "TRANSFORMS", "Tuned", "run_at"]
