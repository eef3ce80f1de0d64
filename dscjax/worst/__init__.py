"""Worst-case search: maximise a metric of the closed loop over a box of plant / hysteresis /
initial-state parameters and a bounded disturbance waveform.

    problem = make_problem(setup, ranges=[parse_range("hysteresis.alpha=30%")],
                           disturbance="fourier:16:0.5", t_final=20.0, dt=1e-3)
    result = worst_case(problem, time_limit=60.0, starts=4, out_dir="results/worst")

Normalised coordinates z = (u, c): u in [0, 1]^d places each ranged parameter in its box, c
(m coefficients) is the waveform in units of the bound D (max |dbar| <= D). Each method of
`dscjax.search` ("gradient": projected ascent from M starts; "random"; "cma") minimises -metric
there for the same search time. The value reported is `simulate`'s (with refinement) on the
worst setup (+inf if it diverges), which `worst_config.toml` reproduces.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal, get_args

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import disturbance as dist_mod
from dscjax import files, params, search, validation
from dscjax.closed_loop import Setup
from dscjax.runspec import RunSpec
from dscjax.simulate import check, run, simulate
from dscjax.validation import ConfigError

Method = Literal["gradient", "random", "cma"]
METHODS: tuple[str, ...] = get_args(Method)
# metrics of `run` a search may maximise (windowed L-inf of e by default)
METRICS = ("linf_error_window", "linf_error", "l2_error_window", "rms_error_window",
           "max_abs_u", "l2_u", "tv_u", "max_abs_w")
DEFAULT_METRIC = "linf_error_window"
# "requirement:NAME" maximises a requirement's "margin" (> 0 when violated)
REQUIREMENT = "requirement:"
DEFAULT_STARTS = 4  # docs/worst-case.md
DEFAULT_BATCH = 32  # random and CMA-ES candidates per batched simulation
DEFAULT_LR = 0.1
DEFAULT_COARSENING = 4  # gradients at 4 dt (docs/worst-case.md)


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
    def n_steps(self) -> int:
        return self.spec.n_steps

    @property
    def t_final(self) -> float:
        return self.spec.t_final

    @property
    def dt(self) -> float:
        return float(self.spec.dt)

    @property
    def window_start(self) -> float:
        return float(self.spec.window_start)

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
                       self.metric_key)

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
                "metric": self.metric, "run": self.spec.describe(),
                "requirement": _describe(self.requirement)}


def assumption_warnings(problem: Problem) -> list[str]:
    """The paper's assumptions (`validation.assumption_warnings`) that the base setup, or an
    end of a searched box, violates: a box on plant.g[i] reaching below controller.g_min is
    named with its --range."""
    return [w.replace("--range.", "--range ") for w in
            params.assumption_warnings(problem.setup, problem.ranges, "--range")]


def _describe(reduction) -> dict | None:
    """The kind and numbers of a requirement (for fingerprints)."""
    if reduction is None:
        return None
    return {"kind": type(reduction).__name__,
            **{f.name: np.asarray(getattr(reduction, f.name)).tolist()
               for f in dataclasses.fields(reduction)}}


def _dtype(setup):
    return jnp.result_type(setup.plant.x0)


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
    if spec is None:
        spec = RunSpec.make(**run)
    elif run:
        raise TypeError("make_problem: give spec or its fields, not both")
    options, spec = spec, spec.replace(save_every=spec.n_steps)
    t_final, dt, window_start = spec.t_final, float(spec.dt), float(spec.window_start)
    setup = params.cast(setup, _dtype(setup))
    if disturbance is not None:
        zero = disturbance.model(np.zeros(disturbance.size), t_final)
        setup = setup.replace(plant=dataclasses.replace(
            setup.plant, disturbance=params.cast(zero, _dtype(setup))))
    validation.validate_setup(setup)
    check(setup, spec)
    if any(r.param.path.startswith("plant.disturbance") for r in ranges):
        raise ConfigError(f"{field}: the disturbance waveform is searched by --disturbance, "
                          f"not by a range")
    resolved = params.check(list(ranges), setup, field, t_final=t_final, dt=dt,
                                window_start=window_start)
    if requirement is not None and hasattr(requirement, "n_steps"):
        requirement = dataclasses.replace(requirement, n_steps=spec.n_steps)
    return Problem(setup, resolved, disturbance, metric, spec, requirement, options)


# -- the compiled programs ----------------------------------------------------------------------


GRADIENTS = ("time_parallel", "batch")


@dataclasses.dataclass(frozen=True)
class _Static:
    """The static (hashable) part of a problem's compiled programs; the setup, the box and
    the bound are traced, so problems that differ only in numbers share one compilation."""

    columns: tuple[params.Param, ...]
    coef_path: str | None
    metric: str


def _overrides(setup, st: _Static, z, lo, hi, bound):
    d = len(st.columns)
    out = {}
    if d:
        out = params.overrides(setup, list(st.columns), lo + z[:, :d] * (hi - lo))
    if st.coef_path is not None:
        xp = np if isinstance(z, np.ndarray) else jnp
        out[st.coef_path] = xp.asarray(bound * z[:, d:], dtype=_dtype(setup))
    return out


def _problem_values(setup, z, lo, hi, bound, spec, extra=None, *, st: _Static):
    traj = run(setup, spec, overrides=_overrides(setup, st, z, lo, hi, bound), extra=extra)
    return traj.metrics[st.metric], traj.diverged


def _problem_single(setup, z1, lo, hi, bound, spec, extra=None, *, st: _Static):
    one = {p: v[0] for p, v in _overrides(setup, st, z1[None, :], lo, hi, bound).items()}
    traj = run(params.set_many(setup, one), spec, extra=extra)
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
def _problem_value_and_grad(setup, z, lo, hi, bound, spec, extra, *, st: _Static,
                            gradient: str):
    def values(z_, *a):
        return _problem_values(*a[:1], z_, *a[1:], st=st)

    def single(z1, *a):
        return _problem_single(*a[:1], z1, *a[1:], st=st)

    return _value_and_grad(values, single, gradient, z, setup, lo, hi, bound, spec, extra)


@functools.partial(jax.jit, static_argnames=("st", "gradient"))
def _problem_coarse(setup, z, lo, hi, bound, spec, extra, spec_g, extra_g, *, st: _Static,
                    gradient: str):
    """Values of the loop of `spec`, gradients of the loop of `spec_g` (a coarser step; zero
    where that run diverged)."""
    v, bad = _problem_values(setup, z, lo, hi, bound, spec, extra, st=st)
    _, bad_g, g = _problem_value_and_grad(setup, z, lo, hi, bound, spec_g, extra_g, st=st,
                                          gradient=gradient)
    return v, bad, jnp.where(bad_g[:, None], 0.0, g)


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


class _Fixed:
    """A module-level jitted function with every argument but the points z fixed, so that
    problems of one structure share its compilations: call it on z, or `lower` it for z."""

    def __init__(self, fn, before=(), after=(), **kwargs):
        self.fn, self.before, self.after, self.kwargs = fn, before, after, kwargs

    def __call__(self, z):
        return self.fn(*self.before, z, *self.after, **self.kwargs)

    def lower(self, z):
        return self.fn.lower(*self.before, z, *self.after, **self.kwargs)


class Programs(search.Problem):
    """The compiled programs of a search on (B, d + m) batches of normalised points, as the
    `dscjax.search` problem: minimise -metric over [0, 1]^d x [-1, 1]^m, projected onto the
    waveform's bound (waveform `c @ basis.T`, `project_coef`), from `x0` (the nominal point);
    a diverged candidate's loss is +inf. `values(z) -> (v, diverged)`. `for_problem` builds
    them for a `Problem` (shared by problems of one structure), `from_functions` for any
    objective (a search checked on a known answer)."""

    def __init__(self, d: int, m: int, basis, project_coef, values, value_and_grad,
                 nominal_u: np.ndarray | None = None):
        self.d, self.m, self.nominal_u = d, m, nominal_u
        self.basis = jnp.asarray(basis)
        pc = project_coef if m else None
        self.values = search.Batched(values)
        self._value_and_grad = search.Batched(value_and_grad)
        self.project = search.Batched(_Fixed(_project, after=(self.basis,), d=d,
                                             project_coef=pc))
        self.rescale = search.Batched(_Fixed(_rescale, after=(self.basis,), d=d))
        self.lower = np.concatenate([np.zeros(d), -np.ones(m)])
        self.upper = np.ones(d + m)
        self.x0 = np.concatenate([nominal_u if nominal_u is not None else np.full(d, 0.5),
                                  np.zeros(m)])

    @property
    def compile_seconds(self) -> float:
        return sum(p.seconds for p in (self.values, self._value_and_grad, self.project,
                                       self.rescale))

    @staticmethod
    def _evaluation(v, bad) -> search.Evaluation:
        v, bad = np.asarray(v, dtype=np.float64), np.asarray(bad, dtype=bool)
        return search.Evaluation.of(np.where(bad, np.inf, -v), ~bad, bad)

    def evaluate(self, z) -> search.Evaluation:
        return self._evaluation(*self.values(z))

    def value_and_grad(self, z) -> tuple[search.Evaluation, np.ndarray]:
        v, bad, g = self._value_and_grad(z)
        return self._evaluation(v, bad), -np.asarray(g, dtype=np.float64)

    def sample(self, rng: np.random.Generator, b: int) -> np.ndarray:
        """b uniform points of the box, coefficients uniform in [-1, 1]^m rescaled so that
        max |dbar| = D exactly."""
        return self.rescale(np.concatenate([rng.random((b, self.d)),
                                            rng.uniform(-1.0, 1.0, (b, self.m))], axis=1))

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
        """The programs of `problem`; with `coarsening` F > 1 the gradients are the loop's at
        F dt (a search direction only), the values always at dt."""
        validation.one_of(gradient, "gradient", GRADIENTS)
        p = problem
        _check_coarsening(coarsening, p.spec)
        basis, project_coef = np.zeros((1, 0)), None
        if p.m:
            grid = dist_mod.half_step_grid(p.t_final, p.dt)
            model = p.setup.plant.disturbance
            basis = np.stack([np.asarray(dist_mod.sample(
                dataclasses.replace(model, **{model.coefficients_name: e}), grid))
                for e in np.eye(p.m)], axis=1)  # (G, m): each unit coefficient on the grid
            project_coef = type(model).project_coefficients
        lo, hi = p.lows_highs()
        spec = p.spec.for_dtype(_dtype(p.setup)).program()  # (refinement is simulate's)
        args = (lo, hi, p.disturbance.bound if p.m else 0.0, spec, p.requirement)
        st = p.static()
        values = _Fixed(_problem_values_jit, (p.setup,), args, st=st)
        if coarsening == 1:
            vg = _Fixed(_problem_value_and_grad, (p.setup,), args, st=st, gradient=gradient)
        else:
            f = coarsening
            spec_g = dataclasses.replace(spec, dt=spec.dt * f, n_steps=spec.n_steps // f,
                                         save_every=spec.n_steps // f,
                                         sample_every=spec.sample_every // f)
            extra_g = p.requirement
            if extra_g is not None and hasattr(extra_g, "n_steps"):
                extra_g = dataclasses.replace(extra_g, n_steps=spec_g.n_steps)
            vg = _Fixed(_problem_coarse, (p.setup,), args + (spec_g, extra_g), st=st,
                        gradient=gradient)
        nominal_u = None
        if p.d:
            nominal = np.array([r.param.nominal(p.setup) for r in p.ranges])
            nominal_u = np.clip((nominal - lo) / (hi - lo), 0.0, 1.0)
        return cls(p.d, p.m, basis, project_coef, values, vg, nominal_u)


def best_value(trace: search.Trace) -> float:
    """The best metric value of a method's trace (-inf before a finite one)."""
    return -trace.best_loss


