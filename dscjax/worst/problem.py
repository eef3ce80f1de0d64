"""What a worst-case search maximises: a `Problem` (`make_problem`), a metric of the closed
loop over a box of parameters (`dscjax.params` ranges) and a bounded disturbance waveform
(`DisturbanceSpec`), in normalised coordinates z = (u, c): u in [0, 1]^d places each ranged
parameter in its box, c (m coefficients) is the waveform in units of the bound D.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np

from dscjax import disturbance as dist_mod
from dscjax import params, validation
from dscjax.closed_loop import Setup
from dscjax.runspec import RunSpec
from dscjax.simulate import check, dtype_of
from dscjax.validation import ConfigError

# metrics of `run` a search may maximise (windowed L-inf of e by default)
METRICS = ("linf_error_window", "linf_error", "l2_error_window", "rms_error_window",
           "max_abs_u", "l2_u", "tv_u", "max_abs_w")


DEFAULT_METRIC = "linf_error_window"


# "requirement:NAME" maximises a requirement's "margin" (> 0 when violated)
REQUIREMENT = "requirement:"


def _number(text: str, cast):
    """`text` as a number, else as it is: `DisturbanceSpec.checked` names it in its message."""
    try:
        return cast(text)
    except ValueError:
        return text


@dataclasses.dataclass(frozen=True)
class DisturbanceSpec:
    """The searched waveform: `kind` ("fourier" | "spline"), K harmonics or knots, the bound D
    on max |dbar|, and (Fourier) the period, None for the horizon."""

    kind: str
    k: int
    bound: float
    period: float | None = None

    @classmethod
    def parse(cls, text: str, period: float | None = None,
              field: str = "--disturbance") -> DisturbanceSpec:
        """`fourier:K:D` or `spline:K:D`."""
        parts = [p.strip() for p in str(text).split(":")]
        if len(parts) != 3:
            raise ConfigError(f"{field} must be fourier:K:D or spline:K:D (got {text!r})")
        kind, k, bound = parts
        return cls(kind, _number(k, int), _number(bound, float), period).checked(field)

    # K below which a waveform is not one: a spline needs two knots to have a knot spacing
    MIN_K: ClassVar[dict[str, int]] = {"fourier": 1, "spline": 2}

    def checked(self, field: str = "--disturbance") -> DisturbanceSpec:
        validation.one_of(self.kind, f"{field} kind", tuple(dist_mod.KINDS))
        low = self.MIN_K[self.kind]
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < low:
            raise ConfigError(f"{field}: K must be an integer >= {low} for {self.kind} (got "
                              f"{self.k!r})")
        validation.finite_positive(self.bound, f"{field}: the bound D")
        if self.period is not None:
            validation.finite_positive(self.period, "--period")
            if self.kind != "fourier":
                raise ConfigError("--period applies to a fourier disturbance only")
        return self

    @property
    def size(self) -> int:
        """m, the number of searched coefficients."""
        return 2 * self.k + 1 if self.kind == "fourier" else self.k

    def model(self, coefficients, t_final: float) -> dist_mod.Disturbance:
        coefficients = np.asarray(coefficients, dtype=np.float64)
        if self.kind == "fourier":
            period = self.period if self.period is not None else t_final
            return dist_mod.Fourier(coefficients, np.asarray(period, dtype=np.float64))
        return dist_mod.Spline(coefficients, np.asarray(t_final, dtype=np.float64))

    def spec(self) -> str:
        return f"{self.kind}:{self.k}:{self.bound:g}"


@dataclasses.dataclass(frozen=True)
class Problem:
    """What a search maximises (see `make_problem`)."""

    setup: Setup  # the base setup, with a zero waveform of `disturbance` installed
    ranges: tuple[params.Range, ...]  # resolved (absolute bounds)
    disturbance: DisturbanceSpec | None
    metric: str
    spec: RunSpec  # how every candidate is simulated (metrics only: save_every = n_steps)
    requirement: Any = None  # the reduction of a "requirement:NAME" metric, else None
    # the run as the user gave it (`spec` before the search's metrics-only settings): what
    # worst_config.toml writes, so that it replays as a trajectory one can look at
    options: RunSpec | None = None

    @property
    def metric_key(self) -> str:
        """The entry of the run's metrics that is maximised."""
        return "margin" if self.requirement is not None else self.metric

    @property
    def d(self) -> int:
        return len(self.ranges)

    @property
    def m(self) -> int:
        return 0 if self.disturbance is None else self.disturbance.size

    def box(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The traced numbers of the box: its lows, its highs and the waveform's bound."""
        return (np.array([r.low for r in self.ranges], dtype=np.float64),
                np.array([r.high for r in self.ranges], dtype=np.float64),
                self.disturbance.bound if self.m else 0.0)

    def static(self) -> Static:
        coef = (f"plant.disturbance.{self.setup.plant.disturbance.coefficients_name}"
                if self.m else None)
        return Static(tuple(r.param for r in self.ranges), coef, self.metric_key)

    def overrides(self, z):
        """{path: (B, ...)} of a (B, dim) batch of normalised points (traced or NumPy)."""
        return box_overrides(self.setup, self.static(), z, *self.box())

    def setup_at(self, z) -> Setup:
        """The concrete setup of one normalised point."""
        return box_setup(self.setup, self.static(), np.asarray(z, dtype=np.float64), *self.box())

    def values_at(self, z) -> tuple[dict[str, float], dict | None]:
        """The searched parameters by config path and the disturbance record of a point."""
        z = np.asarray(z, dtype=np.float64)
        values = {r.name: float(r.low + z[j] * (r.high - r.low)) for j, r in enumerate(self.ranges)}
        if self.disturbance is None:
            return values, None
        model, spec = self.setup_at(z).plant.disturbance, self.disturbance
        return values, {"kind": spec.kind, "K": spec.k, "bound": spec.bound,
                        "period": float(model.period) if spec.kind == "fourier" else None,
                        "horizon": float(model.horizon) if spec.kind == "spline" else None,
                        "coefficients": np.asarray(model.coefficient_values()).tolist()}

    def fingerprint(self) -> dict[str, Any]:
        from dscjax import config

        req = self.requirement  # a requirement by its kind and numbers
        return {"setup": config.to_dict(self.setup), "ranges": [r.spec() for r in self.ranges],
                "disturbance": None if self.disturbance is None else
                dataclasses.asdict(self.disturbance),
                "metric": self.metric, "run": self.spec.describe(),
                "requirement": None if req is None else {"kind": type(req).__name__, **{
                    f.name: np.asarray(getattr(req, f.name)).tolist()
                    for f in dataclasses.fields(req)}}}


def check_disturbance(value, field: str) -> str:
    """A searched waveform's text, KIND:K:D, in its canonical form (else ConfigError naming
    `field`)."""
    return DisturbanceSpec.parse(validation.string(value, field), field=field).spec()


def check_metric(value, field: str = "--metric") -> str:
    """A metric's name, one of METRICS or requirement:NAME (else ConfigError naming `field`)."""
    text = validation.string(value, field)
    if text not in METRICS and not text.startswith(REQUIREMENT):
        raise ConfigError(f"{field} must be one of {', '.join(METRICS)}, or {REQUIREMENT}NAME "
                          f"(got {text!r})")
    return text


def assumption_warnings(problem: Problem) -> list[str]:
    """The paper's assumptions (`validation.assumption_warnings`) that the base setup, or an
    end of a searched box, violates: a box on plant.g[i] reaching below controller.g_min is
    named with its --range."""
    return [w.replace("--range.", "--range ") for w in
            params.assumption_warnings(problem.setup, problem.ranges, "--range")]


def make_problem(setup: Setup, ranges: Sequence[params.Range] = (),
                 disturbance: DisturbanceSpec | str | None = None, *, metric: str = DEFAULT_METRIC,
                 spec: RunSpec | None = None, period: float | None = None,
                 field: str = "--range", requirement: Any = None, **run) -> Problem:
    """Validate and build a `Problem`; ConfigError (one line, naming the field) if bad.

    Args:
        setup: the closed loop (its values are the nominal point).
        ranges: boxes of parameters, by config path (`dscjax.params`).
        disturbance: "fourier:K:D", "spline:K:D" or a `DisturbanceSpec`; None: no waveform.
        metric: one of `METRICS`, or "requirement:NAME": the margin of `requirement`.
        spec: how every candidate is simulated; or its fields as keywords (`run`).
        period: the Fourier period (default: the horizon).
        requirement: a `metrics.Running` whose results include "margin" (<= 0 when met),
            e.g. `tuning.Envelope`.
    """
    maximises_requirement = check_metric(metric).startswith(REQUIREMENT)
    if maximises_requirement and requirement is None:
        raise ConfigError(f"--metric {metric}: no requirement given (the [tuning."
                          f"requirements.{metric[len(REQUIREMENT):]}] table of --config)")
    if requirement is not None and not maximises_requirement:
        raise ConfigError(f"a requirement is maximised with --metric {REQUIREMENT}NAME "
                          f"(got --metric {metric})")
    if isinstance(disturbance, str):
        disturbance = DisturbanceSpec.parse(disturbance, period)
    elif disturbance is not None:
        disturbance = disturbance.checked()
    if not ranges and disturbance is None:
        raise ConfigError("nothing to search: give at least one --range or a --disturbance")
    if disturbance is not None and getattr(setup.plant, "disturbance", "absent") == "absent":
        raise ConfigError(f"--disturbance: plant.family {type(setup.plant).kind!r} takes no "
                          f"waveform (use paper or strict_feedback)")
    spec = RunSpec.given(spec, run, "make_problem")
    options, spec = spec, spec.replace(save_every=spec.n_steps)
    setup = params.cast(setup, dtype_of(setup))
    if disturbance is not None:
        zero = disturbance.model(np.zeros(disturbance.size), spec.t_final)
        setup = setup.replace(plant=dataclasses.replace(
            setup.plant, disturbance=params.cast(zero, dtype_of(setup))))
    check(setup, spec)
    if any(r.param.path.startswith("plant.disturbance") for r in ranges):
        raise ConfigError(f"{field}: the disturbance waveform is searched by --disturbance")
    resolved = params.check(list(ranges), setup, field, spec=spec)
    return Problem(setup, resolved, disturbance, metric, spec,
                   with_steps(requirement, spec.n_steps), options)


def with_steps(requirement, n_steps: int):
    """`requirement` measured over a run of `n_steps` (one that counts its steps), else as
    it is (None included)."""
    if hasattr(requirement, "n_steps"):
        return dataclasses.replace(requirement, n_steps=n_steps)
    return requirement


@dataclasses.dataclass(frozen=True)
class Static:
    """The static (hashable) part of a problem's compiled programs; the setup, the box and
    the bound are traced, so problems that differ only in numbers share one compilation."""

    columns: tuple[params.Param, ...]
    coef_path: str | None
    metric: str


def box_overrides(setup, st: Static, z, lo, hi, bound):
    """{path: (B, ...)} of a (B, d + m) batch of normalised points in the box [lo, hi] and the
    waveform's bound (traced or NumPy)."""
    d = len(st.columns)
    out = params.overrides(setup, list(st.columns), lo + z[:, :d] * (hi - lo)) if d else {}
    if st.coef_path is not None:
        xp = np if isinstance(z, np.ndarray) else jnp
        out[st.coef_path] = xp.asarray(bound * z[:, d:], dtype=dtype_of(setup))
    return out


def box_setup(setup, st: Static, z1, lo, hi, bound):
    """`setup` at one normalised point z1 (d + m,) of the box (traced or NumPy)."""
    one = {p: v[0] for p, v in box_overrides(setup, st, z1[None, :], lo, hi, bound).items()}
    return params.set_many(setup, one)
