"""Compilations in the tests: `counted` counts every trace of a jitted function (each one
compiles) by its name, as JAX reports them (`jax.monitoring`); `lean` compiles a test's own
program as dscjax compiles its run-once programs (`dscjax.xla.jit(fn, lean=True)`)."""

import collections
import contextlib

from jax import monitoring

from dscjax import xla

TRACE = "/jax/core/compile/jaxpr_trace_duration"


@contextlib.contextmanager
def counted():
    """{function name: traces} of the jitted functions traced inside the block."""
    seen = collections.Counter()

    def count(event, duration, **kwargs):
        if event == TRACE:
            seen[kwargs.get("fun_name")] += 1

    monitoring.register_event_duration_secs_listener(count)
    try:
        yield seen
    finally:
        monitoring.unregister_event_duration_listener(count)


def lean(fn, **jit_options):
    """`fn` jitted as dscjax's run-once programs are (`dscjax.xla.lean_options`): one program
    instead of the many small ones of an eager `jax.grad`."""
    return xla.jit(fn, lean=True, **jit_options)
