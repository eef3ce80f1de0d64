"""Grey-box identification: the free numbers of a config (and each segment's initial plant
state) that minimise the simulation error of the measured columns, by Levenberg-Marquardt on
exact Jacobians through the simulator, with the Gauss-Newton covariance.

    problem = Problem.make(setup, record, ["plant.g", "hysteresis.alpha"], plant=True, dt=1e-3)
    fit = solve(problem)                       # fit.theta, fit.cost
    est, corr, sv, s2 = estimates(problem, fit)  # standard errors, intervals, ...
    figures = fit_figures(problem, fit)        # NRMSE, MSE, FPE

Residuals are (y - y_hat) / sigma per measured column (sigma given, or estimated from the
record's second differences), plus each segment's continuity (its end state against the next
segment's start) with weight CONTINUITY. Free numbers that must be positive are fitted in log
coordinates (their intervals stay positive), signed ones as they are.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import params, xla
from dscjax.closed_loop import Setup
from dscjax.identify.data import Record
from dscjax.identify.experiment import Experiment, simulate
from dscjax.selection import Linear, Log, Selection, Tuned
from dscjax.sensitivity import columns

LAMBDA0 = 1e-3  # the first damping, relative to each coordinate's curvature
CONTINUITY = 10.0  # a segment's end state against the next's start, in units of its sigma
RANK_TOL = 1e-8  # singular values below this x the largest: directions the data do not fix
LOOSE = 1.0  # a relative standard error above this (100 %): not identified
Z95 = 1.959963984540054  # the 97.5 % quantile of the standard normal


class Problem(eqx.Module):
    """What is fitted: the setup, the free numbers, the experiment and the data it is fitted
    to (`fit_index`: the samples of the fit; the rest validates). A pytree whose numbers are
    traced: records of the same shape share one compiled fit."""

    setup: Setup
    exp: Experiment
    y: dict  # {column: (N,)} the measured columns
    sigma: dict  # {column: ()} their noise std
    fit_index: jax.Array  # (M,) sample indices fitted
    free: tuple[Tuned, ...] = eqx.field(static=True)  # Log where positive, else Linear
    h0: Any = None  # the actuator's state at the first sample (None: at rest)
    source: str = eqx.field(static=True, default="")

    @property
    def record(self) -> Record:
        return Record(np.asarray(self.exp.t), np.asarray(self.exp.u),
                      {c: np.asarray(v) for c, v in self.y.items()}, self.source)

    @classmethod
    def make(cls, setup: Setup, record: Record, paths: Sequence[str], *, plant: bool,
             dt: float, segments: int = 1, hold: str = "zoh",
             sigma: Mapping[str, float] | None = None, fit_index=None, h0=None) -> Problem:
        """The problem of fitting `paths` (none: only the start state) of `setup` to
        `record`."""
        free = [Tuned(q, Log() if q.scale or _positive(setup, q) and float(q.value(setup)) > 0
                      else Linear()) for q in (columns(setup, paths, "--free") if paths else ())]
        exp = Experiment.make(record.t, record.u, plant=plant, dt=dt, segments=segments,
                              hold=hold)
        sigma = {c: float((sigma or {}).get(c, noise_level(y))) for c, y in record.y.items()}
        index = np.arange(len(record)) if fit_index is None else np.asarray(fit_index)
        return cls(setup, exp, {c: jnp.asarray(v) for c, v in record.y.items()},
                   {c: jnp.asarray(v) for c, v in sigma.items()}, jnp.asarray(index),
                   tuple(free), h0, record.source)

    # -- coordinates ------------------------------------------------------------------------
    def z0(self) -> dict:
        """The start: the setup's numbers (logs where positive) and each segment's start
        state (the measured states there, the setup's x0 or a simulation elsewhere)."""
        z = jnp.asarray([math.log(float(f.param.value(self.setup))) if _log(f) else
                         float(f.param.value(self.setup)) for f in self.free])
        return {"z": z, "x": self.initial_states(self.setup)}

    def setup_at(self, z) -> Setup:
        free = Selection(self.free)
        return free.apply(self.setup, dict(zip(free.names, z, strict=True)))

    def initial_states(self, setup) -> jnp.ndarray:
        """(S, n) each segment's start state: measured columns from the record, the others
        from a single-shot simulation of `setup` from x0 (0 where it left the finite)."""
        if not self.exp.plant:
            return jnp.zeros((1, 0))
        x0 = jnp.asarray(setup.plant.x0, float)
        x, _, _ = _simulate(setup, dataclasses.replace(self.exp, starts=(0,)), x0[None], self.h0)
        x = np.where(np.isfinite(np.asarray(x)), np.asarray(x), 0.0)
        out = x[list(self.exp.starts)]
        for i in range(setup.order):
            if f"x{i + 1}" in self.y:
                out[:, i] = np.asarray(self.y[f"x{i + 1}"])[list(self.exp.starts)]
        return jnp.asarray(out)

    # -- residuals --------------------------------------------------------------------------
    def predict(self, theta):
        """{column: (N,) the model's value at every sample}, and the segment ends."""
        x, w, ends = simulate(self.setup_at(theta["z"]), self.exp, theta["x"], self.h0)
        out = {"w": w}
        if x is not None:
            out |= {f"x{i + 1}": x[:, i] for i in range(x.shape[1])}
        return out, ends

    def residuals(self, theta) -> jax.Array:
        """The weighted residuals of the fitted samples, then the continuity of segments."""
        pred, ends = self.predict(theta)
        idx = self.fit_index
        parts = [(self.y[c][idx] - pred[c][idx]) / self.sigma[c] for c in self.y]
        if ends is not None and ends.shape[0]:
            # an unmeasured state in units of the median noise of the measured columns
            median = jnp.median(jnp.stack([self.sigma[c] for c in self.y]))
            scale = jnp.asarray([self.sigma.get(f"x{i + 1}", median)
                                 for i in range(ends.shape[1])])
            parts.append((CONTINUITY * (ends - theta["x"][1:]) / scale).ravel())
        return jnp.concatenate(parts)


def noise_level(y) -> float:
    """The std of white noise on a smooth signal sampled finely: that of its second
    differences over sqrt(6) (floored at 1e-9 of its range)."""
    y = np.asarray(y, float)
    d2 = np.diff(y, 2)
    level = float(np.std(d2) / math.sqrt(6.0)) if d2.size > 2 else 0.0
    return max(level, 1e-9 * float(np.ptp(y)), 1e-12)


def _log(f: Tuned) -> bool:
    """Whether the free number f is fitted in log coordinates."""
    return isinstance(f.transform, Log)


def _positive(setup, p: params.Param) -> bool:
    """Whether the field of p must be > 0 (its range rule), so that log coordinates fit it."""
    part, name = p.path.split(".")[:2]  # (a path the setup has: `Param.check`)
    fields = {f.name: f for f in dataclasses.fields(getattr(setup, part))}
    return fields[name].metadata.get("check") == "positive"


@dataclasses.dataclass(frozen=True)
class Fit:
    """A solution: theta (the free numbers' coordinates z and the segments' start states),
    its cost 0.5 sum r^2, the solver's steps and status, the residual function's calls."""

    theta: dict
    cost: float
    steps: int
    status: str
    jacobian: np.ndarray  # (m, p) of the weighted residuals at theta, p = free + states
    residuals: np.ndarray  # (m,)
    start: int = 0  # which start (of --starts) it came from


def solve(problem: Problem, theta0: dict | None = None, max_steps: int = 200,
          tol: float = 1e-10) -> Fit:
    """Levenberg-Marquardt from theta0 (default the problem's start): the Jacobian exact, by
    forward mode through the simulator (one JVP a column, vectorised), taken with the
    residuals at every trial point; Marquardt's diagonal scaling and Nielsen's damping update;
    it stops when a step or the cost's relative decrease falls below `tol`."""
    theta0 = problem.z0() if theta0 is None else theta0
    flat0, unravel = ravel_pytree((jnp.asarray(theta0["z"]), jnp.asarray(theta0["x"])))
    theta = np.asarray(flat0, float)
    r, jac = (np.asarray(a, float) for a in _rj(problem, jnp.asarray(theta)))
    cost, lam, nu, steps, status = 0.5 * float(r @ r), LAMBDA0, 2.0, 0, "stopped at max_steps"
    if not math.isfinite(cost):
        status = "the start's residuals are not finite"
    elif theta.size == 0:  # e.g. the actuator alone validated: no state to fit
        status = "nothing to fit"
    while math.isfinite(cost) and theta.size and steps < max_steps:
        a, g = jac.T @ jac, jac.T @ r
        d = np.where(np.diag(a) <= 0, 1.0, np.diag(a))
        if float(np.max(np.abs(g))) <= tol * max(1.0, cost):
            status = "converged"
            break
        try:
            step = np.linalg.solve(a + lam * np.diag(d), -g)  # Marquardt: lam relative to d
        except np.linalg.LinAlgError:
            lam, nu = lam * nu, nu * 2
            continue
        trial = theta + step
        # the trial's Jacobian with its residuals: one program a step, and most steps pass
        r_new, jac_new = (np.asarray(x, float) for x in _rj(problem, jnp.asarray(trial)))
        new = 0.5 * float(r_new @ r_new)
        predicted = -(g @ step + 0.5 * step @ a @ step)
        steps += 1
        if math.isfinite(new) and new < cost:
            rho = (cost - new) / max(predicted, 1e-300)
            small = np.linalg.norm(step) <= tol * (np.linalg.norm(theta) + tol)
            flat_cost = cost - new <= tol * cost
            theta, cost, r, jac = trial, new, r_new, jac_new
            lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
            nu = 2.0
            if small or flat_cost:
                status = "converged"
                break
        else:
            lam, nu = lam * nu, nu * 2
            if lam > 1e16:
                status = "converged"  # no step lowers the cost: a minimum to round-off
                break
    z, x = unravel(jnp.asarray(theta))
    return Fit({"z": np.asarray(z), "x": np.asarray(x)}, cost, steps, status, jac, r)


def _flat(problem: Problem, v):
    """The residuals at the flat coordinates v: the free numbers' z, then the segments' start
    states."""
    k = len(problem.free)
    shape = (problem.exp.segments, problem.setup.order) if problem.exp.plant else (1, 0)
    return problem.residuals({"z": v[:k], "x": v[k:].reshape(shape)})


@functools.partial(xla.jit, lean=True)
def _rj(problem: Problem, v):
    """(r, dr/dv): `jax.jacfwd`, one JVP a column, vectorised over the columns (a program run
    at each Marquardt step: lean, `dscjax.xla`)."""
    return _flat(problem, v), jax.jacfwd(lambda w: _flat(problem, w))(v)


_simulate = eqx.filter_jit(simulate)
_predict = eqx.filter_jit(lambda problem, theta: problem.predict(theta))


def solve_starts(problem: Problem, starts: int = 1, seed: int = 0, spread: float = 0.5,
                 **kw) -> tuple[Fit, list[float]]:
    """The best of `starts` fits: the problem's start, then starts whose free numbers are
    scattered (log coordinates: x e^(+-spread); others: +-spread x |value|, at least spread)
    around it; (best fit, every start's cost)."""
    rng = np.random.default_rng(seed)
    base = problem.z0()
    fits = [solve(problem, base, **kw)]
    for k in range(1, starts):
        z = np.asarray(base["z"], float).copy()
        for i, f in enumerate(problem.free):
            z[i] += rng.uniform(-spread, spread) * (1.0 if _log(f) else max(abs(z[i]), 1.0))
        theta = {"z": jnp.asarray(z), "x": problem.initial_states(problem.setup_at(z))}
        fits.append(dataclasses.replace(solve(problem, theta, **kw), start=k))
    costs = [f.cost if math.isfinite(f.cost) else math.inf for f in fits]
    return fits[int(np.argmin(costs))], costs


@dataclasses.dataclass(frozen=True)
class Estimate:
    """One free number: its value, standard error, 95 % interval, and whether the data fix
    it (`why` says why not)."""

    name: str
    value: float
    se: float
    low: float
    high: float
    identifiable: bool
    why: str = ""


def estimates(problem: Problem, fit: Fit) -> tuple[list[Estimate], np.ndarray, np.ndarray,
                                                    float]:
    """(each free number's `Estimate`, their correlation matrix, the Jacobian's singular
    values, the residual variance factor s^2). Covariance s^2 (J^T J)^-1 (Gauss-Newton) in the
    fit's coordinates, s^2 = |r|^2 / (m - p); a log coordinate's interval is exp(z +- 1.96 se),
    its se the delta method's value x se_z. A number is not identifiable where it loads on a
    direction whose singular value is below RANK_TOL x the largest, or where its relative
    standard error exceeds LOOSE."""
    jac, r = fit.jacobian, fit.residuals
    m, p = jac.shape
    k = len(problem.free)
    s2 = float(r @ r) / max(m - p, 1)
    u, sv, vt = np.linalg.svd(jac, full_matrices=False)
    keep = sv > RANK_TOL * sv[0]
    inv = (vt[keep].T / sv[keep] ** 2) @ vt[keep]  # the pseudo-inverse of J^T J
    cov = s2 * inv[:k, :k]
    se_z = np.sqrt(np.clip(np.diag(cov), 0, None))
    weak = np.any(np.abs(vt[~keep, :k]) > 0.3, axis=0)  # loads on an undetermined direction
    z = np.asarray(fit.theta["z"], float)
    out = []
    for i, f in enumerate(problem.free):
        if _log(f):
            value, se = math.exp(z[i]), math.exp(z[i]) * se_z[i]
            low, high = math.exp(z[i] - Z95 * se_z[i]), math.exp(z[i] + Z95 * se_z[i])
            rel = se_z[i]
        else:
            value, se = z[i], se_z[i]
            low, high = value - Z95 * se, value + Z95 * se
            rel = se / abs(value) if value else math.inf
        why = ""
        if weak[i]:
            why = "the data leave its direction undetermined (a singular value below " \
                  f"{RANK_TOL:g} x the largest)"
        elif not rel <= LOOSE:
            why = f"its relative standard error is {100 * rel:.3g} % (> {100 * LOOSE:g} %)"
        out.append(Estimate(f.param.name, value, float(se), low, high, not why, why))
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return out, cov / np.outer(d, d), sv, s2


def fitted(problem: Problem, fit: Fit) -> dict[str, tuple]:
    """{column: (t, y measured, y of the model) on the fitted samples} (the figures' and the
    plots' data)."""
    index = np.asarray(problem.fit_index)
    pred, _ = _predict(problem, jax.tree.map(jnp.asarray, fit.theta))
    return {c: (np.asarray(problem.record.t)[index], np.asarray(y)[index],
                np.asarray(pred[c])[index]) for c, y in problem.record.y.items()}


def fit_figures(problem: Problem, fit: Fit) -> dict[str, dict[str, float]]:
    """Per measured column on the fitted samples: NRMSE fit in
    percent, 100 (1 - |y - y_hat| / |y - mean y|), and MSE; over all columns, FPE =
    det(E^T E / N) (1 + d/N) / (1 - d/N) (E the residuals, d the free numbers and start
    states, N the samples)."""
    out, errs = {}, []
    for c, (_, y, y_hat) in fitted(problem, fit).items():
        e = y - y_hat
        errs.append(e)
        nrmse = 100 * (1 - np.linalg.norm(e) / max(np.linalg.norm(y - y.mean()), 1e-300))
        out[c] = {"nrmse_fit_percent": float(nrmse), "mse": float(np.mean(e * e))}
    e = np.column_stack(errs)
    n, d = e.shape[0], fit.jacobian.shape[1]
    det = float(np.linalg.det(e.T @ e / n))
    out["all"] = {"fpe": det * (1 + d / n) / (1 - d / n) if d < n else math.inf}
    return out


def validation_fit(problem: Problem, fit: Fit, record: Record, h0=None
                   ) -> tuple[Problem, Fit]:
    """The identified model on another record (or the record's tail, its actuator going on
    from `h0`): its numbers fixed, only its initial plant state fitted (one segment), as a
    grey-box user compares."""
    setup = problem.setup_at(jnp.asarray(fit.theta["z"]))
    dt = float(np.max(np.diff(np.asarray(problem.exp.t)))) / problem.exp.substeps
    val = Problem.make(setup, record, (), plant=problem.exp.plant, dt=dt, hold=problem.exp.hold,
                       sigma={c: problem.sigma[c] for c in record.y}, h0=h0)
    return val, solve(val, {"z": jnp.zeros((0,)), "x": val.initial_states(setup)})


__all__ = ["CONTINUITY", "Estimate", "Fit", "Problem", "estimates", "fit_figures", "fitted",
           "noise_level", "solve", "solve_starts", "validation_fit"]
