"""Time-domain requirements as differentiable penalties (requirement-based tuning).

Each requirement is a `dscjax.metrics.Running` reduction (numbers traced: a new bound never
recompiles) giving, at every RK4 step, a **penalty** weight x (1/T) integral relu(violation)^2
dt (zero when met, C^1, pulling on every violating sample) and an exact **check** (met, margin).

    Envelope     |e(t)| <= b(t) = b_inf + (b0 - b_inf) exp(-t / decay)
    StepResponse overshoot <= overshoot and |y - y_final| <= band |height| for t >= settling_time
    UBound       |u(t)| <= max
    URate        |u'(t)| <= max          (u' is the exact derivative the loop computes)

Violations are relative (divided by the bound), so weights are dimensionless.
"""


import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from dscjax.metrics import trapezoid_weight
from dscjax.reference import SmoothStep
from dscjax.validation import ConfigError


def _relu(x):
    return jnp.maximum(x, 0.0)


class Requirement(eqx.Module):
    """A `Running` reduction whose `finalize` gives 'penalty', 'met' (1.0 or 0.0), 'margin' (<= 0
    when met, in the bound's units) and its own figures. A subclass gives `init`, `sample(acc,
    k, t, e, y, obs, w)` (one step: tracking error e, trapezoid weight w) and `check`
    (`penalty`: weight x viol/T unless it says otherwise); `n_steps` is set by `tuning_metrics`."""

    weight: jax.Array = eqx.field(default=1.0, kw_only=True)
    n_steps: int = eqx.field(static=True, default=0, kw_only=True)
    name: ClassVar[str]

    @abc.abstractmethod
    def init(self, dtype) -> dict: ...

    def update(self, acc, k, t, y, obs, dt) -> dict:
        w = trapezoid_weight(k, dt, self.n_steps)
        return self.sample(acc, k, t, y.x[0] - obs.yr, y, obs, w)

    @abc.abstractmethod
    def sample(self, acc, k, t, e, y, obs, w) -> dict: ...

    def penalty(self, acc, t_final):
        return self.weight * acc["viol"] / t_final

    @abc.abstractmethod
    def check(self, acc, t_final) -> dict: ...

    def finalize(self, acc, t_final) -> dict:
        return {"penalty": self.penalty(acc, t_final), **self.check(acc, t_final)}


def _zeros(dtype, *names):
    return {n: jnp.zeros((), dtype) for n in names}


def _met(margin, **figures):
    return {"met": (margin <= 0).astype(margin.dtype), "margin": margin, **figures}


class Envelope(Requirement):
    """|e(t)| <= b(t) = b_inf + (b0 - b_inf) exp(-t/decay) for all t (a decaying tube)."""

    b0: jax.Array
    b_inf: jax.Array
    decay: jax.Array
    name: ClassVar[str] = "envelope"

    def init(self, dtype):
        return _zeros(dtype, "viol") | {"margin": jnp.asarray(-jnp.inf, dtype)}

    def sample(self, acc, k, t, e, y, obs, w):
        b = self.b_inf + (self.b0 - self.b_inf) * jnp.exp(-t / self.decay)
        a = jnp.abs(e)
        return {"viol": acc["viol"] + w * _relu(a / b - 1.0) ** 2,
                "margin": jnp.maximum(acc["margin"], a - b)}

    def check(self, acc, t_final):
        return _met(acc["margin"])


class StepResponse(Requirement):
    """A step reference to `final` = initial + height: excursion beyond `final` <= overshoot
    |height|, and |y - final| <= band |height| for t >= settling_time. Reports the overshoot
    (fraction) and the settling time (the last time |y - final| > band |height|; 0: never)."""

    overshoot: jax.Array = 0.05
    settling_time: jax.Array = 5.0
    band: jax.Array = 0.02
    # required, but a table may leave them to the step reference (`build_requirements`)
    final: jax.Array = eqx.field(kw_only=True)
    height: jax.Array = eqx.field(kw_only=True)
    name: ClassVar[str] = "step"

    def init(self, dtype):
        return _zeros(dtype, "os_viol", "set_viol", "os_max", "set_max", "t_settle")

    def sample(self, acc, k, t, e, y, obs, w):
        h = jnp.abs(self.height)
        dev = jnp.sign(self.height) * (y.x[0] - self.final) / h
        rel = jnp.abs(y.x[0] - self.final) / h
        late = t >= self.settling_time
        return {
            "os_viol": acc["os_viol"] + w * _relu(dev - self.overshoot) ** 2,
            "set_viol": acc["set_viol"] + jnp.where(late, w * _relu(rel - self.band) ** 2, 0.0),
            "os_max": jnp.maximum(acc["os_max"], dev),
            "set_max": jnp.where(late, jnp.maximum(acc["set_max"], rel), acc["set_max"]),
            "t_settle": jnp.where(rel > self.band, t, acc["t_settle"]),
        }

    def penalty(self, acc, t_final):
        return self.weight * (acc["os_viol"] + acc["set_viol"]) / t_final

    def check(self, acc, t_final):
        margin = jnp.maximum(acc["os_max"] - self.overshoot, acc["set_max"] - self.band)
        return _met(margin, overshoot=acc["os_max"], settling_time=acc["t_settle"])


class UBound(Requirement):
    """|u(t)| <= max at every step."""

    max: jax.Array
    name: ClassVar[str] = "u_bound"
    signal: ClassVar[str] = "u"  # the observation bounded

    def init(self, dtype):
        return _zeros(dtype, "viol", "peak")

    def sample(self, acc, k, t, e, y, obs, w):
        a = jnp.abs(getattr(obs, self.signal))
        return {"viol": acc["viol"] + w * _relu(a / self.max - 1.0) ** 2,
                "peak": jnp.maximum(acc["peak"], a)}

    def check(self, acc, t_final):
        return _met(acc["peak"] - self.max, peak=acc["peak"])


class URate(UBound):
    """|u'(t)| <= max at every step (u' exact: the loop's forward-mode derivative of the law)."""

    name: ClassVar[str] = "u_rate"
    signal: ClassVar[str] = "u_dot"


KINDS = {cls.name: cls for cls in (Envelope, StepResponse, UBound, URate)}


def build_requirements(setup, table) -> tuple:
    out = []
    dtype = jnp.result_type(setup.plant.x0)
    for name, values in table.items():
        values = dict(values)
        if name == "step":
            ref = setup.reference
            if "final" not in values or "height" not in values:
                if not isinstance(ref, SmoothStep):
                    raise ConfigError("tuning.requirements.step needs 'final' and 'height', "
                                      "or a step reference (reference.kind = \"smooth_step\")")
                values.setdefault("height", float(ref.height))
                values.setdefault("final", float(ref.initial) + float(ref.height))
            if values["height"] == 0:
                raise ConfigError("tuning.requirements.step.height must be != 0")
        out.append(KINDS[name](**{k: jnp.asarray(v, dtype) for k, v in values.items()}))
    return tuple(out)
