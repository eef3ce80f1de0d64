"""The tuning objective: per plant, a weighted sum of terms normalised by the start gains'
figures on the nominal plant (window W = [t0, T], every RK4 step; docs/tuning.md), aggregated
over a batch of plants (`Mean`, `CVaR(a)`: the mean of the worst ceil(a B), or `Max`):

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
are `dscjax.metrics.SmoothMax` of the `LogSumExp` form: Linf~'s gradient is the
softmax-weighted one of the largest errors, and max~|u| >= max|u|, so penalising it keeps the
exact max|u| under its bound. A run's metrics are NaN where it diverged
(`dscjax.selection.run_at`); the loss maps such a plant to its finite penalty explicitly.

Bounds "start" are the start gains' figures over the whole horizon [0, T] (the transient
included) on the nominal plant, or on each training plant its own (`tuning.scales`).

e is measured against the reference the controller tracks: a controller whose initialisation
shifts it (the DSC's init = "linf": y_r(0) moved to x_1(0), the offset decaying) is tuned on
that error; `UserError` measures the same figures against the config's own y_r beside it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from dscjax import params
from dscjax.closed_loop import SCHEME, Setup
from dscjax.runspec import RunSpec
from dscjax.selection import Selection, run_at
from tuning.config import TERMS, ObjectiveSpec
from tuning.optimize import CVaR, Mean
from tuning.reductions import shifted_reference, tuning_metrics
from tuning.scales import Scales

# a bound "start" is the start's own figure from another compiled program: rounding may put
# the start a few ulps over it
BOUND_RTOL = 1e-9
# the effort bounds in words and by their metric, in `Scales.bounds`' order
EFFORTS = (("max|u|", "max_abs_u"), ("TV(u)", "tv_u"))


def bound_terms(spec: ObjectiveSpec, u_bound, tv_bound) -> list[tuple]:
    """(term, figure, bound, weight) of each effort bound's penalty there is."""
    return [t for t in (("u_bound", "smooth_max_abs_u", u_bound, spec.u_max_weight),
                        ("tv_bound", "tv_u", tv_bound, spec.tv_max_weight))
            if t[2] is not None and t[3]]


class CheckLoop(eqx.Module):
    """A loop the gains must also hold in: `sim`, the loop tuned with one thing changed. Its
    windowed L-inf at most `linf_factor` x the loop tuned's, its max|u| at most `u_factor` x
    the max|u| bound and its TV(u) at most `tv_factor` x the TV(u) bound (None: not checked);
    `weight` of its penalty, the setting tuning.objective.`weight_key`; its metrics in
    `loop_metrics` are prefixed `name`_; `label` says the loop in the report. `smooth`: its
    figures have slopes in the gains (the report's elasticities); a loop at the edge of a
    limit cycle has tangents that are not. A pytree whose one leaf is its `sim`."""

    name: str = eqx.field(static=True)
    sim: RunSpec
    linf_factor: float = eqx.field(static=True)
    u_factor: float | None = eqx.field(static=True)
    tv_factor: float | None = eqx.field(static=True)
    weight: float = eqx.field(static=True)
    weight_key: str = eqx.field(static=True)
    label: str = eqx.field(static=True)
    smooth: bool = eqx.field(static=True, default=True)

    def program(self) -> CheckLoop:
        """The loop as a jitted program takes it (`RunSpec.program`)."""
        return dataclasses.replace(self, sim=self.sim.program())

    def bounded(self, bounds: tuple) -> list[tuple[str, str, Any, float]]:
        """(what, metric key, bound, factor) of each effort bound checked in this loop."""
        return [(what, key, b, f) for (what, key), b, f in
                zip(EFFORTS, bounds, (self.u_factor, self.tv_factor), strict=True)
                if b is not None and f is not None]

    def penalty(self, m: Mapping[str, jax.Array], u_bound, tv_bound) -> jax.Array:
        """weight x the sum of relu(r - 1)^2 over the ratios r of its smooth figures to their
        bounds (L-inf~ to linf_factor x the loop tuned's, each effort bound checked)."""
        p, smooth = self.name, {"max_abs_u": "smooth_max_abs_u", "tv_u": "tv_u"}
        ratios = [m[f"{p}_smooth_linf_window"] / (self.linf_factor * m["smooth_linf_window"])]
        ratios += [m[f"{p}_{smooth[key]}"] / (f * b)
                   for _, key, b, f in self.bounded((u_bound, tv_bound))]
        return self.weight * sum(jnp.maximum(r - 1.0, 0.0) ** 2 for r in ratios)


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
        out.append(CheckLoop("sampled", other, spec.sampled_factor, 1.0, 1.0, spec.sampled_weight,
                             "sampled_weight", f"the states by {other.discretisation.words}"))
    if spec.delay_samples and spec.delay_weight:
        d = sim.delay + spec.delay_samples
        out.append(CheckLoop("delayed", sim.replace(delay=d), spec.delay_factor,
                             None, spec.delay_tv_factor, spec.delay_weight, "delay_weight",
                             f"the input delayed {d} sample{'s' if d != 1 else ''}", smooth=False))
    return tuple(out)