def search_method(name: str, *, starts: int = DEFAULT_STARTS, batch: int = DEFAULT_BATCH,
                  lr: float = DEFAULT_LR, m: int = 0):
    """The `dscjax.search` method of a worst-case method name (m: waveform coefficients)."""
    return {"gradient": lambda: search.Gradient(lr=lr, starts=starts, screen=max(batch, starts),
                                                coupled=m),
            "random": lambda: search.Random(batch=batch),
            "cma": lambda: search.CMA(popsize=batch)}[name]()


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
    traces: dict[str, search.Trace]
    nominal_value: float
    info: dict
    trajectory: Any  # `simulate`'s run of `setup` (kept for the report's files)
    nominal: Any  # and of the nominal point (zero waveform: the same values exactly)


def _check_run(problem: Problem, setup) -> tuple[float, bool, float | None, int, Any]:
    """`simulate` of one candidate with refinement: (value, diverged, t_diverged, level, traj)."""
    traj = simulate(setup, spec=problem.spec.replace(save_every=1), throw=False,
                    extra=problem.requirement)
    bad = bool(traj.diverged)
    value = math.inf if bad else float(traj.metrics[problem.metric_key])
    return value, bad, (float(traj.t_diverged) if bad else None), int(traj.refinements), traj


def _check_coarsening(coarsening: int, spec: RunSpec) -> None:
    validation.integer(coarsening, "--gradient-coarsening", 1)
    if spec.n_steps % coarsening:
        raise ConfigError(f"--gradient-coarsening {coarsening} must divide the number of "
                          f"steps t_final/dt = {spec.n_steps}")
    if spec.sampled and spec.sample_every % coarsening:
        raise ConfigError(f"--gradient-coarsening {coarsening} must divide the steps per "
                          f"controller sample, sample_time/dt = {spec.sample_every}")


