"""The tuning objective: a weighted sum of normalised tracking, effort and penalty terms per
plant, aggregated over a batch of plants, as one pure, differentiable function of the tuned
coordinates z.

Per plant (window W = [t0, T], every RK4 step, see `TuningMetrics`):

    J = w_linf  Linf~(e on W) / Linf(start)       smooth L-inf surrogate (log-sum-exp)
      + w_l2    L2(e on W)    / L2(start)
      + w_effort_l2  L2(u)    / L2(u)(start)
      + w_effort_max max~|u|  / max|u|(start)
      + w_effort_tv  TV(u)    / TV(u)(start)      total variation: ringing and chattering of u
      + w_u     relu(max~|u| / u_max - 1)^2       hard-ish bound on max|u|
      + w_tv    relu(TV(u) / tv_max - 1)^2         hard-ish bound on TV(u) = sum_k |u_(k+1) - u_k|
      + sum of requirement penalties (requirements.py)
    J = divergence_penalty                        if the trajectory diverged (finite, no NaN)

where "(start)" is the value for the start gains on the nominal plant, so that weights are
dimensionless and J(start) is about the sum of the active weights. The bounds u_max and
tv_max given as "start" are the start gains' figures on the nominal plant for every plant
(effort_bounds = "nominal"), or on each training plant its own (effort_bounds = "per_plant":
the start gains' max|u| and tv_max_factor x TV(u) simulated on that plant, see
`start_scales`). Over a batch of plants the loss is the mean, the CVaR at level a (the mean of
the worst ceil(a B) values) or the max.

Smooth surrogates (both running log-sum-exp accumulators, stable by a running max):

    Linf~ = (1/s) log( (1/|W|) integral_W exp(s |e|) dt ),   s = sharpness / Linf(start)
    max~|u| = (1/r) log( sum_k exp(r |u_k|) ),               r = u_sharpness / u_max

Linf~ lies between the mean and the max of |e| on W: its gradient is the softmax-weighted
gradient of the largest errors (the exact max's gradient goes to one sample only). max~|u|
is >= max|u| (by at most log(#samples near the peak)/r), so penalising it keeps the exact
max|u| below the bound.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import params, validation
from dscjax.closed_loop import Setup
from dscjax.metrics import step_weights
from dscjax.runspec import RunSpec
from dscjax.simulate import run
from dscjax.validation import ConfigError

AGGREGATES = ("mean", "cvar", "max")
# Where the "start" bounds on max|u| and TV(u) are measured: on the nominal plant (one bound
# for every plant) or on each training plant (its own bound).
EFFORT_BOUNDS = ("nominal", "per_plant")
# A bound "start" is the start gains' own figure, computed by another compiled program (the
# nominal one, not the batched one): rounding may put the start a few ulps over its own bound.
# Bounds are met within this relative tolerance; the report prints the exact margin.
BOUND_RTOL = 1e-9


class SmoothLinf(eqx.Module):
    """Linf~ of the tracking error on the window [t0, T] (module docstring), as a
    `dscjax.metrics.Running` reduction: a log-sum-exp with a running max m, s = sum w
    exp(x - m), invariant to the choice of m."""

    window_start: jax.Array  # () t0
    sharpness: jax.Array  # () s (1/units of e)
    n_steps: int = eqx.field(static=True)

    def init(self, dtype):
        z = jnp.zeros((), dtype)
        return {"m": z, "s": z, "w": z}

    def update(self, acc, k, t, y, obs, dt):
        e = y.x[0] - obs.yr
        _, w_win, in_win, _ = step_weights(k, t, dt, self.window_start, self.n_steps)
        x = self.sharpness * jnp.abs(e)
        m = jnp.where(in_win, jnp.maximum(acc["m"], x), acc["m"])
        # Before the window the exponent is masked, not just its weight: exp of a large error
        # before t0 would overflow and 0 * inf is NaN (double where).
        arg = jnp.where(in_win, x - m, 0.0)
        s = acc["s"] * jnp.exp(acc["m"] - m) + jnp.where(in_win, w_win * jnp.exp(arg), 0.0)
        return {"m": m, "s": s, "w": acc["w"] + w_win}

    def finalize(self, acc, t_final):
        return {"smooth_linf_window": (acc["m"] + _safe_log(acc["s"] / _pos(acc["w"])))
                / self.sharpness}


class SmoothMaxU(eqx.Module):
    """max~|u| (module docstring), as a `dscjax.metrics.Running` reduction."""

    sharpness: jax.Array  # () r (1/units of u)

    def init(self, dtype):
        z = jnp.zeros((), dtype)
        return {"m": z, "s": z}

    def update(self, acc, k, t, y, obs, dt):
        x = self.sharpness * jnp.abs(obs.u)
        m = jnp.maximum(acc["m"], x)
        return {"m": m, "s": acc["s"] * jnp.exp(acc["m"] - m) + jnp.exp(x - m)}

    def finalize(self, acc, t_final):
        return {"smooth_max_abs_u": (acc["m"] + _safe_log(acc["s"])) / self.sharpness}


class TuningMetrics(eqx.Module):
    """The running reductions tuning needs beyond `dscjax.metrics` (the `extra` of `run`): a
    `dscjax.metrics.Running` made of other ones, the smooth terms `SmoothLinf` and
    `SmoothMaxU` and every requirement, whose results are named req0_penalty, req0_met, ...

    Attributes:
        window_start: () t0 of the window [t0, T].
        e_sharpness: () s of the smooth L-inf (1/units of e).
        u_sharpness: () r of the smooth max|u| (1/units of u).
        requirements: tuple of `Requirement`s (their number and kinds are static).
        n_steps: static, N (for the trapezoid end weights).
    """

    window_start: jax.Array
    e_sharpness: jax.Array
    u_sharpness: jax.Array
    requirements: tuple = ()
    n_steps: int = eqx.field(static=True, default=1)

    def parts(self) -> tuple[tuple[str, Any], ...]:
        """(prefix of the result names, reduction) of every part."""
        reqs = tuple((f"req{i}_", dataclasses.replace(r, n_steps=self.n_steps))
                     for i, r in enumerate(self.requirements))
        return (("", SmoothLinf(self.window_start, self.e_sharpness, self.n_steps)),
                ("", SmoothMaxU(self.u_sharpness))) + reqs

    def init(self, dtype):
        return tuple(p.init(dtype) for _, p in self.parts())

    def update(self, acc, k, t, y, obs, dt):
        return tuple(p.update(a, k, t, y, obs, dt)
                     for (_, p), a in zip(self.parts(), acc, strict=True))

    def finalize(self, acc, t_final):
        out = {}
        for (prefix, p), a in zip(self.parts(), acc, strict=True):
            out |= {prefix + k: v for k, v in p.finalize(a, t_final).items()}
        return out


def _pos(x):
    return jnp.maximum(x, jnp.finfo(jnp.result_type(x)).tiny)


def _safe_log(x):
    ok = x > 0
    return jnp.where(ok, jnp.log(jnp.where(ok, x, 1.0)), -jnp.inf)


@dataclasses.dataclass(frozen=True)
class ObjectiveSpec:
    """Weights and settings of the per-plant objective (the [tuning.objective] table)."""

    linf: float = 1.0
    l2: float = 0.0
    effort_l2: float = 0.0
    effort_max: float = 0.0
    effort_tv: float = 0.0
    u_max: float | str | None = "start"
    u_max_weight: float = 100.0
    # The deployable default: TV(u) <= tv_max_factor x the start gains' TV(u) on the nominal
    # plant ("start"), an absolute number, or "none" (the old tracking-only problem).
    tv_max: float | str | None = "start"
    tv_max_factor: float = 1.5
    tv_max_weight: float = 100.0
    # the deployable constraint (tuning.sample_time): the loop with the controller sampled
    # keeps its windowed L-inf within sampled_factor x the continuous loop's, per plant
    sampled_factor: float = 2.0
    sampled_weight: float = 100.0
    # "nominal": the "start" bounds are the start gains' figures on the nominal plant, for
    # every plant; "per_plant": each training plant's own (a plant that needs more effort than
    # the nominal one, e.g. a worst case with its disturbance, is bounded by what the start
    # gains spend on it)
    effort_bounds: str = "nominal"
    sharpness: float = 50.0
    u_sharpness: float = 300.0
    divergence_penalty: float = 1000.0
    window_start: float | None = None

    def validate(self, field: str = "tuning.objective") -> None:
        for name in ("linf", "l2", "effort_l2", "effort_max", "effort_tv", "u_max_weight",
                     "tv_max_weight", "sampled_weight"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"{field}.{name} must be a number >= 0 (got {v!r})")
        if self.linf + self.l2 + self.effort_l2 + self.effort_max + self.effort_tv == 0:
            raise ConfigError(f"{field}: every weight is 0 (set linf, l2, effort_l2, "
                              f"effort_max or effort_tv > 0)")
        for name in ("sharpness", "u_sharpness", "divergence_penalty", "tv_max_factor",
                     "sampled_factor"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{field}.{name} must be a number > 0 (got {v!r})")
        u = self.u_max
        if not (u is None or u == "start" or (isinstance(u, int | float) and not isinstance(
                u, bool) and math.isfinite(u) and u > 0)):
            raise ConfigError(f"{field}.u_max must be a number > 0, \"start\" (the start gains' "
                              f"max|u| on the nominal plant) or \"none\" (got {u!r})")
        v = self.tv_max
        if not (v is None or v == "start" or (isinstance(v, int | float) and not isinstance(
                v, bool) and math.isfinite(v) and v > 0)):
            raise ConfigError(f"{field}.tv_max must be a number > 0, \"start\" (tv_max_factor "
                              f"x the start gains' TV(u) on the nominal plant) or \"none\" "
                              f"(got {v!r})")
        validation.one_of(self.effort_bounds, f"{field}.effort_bounds", EFFORT_BOUNDS)


@dataclasses.dataclass(frozen=True)
class Scales:
    """The start gains' figures on the nominal plant, used to normalise the terms, and the
    bounds: on the nominal plant (u_max, tv_max) and, with effort_bounds = "per_plant", on
    each plant of the objective's training batch (u_max_train, tv_max_train: (B,) float64)."""

    linf: float
    l2: float
    l2_u: float
    max_u: float
    u_max: float | None  # the bound on max|u| (None: no bound)
    tv_u: float = 1.0
    tv_max: float | None = None  # the bound on TV(u) (None: no bound)
    # per training plant (None: u_max / tv_max for every plant); only for the objective's own
    # training batch: any other batch (held-out plants, the nominal plant) gets the nominal ones
    u_max_train: np.ndarray | None = dataclasses.field(default=None, compare=False)
    tv_max_train: np.ndarray | None = dataclasses.field(default=None, compare=False)
    # training plants on which the start gains diverge: they keep the nominal bounds
    n_train_fallback: int = 0

    @property
    def per_plant(self) -> bool:
        return self.u_max_train is not None or self.tv_max_train is not None

    def bounds(self, train: bool, tile: int = 1) -> tuple:
        """(bound on max|u|, bound on TV(u)) of a batch: the training batch's own per plant
        if `train` (repeated `tile` times, as a batch of candidates x training plants lays
        them out), else the nominal ones; None where there is no bound."""
        out = []
        for nominal, per in ((self.u_max, self.u_max_train), (self.tv_max, self.tv_max_train)):
            out.append(np.tile(per, tile) if train and per is not None else nominal)
        return tuple(out)