# the exact figures as `loop_metrics` names a check loop's (c_NAME) and `Objective.summary`
# reports them, and the run's metric each is; with c_smooth_linf_window, c_smooth_max_abs_u
# and c_diverged beside a check loop's
CHECK_FIGURES = {"linf_window": "linf_error_window", "max_abs_u": "max_abs_u", "tv_u": "tv_u"}


def loop_metrics(objective, z, overrides=None, *, points: bool = False, setup=None
                 ) -> tuple[dict, jax.Array]:
    """(metrics, diverged) of the objective's loop at z on `setup` (default its own; a batch
    with `overrides`, `points` as `run_at` reads it), and of each of its check loops c:
    c_linf_window, c_smooth_linf_window, c_diverged, c_max_abs_u, c_smooth_max_abs_u and
    c_tv_u. NaN where a loop diverged (`run_at`); traceable."""
    setup = objective.setup if setup is None else setup
    traj = run_at(objective.selection, setup, z, objective.sim, overrides=overrides,
                  extra=objective.extra(shifted_reference(setup, overrides)), points=points)
    m = traj.metrics
    for c in objective.checks:
        tc = run_at(objective.selection, setup, z, c.sim, overrides=overrides,
                    extra=objective.extra(loop=c.sim), points=points)
        figures = {k: tc.metrics[key] for k, key in CHECK_FIGURES.items()}
        smooth = {k: tc.metrics[k] for k in ("smooth_linf_window", "smooth_max_abs_u")}
        m = m | {f"{c.name}_{k}": v
                 for k, v in (figures | smooth | {"diverged": tc.diverged}).items()}
    return m, traj.diverged


def exact_constraints(bounds: tuple, linf, checks=()) -> list[tuple[str, str, Any]]:
    """(name, metric key, bound) of each constraint checked exactly, against the effort
    `bounds` (`Scales.bounds`; None: none): max|u|, TV(u) and each check loop's windowed L-inf
    (at most its factor x `linf`, the loop tuned's) and effort bounds. `Objective.judged`'s
    feasibility and the report's rows (`report.constraint_checks`)."""
    out = [(name, key, b) for (name, key), b in zip(EFFORTS, bounds, strict=True) if b is not None]
    for c in checks:
        out.append((f"L-inf on [t0,T], {c.label}", f"{c.name}_linf_window", c.linf_factor * linf))
        out += [(f"{what}, {c.label}", f"{c.name}_{key}", f * b)
                for what, key, b, f in c.bounded(bounds)]
    return out


def plant_count(plants: Mapping[str, Any] | None) -> int:
    """The plants of {path: (n, ...)} (None or empty: the nominal plant alone, 1)."""
    return len(next(iter(plants.values()))) if plants else 1


def within(value, bound):
    """value <= bound, up to BOUND_RTOL (relative)."""
    return value <= bound * (1.0 + BOUND_RTOL)