def worst_case(problem: Problem | Setup, ranges: Sequence[params.Range | str] = (),
               disturbance: DisturbanceSpec | str | None = None, *,
               time_limit: float = 60.0, starts: int = DEFAULT_STARTS,
               methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
               lr: float = DEFAULT_LR, gradient: str = "time_parallel",
               coarsening: int = DEFAULT_COARSENING, out_dir: str | Path | None = None,
               resume: bool = False, max_evals: int | None = None,
               progress: Callable[[str, search.Trace, float], None] | None = None,
               say: Callable[[str], None] | None = None, **problem_options) -> Result:
    """Search the worst case of `problem` with each method for `time_limit` seconds (or
    `max_evals` evaluations, whichever comes first).

    Args:
        problem: from `make_problem`; or a Setup, then `make_problem(problem, ranges,
            disturbance, **problem_options)` (ranges may be text, "PATH=30%").
        time_limit: search seconds per method (compilation excluded).
        starts: M, the gradient method's starts, advanced as one batch.
        methods: any of "gradient", "random", "cma".
        seed: every random draw is a function of (seed, method, iteration).
        batch: candidates per batch of random and CMA-ES.
        lr: the gradient method's initial step (box widths, units of D).
        gradient: "time_parallel" (per start, vmapped) or "batch" (through the batch's scan).
        coarsening: F, gradients of the loop at F dt (1: exact gradients of the values).
        out_dir: where each method's state is saved after every iteration (for `resume`).
        max_evals: stop a method after this many candidates (its last batch finished); a
            count, unlike a time, sees the same points under any load.
        progress: called with (method, trace, time_limit) after every iteration.
        say: called with a line of text as each phase begins (a method's compilation and
            search, the re-check), so that no long phase passes in silence.

    Returns:
        `Result`; its value is re-checked by `simulate` (with refinement) on the worst setup.

    Example:
        >>> import dscjax
        >>> res = dscjax.worst_case(dscjax.paper_example(), ["hysteresis.alpha=30%"],
        ...                         "fourier:2:0.5", t_final=2.0, time_limit=5.0)  # doctest: +SKIP
        >>> res.value, res.problem.values_at(res.z)  # doctest: +SKIP
    """
    if not isinstance(problem, Problem):
        problem = make_problem(problem, [params.parse_range(r) if isinstance(r, str) else r
                                         for r in ranges], disturbance, **problem_options)
    elif ranges or disturbance is not None or problem_options:
        raise ConfigError("worst_case: give ranges, disturbance and simulation options to "
                          "make_problem, not with a Problem")
    check_search(problem, methods, starts=starts, batch=batch, time_limit=time_limit,
                 max_evals=max_evals, coarsening=coarsening)
    fp = {"problem": files.digest(problem.fingerprint()), "gradient": gradient,
          "coarsening": coarsening}
    prog = Programs.for_problem(problem, gradient, coarsening)
    traces = run_methods(prog, time_limit=time_limit, starts=starts, methods=methods,
                         seed=seed, batch=batch, lr=lr, out_dir=out_dir, resume=resume,
                         fingerprint=fp, progress=progress, max_evals=max_evals, say=say)
    return _finish(problem, traces, say)


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
    _check_coarsening(coarsening, problem.spec)


