"""Normalised sensitivities d ln m / d ln p of a loop's metrics m to its numbers p, by reverse
mode: one pull-back through the loop per metric, whatever the number of parameters.

    res = sensitivity(setup, spec)                     # every number of the setup, METRICS
    res.values["l2_error_window"]["controller.k[0]"]   # (p / m) dm/dp; None where p = 0

Each number is moved multiplicatively, p -> p exp(z_p), and the derivative taken at z = 0. A
number whose value is 0 has no d ln p: it is differentiated additively (p -> p + z_p) but its
value is None (`Sensitivity.zero` lists them). With `overrides` (a batch of plants) m is the
mean over the batch, and an overridden number is scaled in every plant alike. The loop is
piecewise smooth (sat(), max, |.|): the result is the exact derivative of the discrete loop at
the point, which a difference quotient matches only for small steps (docs/sensitivity.md).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import params, validation, xla
from dscjax.closed_loop import Setup
from dscjax.divergence import DivergenceError, diverged_lines
from dscjax.metrics import Power, SmoothMax
from dscjax.params import Param
from dscjax.runspec import RunSpec
from dscjax.selection import Relative, Selection, Shift, Tuned, run_at
from dscjax.simulate import canonical, check, dtype_of
from dscjax.validation import ConfigError

# l2_error_window, max_abs_u and tv_u as `dscjax.metrics` defines them; lp_error_window the
# windowed L_p norm of e (`metrics.SmoothMax` of the `Power` form), a smooth windowed L-inf
METRICS = ("l2_error_window", "lp_error_window", "max_abs_u", "tv_u")
LP_ORDER = 16.0  # p of lp_error_window
PARTS = ("controller", "plant", "hysteresis")  # whose numbers are differentiated by default


@dataclasses.dataclass(frozen=True)
class Sensitivity:
    """The result of `sensitivity`.

    Attributes:
        columns: the numbers differentiated (`Param`s), in order; `names` their paths.
        metrics: the metrics' names; `value` their values (mean over the batch), (k,).
        gradient: (k, d) d m_i / d z_j (z_j = ln p_j, or p_j itself where p_j = 0).
        zero: (d,) True where p_j = 0 (no d ln p: its sensitivity is None).
    """

    columns: tuple[Param, ...]
    metrics: tuple[str, ...]
    value: np.ndarray
    gradient: np.ndarray
    zero: np.ndarray

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.columns)

    @property
    def normalised(self) -> np.ndarray:
        """(k, d) d ln m_i / d ln p_j; NaN where p_j = 0 or m_i = 0."""
        with np.errstate(divide="ignore", invalid="ignore"):
            out = self.gradient / self.value[:, None]
        out[:, self.zero] = np.nan
        out[self.value == 0, :] = np.nan
        return out

    @property
    def values(self) -> dict[str, dict[str, float | None]]:
        """{metric: {path: d ln m / d ln p, or None}} (`normalised`), as sensitivity.json."""
        n = self.normalised
        return {m: {name: (None if np.isnan(v) else float(v))
                    for name, v in zip(self.names, n[i], strict=True)}
                for i, m in enumerate(self.metrics)}


def columns(setup, paths: Sequence[str] | None = None, field: str = "--param"
            ) -> tuple[Param, ...]:
    """One `Param` per scalar differentiated (or fitted, `dscjax.identify`): `paths` (default
    every number of the controller, the plant and the hysteresis model) checked against the
    setup (ConfigError naming `field`), a vector leaf given whole split into its elements; a
    number given twice is refused."""
    if paths is None:
        paths = [f"{part}.{p}" for part in PARTS
                 for p in validation.numeric_paths(getattr(setup, part))]
    out = Selection.of([Param.parse(text, field, setup) for text in paths]).columns(setup)
    params.check_columns(out, field)
    if not out:
        raise ConfigError(f"{field}: no number given")
    return tuple(out)


def check_metrics(metrics: Sequence[str], field: str = "--metric") -> tuple[str, ...]:
    """The metrics, each one of METRICS and none twice (ConfigError naming `field`)."""
    for m in metrics:
        validation.one_of(m, field, METRICS)
    if len(set(metrics)) != len(metrics):
        raise ConfigError(f"{field}: a metric is given twice (got {', '.join(metrics)})")
    return tuple(metrics)


def _metrics(z, selection, setup, spec, overrides, lp_order, metrics):
    """(the metrics (k,), the run's status): the loop at the numbers moved by z, with
    lp_error_window = ((1/|W|) trapezoid_W(|e|^p))^(1/p) on the window W = [t0, T], p =
    `lp_order`."""
    lp = SmoothMax(Power(lp_order), spec.window_start, "lp_error_window", n_steps=spec.n_steps)
    traj = run_at(selection, setup, dict(zip(selection.names, z, strict=True)), spec,
                  overrides=overrides, extra=lp)
    return jnp.stack([jnp.mean(traj.metrics[m]) for m in metrics]), traj.status


@functools.partial(xla.jit, lean=True, static_argnums=(1, 6))
def _jacobian(z, *args):
    """(metrics, d metrics / d z (k, d), status): one forward pass, then one pull-back per
    metric (its unit cotangent), vectorised."""
    k, vjp, status = jax.vjp(lambda z_: _metrics(z_, *args), z, has_aux=True)
    (grad,) = jax.vmap(vjp)(jnp.eye(k.shape[0], dtype=k.dtype))
    return k, grad, status


_metrics_jit = xla.jit(_metrics, lean=True, static_argnums=(1, 6))


@dataclasses.dataclass(frozen=True)
class Problem:
    """What `sensitivity` differentiates, checked and ready: the compiled programs take `z`
    (the log-factors, 0 at the point) and are shared by every Problem of the same structure."""

    setup: Setup
    spec: RunSpec
    overrides: Mapping[str, Any] | None
    columns: tuple[Param, ...]
    zero: tuple[bool, ...]
    metrics: tuple[str, ...]
    lp_order: float = LP_ORDER

    @classmethod
    def make(cls, setup: Setup, spec: RunSpec, paths: Sequence[str] | None = None,
             metrics: Sequence[str] = METRICS, overrides: Mapping[str, Any] | None = None,
             lp_order: float = LP_ORDER) -> Problem:
        setup = canonical(setup)
        ov = None if overrides is None else {p: np.asarray(v, np.dtype(spec.dtype))
                                             for p, v in overrides.items()}
        check(setup, spec, ov)  # the setup's models (each plant's), the filters against RK4
        cols = columns(setup, paths)
        zero = tuple(bool(p.nominal(setup) == 0.0) and (ov is None or p.path not in ov)
                     for p in cols)
        return cls(setup, spec, ov, cols, zero, check_metrics(metrics), float(lp_order))

    @property
    def selection(self) -> Selection:
        """Each column moved by p exp(z), or by p + z where p = 0."""
        return Selection(tuple(Tuned(p, Shift() if zero else Relative())
                               for p, zero in zip(self.columns, self.zero, strict=True)))

    def args(self, z=None):
        """The arguments of the compiled programs at z (default the point itself): the
        numbers traced, the structure static, the spec's host-side settings out
        (`RunSpec.program`)."""
        z = self.z0() if z is None else z
        dtype = dtype_of(self.setup)
        return (jnp.asarray(z, dtype), self.selection, self.setup, self.spec.program(),
                self.overrides, jnp.asarray(self.lp_order, dtype), self.metrics)

    def z0(self) -> np.ndarray:
        return np.zeros(len(self.columns), np.dtype(self.spec.dtype))

    def compile(self):
        """`jacobian`, compiled now (ahead of time: a caller can time its compilation)."""
        _jacobian.lower(*self.args()).compile()  # (the jit's own cache keeps it)
        return self.jacobian

    def jacobian(self, z=None):
        """(metrics (k,), gradient (k, d), status) at z (default the point itself): one
        forward pass and one pull-back per metric."""
        return _jacobian(*self.args(z))

    def metrics_at(self, z):
        """(metrics (k,), status) of the loop at z, forward only (difference quotients)."""
        return _metrics_jit(*self.args(z))

    def result(self, out) -> Sensitivity:
        """The `Sensitivity` of `jacobian`'s output; DivergenceError if the loop diverged."""
        k, grad, status = out
        if np.any(np.asarray(status.code) != 0):
            lines = diverged_lines(status, np.asarray(status.step) * float(self.spec.dt),
                                   float(self.spec.state_bound))
            raise DivergenceError("no sensitivity: " + ", ".join(lines[:3])
                                  + (f" (and {len(lines) - 3} more)" if len(lines) > 3 else "")
                                  + "; reduce dt, use the etdrk4 solver or revise the gains",
                                  None)
        return Sensitivity(self.columns, self.metrics, np.asarray(k, float),
                           np.asarray(grad, float), np.asarray(self.zero, bool))


def sensitivity(setup: Setup, spec: RunSpec, paths: Sequence[str] | None = None,
                metrics: Sequence[str] = METRICS, overrides: Mapping[str, Any] | None = None,
                lp_order: float = LP_ORDER) -> Sensitivity:
    """d ln m / d ln p of each metric m to each number p (module docstring).

    Args:
        setup, spec: the loop and how it is run (a sampled controller with spec.sample_time).
        paths: config paths (a vector whole, or one element "plant.g[1]", or a scale
            "hysteresis.p*"); default every number of the controller, plant and hysteresis.
        metrics: names from METRICS.
        overrides: {path: (B, ...)} a batch of plants; m is then the mean over them.
        lp_order: p of lp_error_window.

    Example:
        >>> import dscjax
        >>> from dscjax.sensitivity import sensitivity
        >>> spec = dscjax.RunSpec.make(1.0, 1e-3)
        >>> res = sensitivity(dscjax.paper_example(), spec, ["controller.k"], ["l2_error_window"])
        >>> sorted(res.values["l2_error_window"])
        ['controller.k[0]', 'controller.k[1]']
    """
    problem = Problem.make(setup, spec, paths, metrics, overrides, lp_order)
    return problem.result(problem.jacobian())


__all__ = ["LP_ORDER", "METRICS", "Problem", "Sensitivity", "columns", "check_metrics",
           "sensitivity"]