def simulate_metrics(setup: Setup, sim: RunSpec, extra: TuningMetrics | None,
                     overrides: Mapping[str, Any] | None = None,
                     checkpoint_every: int | None = None) -> tuple[dict, jax.Array]:
    """(metrics, diverged) of one plant (or a batch with overrides), traceable. `sim` keeps
    only the first and last points (save_every = n_steps); `checkpoint_every` replaces the
    checkpoint segment of a batch's reverse-mode gradient."""
    if checkpoint_every is not None:
        sim = dataclasses.replace(sim, gradient=dataclasses.replace(sim.gradient,
                                                                    every=checkpoint_every))
    traj = run(setup, sim, overrides=dict(overrides) if overrides else None, extra=extra)
    return traj.metrics, traj.diverged


def extra_for(spec: ObjectiveSpec, scales: Scales, sim: RunSpec, requirements=(),
              dtype=jnp.float64) -> TuningMetrics:
    u_ref = scales.u_max if scales.u_max is not None else scales.max_u
    return TuningMetrics(
        window_start=jnp.asarray(sim.window_start, dtype),
        e_sharpness=jnp.asarray(spec.sharpness / scales.linf, dtype),
        u_sharpness=jnp.asarray(spec.u_sharpness / u_ref, dtype),
        requirements=tuple(requirements), n_steps=sim.n_steps)


