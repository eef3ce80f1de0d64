"""The tuning objective: per plant, a weighted sum of terms normalised by the start gains'
figures on the nominal plant (window W = [t0, T], every RK4 step; docs/tuning.md), aggregated
over a batch of plants (mean, CVaR at level a: the mean of the worst ceil(a B), or max):

    J = w_linf Linf~(e on W)/(start) + w_l2 L2(e on W)/(start) + w_effort_l2 L2(u)/(start)
      + w_effort_max max~|u|/(start) + w_effort_tv TV(u)/(start)
      + w_u relu(max~|u|/u_max - 1)^2 + w_tv relu(TV(u)/tv_max - 1)^2 + requirement penalties
      + sum over the check loops c of
        w_c [relu(Linf~_c/(f_c Linf~) - 1)^2 + relu(max~|u|_c/(g_c u_max) - 1)^2
             + relu(TV(u)_c/(h_c tv_max) - 1)^2]
    J = divergence_penalty if the trajectory diverged in any loop (finite, no NaN)

The check loops (`CheckLoop`) are the loop tuned with one thing changed that the gains must
survive: `dscjax tune`'s other discretisation of the sampled controller (f = 2, g = h = 1) and
its input delayed one sample (f = 2, h = 1.5, max|u| unchecked).

Linf~ = (1/s) log((1/|W|) integral_W exp(s |e|) dt) and max~|u| = (1/r) log(sum_k exp(r |u_k|))
are running log-sum-exps (stable by a running max): Linf~'s gradient is the softmax-weighted
one of the largest errors, and max~|u| >= max|u|, so penalising it keeps the exact max|u| under
its bound. Bounds "start" are the start gains' figures over the whole horizon [0, T] (the
transient included) on the nominal plant, or on each training plant its own (effort_bounds =
"per_plant", `start_scales`).

e is measured against the reference the controller tracks: a controller whose initialisation
shifts it (the DSC's init = "linf": y_r(0) moved to x_1(0), the offset decaying) is tuned on
that error; `UserError` measures the same figures against the config's own y_r beside it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from types import SimpleNamespace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import params
from dscjax.closed_loop import SCHEME, Setup
from dscjax.runspec import RunSpec, discretisation, loop_words
from dscjax.simulate import DivergenceError, divergence_report, run
from dscjax.validation import ConfigError
from tuning.config import AGGREGATES, ObjectiveSpec
from tuning.reductions import TuningMetrics, UserError, shifted_reference

# a bound "start" is the start's own figure from another compiled program: rounding may put
# the start a few ulps over it
BOUND_RTOL = 1e-9


@dataclasses.dataclass(frozen=True)
class Scales:
    """The start gains' figures on the nominal plant (the terms' normalisation) and the bounds,
    with effort_bounds = "per_plant" also per training plant (u_max_train, tv_max_train)."""

    linf: float
    l2: float
    l2_u: float
    max_u: float
    u_max: float | None  # the bound on max|u| (None: no bound)
    tv_u: float = 1.0
    tv_max: float | None = None  # the bound on TV(u) (None: no bound)
    # (B,) float64 per training plant (None: the nominal bound); other batches get the nominal
    u_max_train: np.ndarray | None = dataclasses.field(default=None, compare=False)
    tv_max_train: np.ndarray | None = dataclasses.field(default=None, compare=False)
    # training plants on which the start gains diverge: they keep the nominal bounds
    n_train_fallback: int = 0
    # every figure of the start gains on the nominal plant (the loop tuned): the effort on the
    # window beside the bounds' [0, T], the error against the config's reference
    start: dict = dataclasses.field(default_factory=dict, compare=False)

    @property
    def per_plant(self) -> bool:
        return self.u_max_train is not None or self.tv_max_train is not None

    def bounds(self, train: bool, tile: int = 1) -> tuple:
        """(bound on max|u|, bound on TV(u)) of a batch (None: no bound): the training batch's
        own if `train` (tiled `tile` times: candidates x training plants), else the nominal."""
        return tuple(np.tile(per, tile) if train and per is not None else nominal
                     for nominal, per in ((self.u_max, self.u_max_train),
                                          (self.tv_max, self.tv_max_train)))


def simulate_metrics(setup: Setup, sim: RunSpec, extra: TuningMetrics | None,
                     overrides: Mapping[str, Any] | None = None,
                     checkpoint_every: int | None = None) -> tuple[dict, jax.Array]:
    """(metrics, diverged) of one plant (or a batch with overrides), traceable;
    `checkpoint_every` replaces the checkpoint segment of the reverse-mode gradient."""
    if checkpoint_every is not None:
        sim = dataclasses.replace(sim, gradient=dataclasses.replace(sim.gradient,
                                                                    every=checkpoint_every))
    traj = run(setup, sim, overrides=dict(overrides) if overrides else None, extra=extra)
    return traj.metrics, traj.diverged


def plant_loss(metrics: Mapping[str, jax.Array], diverged, spec: ObjectiveSpec, scales: Scales,
               n_requirements: int, bounds: tuple | None = None, checks: tuple = ()
               ) -> tuple[jax.Array, dict[str, jax.Array]]:
    """J of one plant (or elementwise over a batch) and its weighted terms; `bounds` as
    `Scales.bounds` gives them (default the nominal ones); `checks` the `CheckLoop`s whose
    metrics `loop_metrics` added."""
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
    for c in checks:
        terms[c.name] = c.penalty(metrics, u_bound, tv_bound)
    total = sum(terms.values())
    # a diverged plant (either loop) costs a finite constant, so that means and CVaRs stay
    # usable; any other non-finite J stays so, and the search ranks it last
    for c in checks:
        diverged = diverged | metrics[f"{c.name}_diverged"]
    total = jnp.where(diverged, spec.divergence_penalty, total)
    return total, terms


def feasible_plants(metrics: Mapping[str, jax.Array], diverged, bounds: tuple,
                    n_requirements: int, checks: tuple = ()) -> jax.Array:
    """Each plant's exact feasibility: no divergence, the effort bounds, the requirements and
    each check loop's constraints met."""
    ok = ~diverged & within_bounds(metrics, bounds)
    for i in range(n_requirements):
        ok = ok & (metrics[f"req{i}_met"] > 0)
    for c in checks:
        ok = ok & c.met(metrics, bounds)
    return ok


