"""Fusion control for XLA:CPU: optimisation barriers on in batched traces only.

In a batch, XLA:CPU fuses an intermediate used by many consumers into each of them and
recomputes it per consumer (one RK4 step of the paper's loop ended up with ~10x its sines and
multiplies in the optimised HLO); `optimization_barrier` makes it computed once. For a single
trajectory the same barriers only add kernels (each costs ~10 ns of dispatch on this CPU:
29 ms with them against 24 ms without, 20,000 steps). The batched integrator switches them on
while it traces; the decision is made at trace time and costs nothing at run time.
"""

from __future__ import annotations

import contextlib
import contextvars

import jax

_ENABLED = contextvars.ContextVar("dscjax_fusion_barriers", default=False)


def barrier(tree):
    """Materialise `tree` (computed once, not re-fused into consumers) in batched traces."""
    return jax.lax.optimization_barrier(tree) if _ENABLED.get() else tree


@contextlib.contextmanager
def barriers(enabled: bool = True):
    """Within this block, `barrier` is active (used by integrate's batched layout)."""
    token = _ENABLED.set(enabled)
    try:
        yield
    finally:
        _ENABLED.reset(token)
