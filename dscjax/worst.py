"""Worst-case search: maximise a metric of the closed loop over a box of plant / hysteresis /
initial-state parameters and a bounded disturbance waveform.

    problem = make_problem(setup, ranges=[parse_range("hysteresis.alpha=30%")],
                           disturbance="fourier:16:0.5", t_final=20.0, dt=1e-3)
    result = worst_case(problem, time_limit=60.0, starts=4, out_dir="results/worst")
    result = dscjax.worst_case(setup, ["hysteresis.alpha=30%"], "spline:8:0.5")   # the same

The search runs in normalised coordinates z = (u, c): u in [0, 1]^d places each ranged
parameter in its box (value = low + u (high - low)); c (m coefficients) is the waveform in
units of the bound D (coefficients = D c). The feasible set is u in the box and max |dbar| <= D
(`dscjax.disturbance`: knots clipped, or a Fourier series scaled on the half-step grid).

Three methods, each given the same wall time (compilation excluded and reported apart):
  - "gradient": a screened batch of random points gives the M best starts; then projected
    gradient ascent, all M starts advanced together in ONE compiled program (each start's
    time-parallel gradient, vmapped; by default of the loop at 4 dt, values always at dt):
    Adam steps on the box, a normalised step on the waveform, a step that grows by 1.2 after
    an improvement and backs off by half after a loss, then the projection;
  - "random": uniform points of the box with coefficients drawn uniformly in [-1, 1]^m and
    rescaled so that max |dbar| = D exactly;
  - "cma": CMA-ES (`cma` package) on the same coordinates, one batch per generation.

A candidate whose batch simulation diverged is not a worst case yet: it is re-simulated by
`simulate` with refinement (ETDRK4 at dt, dt/2, ...). If that run stays finite, its metric
is the candidate's value; if not, the loop itself diverges there and that is reported, with
the time, as the worst case (value +inf, never NaN). The value reported is always that of
`simulate` on the worst setup, which `worst_config.toml` reproduces exactly.

Every method saves its state after each iteration (`state_<method>.npz`, atomic), so a run
killed at any point continues with `resume=True` losing only the iteration in progress.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal, get_args

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import disturbance as dist_mod
from dscjax import files, params, validation
from dscjax import ranges as ranges_mod
from dscjax.closed_loop import Setup
from dscjax.metrics import default_window
from dscjax.progress import critical
from dscjax.validation import ConfigError

Method = Literal["gradient", "random", "cma"]
METHODS: tuple[str, ...] = get_args(Method)
# metrics of `run` a search may maximise (windowed L-inf of e by default)
METRICS = ("linf_error_window", "linf_error", "l2_error_window", "rms_error_window",
           "max_abs_u", "l2_u", "tv_u", "max_abs_w")
DEFAULT_METRIC = "linf_error_window"
# "requirement:NAME" maximises the violation margin of a requirement (a `metrics.Running`
# reduction whose results include "margin", e.g. `tuning.Envelope`): > 0 when it is violated
REQUIREMENT = "requirement:"
DEFAULT_STARTS = 4  # measured: see docs/worst-case.md
DEFAULT_BATCH = 32  # random and CMA-ES candidates per batched simulation
DEFAULT_LR = 0.1
DEFAULT_COARSENING = 4  # gradients at 4 dt: measured, see docs/worst-case.md
STATE_VERSION = 1
TOP = 8  # best distinct points a trace keeps


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
        parts = str(text).split(":")
        if len(parts) != 3:
            raise ConfigError(f"{field} must be fourier:K:D or spline:K:D (got {text!r})")
        kind, k_text, d_text = (p.strip() for p in parts)
        validation.one_of(kind, f"{field} kind", tuple(dist_mod.KINDS))
        low = cls.MIN_K[kind]
        try:
            k = int(k_text)
        except ValueError:
            raise ConfigError(f"{field}: K must be an integer >= {low} (got {k_text!r})") \
                from None
        try:
            bound = float(d_text)
        except ValueError:
            raise ConfigError(f"{field}: D must be a finite number > 0 (got {d_text!r})") \
                from None
        return cls(kind, k, bound, period).checked(field)

    # K below which a waveform is not one: a spline needs two knots to have a knot spacing
    MIN_K: ClassVar[dict[str, int]] = {"fourier": 1, "spline": 2}

    def checked(self, field: str = "--disturbance") -> DisturbanceSpec:
        validation.one_of(self.kind, f"{field} kind", tuple(dist_mod.KINDS))
        low = self.MIN_K[self.kind]
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < low:
            raise ConfigError(f"{field}: K must be an integer >= {low} for {self.kind} (got "
                              f"{self.k!r})")
        if not (math.isfinite(self.bound) and self.bound > 0):
            raise ConfigError(f"{field}: the bound D must be a finite number > 0 (max|dbar| "
                              f"<= D; D = 0 leaves nothing to search) (got {self.bound!r})")
        if self.period is not None and not (math.isfinite(self.period) and self.period > 0):
            raise ConfigError(f"--period must be > 0 (got {self.period!r})")
        if self.period is not None and self.kind != "fourier":
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
    ranges: tuple[ranges_mod.Range, ...]  # resolved (absolute bounds)
    disturbance: DisturbanceSpec | None
    metric: str
    t_final: float
    dt: float
    window_start: float
    state_bound: float = 1e6
    solver: str = "rk4"
    refine: int = 6
    requirement: Any = None  # the reduction of a "requirement:NAME" metric, else None

    @property
    def metric_key(self) -> str:
        """The entry of the run's metrics that is maximised."""
        return "margin" if self.requirement is not None else self.metric

    @property
    def n_steps(self) -> int:
        return int(round(self.t_final / self.dt))

    @property
    def d(self) -> int:
        return len(self.ranges)

    @property
    def m(self) -> int:
        return 0 if self.disturbance is None else self.disturbance.size

    @property
    def dim(self) -> int:
        return self.d + self.m

    @property
    def columns(self) -> list[params.Param]:
        return [r.param for r in self.ranges]

    @property
    def coef_path(self) -> str:
        return f"plant.disturbance.{self.setup.plant.disturbance.coefficients_name}"

    def lows_highs(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([r.low for r in self.ranges], dtype=np.float64),
                np.array([r.high for r in self.ranges], dtype=np.float64))

    def static(self) -> _Static:
        return _Static(tuple(self.columns), self.coef_path if self.m else None,
                       self.metric_key, self.n_steps, self.solver)

    def overrides(self, z):
        """{path: (B, ...)} of a (B, dim) batch of normalised points (traced or NumPy)."""
        lo, hi = self.lows_highs()
        return _overrides(self.setup, self.static(), z, lo, hi,
                          self.disturbance.bound if self.m else 0.0)

    def setup_at(self, z) -> Setup:
        """The concrete setup of one normalised point."""
        ov = self.overrides(np.asarray(z, dtype=np.float64)[None, :])
        return params.set_many(self.setup, {p: np.asarray(v)[0] for p, v in ov.items()})

    def values_at(self, z) -> tuple[dict[str, float], dict | None]:
        """The searched parameters by config path and the disturbance record of a point."""
        lo, hi = self.lows_highs()
        z = np.asarray(z, dtype=np.float64)
        values = {r.name: float(lo[j] + z[j] * (hi[j] - lo[j])) for j, r in enumerate(self.ranges)}
        if self.disturbance is None:
            return values, None
        model = self.setup_at(z).plant.disturbance
        spec = self.disturbance
        record = {"kind": spec.kind, "K": spec.k, "bound": spec.bound,
                  "period": float(model.period) if spec.kind == "fourier" else None,
                  "horizon": float(model.horizon) if spec.kind == "spline" else None,
                  "coefficients": np.asarray(model.coefficient_values()).tolist()}
        return values, record

    def fingerprint(self) -> dict[str, Any]:
        from dscjax import config

        return {"setup": config.to_dict(self.setup), "ranges": [r.spec() for r in self.ranges],
                "disturbance": None if self.disturbance is None else
                dataclasses.asdict(self.disturbance),
                "metric": self.metric, "t_final": self.t_final, "dt": self.dt,
                "window_start": self.window_start, "state_bound": self.state_bound,
                "solver": self.solver, "refine": self.refine,
                "requirement": _describe(self.requirement)}