@dataclasses.dataclass(frozen=True)
class CheckLoop:
    """A loop the gains must also hold in: `sim`, the loop tuned with one thing changed. Its
    windowed L-inf at most `linf_factor` x the loop tuned's, its max|u| at most `u_factor` x
    the max|u| bound and its TV(u) at most `tv_factor` x the TV(u) bound (None: not checked);
    `weight` of its penalty, the setting tuning.objective.`weight_key`; its metrics in
    `loop_metrics` are prefixed `name`_; `label` says the loop in the report. `smooth`: its
    figures have slopes in the gains (the report's elasticities); a loop at the edge of a
    limit cycle has tangents that are not."""

    name: str
    sim: RunSpec
    linf_factor: float
    u_factor: float | None
    tv_factor: float | None
    weight: float
    weight_key: str
    label: str
    smooth: bool = True

    def bounded(self, bounds: tuple) -> list[tuple[str, str, Any, float]]:
        """(what, metric key, bound, factor) of each effort bound checked in this loop."""
        return [(what, key, b, f) for what, key, b, f in
                zip(("max|u|", "TV(u)"), ("max_abs_u", "tv_u"), bounds,
                    (self.u_factor, self.tv_factor), strict=True)
                if b is not None and f is not None]

    def penalty(self, m: Mapping[str, jax.Array], u_bound, tv_bound) -> jax.Array:
        p = self.name
        ratio = m[f"{p}_smooth_linf_window"] / (self.linf_factor * m["smooth_linf_window"])
        out = jnp.maximum(ratio - 1.0, 0.0) ** 2
        smooth = {"max_abs_u": f"{p}_smooth_max_abs_u", "tv_u": f"{p}_tv_u"}
        for _, key, b, f in self.bounded((u_bound, tv_bound)):
            out = out + jnp.maximum(m[smooth[key]] / (f * b) - 1.0, 0.0) ** 2
        return self.weight * out

    def met(self, m: Mapping[str, jax.Array], bounds: tuple) -> jax.Array:
        p = self.name
        ok = ~m[f"{p}_diverged"] & within(m[f"{p}_linf_window"],
                                          self.linf_factor * m["linf_error_window"])
        for _, key, b, f in self.bounded(bounds):
            ok = ok & within(m[f"{p}_{key}"], f * _like(b, m[f"{p}_{key}"]))
        return ok