def plant_loss(metrics: Mapping[str, jax.Array], diverged, spec: ObjectiveSpec, scales: Scales,
               n_requirements: int, bounds: tuple | None = None
               ) -> tuple[jax.Array, dict[str, jax.Array]]:
    """J of one plant (or elementwise over a batch) and its weighted terms. `bounds`: (bound
    on max|u|, bound on TV(u)), scalars or one per plant (`Scales.bounds`); default the
    nominal ones."""
    u_bound, tv_bound = bounds if bounds is not None else (scales.u_max, scales.tv_max)
    u_bound, tv_bound = _like(u_bound, metrics["max_abs_u"]), _like(tv_bound, metrics["tv_u"])
    terms = {}
    if spec.linf:
        terms["linf"] = spec.linf * metrics["smooth_linf_window"] / scales.linf
    if spec.l2:
        terms["l2"] = spec.l2 * metrics["l2_error_window"] / scales.l2
    if spec.effort_l2:
        terms["effort_l2"] = spec.effort_l2 * metrics["l2_u"] / scales.l2_u
    if spec.effort_max:
        terms["effort_max"] = spec.effort_max * metrics["smooth_max_abs_u"] / scales.max_u
    if spec.effort_tv:
        terms["effort_tv"] = spec.effort_tv * metrics["tv_u"] / scales.tv_u
    if u_bound is not None and spec.u_max_weight:
        terms["u_bound"] = spec.u_max_weight * jnp.maximum(
            metrics["smooth_max_abs_u"] / u_bound - 1.0, 0.0) ** 2
    if tv_bound is not None and spec.tv_max_weight:
        terms["tv_bound"] = spec.tv_max_weight * jnp.maximum(
            metrics["tv_u"] / tv_bound - 1.0, 0.0) ** 2
    for i in range(n_requirements):
        terms[f"req{i}"] = metrics[f"req{i}_penalty"]
    if SAMPLED in metrics and spec.sampled_weight:
        ratio = metrics[SAMPLED] / (spec.sampled_factor * metrics["smooth_linf_window"])
        terms["sampled"] = spec.sampled_weight * jnp.maximum(ratio - 1.0, 0.0) ** 2
    total = sum(terms.values())
    # A diverged plant (in either loop) costs a large constant: finite, so that means and
    # CVaRs stay usable. Anything else non-finite stays NaN/inf, so that the search ranks it
    # last instead of silently seeing a flat penalty.
    total = jnp.where(diverged | metrics.get("sampled_diverged", False),
                      spec.divergence_penalty, total)
    return total, terms