def _describe(reduction) -> dict | None:
    """The kind and numbers of a requirement (for fingerprints)."""
    if reduction is None:
        return None
    return {"kind": type(reduction).__name__,
            **{f.name: np.asarray(getattr(reduction, f.name)).tolist()
               for f in dataclasses.fields(reduction)}}


def _dtype(setup):
    return jnp.result_type(setup.plant.x0)


def make_problem(setup: Setup, ranges: Sequence[ranges_mod.Range] = (),
                 disturbance: DisturbanceSpec | str | None = None, *, metric: str = DEFAULT_METRIC,
                 t_final: float = 20.0, dt: float = 1e-3, window_start: float | None = None,
                 state_bound: float = 1e6, solver: str = "rk4", refine: int = 6,
                 period: float | None = None, field: str = "--range",
                 requirement: Any = None) -> Problem:
    """Validate and build a `Problem`; ConfigError (one line, naming the field) if bad.

    Args:
        setup: the closed loop (its values are the nominal point).
        ranges: boxes of parameters, by config path (`dscjax.ranges`).
        disturbance: "fourier:K:D", "spline:K:D" or a `DisturbanceSpec`; None: no waveform.
        metric: one of `METRICS` (default the windowed L-inf of the tracking error), or
            "requirement:NAME": the violation margin of `requirement` (> 0: violated).
        period: the Fourier period (default: the horizon).
        requirement: with metric "requirement:NAME", a `dscjax.metrics.Running` reduction
            whose results include "margin" (in the bound's units, <= 0 when met), such as
            `tuning.Envelope`, `tuning.UBound`, `tuning.URate`, `tuning.StepResponse`.
    """
    if str(metric).startswith(REQUIREMENT):
        if requirement is None:
            raise ConfigError(f"--metric {metric}: no requirement given (the [tuning."
                              f"requirements.{metric[len(REQUIREMENT):]}] table of --config)")
    else:
        validation.one_of(metric, "--metric", METRICS + (REQUIREMENT + "NAME",))
        if requirement is not None:
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
    window_start = default_window(t_final, window_start)
    setup = params.cast(setup, _dtype(setup))
    if disturbance is not None:
        zero = disturbance.model(np.zeros(disturbance.size), t_final)
        setup = setup.replace(plant=dataclasses.replace(
            setup.plant, disturbance=params.cast(zero, _dtype(setup))))
    validation.validate_setup(setup)
    validation.validate_run(setup, t_final, dt, 1, window_start)
    if any(r.param.path.startswith("plant.disturbance") for r in ranges):
        raise ConfigError(f"{field}: the disturbance waveform is searched by --disturbance, "
                          f"not by a range")
    resolved = ranges_mod.check(list(ranges), setup, field, t_final=t_final, dt=dt,
                                window_start=window_start)
    if requirement is not None and hasattr(requirement, "n_steps"):
        requirement = dataclasses.replace(requirement, n_steps=int(round(t_final / dt)))
    return Problem(setup, resolved, disturbance, metric, float(t_final), float(dt),
                   float(window_start), float(state_bound), solver, int(refine), requirement)