def _like(bound, x):
    """A per-plant bound (float64) in the dtype of the figures `x` (or dtype `x`): float32 runs
    stay float32."""
    if bound is None or np.ndim(bound) == 0:
        return bound
    return jnp.asarray(bound, jnp.result_type(x))


def _max_measured(values: jax.Array, ignored) -> jax.Array:
    """max over the plants not `ignored` (diverged, or padding); NaN if every one is."""
    top = jnp.max(jnp.where(ignored, -jnp.inf, values))
    return jnp.where(jnp.all(ignored), jnp.nan, top)


class Objective(eqx.Module):
    """loss(z) for a Selection over a fixed setup and (optional) batch of plants: a pytree
    whose numbers (the setup, the training plants, their mask, the scales and bounds) are
    traced leaves, so that one compiled program serves every objective of the same structure
    (an adversarial round's new plants, padded to one count)."""

    setup: Setup
    sim: RunSpec  # how every plant is simulated (metrics only: save_every = n_steps)
    scales: Scales
    selection: Selection = eqx.field(static=True)
    spec: ObjectiveSpec = eqx.field(static=True)
    requirements: tuple = ()
    overrides: Mapping[str, Any] | None = None  # the training batch, {path: (B, ...)}
    mask: Any = None  # (B,) the real plants of a padded batch (None: every one)
    aggregate: Mean | CVaR = eqx.field(static=True, default=Mean())
    # the loops the gains must also hold in (`CheckLoop`)
    checks: tuple = ()

    @property
    def batch_size(self) -> int:
        """Rows of the training batch, padding included (1: the nominal plant alone)."""
        return plant_count(self.overrides)

    def program(self) -> Objective:
        """The objective a jitted program takes: its loops' host-side settings out
        (`RunSpec.program`)."""
        return dataclasses.replace(self, sim=self.sim.program(),
                                   checks=tuple(c.program() for c in self.checks))

    def extra(self, reference=None, loop: RunSpec | None = None):
        """The tuning's reductions (`tuning_metrics`) in the loop tuned; with `reference`
        (`shifted_reference`) the error against it too; in a check loop `loop` the smooth
        figures alone."""
        dtype, sc = jnp.result_type(self.setup.plant.x0), self.scales
        u_ref = sc.u_max if sc.u_max is not None else sc.max_u
        return tuning_metrics(jnp.asarray(self.sim.window_start, dtype),
                              jnp.asarray(self.spec.sharpness / sc.linf, dtype),
                              jnp.asarray(self.spec.u_sharpness / u_ref, dtype),
                              tuple(self.requirements) if loop is None else (),
                              (self.sim if loop is None else loop).n_steps, reference)

    def evaluate(self, z, overrides=None):
        """(loss, aux) at z; aux has the terms (aggregated as the loss is), the exact metrics
        and the feasibility of the bounds (all plants)."""
        return self._evaluate(z, overrides)[:2]

    def judged(self, metrics, diverged, bounds: tuple):
        """(J, its weighted terms (0 where a loop diverged), exact feasibility) of each plant of
        these metrics (`loop_metrics`) against `bounds` (`Scales.bounds`): feasible where no loop
        diverged and the effort bounds, the requirements and each check loop's constraints are
        met."""
        spec, n_req = self.spec, len(self.requirements)
        # a plant diverged in any loop costs a finite constant, so that means and CVaRs stay
        # usable; its metrics (NaN) are replaced first, or their 0 x NaN would reach the
        # gradient. Any other non-finite J stays so, and the search ranks it last.
        bad = diverged
        for c in self.checks:
            bad = bad | metrics[f"{c.name}_diverged"]
        u_bound, tv_bound = (_like(b, metrics["max_abs_u"]) for b in bounds)
        ok = ~bad
        for _, key, bound in exact_constraints((u_bound, tv_bound),
                                               metrics["linf_error_window"], self.checks):
            ok = ok & within(metrics[key], bound)
        m = {k: jnp.where(bad, 1.0, v) for k, v in metrics.items()}
        terms = {name: getattr(spec, name) * m[figure] / getattr(self.scales, scale)
                 for name, (figure, _, scale, _) in TERMS.items() if getattr(spec, name)}
        for name, figure, bound, weight in bound_terms(spec, u_bound, tv_bound):
            terms[name] = weight * jnp.maximum(m[figure] / bound - 1.0, 0.0) ** 2
        for i in range(n_req):
            terms[f"req{i}"] = m[f"req{i}_penalty"]
            ok = ok & (metrics[f"req{i}_met"] > 0)
        terms |= {c.name: c.penalty(m, u_bound, tv_bound) for c in self.checks}
        total = jnp.where(bad, spec.divergence_penalty, sum(terms.values()))
        return total, {k: jnp.where(bad, 0.0, v) for k, v in terms.items()}, ok

    def summary(self, per_plant, terms, metrics, diverged, feasible, mask=None):
        """(loss, aux) of one point from its plants' `judged` figures (axis 0, or none without
        a batch; `mask`: the real plants, None: every one)."""
        real = jnp.ones_like(diverged) if mask is None else mask
        ignored = diverged | ~real
        return self.aggregate(per_plant, mask), {
            "terms": {k: self.aggregate(v, mask) for k, v in terms.items()},
            # reported, not differentiated: over the plants that did not diverge (a diverged
            # plant's metrics were not measured), NaN if none did
            **{k: _max_measured(metrics[key], ignored) for k, key in CHECK_FIGURES.items()},
            "n_diverged": jnp.sum(jnp.asarray(diverged & real, jnp.int32)),
            "feasible": jnp.all(feasible | ~real),
        }

    def _evaluate(self, z, overrides=None, bounds=None):
        """(loss, aux, `per_plant`)."""
        ov, mask = (self.overrides, self.mask) if overrides is None else (overrides, None)
        metrics, diverged = loop_metrics(self, z, ov)
        if bounds is None:  # the training batch's own (per-plant) bounds, or the nominal ones
            bounds = self.scales.bounds(train=overrides is None and bool(self.overrides))
        per_plant, terms, feasible = self.judged(metrics, diverged, bounds)
        loss, aux = self.summary(per_plant, terms, metrics, diverged, feasible, mask)
        return loss, aux, {"loss": per_plant, "diverged": diverged, **metrics}

    def value_and_grad_plants(self, z):
        """((loss, aux), d loss / d z) with the gradient plant by plant (`optimize.Plants`):
        the weighted sum of the gradients of the plants the aggregate weighs (as `top_k` picks
        them), each simulated again alone; exact where the worst plants are not tied. The loss
        and aux are `evaluate`'s, from one batched forward run."""
        loss, aux, per = self._evaluate(jax.lax.stop_gradient(z))
        idx, w = (self.aggregate.weights(per["loss"], self.mask) if self.overrides
                  else (jnp.zeros(1, int), jnp.ones(1)))
        train = {p: jnp.asarray(v) for p, v in (self.overrides or {}).items()}
        bounds = self.scales.bounds(train=bool(self.overrides))
        dtype = jnp.result_type(self.setup.plant.x0)  # per-plant bounds as `judged` casts them

        def one(z_, i):
            setup = params.set_many(self.setup, {p: v[i] for p, v in train.items()})
            metrics, diverged = loop_metrics(self, z_, setup=setup)
            b = tuple(_like(v, dtype)[i] if np.ndim(v) else v for v in bounds)
            return self.judged(metrics, diverged, b)[0]

        grads = jax.vmap(jax.grad(one), in_axes=(None, 0))(z, idx)
        return (loss, aux), jax.tree.map(lambda g: jnp.tensordot(w, g, 1), grads)

    def per_plant(self, z, overrides=None, bounds=None):
        """Every plant's J, divergence flag and metrics (exact and smooth; NaN where a loop
        diverged) at z: leaves of shape (B,) with a batch (padding included), () without;
        `bounds` each plant's effort bounds (`Scales.bounds`' layout; None: the training
        batch's own for the training batch, else the nominal ones)."""
        return self._evaluate(z, overrides, bounds)[2]