def feasible_plants(metrics: Mapping[str, jax.Array], diverged, bounds: tuple,
                    n_requirements: int, spec: ObjectiveSpec) -> jax.Array:
    """Each plant's feasibility, exactly: no divergence, the effort bounds, every requirement
    met and, with the deployable constraint, the sampled loop within sampled_factor x the
    continuous loop's windowed L-inf."""
    ok = ~diverged & within_bounds(metrics, bounds)
    for i in range(n_requirements):
        ok = ok & (metrics[f"req{i}_met"] > 0)
    if SAMPLED in metrics:
        ok = ok & ~metrics["sampled_diverged"] & within(
            metrics["sampled_linf_window"], spec.sampled_factor * metrics["linf_error_window"])
    return ok


# the metrics of the sampled loop of the deployable constraint (`loop_metrics`)
SAMPLED = "sampled_smooth_linf_window"


def loop_metrics(objective, setup: Setup, overrides=None, checkpoint_every=None
                 ) -> tuple[dict, jax.Array]:
    """(metrics, diverged) of the objective's loop on `setup` (a batch with `overrides`), and,
    with the deployable constraint (`objective.sampled`, the same loop with the controller
    sampled), that loop's windowed L-inf exact and smooth and its divergence, as
    sampled_linf_window, sampled_smooth_linf_window and sampled_diverged. Traceable."""
    m, div = simulate_metrics(setup, objective.sim, objective.extra(), overrides,
                              checkpoint_every)
    if objective.sampled is not None:
        e = objective.extra()
        smooth = SmoothLinf(e.window_start, e.e_sharpness, objective.sampled.n_steps)
        ms, div_s = simulate_metrics(setup, objective.sampled, smooth, overrides,
                                     checkpoint_every)
        m = m | {"sampled_linf_window": ms["linf_error_window"],
                 SAMPLED: ms["smooth_linf_window"], "sampled_diverged": div_s}
    return m, div