# -- the compiled programs ----------------------------------------------------------------------


GRADIENTS = ("time_parallel", "batch")


@dataclasses.dataclass(frozen=True)
class _Static:
    """The static (hashable) part of a problem's compiled programs; the setup, the box and
    the bound are traced, so problems that differ only in numbers share one compilation."""

    columns: tuple[params.Param, ...]
    coef_path: str | None
    metric: str
    n_steps: int
    solver: str


def _overrides(setup, st: _Static, z, lo, hi, bound):
    d = len(st.columns)
    out = {}
    if d:
        out = params.overrides(setup, list(st.columns), lo + z[:, :d] * (hi - lo))
    if st.coef_path is not None:
        xp = np if isinstance(z, np.ndarray) else jnp
        out[st.coef_path] = xp.asarray(bound * z[:, d:], dtype=_dtype(setup))
    return out


def _problem_values(setup, z, lo, hi, bound, dt, window_start, state_bound, extra=None, *,
                    st: _Static):
    from dscjax.simulate import run

    traj = run(setup, dt, window_start, state_bound, n_steps=st.n_steps, save_every=st.n_steps,
               overrides=_overrides(setup, st, z, lo, hi, bound), solver=st.solver, extra=extra)
    return traj.metrics[st.metric], traj.diverged


def _problem_single(setup, z1, lo, hi, bound, dt, window_start, state_bound, extra=None, *,
                    st: _Static):
    from dscjax.simulate import run

    one = {p: v[0] for p, v in _overrides(setup, st, z1[None, :], lo, hi, bound).items()}
    traj = run(params.set_many(setup, one), dt, window_start, state_bound, n_steps=st.n_steps,
               save_every=st.n_steps, solver=st.solver, gradient="time_parallel", extra=extra)
    return traj.metrics[st.metric], traj.diverged


def _masked_total(values, z, *args):
    v, bad = values(z, *args)
    return jnp.sum(jnp.where(bad, 0.0, v)), (v, bad)


def _value_and_grad(values, single, gradient, z, *args):
    """(values, diverged, d values / d z) of a batch; a diverged member's gradient is 0."""
    if gradient == "batch" or single is None:
        (_, (v, bad)), g = jax.value_and_grad(
            lambda z_: _masked_total(values, z_, *args), has_aux=True)(z)
    else:  # each start's own time-parallel gradient, vmapped over the starts
        def one(z1):
            v1, bad1 = single(z1, *args)
            return jnp.where(bad1, 0.0, v1), (v1, bad1)

        (_, (v, bad)), g = jax.vmap(jax.value_and_grad(one, has_aux=True))(z)
    return v, bad, g


_STATIC_PROBLEM = ("st",)
_problem_values_jit = jax.jit(_problem_values, static_argnames=_STATIC_PROBLEM)


@functools.partial(jax.jit, static_argnames=("st", "gradient"))
def _problem_value_and_grad(setup, z, lo, hi, bound, dt, window_start, state_bound, extra, *,
                            st: _Static, gradient: str):
    def values(z_, *a):
        return _problem_values(*a[:1], z_, *a[1:], st=st)

    def single(z1, *a):
        return _problem_single(*a[:1], z1, *a[1:], st=st)

    return _value_and_grad(values, single, gradient, z, setup, lo, hi, bound, dt,
                           window_start, state_bound, extra)


