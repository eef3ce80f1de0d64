"""The one base of every model class: plants, hysteresis, controllers, references, the Setup
that holds them, and the objects tuning and the integrator carry.

A model is an `equinox.Module` (a frozen dataclass, a JAX pytree). Its numbers are typed fields
(`jax.Array`), traced leaves; its choices are static fields (`option(...)`, typed
`Literal[...]`): changing one recompiles, changing a number never does. Range rules live on
the fields:

    class Backlash(Model):
        alpha: jax.Array = positive()   # validate(): "hysteresis.alpha must be > 0 (got -1)"
        smooth: bool = option(False)    # static

`validate(prefix)` checks every rule and `Literal` option, naming the field by its config
path; a model adds rules tying fields together (lam > psi) by overriding it. Validation is
explicit (`validation.validate_setup`), not in `__init__`: models are also built from tracers,
and only the Setup knows the config path a message must name.
"""

from __future__ import annotations

import dataclasses
import functools
import typing

import equinox as eqx
import jax.numpy as jnp

from dscjax import validation as v

_CHECKS = {"positive": v.positive, "nonnegative": v.nonnegative}


def positive(**kwargs):
    """A number field whose every element must be > 0."""
    return eqx.field(metadata={"check": "positive"}, **kwargs)


def nonnegative(**kwargs):
    """A number field whose every element must be >= 0."""
    return eqx.field(metadata={"check": "nonnegative"}, **kwargs)


def option(default):
    """A static field: a structural choice (a `Literal[...]` of strings, or a bool)."""
    return eqx.field(default=default, static=True)


@functools.cache  # a model class's hints, read once (validate runs on every simulate)
def _options(cls: type) -> dict[str, tuple]:
    """{field: allowed values} of the `Literal`-typed fields of a model class."""
    hints = typing.get_type_hints(cls)
    return {f.name: typing.get_args(hints[f.name]) for f in dataclasses.fields(cls)
            if typing.get_origin(hints[f.name]) is typing.Literal}


class Model(eqx.Module):
    """Base of every model: see the module docstring."""

    def validate(self, prefix: str) -> None:
        """Check every option (a `Literal` field) and every field's range rule; ConfigError
        names the field."""
        for name, allowed in _options(type(self)).items():
            v.one_of(getattr(self, name), f"{prefix}.{name}", allowed)
        for f in dataclasses.fields(self):
            check = f.metadata.get("check")
            if check is not None:
                _CHECKS[check](getattr(self, f.name), f"{prefix}.{f.name}")

    def expected_shapes(self, n: int) -> dict[str, tuple[int, ...]]:
        """Shape of every number field for a plant of order n; default: all scalars."""
        return {f.name: () for f in dataclasses.fields(self) if not f.metadata.get("static")}


# -- the loop's kinks, exact and smooth ------------------------------------------------------------
# The closed loop has two kinks: |u'| in the hysteresis model (4) and sat(.) in the robust term
# of (30). Fixed-step RK4 loses its fourth order at every crossing of a kink and gradients there
# are one-sided, so each comes in an exact form and a smooth form with a bounded bias; which one
# a model uses is a static switch.


def smooth_abs(x, delta):
    """sqrt(x^2 + delta^2) - delta: a C-infinity |x|.

    Exact at x = 0 (so w' = 0 when u' = 0 is kept), and 0 <= |x| - smooth_abs(x) <= delta.
    """
    return jnp.sqrt(x * x + delta * delta) - delta


def sat(s):
    """Unit saturation sat(s) = clip(s, -1, 1)."""
    return jnp.clip(s, -1.0, 1.0)


def smooth_sat(s, delta):
    """(sqrt((s+1)^2 + delta^2) - sqrt((s-1)^2 + delta^2)) / 2: a C-infinity sat(s).

    Equal to (|s+1| - |s-1|)/2 = sat(s) when delta = 0; odd; |smooth_sat - sat| <= delta/2,
    the largest bias being at the corners s = +-1.
    """
    d2 = delta * delta
    return 0.5 * (jnp.sqrt((s + 1.0) ** 2 + d2) - jnp.sqrt((s - 1.0) ** 2 + d2))


__all__ = ["Model", "nonnegative", "option", "positive", "sat", "smooth_abs", "smooth_sat"]