def within(value, bound):
    """value <= bound, up to BOUND_RTOL (relative)."""
    return value <= bound * (1.0 + BOUND_RTOL)


def within_bounds(metrics: Mapping[str, jax.Array], bounds: tuple) -> jax.Array:
    """Every effort bound of `bounds` (`Scales.bounds`) met by each plant's exact figures."""
    ok = jnp.ones(jnp.shape(metrics["max_abs_u"]), bool)
    for key, bound in zip(("max_abs_u", "tv_u"), bounds, strict=True):
        if bound is not None:
            ok = ok & within(metrics[key], _like(bound, metrics[key]))
    return ok


def _like(bound, x):
    """A per-plant bound (a float64 array) in the dtype of the figures `x` it bounds, as a
    scalar bound (a weakly typed Python float) is: float32 runs stay float32."""
    if bound is None or np.ndim(bound) == 0:
        return bound
    return jnp.asarray(bound, jnp.result_type(x))


def _max_measured(values: jax.Array, diverged) -> jax.Array:
    """max over the plants that did not diverge; NaN if every one did."""
    top = jnp.max(jnp.where(diverged, -jnp.inf, values))
    return jnp.where(jnp.all(diverged), jnp.nan, top)


def n_worst(level: float, n: int) -> int:
    """How many of n plants CVaR at `level` averages: the worst ceil(level n), at least 1."""
    return max(1, int(math.ceil(level * n - 1e-9)))


def aggregate(values: jax.Array, how: str, level: float = 1.0) -> jax.Array:
    """Mean, CVaR at `level` (mean of the worst ceil(level B) values) or max over axis 0."""
    if values.ndim == 0:
        return values
    if how == "mean":
        return jnp.mean(values)
    if how == "max":
        return jnp.max(values)
    if how == "cvar":
        return jnp.mean(jax.lax.top_k(values, n_worst(level, values.shape[0]))[0])
    raise ValueError(f"aggregate must be one of {AGGREGATES} (got {how!r})")


# one compilation per setup structure and run structure (adversarial tuning builds a problem
# a round)
_start_metrics = jax.jit(functools.partial(simulate_metrics, extra=None))


def start_scales(setup: Setup, sim: RunSpec, spec: ObjectiveSpec,
                 train: Mapping[str, Any] | None = None) -> Scales:
    """Figures of the start gains on the nominal plant (raises if they diverge there); with
    effort_bounds = "per_plant" and a training batch `train`, also the "start" bounds of
    each training plant: the start gains' exact max|u| and tv_max_factor x TV(u) (every RK4
    step) simulated on that plant, once (a plant on which the start diverges keeps the
    nominal bounds)."""
    metrics, diverged = _start_metrics(setup, sim)
    if bool(diverged):
        raise ConfigError("the start gains diverge on the nominal plant; tuning needs a "
                          "stable start (revise the gains, dt or tau)")
    m = {k: float(v) for k, v in metrics.items()}
    u_max = spec.u_max
    if u_max == "start":
        u_max = m["max_abs_u"]
    tv_max = spec.tv_max
    if tv_max == "start":
        tv_max = spec.tv_max_factor * m["tv_u"]
    for name, key in (("linf", "linf_error_window"), ("l2", "l2_error_window"),
                      ("effort_l2", "l2_u"), ("effort_max", "max_abs_u"), ("effort_tv", "tv_u")):
        if getattr(spec, name) and not m[key] > 0:
            raise ConfigError(f"tuning.objective.{name}: the start gains give {key} = "
                              f"{m[key]:g}, which cannot normalise the term")
    tiny = 1e-300
    u_max = None if u_max is None else float(u_max)
    tv_max = None if tv_max is None else float(tv_max)
    per: dict[str, Any] = {}
    if spec.effort_bounds == "per_plant" and train and "start" in (spec.u_max, spec.tv_max):
        mb, div = jax.device_get(_start_metrics(setup, sim, overrides=dict(train)))
        div = np.asarray(div, bool)
        for key, name, factor, nominal in (("max_abs_u", "u_max", 1.0, u_max),
                                           ("tv_u", "tv_max", spec.tv_max_factor, tv_max)):
            if getattr(spec, name) == "start":
                v = factor * np.asarray(mb[key], np.float64)
                # a figure of 0 (no effort at all on that plant) would leave no room at all
                per[f"{name}_train"] = np.where(div | ~(v > 0), nominal, v)
        per["n_train_fallback"] = int(div.sum())
    return Scales(linf=max(m["linf_error_window"], tiny), l2=max(m["l2_error_window"], tiny),
                  l2_u=max(m["l2_u"], tiny), max_u=max(m["max_abs_u"], tiny),
                  u_max=u_max, tv_u=max(m["tv_u"], tiny), tv_max=tv_max, **per)