@functools.partial(jax.jit, static_argnames=("d", "project_coef"))
def _project(z, basis, *, d, project_coef):
    u = jnp.clip(z[:, :d], 0.0, 1.0)
    if project_coef is None:
        return u
    c = z[:, d:]
    return jnp.concatenate([u, project_coef(c, 1.0, c @ basis.T)], axis=1)


@functools.partial(jax.jit, static_argnames=("d",))
def _rescale(z, basis, *, d):
    """Random points: the waveform scaled so that max |dbar| = D exactly."""
    if z.shape[1] == d:
        return z
    c = z[:, d:]
    peak = jnp.max(jnp.abs(c @ basis.T), axis=1, keepdims=True)
    c = jnp.where(peak > 0, c / jnp.where(peak > 0, peak, 1.0), c)
    return jnp.concatenate([z[:, :d], c], axis=1)


class Programs:
    """The compiled programs of a search on (B, d + m) batches of normalised points:
    `project`, `rescale`, `values(z) -> (v, diverged)` and `value_and_grad(z) -> (v,
    diverged, g)`. `for_problem` builds them for a `Problem` (module-level jitted functions,
    shared by every problem of the same structure); `from_functions` for any objective, so
    that a search can be checked on a problem with a known answer.

    d box coordinates in [0, 1]; m waveform coefficients whose waveform on a grid is
    `c @ basis.T` (basis (G, m)); `project_coef` the waveform's projection onto max|.| <= 1.
    """

    def __init__(self, d: int, m: int, basis, project_coef, values: Callable,
                 value_and_grad: Callable, nominal_u: np.ndarray | None = None):
        self.d, self.m, self.nominal_u = d, m, nominal_u
        self.basis = jnp.asarray(basis)
        self.values, self.value_and_grad = values, value_and_grad
        pc = project_coef if m else None
        self.project = lambda z: _project(z, self.basis, d=d, project_coef=pc)
        self.rescale = lambda z: _rescale(z, self.basis, d=d)

    @classmethod
    def from_functions(cls, d: int, m: int, basis, project_coef, values: Callable,
                       single: Callable | None = None, gradient: str = "time_parallel",
                       nominal_u=None) -> Programs:
        """From a batch objective `values(z) -> (v, diverged)` and optionally its one-point
        version `single(z1)` (differentiated per start when gradient = "time_parallel")."""
        validation.one_of(gradient, "gradient", GRADIENTS)
        vg = jax.jit(lambda z: _value_and_grad(values, single, gradient, z))
        return cls(d, m, basis, project_coef, jax.jit(values), vg, nominal_u)

    @classmethod
    def for_problem(cls, problem: Problem, gradient: str = "time_parallel",
                    coarsening: int = 1) -> Programs:
        """The programs of `problem`. With `coarsening` F > 1 the gradients are those of the
        same loop simulated at F dt (F times cheaper: a search direction only), while every
        value (what the search compares and reports) is simulated at dt."""
        validation.one_of(gradient, "gradient", GRADIENTS)
        p = problem
        _check_coarsening(coarsening, p.n_steps)
        basis, project_coef = np.zeros((1, 0)), None
        if p.m:
            grid = dist_mod.half_step_grid(p.t_final, p.dt)
            model = p.setup.plant.disturbance
            basis = np.stack([np.asarray(dist_mod.sample(
                dataclasses.replace(model, **{model.coefficients_name: e}), grid))
                for e in np.eye(p.m)], axis=1)  # (G, m): each unit coefficient on the grid
            project_coef = type(model).project_coefficients
        lo, hi = p.lows_highs()
        args = (p.setup, lo, hi, p.disturbance.bound if p.m else 0.0, p.dt, p.window_start,
                p.state_bound, p.requirement)
        st = p.static()

        def values(z):
            return _problem_values_jit(args[0], z, *args[1:], st=st)

        if coarsening == 1:
            def value_and_grad(z):
                return _problem_value_and_grad(args[0], z, *args[1:], st=st, gradient=gradient)
        else:
            st_g = dataclasses.replace(st, n_steps=st.n_steps // coarsening)
            extra_g = p.requirement
            if extra_g is not None and hasattr(extra_g, "n_steps"):
                extra_g = dataclasses.replace(extra_g, n_steps=st_g.n_steps)
            args_g = args[:4] + (p.dt * coarsening,) + args[5:7] + (extra_g,)

            def value_and_grad(z):
                v, bad = values(z)
                _, bad_g, g = _problem_value_and_grad(args_g[0], z, *args_g[1:], st=st_g,
                                                      gradient=gradient)
                return v, bad, jnp.where(bad_g[:, None], 0.0, g)

        nominal_u = None
        if p.d:
            nominal = np.array([r.param.nominal(p.setup) for r in p.ranges])
            nominal_u = np.clip((nominal - lo) / (hi - lo), 0.0, 1.0)
        return cls(p.d, p.m, basis, project_coef, values, value_and_grad, nominal_u)


# -- the methods' states (resumable) -------------------------------------------------------------


@dataclasses.dataclass
class Trace:
    """A method's progress: best value against its search time, its best point, and the
    candidates whose batch run diverged (to be re-checked)."""

    method: str
    t: list[float] = dataclasses.field(default_factory=list)  # search seconds at iteration end
    best: list[float] = dataclasses.field(default_factory=list)  # best value so far then
    best_value: float = -math.inf
    best_z: np.ndarray | None = None
    evaluations: int = 0
    iterations: int = 0
    elapsed: float = 0.0
    compile_s: float = 0.0
    diverged_z: list = dataclasses.field(default_factory=list)
    extra: dict = dataclasses.field(default_factory=dict)  # method state arrays

    def record(self, z: np.ndarray, v: np.ndarray, bad: np.ndarray, seconds: float) -> None:
        v = np.where(bad, -np.inf, np.asarray(v, dtype=np.float64))
        v = np.where(np.isfinite(v), v, -np.inf)
        i = int(np.argmax(v))
        if v[i] > self.best_value:
            self.best_value, self.best_z = float(v[i]), np.array(z[i])
        for j in np.flatnonzero(bad)[:max(0, 8 - len(self.diverged_z))]:
            self.diverged_z.append(np.array(z[j]))
        # the TOP best distinct points so far (worst cases for adversarial tuning)
        zs = np.concatenate([self.extra.get("top_z", np.zeros((0, z.shape[1]))), z])
        vs = np.concatenate([self.extra.get("top_v", np.zeros(0)), v])
        _, first = np.unique(zs, axis=0, return_index=True)
        keep = first[np.argsort(-vs[first], kind="stable")][:TOP]
        keep = keep[np.isfinite(vs[keep])]
        self.extra["top_z"], self.extra["top_v"] = zs[keep], vs[keep]
        self.evaluations += len(v)
        self.iterations += 1
        self.elapsed += seconds
        self.t.append(self.elapsed)
        self.best.append(self.best_value)

    def save(self, path: Path, fingerprint: str) -> None:
        arrays = {"t": np.asarray(self.t), "best": np.asarray(self.best),
                  "best_value": np.asarray(self.best_value),
                  "best_z": np.asarray(self.best_z if self.best_z is not None else []),
                  "counts": np.asarray([self.evaluations, self.iterations, STATE_VERSION]),
                  "seconds": np.asarray([self.elapsed, self.compile_s]),
                  "diverged_z": (np.asarray(self.diverged_z) if self.diverged_z
                                 else np.zeros((0, 0))),
                  "fingerprint": np.frombuffer(fingerprint.encode(), dtype=np.uint8)}
        arrays |= {f"x_{k}": np.asarray(v) for k, v in self.extra.items()}
        files.write_npz(path, arrays)

    @classmethod
    def load(cls, path: Path, method: str, fingerprint: str) -> Trace | None:
        a = files.read_npz(path)
        if a is None or bytes(a["fingerprint"]).decode() != fingerprint:
            return None
        ev, it, version = (int(x) for x in a["counts"])
        if version != STATE_VERSION:
            return None
        tr = cls(method, list(a["t"]), list(a["best"]), float(a["best_value"]),
                 a["best_z"] if a["best_z"].size else None, ev, it, float(a["seconds"][0]),
                 float(a["seconds"][1]), list(a["diverged_z"]))
        tr.extra = {k[2:]: v for k, v in a.items() if k.startswith("x_")}
        return tr


def _rng(seed: int, method: str, iteration: int) -> np.random.Generator:
    """A generator that depends only on (seed, method, iteration): a resumed run draws what an
    uninterrupted one would have drawn."""
    return np.random.default_rng([seed, METHODS.index(method), iteration])


def _random_points(prog: Programs, rng: np.random.Generator, b: int) -> np.ndarray:
    z = np.concatenate([rng.random((b, prog.d)), rng.uniform(-1.0, 1.0, (b, prog.m))], axis=1)
    return np.array(prog.rescale(jnp.asarray(z)))


def _gradient_step(prog, tr, seed, starts, lr0, batch):
    """One iteration of projected gradient ascent for all starts: (z, values, diverged).

    The box coordinates u take Adam steps (per coordinate, lr box widths at most); the
    waveform coefficients a normalised gradient step (the largest moves by lr in units of D),
    since the waveform's constraint couples them; then the projection. Each start's lr grows
    by 1.2 after an improvement and halves after a loss."""
    d = prog.d
    x = tr.extra
    if "z" not in x:
        # the first iteration screens a batch of random points (the nominal box point among
        # them) by value alone and starts the ascent from the M best
        pool = _random_points(prog, _rng(seed, "gradient", 0), max(batch, starts))
        if prog.nominal_u is not None:
            pool[0, :d] = prog.nominal_u
        v, bad = (np.asarray(a) for a in prog.values(jnp.asarray(pool)))
        order = np.argsort(np.where(bad, -np.inf, v))[::-1]
        z = pool[order[:starts]]
        x.update(z=z, m1=np.zeros_like(z[:, :d]), m2=np.zeros_like(z[:, :d]),
                 lr=np.full(starts, lr0), prev=np.full(starts, -np.inf), k=np.zeros(starts))
        return pool, v, bad
    z = x["z"]
    v, bad, g = (np.array(a) for a in prog.value_and_grad(jnp.asarray(z)))
    v = np.asarray(v, dtype=np.float64)
    g = np.where(np.isfinite(g), g, 0.0)
    better = v >= x["prev"]
    lr = np.where(better, np.minimum(x["lr"] * 1.2, 8 * lr0), x["lr"] * 0.5)
    k = x["k"] + 1
    m1 = 0.9 * x["m1"] + 0.1 * g[:, :d]
    m2 = 0.999 * x["m2"] + 0.001 * g[:, :d] ** 2
    step_u = (m1 / (1 - 0.9 ** k[:, None])) / (np.sqrt(m2 / (1 - 0.999 ** k[:, None])) + 1e-30)
    gc = g[:, d:]
    peak = np.max(np.abs(gc), axis=1, keepdims=True) if prog.m else np.ones((len(z), 1))
    step_c = gc / np.where(peak > 0, peak, 1.0)
    step = np.concatenate([step_u, step_c], axis=1)
    # a worse point: step back from the previous one with half the step; else step from here
    base = np.where(better[:, None] | ~np.isfinite(x["prev"])[:, None], z, x.get("zprev", z))
    gradient = np.where(better[:, None], step, x.get("stepprev", step))
    new = np.array(prog.project(jnp.asarray(base + lr[:, None] * gradient)))
    # a start that diverged (to be re-checked), or whose step has collapsed, starts afresh
    restart = bad | (lr < lr0 / 64)
    if restart.any():
        fresh = _random_points(prog, _rng(seed, "gradient", tr.iterations + 1), starts)
        new[restart] = fresh[restart]
        m1[restart] = 0.0
        m2[restart] = 0.0
        k = np.where(restart, 0.0, k)
        lr = np.where(restart, lr0, lr)
    keep = better | ~np.isfinite(x["prev"])
    x.update(zprev=np.where(keep[:, None], z, x.get("zprev", z)),
             stepprev=np.where(keep[:, None], step, x.get("stepprev", step)),
             prev=np.where(restart, -np.inf, np.where(keep, v, x["prev"])),
             z=new, m1=m1, m2=m2, k=k, lr=lr)
    return z, v, bad


def _random_step(prog, tr, seed, batch):
    z = _random_points(prog, _rng(seed, "random", tr.iterations), batch)
    v, bad = (np.asarray(a) for a in prog.values(jnp.asarray(z)))
    return z, v, bad


class _CMA:
    """CMA-ES of the `cma` package, resumable without pickles: the fitness of every
    generation is kept, and a resumed run replays ask/tell from the same seed (cma draws from
    NumPy's global generator, seeded by its `seed` option), checked against the stored last
    generation."""

    def __init__(self, prog, seed, popsize, x):
        from dscjax.cmaes import ReplayCMA

        lower = [0.0] * prog.d + [-1.0] * prog.m
        upper = [1.0] * prog.d + [1.0] * prog.m
        x0 = np.concatenate([np.full(prog.d, 0.5), np.zeros(prog.m)])
        self.es = ReplayCMA(x0, 0.3, {"seed": seed + 1, "verbose": -9, "popsize": popsize,
                                      "bounds": [lower, upper]})
        if len(x.get("fitness", ())):
            try:
                self.es.replay({"fitness": x["fitness"], "asked": x["last_x"]})
            except ValueError:
                raise ConfigError("--resume: CMA-ES could not replay its stored generations; "
                                  "use --overwrite") from None
        self.x = x

    def step(self, prog):
        asked = self.es.ask()
        z = np.asarray(prog.project(jnp.asarray(asked)))
        v, bad = (np.asarray(a) for a in prog.values(jnp.asarray(z)))
        f = np.where(bad | ~np.isfinite(v), -1e30, np.asarray(v, dtype=np.float64))
        self.es.tell(asked, -f)  # cma minimises
        saved = self.es.arrays()
        self.x["fitness"], self.x["last_x"] = saved["fitness"], saved["asked"]
        return z, v, bad


# -- the search ---------------------------------------------------------------------------------


@dataclasses.dataclass
class Result:
    """The worst case found and each method's trace."""

    problem: Problem
    value: float  # the metric of `simulate` on the worst setup (+inf: the loop diverges)
    z: np.ndarray
    method: str
    setup: Setup
    diverged: bool
    t_diverged: float | None
    refinements: int
    traces: dict[str, Trace]
    nominal_value: float
    info: dict
    trajectory: Any  # `simulate`'s run of `setup` (kept for the report's files)
    nominal: Any  # and of the nominal point (zero waveform: the same values exactly)


def _check_run(problem: Problem, setup) -> tuple[float, bool, float | None, int, Any]:
    """`simulate` of one candidate with refinement: (value, diverged, t_diverged, level, traj)."""
    from dscjax.simulate import simulate

    traj = simulate(setup, problem.t_final, problem.dt, window_start=problem.window_start,
                    state_bound=problem.state_bound, throw=False, refine=problem.refine,
                    solver=problem.solver, extra=problem.requirement)
    bad = bool(traj.diverged)
    value = math.inf if bad else float(traj.metrics[problem.metric_key])
    return value, bad, (float(traj.t_diverged) if bad else None), int(traj.refinements), traj


def _check_coarsening(coarsening: int, n_steps: int) -> None:
    validation.integer(coarsening, "--gradient-coarsening", 1)
    if n_steps % coarsening:
        raise ConfigError(f"--gradient-coarsening {coarsening} must divide the number of "
                          f"steps t_final/dt = {n_steps}")


def worst_case(problem: Problem | Setup, ranges: Sequence[ranges_mod.Range | str] = (),
               disturbance: DisturbanceSpec | str | None = None, *,
               time_limit: float = 60.0, starts: int = DEFAULT_STARTS,
               methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
               lr: float = DEFAULT_LR, gradient: str = "time_parallel",
               coarsening: int = DEFAULT_COARSENING, out_dir: str | Path | None = None,
               resume: bool = False, max_evals: int | None = None,
               progress: Callable[[str, Trace, float], None] | None = None,
               **problem_options) -> Result:
    """Search the worst case of `problem` with each method for `time_limit` seconds (or
    `max_evals` evaluations, whichever comes first).

    Args:
        problem: from `make_problem`; or a Setup, then `make_problem(problem, ranges,
            disturbance, **problem_options)` (ranges may be given as text, "PATH=30%").
        time_limit: search seconds per method (compilation excluded, reported apart).
        starts: M, the starts of the gradient method, advanced together as one batch.
        methods: any of "gradient", "random", "cma" (the last two are the baselines).
        seed: every random draw is a function of (seed, method, iteration).
        batch: candidates per batch of the random and CMA-ES methods.
        lr: the initial step (in box widths and units of D) of the gradient method.
        gradient: "time_parallel" (each start's own time-parallel gradient, vmapped) or
            "batch" (reverse mode through the batch's checkpointed scan).
        coarsening: F, gradients taken on the loop simulated at F dt (values always at dt);
            1: exact gradients of the values.
        out_dir: where each method's state is saved after every iteration (for `resume`).
        max_evals: stop a method once it has evaluated this many candidates (its last batch
            is finished, so it may evaluate up to a batch more); None: the time limit alone.
            A count, unlike a time, makes searches of different gains or under different
            loads see the same points (random sampling with the same seed: exactly the same).
        progress: called with (method, trace, time_limit) after every iteration.

    Returns:
        `Result`; its value is re-checked by `simulate` (with refinement) on the worst setup.

    Example:
        >>> import dscjax
        >>> res = dscjax.worst_case(dscjax.paper_example(), ["hysteresis.alpha=30%"],
        ...                         "fourier:2:0.5", t_final=2.0, time_limit=5.0)  # doctest: +SKIP
        >>> res.value, res.problem.values_at(res.z)  # doctest: +SKIP
    """
    if not isinstance(problem, Problem):
        problem = make_problem(problem, [ranges_mod.parse_range(r) if isinstance(r, str) else r
                                         for r in ranges], disturbance, **problem_options)
    elif ranges or disturbance is not None or problem_options:
        raise ConfigError("worst_case: give ranges, disturbance and simulation options to "
                          "make_problem, not with a Problem")
    check_search(problem, methods, starts=starts, batch=batch, time_limit=time_limit,
                 max_evals=max_evals, coarsening=coarsening)
    fp = files.digest({"problem": problem.fingerprint(), "seed": seed, "starts": starts,
                       "batch": batch, "lr": lr, "gradient": gradient,
                       "coarsening": coarsening})
    prog = Programs.for_problem(problem, gradient, coarsening)
    traces = search(prog, time_limit=time_limit, starts=starts, methods=methods, seed=seed,
                    batch=batch, lr=lr, out_dir=out_dir, resume=resume, fingerprint=fp,
                    progress=progress, max_evals=max_evals)
    return _finish(problem, traces)


def check_search(problem: Problem, methods: Sequence[str], *, starts: int, batch: int,
                 time_limit: float, max_evals: int | None = None, coarsening: int = 1) -> None:
    """The search settings of `worst_case`, checked before anything runs (ConfigError naming
    the option)."""
    if not methods:
        raise ConfigError(f"--methods must name at least one of {', '.join(METHODS)}")
    for mth in methods:
        validation.one_of(mth, "--methods", METHODS)
    validation.integer(starts, "--starts", 1)
    validation.integer(batch, "batch", 1)
    if not (time_limit > 0):
        raise ConfigError(f"--time-limit must be > 0 (got {time_limit!r})")
    if max_evals is not None:
        validation.integer(max_evals, "--max-evals", 1)
    validation.integer(coarsening, "--gradient-coarsening", 1)
    if problem.n_steps % coarsening:
        raise ConfigError(f"--gradient-coarsening {coarsening} must divide the number of "
                          f"steps t_final/dt = {problem.n_steps}")


def _warm_up(prog: Programs, method: str, starts: int, batch: int) -> float:
    """Compile the method's programs before its clock starts: the seconds of compilation (a
    first call less a second one)."""
    z0 = np.zeros((max(batch, starts) if method == "gradient" else batch, prog.d + prog.m))
    calls = [lambda: prog.values(jnp.asarray(z0)), lambda: prog.project(jnp.asarray(z0)),
             lambda: prog.rescale(jnp.asarray(z0))]
    if method == "gradient":  # its iterations project and restart M = `starts` points
        calls += [lambda: prog.value_and_grad(jnp.asarray(z0[:starts])),
                  lambda: prog.project(jnp.asarray(z0[:starts])),
                  lambda: prog.rescale(jnp.asarray(z0[:starts]))]
    total = 0.0
    for call in calls:
        t0 = time.perf_counter()
        jax.block_until_ready(call())
        t1 = time.perf_counter()
        jax.block_until_ready(call())
        total += max((t1 - t0) - (time.perf_counter() - t1), 0.0)
    return total


def search(prog: Programs, *, time_limit: float, starts: int = DEFAULT_STARTS,
           methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
           lr: float = DEFAULT_LR, out_dir: str | Path | None = None, resume: bool = False,
           fingerprint: str = "", progress: Callable | None = None,
           max_evals: int | None = None) -> dict[str, Trace]:
    """Run each method on the programs for `time_limit` search seconds or `max_evals`
    evaluations, whichever comes first; {method: Trace}."""
    out = Path(out_dir) if out_dir is not None else None
    traces: dict[str, Trace] = {}
    cap = math.inf if max_evals is None else max_evals

    def running(tr: Trace) -> bool:
        return tr.elapsed < time_limit and tr.evaluations < cap

    for mth in methods:
        path = out / f"state_{mth}.npz" if out is not None else None
        tr = Trace.load(path, mth, fingerprint) if (resume and path is not None) else None
        tr = tr or Trace(mth)
        cma_es = _CMA(prog, seed, batch, tr.extra) if mth == "cma" else None
        if running(tr):
            tr.compile_s += _warm_up(prog, mth, starts, batch)
        while running(tr):
            # a Ctrl-C waits for the iteration and its state file (dscjax.progress)
            with critical():
                t0 = time.perf_counter()
                if mth == "gradient":
                    z, v, bad = _gradient_step(prog, tr, seed, starts, lr, batch)
                elif mth == "random":
                    z, v, bad = _random_step(prog, tr, seed, batch)
                else:
                    z, v, bad = cma_es.step(prog)
                seconds = time.perf_counter() - t0
                tr.record(z, v, bad, seconds)
                if path is not None:
                    tr.save(path, fingerprint)
            if progress is not None:
                progress(mth, tr, time_limit)
        traces[mth] = tr
    return traces


def _finish(problem: Problem, traces: dict[str, Trace]) -> Result:
    """Re-check each method's best point and its diverged candidates with `simulate`; the
    worst of them is the result."""
    candidates = []
    for mth, tr in traces.items():
        if tr.best_z is not None:
            candidates.append((mth, tr.best_z))
        candidates += [(mth, z) for z in tr.diverged_z[:2]]
    if not candidates:
        raise ConfigError("no candidate was evaluated: give a larger --time-limit")
    best = None
    checked = {}
    for mth, z in candidates:
        key = np.asarray(z).tobytes()
        if key in checked:
            continue
        setup = problem.setup_at(z)
        value, bad, t_bad, level, traj = _check_run(problem, setup)
        checked[key] = value
        score = (math.inf, -t_bad) if bad else (value, 0.0)
        if best is None or score > best[0]:
            best = (score, mth, z, setup, value, bad, t_bad, level, traj)
    _, mth, z, setup, value, bad, t_bad, level, traj = best
    # the nominal point with the zero waveform: the value without one exactly (dbar + 0), and
    # the program of the candidates' re-check serves it
    nominal_value, *_, nominal = _check_run(problem, problem.setup)
    return Result(problem, value, np.asarray(z), mth, setup, bad, t_bad, level, traces,
                  nominal_value, {"rechecked": len(checked)}, traj, nominal)


__all__ = ["DEFAULT_METRIC", "DEFAULT_STARTS", "METHODS", "METRICS", "REQUIREMENT",
           "DisturbanceSpec",
           "Problem", "Programs", "Result", "Trace", "make_problem", "worst_case"]
