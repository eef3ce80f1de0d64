"""The worst-case search: each method of `dscjax.search` ("gradient": projected ascent from M
starts; "random"; "cma") minimises -metric over a `Problem`'s box for the same search time,
and the best points are re-checked by `simulate` (with refinement) on the worst setup
(`worst_case`, `Result`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from dscjax import files, search, settings, validation
from dscjax.closed_loop import Setup
from dscjax.rules import AtLeast, Custom, Maybe, Positive, Strings
from dscjax.settings import setting
from dscjax.simulate import simulate
from dscjax.validation import ConfigError
from dscjax.worst.problem import (
    DEFAULT_METRIC,
    METRICS,
    REQUIREMENT,
    Problem,
    check_disturbance,
    check_metric,
)
from dscjax.worst.programs import Programs

Method = Literal["gradient", "random", "cma"]
METHODS: tuple[str, ...] = get_args(Method)
DEFAULT_STARTS = 4  # docs/worst-case.md
DEFAULT_BATCH = 32  # random and CMA-ES candidates per batched simulation
DEFAULT_COARSENING = 4  # gradients at 4 dt (docs/worst-case.md)


@dataclasses.dataclass(frozen=True)
class WorstSettings:
    """[worst]: what `dscjax worst-case` maximises and how it searches (the box: --range or
    [worst.ranges], as a sweep's)."""

    metric: str = setting(
        DEFAULT_METRIC, f"the metric maximised: one of {', '.join(METRICS)}, or "
        f"{REQUIREMENT}NAME, the violation margin of [tuning.requirements.NAME] of the config "
        f"(> 0: violated)", Custom(check_metric, "a metric's name"), flag="--metric")
    disturbance: str | None = setting(
        None, "a searched waveform added to dbar with max|dbar| <= D: fourier:K:D (K "
        "harmonics) or spline:K:D (K knots over the horizon); none",
        Maybe(Custom(check_disturbance, "fourier:K:D or spline:K:D", metavar="KIND:K:D")),
        flag="--disturbance")
    period: float | None = setting(None, "period [s] of a fourier waveform; none: the horizon",
                                   Maybe(Positive()), flag="--period")
    time_limit: float = setting(60.0, "search seconds per method, compilation excluded",
                                Positive(), flag="--time-limit")
    max_evals: int | None = setting(
        None, "evaluations after which a method ends (its last batch finished), unless "
        "time_limit comes first; none: the time alone", Maybe(AtLeast(1)), flag="--max-evals")
    starts: int = setting(DEFAULT_STARTS, "starts of the gradient search, one batch",
                          AtLeast(1), flag="--starts")
    batch: int = setting(DEFAULT_BATCH, "candidates per batch of random sampling and CMA-ES",
                         AtLeast(1), flag="--batch")
    gradient_coarsening: int = setting(
        DEFAULT_COARSENING, "the gradient method's gradients are the loop's at this x dt, its "
        "values at dt (1: exact gradients)", AtLeast(1), flag="--gradient-coarsening")
    methods: tuple[str, ...] = setting(METHODS, f"the methods run, of {', '.join(METHODS)}",
                                       Strings(), flag="--methods")
    seed: int = setting(0, "seed of every random draw", AtLeast(0), flag="--seed")

    def validate(self, prefix: str = "worst") -> None:
        for m in self.methods:
            validation.one_of(m, f"{prefix}.methods", METHODS)
        if not self.methods:
            raise ConfigError(f"{prefix}.methods: give at least one of {', '.join(METHODS)}")


def best_value(trace: search.Trace) -> float:
    """The best metric value of a method's trace (-inf before a finite one)."""
    return -trace.best_loss


def search_method(name: str, *, starts: int = DEFAULT_STARTS, batch: int = DEFAULT_BATCH,
                  m: int = 0):
    """The `dscjax.search` method of a worst-case method name (m: waveform coefficients)."""
    return {"gradient": search.Gradient(starts=starts, screen=max(batch, starts), coupled=m),
            "random": search.Random(batch=batch), "cma": search.CMA(popsize=batch)}[name]


@dataclasses.dataclass
class Result:
    """The worst case found and each method's trace."""

    problem: Problem
    value: float  # the metric of `simulate` on the worst setup (+inf: the loop diverges)
    z: np.ndarray
    method: str
    setup: Setup
    diverged: bool
    t_diverged: float | None
    refinements: int
    traces: dict[str, search.Trace]
    nominal_value: float
    info: dict
    trajectory: Any  # `simulate`'s run of `setup` (kept for the report's files)
    nominal: Any  # and of the nominal point (zero waveform: the same values exactly)


def _check_run(problem: Problem, setup) -> dict[str, Any]:
    """`simulate` of one candidate with refinement: the fields of a `Result` that it gives."""
    traj = simulate(setup, spec=problem.spec.replace(save_every=1), throw=False,
                    extra=problem.requirement)
    bad = bool(traj.diverged)
    return dict(value=math.inf if bad else float(traj.metrics[problem.metric_key]), setup=setup,
                diverged=bad, t_diverged=float(traj.t_diverged) if bad else None,
                refinements=int(traj.refinements), trajectory=traj)


def worst_case(problem: Problem, *, time_limit: float = 60.0, starts: int = DEFAULT_STARTS,
               methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
               coarsening: int = DEFAULT_COARSENING, out_dir: str | Path | None = None,
               resume: bool = False, max_evals: int | None = None,
               progress: Callable[[str, search.Trace, float], None] | None = None,
               say: Callable[[str], None] | None = None) -> Result:
    """Search the worst case of `problem` with each method for `time_limit` seconds (or
    `max_evals` evaluations, whichever comes first).

    Args:
        problem: from `make_problem`.
        time_limit: search seconds per method (compilation excluded).
        starts: M, the gradient method's starts, advanced as one batch.
        methods: any of "gradient", "random", "cma".
        seed: every random draw is a function of (seed, method, iteration).
        batch: candidates per batch of random and CMA-ES.
        coarsening: F, gradients of the loop at F dt (1: exact gradients of the values).
        out_dir: where each method's state is saved after every iteration (for `resume`).
        max_evals: stop a method after this many candidates (its last batch finished); a
            count, unlike a time, sees the same points under any load.
        progress: called with (method, trace, time_limit) after every iteration.
        say: called with a line of text as each phase begins (a method's compilation and
            search, the re-check), so that no long phase passes in silence.

    Returns:
        `Result`; its value is re-checked by `simulate` (with refinement) on the worst setup.

    Example:
        >>> import dscjax
        >>> from dscjax.params import parse_range
        >>> from dscjax.worst import make_problem, worst_case
        >>> problem = make_problem(dscjax.paper_example(), [parse_range("hysteresis.alpha=30%")],
        ...                        "fourier:2:0.5", t_final=2.0)  # doctest: +SKIP
        >>> res = worst_case(problem, time_limit=5.0)  # doctest: +SKIP
        >>> res.value, res.problem.values_at(res.z)  # doctest: +SKIP
    """
    check_search(problem, methods, starts=starts, batch=batch, time_limit=time_limit,
                 max_evals=max_evals, coarsening=coarsening)
    # "gradient": the one kind there is, kept so that a search saved with it resumes
    fp = {"problem": files.digest(problem.fingerprint()), "gradient": "time_parallel",
          "coarsening": coarsening}
    prog = Programs.for_problem(problem, coarsening)
    traces = run_methods(prog, time_limit=time_limit, starts=starts, methods=methods,
                         seed=seed, batch=batch, out_dir=out_dir, resume=resume,
                         fingerprint=fp, progress=progress, max_evals=max_evals, say=say)
    return _finish(problem, traces, say)


def check_search(problem: Problem, methods: Sequence[str], *, starts: int, batch: int,
                 time_limit: float, max_evals: int | None = None, coarsening: int = 1) -> None:
    """The search settings of `worst_case`, checked before anything runs by the rules of
    `WorstSettings` (ConfigError naming the option, or `worst.methods`: the command refuses
    bad methods earlier, naming the option typed; an infinite time_limit is allowed here), and
    the coarsening against the problem's steps."""
    if not (time_limit > 0):
        raise ConfigError(f"--time-limit must be > 0 (got {time_limit!r})")
    flags = {key: s.flag for key, s in settings.declared(WorstSettings).items()}
    settings.checked(WorstSettings(methods=tuple(methods), starts=starts, batch=batch,
                                   max_evals=max_evals, gradient_coarsening=coarsening),
                     flags.get).validate("worst")
    spec = problem.spec
    if spec.n_steps % coarsening:
        raise ConfigError(f"--gradient-coarsening {coarsening} must divide the number of "
                          f"steps t_final/dt = {spec.n_steps}")
    if spec.sampled and spec.sample_every % coarsening:
        raise ConfigError(f"--gradient-coarsening {coarsening} must divide the steps per "
                          f"controller sample, sample_time/dt = {spec.sample_every}")


def run_methods(prog: Programs, *, time_limit: float, starts: int = DEFAULT_STARTS,
                methods: Sequence[str] = METHODS, seed: int = 0, batch: int = DEFAULT_BATCH,
                out_dir: str | Path | None = None,
                resume: bool = False, fingerprint: Any = None,
                progress: Callable | None = None,
                max_evals: int | None = None,
                say: Callable[[str], None] | None = None) -> dict[str, search.Trace]:
    """Run each method on the programs for `time_limit` search seconds (compilation apart)
    or `max_evals` evaluations, whichever comes first, each from its `state_<method>.npz` in
    out_dir with `resume`; {method: Trace}. `say` gets a line as each method begins."""
    traces = {}
    for name in methods:
        if say is not None:
            say(f"{name}: compiling its programs, then searching")
        each = None if progress is None else (
            lambda tr, row, name=name: progress(name, tr, time_limit))
        res = search.run(prog, search_method(name, starts=starts, batch=batch, m=prog.m),
                         x0=prog.x0, seed=seed, time_limit=time_limit, max_evals=max_evals,
                         path=None if out_dir is None else Path(out_dir) / f"state_{name}.npz",
                         resume=resume, fingerprint=fingerprint, progress=each, count_compile=False)
        traces[name] = res.trace
    return traces


def _finish(problem: Problem, traces: dict[str, search.Trace],
            say: Callable[[str], None] | None = None) -> Result:
    """Re-check each method's best point and its diverged candidates with `simulate`; the
    worst of them is the result."""
    candidates = {}  # each distinct point once, with the first method that found it
    for mth, tr in traces.items():
        for z in ([] if tr.best_z is None else [tr.best_z]) + list(tr.diverged_z[:2]):
            candidates.setdefault(np.asarray(z).tobytes(), (mth, z))
    if not candidates:
        raise ConfigError("no candidate was evaluated: give a larger --time-limit")
    if say is not None:
        say(f"re-checking {len(candidates)} candidate(s) and the nominal point by simulate")
    # the largest value, of diverged ones (+inf) the earliest, the first found of equals; one
    # trajectory held at a time beside the best (the memory check's count)
    mth, z, worst = max(((mth, z, _check_run(problem, problem.setup_at(z)))
                         for mth, z in candidates.values()),
                        key=lambda run: (run[2]["value"], -(run[2]["t_diverged"] or 0.0)))
    # the nominal point with the zero waveform: the value without one exactly (dbar + 0), and
    # the program of the candidates' re-check serves it
    nominal = _check_run(problem, problem.setup)
    return Result(problem, z=np.asarray(z), method=mth, traces=traces,
                  nominal_value=nominal["value"], info={"rechecked": len(candidates)},
                  nominal=nominal["trajectory"], **worst)