@dataclasses.dataclass(frozen=True, eq=False)
class Objective:
    """loss(z) for a Selection over a fixed setup and (optional) batch of plants.

    Hashable by identity: it is a static argument of the jitted tuning step. Every number in
    it that changes between runs (setup, batch) is a closed-over constant of that step.
    """

    setup: Setup
    selection: Any
    spec: ObjectiveSpec
    sim: RunSpec  # how every plant is simulated (metrics only: save_every = n_steps)
    scales: Scales
    requirements: tuple = ()
    overrides: Mapping[str, Any] | None = None  # the training batch, {path: (B, ...)}
    aggregate: str = "mean"
    cvar_level: float = 1.0
    # the deployable constraint's loop: `sim` with the controller sampled (None: none)
    sampled: RunSpec | None = None
    # Programs compiled for this objective (the tuning step per update rule: `runner`); they
    # live and die with it.
    compiled: dict = dataclasses.field(default_factory=dict, init=False, repr=False,
                                       compare=False)

    @property
    def batch_size(self) -> int:
        return 1 if not self.overrides else int(np.shape(next(iter(self.overrides.values())))[0])

    def extra(self) -> TuningMetrics:
        dtype = jnp.result_type(self.setup.plant.x0)
        return extra_for(self.spec, self.scales, self.sim, self.requirements, dtype)

    def bounds(self, overrides=None) -> tuple:
        """(bound on max|u|, bound on TV(u)) of the plants of `overrides` (None: the training
        batch, with its per-plant bounds if it has them)."""
        return self.scales.bounds(train=overrides is None and bool(self.overrides))

    def evaluate(self, z, overrides=None, checkpoint_every=None):
        """(loss, aux) at z; aux has the terms (aggregated as the loss is), the exact metrics
        and the feasibility of the bounds (all plants)."""
        loss, aux, _ = self._evaluate(z, overrides, checkpoint_every)
        return loss, aux

    def _evaluate(self, z, overrides=None, checkpoint_every=None):
        """(loss, aux, every plant's J)."""
        setup = self.selection.apply(self.setup, z)
        ov = self.overrides if overrides is None else overrides
        metrics, diverged = loop_metrics(self, setup, ov, checkpoint_every)
        bounds = self.bounds(overrides)
        per_plant, terms = plant_loss(metrics, diverged, self.spec, self.scales,
                                      len(self.requirements), bounds)
        loss = aggregate(per_plant, self.aggregate, self.cvar_level)
        feasible = feasible_plants(metrics, diverged, bounds, len(self.requirements),
                                   self.spec)
        aux = {
            "terms": {k: aggregate(jnp.where(diverged, 0.0, v), self.aggregate,
                                   self.cvar_level) for k, v in terms.items()},
            # reported, not differentiated: over the plants that did not diverge (a diverged
            # plant's metrics were not measured), NaN if none did
            "linf_window": _max_measured(metrics["linf_error_window"], diverged),
            "max_abs_u": _max_measured(metrics["max_abs_u"], diverged),
            "tv_u": _max_measured(metrics["tv_u"], diverged),
            "n_diverged": jnp.sum(jnp.asarray(diverged, jnp.int32)),
            "feasible": jnp.all(feasible),
        }
        return loss, aux, per_plant

    def value_and_grad_plants(self, z):
        """((loss, aux), d loss / d z) over the training batch, the gradient taken plant by
        plant (`gradient = "plants"`): the aggregate's gradient is the mean of the gradients
        of the plants it weighs (mean: all B; cvar: the worst ceil(level B), as `top_k` picks
        them; max: the worst), so only those are simulated again, each alone, and
        differentiated by the one-trajectory time-parallel linearisation (vmapped over them).
        Exact, as `jax.grad` of `evaluate` is (where the worst plants are not tied); the loss
        and aux are `evaluate`'s, from one batched forward run of all the plants."""
        loss, aux, per = self._evaluate(jax.lax.stop_gradient(z))
        n = self.batch_size
        if self.aggregate == "mean" or not self.overrides:
            idx = jnp.arange(n)
        else:
            k = 1 if self.aggregate == "max" else n_worst(self.cvar_level, n)
            idx = jax.lax.top_k(per, k)[1]
        train = {p: jnp.asarray(v) for p, v in (self.overrides or {}).items()}
        bounds = self.bounds()
        dtype = jnp.result_type(self.setup.plant.x0)  # per-plant bounds as `_like` casts them
        n_req = len(self.requirements)

        def one(z_, i):
            setup = params.set_many(self.selection.apply(self.setup, z_),
                                    {p: v[i] for p, v in train.items()})
            metrics, diverged = loop_metrics(self, setup)
            b = tuple(None if v is None else jnp.asarray(v, dtype)[i] if np.ndim(v) else v
                      for v in bounds)
            return plant_loss(metrics, diverged, self.spec, self.scales, n_req, b)[0]

        grads = jax.vmap(jax.grad(one), in_axes=(None, 0))(z, idx)
        return (loss, aux), jax.tree.map(lambda g: jnp.mean(g, axis=0), grads)

    def per_plant(self, z, overrides=None):
        """Every plant's J, divergence flag and metrics (exact and smooth) at z: leaves of
        shape (B,) with a batch, () without."""
        setup = self.selection.apply(self.setup, z)
        ov = self.overrides if overrides is None else overrides
        metrics, diverged = loop_metrics(self, setup, ov)
        per_plant, _ = plant_loss(metrics, diverged, self.spec, self.scales,
                                  len(self.requirements), self.bounds(overrides))
        return {"loss": per_plant, "diverged": diverged, **metrics}