def check_loops(sim: RunSpec, spec) -> tuple[CheckLoop, ...]:
    """The loops a sampled loop's gains must also hold in: the other discretisation of the
    controller's states (an embedded engineer may advance them either way) and the input
    delayed `delay_samples` more samples (no limit cycle where the hardware is a sample late)."""
    if not sim.sampled:
        return ()
    out = []
    if spec.sampled_weight:
        # the scheme the loop tuned does not use
        other = dataclasses.replace(
            sim, discretisation=next(s for s in SCHEME.values() if s != sim.discretisation))
        out.append(CheckLoop("sampled", other, spec.sampled_factor, 1.0, 1.0,
                             spec.sampled_weight, "sampled_weight",
                             f"the states by {discretisation(other)}"))
    if spec.delay_samples and spec.delay_weight:
        d = sim.delay + spec.delay_samples
        out.append(CheckLoop("delayed", dataclasses.replace(sim, delay=d), spec.delay_factor,
                             None, spec.delay_tv_factor, spec.delay_weight, "delay_weight",
                             f"the input delayed {d} sample{'s' if d != 1 else ''}",
                             smooth=False))
    return tuple(out)


def loop_metrics(objective, setup: Setup, overrides=None, checkpoint_every=None
                 ) -> tuple[dict, jax.Array]:
    """(metrics, diverged) of the objective's loop on `setup` (a batch with `overrides`), and
    of each of its check loops c: c_linf_window, c_smooth_linf_window, c_diverged,
    c_max_abs_u, c_smooth_max_abs_u and c_tv_u. Traceable."""
    m, div = simulate_metrics(setup, objective.sim,
                              objective.extra(shifted_reference(setup, overrides)), overrides,
                              checkpoint_every)
    for c in objective.checks:
        e = objective.extra()
        smooth = TuningMetrics(e.window_start, e.e_sharpness, e.u_sharpness,
                               n_steps=c.sim.n_steps)
        mc, div_c = simulate_metrics(setup, c.sim, smooth, overrides, checkpoint_every)
        mc = mc | {"linf_window": mc["linf_error_window"], "diverged": div_c}
        m = m | {f"{c.name}_{k}": mc[k] for k in ("linf_window", "smooth_linf_window",
                                                 "max_abs_u", "smooth_max_abs_u", "tv_u",
                                                 "diverged")}
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
    """A per-plant bound (float64) in the dtype of the figures `x`: float32 runs stay float32."""
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


def _start_run(setup: Setup, sim: RunSpec, extra=None, overrides=None):
    """(metrics, `Status`) of the start gains: the status says when a diverged run did."""
    traj = run(setup, sim, overrides=dict(overrides) if overrides else None, extra=extra)
    return traj.metrics, traj.status


# one compilation per setup and run structure (adversarial tuning builds a problem a round)
_start_metrics = jax.jit(_start_run)


def start_scales(setup: Setup, sim: RunSpec, spec: ObjectiveSpec,
                 train: Mapping[str, Any] | None = None) -> Scales:
    """The start gains' `Scales` (DivergenceError, which run and when, if they diverge on the
    nominal plant); with effort_bounds = "per_plant" and a batch `train`, each training
    plant's "start" bounds (a plant on which the start diverges keeps the nominal ones)."""
    reference = shifted_reference(setup)
    user = None if reference is None else UserError(  # reported beside, not tuned
        reference, jnp.asarray(sim.window_start, jnp.result_type(setup.plant.x0)), sim.n_steps)
    metrics, status = _start_metrics(setup, sim.program(), user)
    if int(status.code) != 0:
        raise start_divergence(sim, status)
    m = {k: float(v) for k, v in metrics.items()}

    def bound(v, start):  # "start", a number or None
        return start if v == "start" else None if v is None else float(v)

    u_max = bound(spec.u_max, m["max_abs_u"])
    tv_max = bound(spec.tv_max, spec.tv_max_factor * m["tv_u"])
    for name, key in (("linf", "linf_error_window"), ("l2", "l2_error_window"),
                      ("effort_l2", "l2_u"), ("effort_max", "max_abs_u"), ("effort_tv", "tv_u")):
        if getattr(spec, name) and not m[key] > 0:
            raise ConfigError(f"tuning.objective.{name}: the start gains give {key} = "
                              f"{m[key]:g}, which cannot normalise the term")
    tiny = 1e-300
    per: dict[str, Any] = {}
    if spec.effort_bounds == "per_plant" and train and "start" in (spec.u_max, spec.tv_max):
        mb, status = jax.device_get(_start_metrics(setup, sim.program(),
                                                   overrides=dict(train)))
        div = np.asarray(status.code) != 0
        for key, name, factor, nominal in (("max_abs_u", "u_max", 1.0, u_max),
                                           ("tv_u", "tv_max", spec.tv_max_factor, tv_max)):
            if getattr(spec, name) == "start":
                v = factor * np.asarray(mb[key], np.float64)
                # a figure of 0 (no effort at all on that plant) would leave no room at all
                per[f"{name}_train"] = np.where(div | ~(v > 0), nominal, v)
        per["n_train_fallback"] = int(div.sum())
    return Scales(linf=max(m["linf_error_window"], tiny), l2=max(m["l2_error_window"], tiny),
                  l2_u=max(m["l2_u"], tiny), max_u=max(m["max_abs_u"], tiny),
                  u_max=u_max, tv_u=max(m["tv_u"], tiny), tv_max=tv_max, start=m, **per)


