"""A run that diverges: run again, refined, before it counts as diverged, then reported.

Refinement runs ETDRK4 (exact on the stiff decays) at dt, dt/2, dt/4, ... (`refinement_level`,
`level_spec`), up to `RunSpec.refine` levels that fit `validation.MAX_STEPS`
(`counted_levels`). It runs on the host: a batch re-runs only its diverged rows
(`refine_rows`), and a traced call refuses a spec that would refine
(`refuse_traced_refinement`). A sampled loop refines once: diverging again within a sample
period means the loop is unstable, not the integrator (`sampled_unstable`). What still
diverges is a `DivergenceError` or a line of `divergence_report` (`diverged_lines` of a
run's `Status` alone).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from dscjax import validation, xla
from dscjax.integrate import ETDRK4, RK4, STATUS_BOUND, STATUS_NONFINITE, STATUS_OK, Solver
from dscjax.runspec import RunSpec

# refinement levels of a sampled loop: one, to tell an unstable loop from a numerical accident
SAMPLED_REFINE = 1
# a run's outcome by the key that counts it, in a sweep's summary and tune's batch counts
# (docs/sweeps.md)
OUTCOMES = {"n_tracked": "tracked", "n_refined": "tracked after refinement",
            "n_diverged": "diverged at every step tried"}


def outcome_counts(diverged, refinements) -> tuple[np.ndarray, dict[str, int]]:
    """(the runs of a batch that did not diverge, how many had each outcome of `OUTCOMES`:
    tracked at the step asked, tracked once refined (`refinements` > 0), diverged at every
    step tried)."""
    ok = ~np.asarray(diverged).astype(bool)
    refined = ok & (np.asarray(refinements) > 0)
    return ok, {"n_tracked": int((ok & ~refined).sum()), "n_refined": int(refined.sum()),
                "n_diverged": int((~ok).sum())}


def refinement_level(j: int, solver: Solver | None = None) -> tuple[Solver, int]:
    """(solver, halvings of dt) of refinement level j: 0 is the requested solver (default
    RK4) at dt; then ETDRK4 (exact on the stiff decays) at dt (unless the run was ETDRK4's),
    dt/2, dt/4, ..."""
    if j == 0:
        return solver or RK4(), 0
    return ETDRK4(), (j if isinstance(solver, ETDRK4) else j - 1)


def counted_levels(spec: RunSpec) -> int:
    """The refinement levels up to `spec.refine` whose step count fits `validation.MAX_STEPS`;
    at most one for a sampled loop (its held input makes the plant non-stiff: a sampled loop
    that diverges again once refined is unstable, `sampled_unstable`)."""
    refine = min(spec.refine, SAMPLED_REFINE) if spec.sampled else spec.refine
    while refine and (spec.n_steps * 2 ** refinement_level(refine, spec.solver)[1]
                      > validation.MAX_STEPS):
        refine -= 1
    return refine


def sampled_unstable(spec: RunSpec, t_first, t_refined) -> bool:
    """A sampled loop that diverged at its step and again, refined, within one sample period
    of the same time: the loop (Ts, delay, noise) is unstable, not the integrator."""
    return spec.sampled and bool(abs(float(t_first) - float(t_refined))
                                 <= float(spec.sample_time) * (1 + 1e-9))


def sampled_unstable_line(spec: RunSpec, t_diverged: float) -> str:
    """One line naming what makes a sampled loop unstable: its sample time, delay and noise."""
    what = [f"sample time {spec.sample_time:g} s"]
    delay = int(spec.delay)  # (a number of samples; an array after RunSpec.for_dtype)
    if delay:
        what.append(f"input delay {delay} sample{'s' if delay > 1 else ''}")
    if spec.noise is not None and np.any(np.asarray(spec.noise) > 0):
        what.append("measurement noise std "
                    + ",".join(f"{v:g}" for v in np.atleast_1d(np.asarray(spec.noise, float))))
    return (f"the sampled loop is unstable ({', '.join(what)}): it diverges at t = "
            f"{float(t_diverged):.6g} s at the plant's step and refined alike, so no smaller "
            f"step helps; use a shorter sample time, less delay or noise, or revise the gains")


def level_spec(spec: RunSpec, j: int) -> RunSpec:
    """The spec of refinement level j (`refinement_level`) of a run."""
    solver, halvings = refinement_level(j, spec.solver)
    return spec.refined(halvings, solver) if j else spec


def refuse_traced_refinement(spec: RunSpec, where: str, values) -> None:
    """ValueError if `values` are traced (jit, grad, vmap) and `spec` would refine a diverged
    run: refinement re-runs it on the host, which a traced call cannot do (a silent skip would
    make the traced function another one)."""
    if counted_levels(spec) and not validation.is_concrete(values):
        raise ValueError(
            f"{where}: refine={spec.refine} re-runs a diverged run on the host, which a traced "
            f"call (jit, grad, vmap) cannot do; pass refine=0 (the same single run traced or "
            f"not), or use dscjax.objective (a pure function of chosen numbers)")


def refine_rows(rows, failed: Callable[[Any], np.ndarray], level: Callable, refine: int):
    """(rows as NumPy arrays, each row's level) after re-running the `failed(tree)` rows of
    a batch (leading axis) at levels 1..refine, host-side: `level(j, idx)` runs rows idx at
    level j; each level runs the rows still failed, padded to a power of two (one program for
    similar sizes)."""
    out = jax.tree.map(np.array, rows)
    todo = np.flatnonzero(failed(out))
    levels = np.zeros(len(failed(out)), np.int32)
    for j in range(1, refine + 1):
        if todo.size == 0:
            break
        size = 1 << int(np.ceil(np.log2(todo.size)))
        idx = xla.tiles(todo, size)[0]
        sub = jax.tree.map(lambda a, n=todo.size: np.asarray(a)[:n], level(j, idx))
        for dst, src in zip(jax.tree.leaves(out), jax.tree.leaves(sub), strict=True):
            dst[todo] = src  # out's leaves are its own NumPy arrays: written in place
        levels[todo] = j
        todo = todo[failed(sub)]
    return out, levels


class DivergenceError(RuntimeError):
    """A simulation left the state bound or went non-finite. `.trajectory` holds the run,
    frozen at its last good state."""

    def __init__(self, message: str, trajectory):
        super().__init__(message)
        self.trajectory = trajectory


def diverged_lines(status, t_diverged, state_bound: float | None = None) -> list[str]:
    """One line per diverged run of a `Status` (a batch's or one run's): which one (batch
    index), when (`t_diverged`, per run or one time) and how."""
    code = np.atleast_1d(np.asarray(status.code))
    t_bad = np.broadcast_to(np.asarray(t_diverged), code.shape)
    batched = np.ndim(status.code) > 0
    how = {STATUS_NONFINITE: "a state became non-finite (inf/NaN)",
           STATUS_BOUND: "a state exceeded the state bound"
           + (f" {state_bound:g}" if state_bound is not None else "")}
    return [f"{f'trajectory {i}' if batched else 'the trajectory'} diverged at t = "
            f"{t_bad[i]:.6g} s: {how[int(code[i])]}" for i in np.flatnonzero(code != STATUS_OK)]


def divergence_report(traj, state_bound: float | None = None) -> list[str]:
    """One line per diverged trajectory: which one (batch index), when, and how."""
    advice = ("; outputs after that time hold the last good state. Reduce dt (RK4 stability) "
              "or revise the gains.")
    return [line + advice for line in diverged_lines(traj.status, traj.t_diverged, state_bound)]