COMBINE = ("mean", "max")


@dataclasses.dataclass(frozen=True, eq=False)
class Combined:
    """loss(z) = mean or max over several `Objective`s of their losses, for one tuned
    `Selection`: robust tuning over plants whose STRUCTURE differs (e.g. one batch per
    hysteresis kind: a kind is a class, static, so one batch cannot mix them). Each member
    keeps its own setup, batch, aggregate and start scales, so each member's loss is about 1
    at the start gains and the members weigh alike. Evaluated in one traced function (one
    jitted step); its gradient is the members' (for "max": the worst member's).

    Hashable by identity, like `Objective`; `sim`, `spec`, `scales` and `requirements` are
    the first member's (the members share the tuning settings: see `runner.combine`)."""

    members: tuple[Objective, ...]
    how: str = "mean"
    compiled: dict = dataclasses.field(default_factory=dict, init=False, repr=False,
                                       compare=False)

    def __post_init__(self):
        if self.how not in COMBINE:
            raise ConfigError(f"combine must be one of {', '.join(COMBINE)} (got {self.how!r})")
        if not self.members:
            raise ConfigError("combine needs at least one objective")

    # the members share the tuning settings (`runner.combine`): read off the first one
    sim = property(lambda self: self.members[0].sim)
    spec = property(lambda self: self.members[0].spec)
    scales = property(lambda self: self.members[0].scales)
    requirements = property(lambda self: self.members[0].requirements)
    sampled = property(lambda self: self.members[0].sampled)

    @property
    def batch_size(self) -> int:
        return sum(m.batch_size for m in self.members)

    def _reduce(self, values):
        v = jnp.stack(values)
        return jnp.mean(v) if self.how == "mean" else jnp.max(v)

    def evaluate(self, z, overrides=None, checkpoint_every=None):
        """(loss, aux) as `Objective.evaluate`'s: terms combined as the loss is, the largest
        L-inf and max|u| measured, the diverged plants summed, feasible if every member is."""
        if overrides is not None:
            raise ValueError("a combined objective evaluates its members' own batches")
        out = [m.evaluate(z, checkpoint_every=checkpoint_every) for m in self.members]
        auxes = [a for _, a in out]
        aux = {
            "terms": {k: self._reduce([a["terms"][k] for a in auxes]) for k in auxes[0]["terms"]},
            "linf_window": jnp.nanmax(jnp.stack([a["linf_window"] for a in auxes])),
            "max_abs_u": jnp.nanmax(jnp.stack([a["max_abs_u"] for a in auxes])),
            "n_diverged": sum(a["n_diverged"] for a in auxes),
            "feasible": jnp.all(jnp.stack([a["feasible"] for a in auxes])),
        }
        return self._reduce([loss for loss, _ in out]), aux