def start_divergence(sim: RunSpec, status) -> DivergenceError:
    """The error of start gains that diverge on the nominal plant (their run's `Status`):
    which run, when and how, as `divergence_report` says it."""
    step = int(status.step)
    seen = SimpleNamespace(status=status, t_diverged=step * float(sim.dt) if step >= 0
                           else np.inf)
    how = divergence_report(seen, float(sim.state_bound))[0].split(";")[0]
    return DivergenceError(f"the start gains diverge on the nominal plant in the loop tuned "
                           f"({loop_words(sim)}): the run {how.removeprefix('the trajectory ')}; "
                           f"tuning needs a stable start (revise the gains, dt or tau)", None)


@dataclasses.dataclass(frozen=True, eq=False)
class Objective:
    """loss(z) for a Selection over a fixed setup and (optional) batch of plants; hashable by
    identity (a static argument of the jitted step, its numbers closed-over constants)."""

    setup: Setup
    selection: Any
    spec: ObjectiveSpec
    sim: RunSpec  # how every plant is simulated (metrics only: save_every = n_steps)
    scales: Scales
    requirements: tuple = ()
    overrides: Mapping[str, Any] | None = None  # the training batch, {path: (B, ...)}
    aggregate: str = "mean"
    cvar_level: float = 1.0
    # the loops the gains must also hold in (`CheckLoop`)
    checks: tuple = ()
    # the programs compiled for this objective live and die with it
    compiled: dict = dataclasses.field(default_factory=dict, init=False, repr=False,
                                       compare=False)

    @property
    def batch_size(self) -> int:
        return 1 if not self.overrides else int(np.shape(next(iter(self.overrides.values())))[0])

    def extra(self, reference=None) -> TuningMetrics:
        """The tuning's reductions; with `reference` (`shifted_reference`) the error against
        it too."""
        dtype, sc = jnp.result_type(self.setup.plant.x0), self.scales
        u_ref = sc.u_max if sc.u_max is not None else sc.max_u
        return TuningMetrics(window_start=jnp.asarray(self.sim.window_start, dtype),
                             e_sharpness=jnp.asarray(self.spec.sharpness / sc.linf, dtype),
                             u_sharpness=jnp.asarray(self.spec.u_sharpness / u_ref, dtype),
                             requirements=tuple(self.requirements), n_steps=self.sim.n_steps,
                             reference=reference)

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
                                      len(self.requirements), bounds, self.checks)
        loss = aggregate(per_plant, self.aggregate, self.cvar_level)
        feasible = feasible_plants(metrics, diverged, bounds, len(self.requirements),
                                   self.checks)
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
        """((loss, aux), d loss / d z) with the gradient plant by plant (`gradient = "plants"`):
        the mean of the gradients of the plants the aggregate weighs (as `top_k` picks them),
        each simulated again alone; exact where the worst plants are not tied. The loss and
        aux are `evaluate`'s, from one batched forward run."""
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
            return plant_loss(metrics, diverged, self.spec, self.scales, n_req, b,
                              self.checks)[0]

        grads = jax.vmap(jax.grad(one), in_axes=(None, 0))(z, idx)
        return (loss, aux), jax.tree.map(lambda g: jnp.mean(g, axis=0), grads)

    def per_plant(self, z, overrides=None):
        """Every plant's J, divergence flag and metrics (exact and smooth) at z: leaves of
        shape (B,) with a batch, () without."""
        setup = self.selection.apply(self.setup, z)
        ov = self.overrides if overrides is None else overrides
        metrics, diverged = loop_metrics(self, setup, ov)
        per_plant, _ = plant_loss(metrics, diverged, self.spec, self.scales,
                                  len(self.requirements), self.bounds(overrides), self.checks)
        return {"loss": per_plant, "diverged": diverged, **metrics}
