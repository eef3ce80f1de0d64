"""Box search: minimise a batched objective over search coordinates z in R^n by CMA-ES
(`CMA`), random sampling (`Random`) or projected gradient descent (`Gradient`), under one
loop (`run`), one record (`Trace`) and one resume format (`trace.save`/`load`: an atomic npz
per search). `dscjax tune` and `dscjax worst-case` both search with it; the caller gives the
objective as a `Problem` (the worst case minimises loss = -metric).

    res = search.run(problem, search.CMA(popsize=64, growth=2), x0=z0, seed=0, time_limit=100.0,
                     path="search.npz", fingerprint={"problem": digest})
    res.trace.best_z, res.trace.best_loss, res.stop_reason

Ranking: feasible first, then lower loss (a non-finite loss is never the best; "improved" is
by more than `min_delta`, relative). Each iteration commits its new state and saves inside
`progress.critical`, so a search stopped anywhere resumes bitwise as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from dscjax import files, xla
from dscjax.progress import critical
from dscjax.search.cma import ReplayCMA
from dscjax.search.methods import CMA, Context, Gradient, Random, generator
from dscjax.search.trace import Evaluation, Incumbent, Saved, Step, Trace, load, order, save, take


class Problem(Protocol):
    """What a search minimises. `compile_seconds` (optional, increasing): the seconds its
    programs spent compiling so far, which `run` counts apart."""

    lower: np.ndarray  # (n,) float64, -inf allowed
    upper: np.ndarray  # (n,) float64, +inf allowed

    def evaluate(self, z: np.ndarray) -> Evaluation:
        """The candidates z (B, n); padding a batch to a compiled width is the problem's."""

    def value_and_grad(self, z: np.ndarray) -> tuple[Evaluation, np.ndarray]:
        """The candidates z (M, n) and the gradient of each loss, (M, n) (`Gradient` only)."""

    def project(self, z: np.ndarray) -> np.ndarray:
        """z onto the feasible set: the box by default."""
        return np.clip(z, self.lower, self.upper)

    def sample(self, rng: np.random.Generator, b: int) -> np.ndarray:
        """b random points (b, n) of the region searched."""


Method = CMA | Random | Gradient


class Batched:
    """A batched program `fn(*before, z (w, n), *after, **static) -> arrays (w, ...)` (a
    `jax.jit` function; its other arguments fixed, so that problems of one structure share its
    compilations) compiled ahead of time once per width, its compilation timed (`seconds`): a
    batch of B points runs at width B, except a single point, which runs padded to the
    narrowest width compiled (the start point's evaluation compiles nothing)."""

    def __init__(self, fn, before: tuple = (), after: tuple = (), **static):
        self.fn, self.widths, self.seconds = fn, set(), 0.0
        self.before, self.after, self.static = before, after, static

    def __call__(self, z) -> Any:
        import jax

        z = np.asarray(z, dtype=np.float64)
        b = len(z)
        w = min(self.widths) if b == 1 and self.widths and 1 not in self.widths else b
        x = xla.tiles(z, w)[0] if w > b else z
        args = (*self.before, x, *self.after)
        if w not in self.widths:
            t0 = time.perf_counter()
            self.fn.lower(*args, **self.static).compile()  # (the jit's own cache keeps it)
            self.seconds += time.perf_counter() - t0
            self.widths.add(w)
        out = self.fn(*args, **self.static)
        return jax.tree.map(lambda a: np.asarray(a)[:b], jax.device_get(out))


class Result(NamedTuple):
    trace: Trace
    state: Any  # the method's last state
    stop_reason: str
    resumed_from: int  # iterations done before this call (0: a fresh search)
    compile_seconds: float  # compilation seconds of this call


def run(problem: Problem, method: Method, *, x0, seed: int = 0,
        time_limit: float | None = None, max_evals: int | None = None,
        max_iterations: int | None = None, patience: int = 0, min_delta: float = 0.0,
        path: str | Path | None = None, resume: bool = False, fingerprint: Any = None,
        progress: Callable[[Trace, dict], None] | None = None,
        count_compile: bool = True) -> Result:
    """Search until a limit, `patience` iterations without improvement, or the method's own
    end; save to `path` after every iteration.

    Args:
        x0: (n,) the start point (a resumed search keeps its own).
        time_limit, max_evals, max_iterations: totals over the search's life, resumed calls
            included (compilation counted only with `count_compile`); no iteration begins
            that the last one's time says would pass `time_limit`.
        resume: continue the search in `path` (if any); its `fingerprint` must be equal.
        progress: called with the trace and its new history row after every iteration.
    """
    fp = {"caller": fingerprint, "method": method.name, "settings": dataclasses.asdict(method),
          "seed": seed}
    saved = load(path) if resume and path is not None else None
    if saved is not None:
        files.check_same(saved.fingerprint, fp, where=f"--resume: {path}")
        trace, state = saved.trace, method.restore(problem, saved.trace.start_z, seed, saved.arrays)
    else:
        x0 = np.array(x0, dtype=np.float64).reshape(-1)
        trace, state = Trace(method.name, x0), method.init(problem, x0, seed)
    begun, compiled = trace.iterations, trace.compile_seconds
    # the last iteration's seconds: where the next would pass time_limit, none is begun
    last = float(np.diff([0.0] + [r["seconds"] for r in trace.history[-2:]])[-1]
                 if trace.history else 0.0)
    mark = time.perf_counter()
    while (reason := _limit(trace, last, time_limit, max_evals, max_iterations)) is None:
        # a Ctrl-C waits for the iteration, its commit, its file and the caller's files
        # (dscjax.progress.critical): whatever was saved is a whole state
        with critical():
            c0 = getattr(problem, "compile_seconds", 0.0)
            step = method.step(problem, state, Context(trace.iterations, seed, trace.start_z))
            c = getattr(problem, "compile_seconds", 0.0) - c0
            # (the seconds since the last iteration's step: its save and progress count here)
            now = time.perf_counter()
            wall, mark, last = now - mark, now, now - mark - c
            new = trace.record(step, wall if count_compile else wall - c, c, min_delta)
            # commit, then save: the only place where the search's state changes
            trace, state = new, step.state
            if path is not None:
                save(path, trace, method.arrays(state), fp)
            if progress is not None:
                progress(trace, trace.history[-1])
        if patience and trace.stall >= patience:
            reason = (f"no improvement of the best loss by more than {min_delta:g} (relative) "
                      f"in {patience} iterations")
            break
    return Result(trace, state, reason, begun, trace.compile_seconds - compiled)


def _limit(trace: Trace, last: float, time_limit, max_evals, max_iterations) -> str | None:
    """Why not to begin another iteration, or None."""
    if trace.done:
        return trace.done
    if max_iterations is not None and trace.iterations >= max_iterations:
        return f"reached {max_iterations} iterations"
    if max_evals is not None and trace.evaluations >= max_evals:
        return f"reached {max_evals} evaluations"
    if time_limit is not None and (trace.seconds >= time_limit
                                   or trace.seconds + last > time_limit):
        return f"time limit {time_limit:g} s"
    return None


__all__ = ["Batched", "CMA", "Context", "Evaluation", "Gradient", "Incumbent", "Problem", "Random",
           "ReplayCMA", "Result", "Saved", "Step", "Trace", "generator", "load", "order", "run",
           "save", "take"]