def run_methods(prog: Programs, *, time_limit: float, starts: int = DEFAULT_STARTS,
                methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
                lr: float = DEFAULT_LR, out_dir: str | Path | None = None,
                resume: bool = False, fingerprint: Any = None,
                progress: Callable | None = None,
                max_evals: int | None = None,
                say: Callable[[str], None] | None = None) -> dict[str, search.Trace]:
    """Run each method on the programs for `time_limit` search seconds (compilation apart)
    or `max_evals` evaluations, whichever comes first, each from its `state_<method>.npz` in
    out_dir with `resume`; {method: Trace}. `say` gets a line as each method begins."""
    out = Path(out_dir) if out_dir is not None else None
    traces = {}
    for name in methods:
        if say is not None:
            say(f"{name}: compiling its programs (not counted in the time limit), then "
                f"searching")
        each = None if progress is None else (
            lambda tr, row, name=name: progress(name, tr, time_limit))
        res = search.run(prog, search_method(name, starts=starts, batch=batch, lr=lr, m=prog.m),
                         x0=prog.x0, seed=seed, time_limit=time_limit, max_evals=max_evals,
                         path=None if out is None else out / f"state_{name}.npz",
                         resume=resume, fingerprint=fingerprint, progress=each,
                         count_compile=False)
        traces[name] = res.trace
    return traces


def _finish(problem: Problem, traces: dict[str, search.Trace],
            say: Callable[[str], None] | None = None) -> Result:
    """Re-check each method's best point and its diverged candidates with `simulate`; the
    worst of them is the result."""
    candidates = []
    for mth, tr in traces.items():
        if tr.best_z is not None:
            candidates.append((mth, tr.best_z))
        candidates += [(mth, z) for z in tr.diverged_z[:2]]
    if not candidates:
        raise ConfigError("no candidate was evaluated: give a larger --time-limit")
    if say is not None:
        n = len({np.asarray(z).tobytes() for _, z in candidates})
        say(f"re-checking {n} candidate(s) and the nominal point with simulate (every step, "
            f"refined if they diverge)")
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
           "DisturbanceSpec", "Problem", "Programs", "Result", "assumption_warnings",
           "best_value", "make_problem",
           "run_methods", "search_method", "worst_case"]
