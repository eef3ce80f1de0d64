"""Worst-case search: maximise a metric of the closed loop over a box of plant / hysteresis /
initial-state parameters and a bounded disturbance waveform.

    problem = make_problem(setup, ranges=[parse_range("hysteresis.alpha=30%")],
                           disturbance="fourier:16:0.5", t_final=20.0, dt=1e-3)
    result = worst_case(problem, time_limit=60.0, starts=8, out_dir="results/worst")

The search runs in normalised coordinates z = (u, c): u in [0, 1]^d places each ranged
parameter in its box (value = low + u (high - low)); c (m coefficients) is the waveform in
units of the bound D (coefficients = D c). The feasible set is u in the box and max |dbar| <= D
(`dscjax.disturbance`: knots clipped, or a Fourier series scaled on the half-step grid).

Three methods, each given the same wall time (compilation excluded and reported apart):
  - "gradient": projected gradient ascent from M starts advanced together as ONE batched
    program (reverse mode through the checkpointed scan), per-start Adam steps whose size grows
    by 1.2 after an improvement and halves after a loss, then the projection;
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
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, get_args

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import disturbance as dist_mod
from dscjax import files, params, validation
from dscjax import ranges as ranges_mod
from dscjax.closed_loop import Setup
from dscjax.metrics import default_window
from dscjax.validation import ConfigError

Method = Literal["gradient", "random", "cma"]
METHODS: tuple[str, ...] = get_args(Method)
# metrics of `run` a search may maximise (windowed L-inf of e by default)
METRICS = ("linf_error_window", "linf_error", "l2_error_window", "rms_error_window",
           "max_abs_u", "l2_u", "tv_u", "max_abs_w")
DEFAULT_METRIC = "linf_error_window"
DEFAULT_STARTS = 8  # measured: see docs/worst-case.md
DEFAULT_BATCH = 32  # random and CMA-ES candidates per batched simulation
DEFAULT_LR = 0.1
STATE_VERSION = 1


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
        try:
            k = int(k_text)
        except ValueError:
            raise ConfigError(f"{field}: K must be an integer >= 1 (got {k_text!r})") from None
        try:
            bound = float(d_text)
        except ValueError:
            raise ConfigError(f"{field}: D must be a number >= 0 (got {d_text!r})") from None
        return cls(kind, k, bound, period).checked(field)

    def checked(self, field: str = "--disturbance") -> DisturbanceSpec:
        validation.one_of(self.kind, f"{field} kind", tuple(dist_mod.KINDS))
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise ConfigError(f"{field}: K must be an integer >= 1 (got {self.k!r})")
        if not (math.isfinite(self.bound) and self.bound >= 0):
            raise ConfigError(f"{field}: the bound D must be a finite number >= 0 (got "
                              f"{self.bound!r})")
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

    def overrides(self, z):
        """{path: (B, ...)} of a (B, dim) batch of normalised points (traced or NumPy)."""
        xp = np if isinstance(z, np.ndarray) else jnp
        lo, hi = self.lows_highs()
        out = {}
        if self.d:
            table = lo + z[:, :self.d] * (hi - lo)
            out = params.overrides(self.setup, self.columns, table)
        if self.m:
            out[self.coef_path] = xp.asarray(self.disturbance.bound * z[:, self.d:],
                                             dtype=_dtype(self.setup))
        return out

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
                "solver": self.solver, "refine": self.refine}


def _dtype(setup):
    return np.result_type(np.asarray(setup.plant.x0))


def make_problem(setup: Setup, ranges: Sequence[ranges_mod.Range] = (),
                 disturbance: DisturbanceSpec | str | None = None, *, metric: str = DEFAULT_METRIC,
                 t_final: float = 20.0, dt: float = 1e-3, window_start: float | None = None,
                 state_bound: float = 1e6, solver: str = "rk4", refine: int = 6,
                 period: float | None = None, field: str = "--range") -> Problem:
    """Validate and build a `Problem`; ConfigError (one line, naming the field) if bad.

    Args:
        setup: the closed loop (its values are the nominal point).
        ranges: boxes of parameters, by config path (`dscjax.ranges`).
        disturbance: "fourier:K:D", "spline:K:D" or a `DisturbanceSpec`; None: no waveform.
        metric: one of `METRICS` (default the windowed L-inf of the tracking error).
        period: the Fourier period (default: the horizon).
    """
    validation.one_of(metric, "--metric", METRICS)
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
    return Problem(setup, resolved, disturbance, metric, float(t_final), float(dt),
                   float(window_start), float(state_bound), solver, int(refine))


# -- the compiled programs ----------------------------------------------------------------------


GRADIENTS = ("time_parallel", "batch")


class Programs:
    """The jitted programs of a search: projection, rescaling, batch values, and batch values
    with gradients. Built by `for_problem`; one compile per batch size.

    Generic over the objective, so a search can be checked on a problem with a known answer:
    d box coordinates in [0, 1], m waveform coefficients whose waveform on a grid is
    `c @ basis.T` (G, m), `project_coef` the waveform's projection onto max |.| <= 1,
    `values(z) -> (v, diverged)` on a (B, d + m) batch and `single(z1) -> (v, diverged)` on
    one point (differentiated per start when gradient = "time_parallel").
    """

    def __init__(self, d: int, m: int, basis, project_coef, values: Callable,
                 single: Callable | None = None, gradient: str = "time_parallel",
                 nominal_u: np.ndarray | None = None):
        validation.one_of(gradient, "gradient", GRADIENTS)
        self.d, self.m, self.nominal_u = d, m, nominal_u
        self.basis = jnp.asarray(basis)

        def project(z):
            u = jnp.clip(z[:, :d], 0.0, 1.0)
            if not m:
                return u
            c = z[:, d:]
            c = project_coef(c, 1.0, c @ self.basis.T)
            return jnp.concatenate([u, c], axis=1)

        def rescale(z):  # random points: the waveform scaled so that max |dbar| = D exactly
            if not m:
                return z
            c = z[:, d:]
            peak = jnp.max(jnp.abs(c @ self.basis.T), axis=1, keepdims=True)
            c = jnp.where(peak > 0, c / jnp.where(peak > 0, peak, 1.0), c)
            return jnp.concatenate([z[:, :d], c], axis=1)

        def total(z):
            v, bad = values(z)
            return jnp.sum(jnp.where(bad, 0.0, v)), (v, bad)

        def one(z1):
            v, bad = single(z1)
            return jnp.where(bad, 0.0, v), (v, bad)

        if gradient == "batch" or single is None:
            grad = jax.value_and_grad(total, has_aux=True)
        else:  # each start's own time-parallel gradient, vmapped over the starts
            grad = jax.vmap(jax.value_and_grad(one, has_aux=True))

        def value_and_grad(z):
            (_, (v, bad)), g = grad(z)
            return v, bad, g

        self.project = jax.jit(project)
        self.rescale = jax.jit(rescale)
        self.values = jax.jit(values)
        self.value_and_grad = jax.jit(value_and_grad)

    @classmethod
    def for_problem(cls, problem: Problem, gradient: str = "time_parallel") -> Programs:
        from dscjax.simulate import run

        p = problem
        n = p.n_steps
        basis, project_coef = np.zeros((1, 0)), None
        if p.m:
            grid = dist_mod.half_step_grid(p.t_final, p.dt)
            model = p.setup.plant.disturbance
            basis = np.stack([np.asarray(dist_mod.sample(
                dataclasses.replace(model, **{model.coefficients_name: e}), grid))
                for e in np.eye(p.m)], axis=1)  # (G, m): each unit coefficient on the grid
            project_coef = type(model).project_coefficients

        def values(z):
            traj = run(p.setup, p.dt, p.window_start, p.state_bound, n_steps=n, save_every=n,
                       overrides=p.overrides(z), solver=p.solver)
            return traj.metrics[p.metric], traj.diverged

        def single(z1):
            one = {path: v[0] for path, v in p.overrides(z1[None, :]).items()}
            traj = run(params.set_many(p.setup, one), p.dt, p.window_start, p.state_bound,
                       n_steps=n, save_every=n, solver=p.solver, gradient="time_parallel")
            return traj.metrics[p.metric], traj.diverged

        nominal_u = None
        if p.d:
            lo, hi = p.lows_highs()
            nominal = np.array([r.param.nominal(p.setup) for r in p.ranges])
            nominal_u = np.clip((nominal - lo) / (hi - lo), 0.0, 1.0)
        return cls(p.d, p.m, basis, project_coef, values, single, gradient, nominal_u)


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


def _gradient_step(prog, tr, seed, starts, lr0):
    """One iteration of projected gradient ascent for all starts: (z, values, diverged).

    The box coordinates u take Adam steps (per coordinate, lr box widths at most); the
    waveform coefficients a normalised gradient step (the largest moves by lr in units of D),
    since the waveform's constraint couples them; then the projection. Each start's lr grows
    by 1.2 after an improvement and halves after a loss."""
    d = prog.d
    x = tr.extra
    if "z" not in x:  # the first iteration: the nominal point (with a waveform) and random starts
        z = _random_points(prog, _rng(seed, "gradient", 0), starts)
        if prog.nominal_u is not None:
            z[0, :d] = prog.nominal_u
        x.update(z=z, m1=np.zeros_like(z[:, :d]), m2=np.zeros_like(z[:, :d]),
                 lr=np.full(starts, lr0), prev=np.full(starts, -np.inf), k=np.zeros(starts))
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
        from tuning.baselines import require_cma

        cma = require_cma()
        lower = [0.0] * prog.d + [-1.0] * prog.m
        upper = [1.0] * prog.d + [1.0] * prog.m
        x0 = np.concatenate([np.full(prog.d, 0.5), np.zeros(prog.m)])
        self.es = cma.CMAEvolutionStrategy(x0, 0.3, {"seed": seed + 1, "verbose": -9,
                                                     "popsize": popsize,
                                                     "bounds": [lower, upper]})
        hist = x.get("fitness", np.zeros((0, popsize)))
        for f in hist:
            asked = np.asarray(self.es.ask())
            self.es.tell(list(asked), list(f))
        if len(hist) and "last_x" in x and not np.array_equal(asked, x["last_x"]):
            raise ConfigError("--resume: CMA-ES could not replay its stored generations; use "
                              "--overwrite")
        self.x = x
        self.x.setdefault("fitness", np.zeros((0, popsize)))

    def step(self, prog):
        asked = np.asarray(self.es.ask())
        z = np.asarray(prog.project(jnp.asarray(asked)))
        v, bad = (np.asarray(a) for a in prog.values(jnp.asarray(z)))
        f = np.where(bad | ~np.isfinite(v), -1e30, np.asarray(v, dtype=np.float64))
        self.es.tell(list(asked), list(-f))  # cma minimises
        self.x["fitness"] = np.concatenate([self.x["fitness"], -f[None, :]])
        self.x["last_x"] = asked
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


def _check_run(problem: Problem, setup) -> tuple[float, bool, float | None, int, Any]:
    """`simulate` of one candidate with refinement: (value, diverged, t_diverged, level, traj)."""
    from dscjax.simulate import simulate

    traj = simulate(setup, problem.t_final, problem.dt, window_start=problem.window_start,
                    state_bound=problem.state_bound, throw=False, refine=problem.refine,
                    solver=problem.solver)
    bad = bool(traj.diverged)
    value = math.inf if bad else float(traj.metrics[problem.metric])
    return value, bad, (float(traj.t_diverged) if bad else None), int(traj.refinements), traj


def worst_case(problem: Problem, *, time_limit: float = 60.0, starts: int = DEFAULT_STARTS,
               methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
               lr: float = DEFAULT_LR, gradient: str = "time_parallel",
               out_dir: str | Path | None = None, resume: bool = False,
               progress: Callable[[str, Trace, float], None] | None = None) -> Result:
    """Search the worst case of `problem` with each method for `time_limit` seconds.

    Args:
        problem: from `make_problem`.
        time_limit: search seconds per method (compilation excluded, reported apart).
        starts: M, the starts of the gradient method, advanced together as one batch.
        methods: any of "gradient", "random", "cma" (the last two are the baselines).
        seed: every random draw is a function of (seed, method, iteration).
        batch: candidates per batch of the random and CMA-ES methods.
        lr: the initial step (in box widths and units of D) of the gradient method.
        gradient: "time_parallel" (each start's own time-parallel gradient, vmapped) or
            "batch" (reverse mode through the batch's checkpointed scan).
        out_dir: where each method's state is saved after every iteration (for `resume`).
        progress: called with (method, trace, time_limit) after every iteration.

    Returns:
        `Result`; its value is re-checked by `simulate` (with refinement) on the worst setup.

    Example:
        >>> import dscjax
        >>> from dscjax.ranges import parse_range
        >>> from dscjax.worst_case import make_problem, worst_case
        >>> pb = make_problem(dscjax.paper_example(), [parse_range("hysteresis.alpha=30%")],
        ...                   "fourier:2:0.5", t_final=0.5, dt=1e-3)
        >>> res = worst_case(pb, time_limit=1.0, starts=2, batch=4)  # doctest: +SKIP
    """
    for mth in methods:
        validation.one_of(mth, "--methods", METHODS)
    validation.integer(starts, "--starts", 1)
    validation.integer(batch, "batch", 1)
    if not (time_limit > 0):
        raise ConfigError(f"--time-limit must be > 0 (got {time_limit!r})")
    fp = files.digest({"problem": problem.fingerprint(), "seed": seed, "starts": starts,
                       "batch": batch, "lr": lr, "gradient": gradient})
    prog = Programs.for_problem(problem, gradient)
    traces = search(prog, time_limit=time_limit, starts=starts, methods=methods, seed=seed,
                    batch=batch, lr=lr, out_dir=out_dir, resume=resume, fingerprint=fp,
                    progress=progress)
    return _finish(problem, traces)


def search(prog: Programs, *, time_limit: float, starts: int = DEFAULT_STARTS,
           methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
           lr: float = DEFAULT_LR, out_dir: str | Path | None = None, resume: bool = False,
           fingerprint: str = "", progress: Callable | None = None) -> dict[str, Trace]:
    """Run each method on the programs for `time_limit` search seconds; {method: Trace}."""
    out = Path(out_dir) if out_dir is not None else None
    traces: dict[str, Trace] = {}
    for mth in methods:
        path = out / f"state_{mth}.npz" if out is not None else None
        tr = Trace.load(path, mth, fingerprint) if (resume and path is not None) else None
        tr = tr or Trace(mth)
        cma_es = _CMA(prog, seed, batch, tr.extra) if mth == "cma" else None
        first = True
        while tr.elapsed < time_limit:
            t0 = time.perf_counter()
            if mth == "gradient":
                z, v, bad = _gradient_step(prog, tr, seed, starts, lr)
            elif mth == "random":
                z, v, bad = _random_step(prog, tr, seed, batch)
            else:
                z, v, bad = cma_es.step(prog)
            seconds = time.perf_counter() - t0
            if first:
                # the first call of a session compiles: time the same call again
                t1 = time.perf_counter()
                jax.block_until_ready(prog.value_and_grad(jnp.asarray(z)) if mth == "gradient"
                                      else prog.values(jnp.asarray(z)))
                again = time.perf_counter() - t1
                tr.compile_s += max(seconds - again, 0.0)
                seconds = again
            first = False
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
        value, bad, t_bad, level, _ = _check_run(problem, setup)
        checked[key] = value
        score = (math.inf, -t_bad) if bad else (value, 0.0)
        if best is None or score > best[0]:
            best = (score, mth, z, setup, value, bad, t_bad, level)
    _, mth, z, setup, value, bad, t_bad, level = best
    nominal = problem.setup if problem.m == 0 else problem.setup.replace(
        plant=dataclasses.replace(problem.setup.plant, disturbance=None))
    nominal_value = _check_run(problem, nominal)[0]
    return Result(problem, value, np.asarray(z), mth, setup, bad, t_bad, level, traces,
                  nominal_value, {"rechecked": len(checked)})


__all__ = ["DEFAULT_METRIC", "DEFAULT_STARTS", "METHODS", "METRICS", "DisturbanceSpec",
           "Problem", "Programs", "Result", "Trace", "make_problem", "worst_case"]
