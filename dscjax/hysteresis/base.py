"""The interface every hysteresis model w = P[u] provides (numbers traced, class and options
static):

    init_state(u0) -> h(0)                 output(u, h) -> w, which drives the plant
    rate(u, du, h) -> h' given u' = du     decay_rate(u, du, h) -> rates >= 0 (like h) of the
                                           stiff linear decays in `rate` (ETDRK4's exact part)
    jump(u_from, u_to, h) -> h after u steps (a held input of a sampled controller), along
                             the model's curve
    project(u, h) -> h after a step (only a model that `projects`: its callers check)
    effective_slope() -> lam of w = lam u + d_1(u), eq. (5); d1_limits() -> limits of d_1, (7)-(8)
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from dscjax.model import Model


class Hysteresis(Model):
    """The interface every hysteresis model provides (the module docstring): each model defines
    its methods, this class only the defaults and `d1_bound`."""

    kind: ClassVar[str]
    title: ClassVar[str]  # the model's name in figures
    # h is a discrete state (the plays): held inside a step, changed only by `project`
    projects: ClassVar[bool] = False
    # what `dscjax sweep` varies by default (each +-30 %): paths under [hysteresis]
    default_sweep: ClassVar[tuple[str, ...]] = ()

    def decay_rate(self, u, du, h):
        return jax.tree.map(jnp.zeros_like, h)

    def d1_bound(self):
        """A bound of |d_1| once it has settled: the larger limit (7)-(8) in magnitude."""
        lo, hi = self.d1_limits()
        return jnp.maximum(jnp.abs(lo), jnp.abs(hi))
