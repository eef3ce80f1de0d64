"""A tuning run end to end: build the problem, iterate with progress and checkpoints, resume.

    problem = build_problem(setup, options, TuningConfig())
    result = run(problem, out_dir="results/tune")          # or resume=True
    result.best_setup                                       # the tuned Setup

`run` writes the checkpoint files (see checkpoint.py) every `save_interval` iterations, when
the best point improves (at most once a second), on Ctrl-C and at the end, so an interrupted
run (Ctrl-C, kill) resumes with `resume=True` from its last checkpoint and never loses the
best point written before it stopped.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import config as dconfig
from dscjax import files
from dscjax import ranges as rg
from dscjax.config import SimOptions
from dscjax.plant import PaperPlant
from dscjax.progress import critical
from dscjax.reference import SmoothStep
from dscjax.validation import ConfigError
from tuning import checkpoint as ck
from tuning.config import TuningConfig
from tuning.objective import Combined, Objective, SimSpec, start_scales
from tuning.optimize import SEARCHES, choose_gradient, init_state, make_step
from tuning.params import Selection
from tuning.requirements import KINDS
from tuning.search import line_points

# Elements with no effect on the paper's plant (f_2 = 0 in eq. 73): gamma_g2 and eta_2 only
# act on theta_hat_2, which multiplies f_2. Frozen by default on that plant: tuning them would
# cost a tangent each for a zero gradient.
PAPER_PLANT_FREEZE = ("controller.gamma_g[1]", "controller.eta[1]")
TAU_MIN_STEPS = 2.0  # default lower bound of tau: 2 dt (RK4 is stable for dt/tau <= 2.785)
# Options added after runs were saved, per part of `Problem.describe`: left out of the
# fingerprint at these values (what the older runs did), so that those runs still resume
NEW_OPTIONS = {"params": {"scale": False}, "objective": {"effort_bounds": "nominal"},
               "optimizer": {"line_backoff": 0, "line_inject": True,
                             "line_generations": 0}}


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Everything a run needs, built and validated (see `build_problem`)."""

    setup: Any
    options: SimOptions
    cfg: TuningConfig
    selection: Selection
    objective: Objective
    heldout: dict | None
    mode: str
    z0: dict
    notes: tuple[str, ...] = ()
    extra_plants: dict | None = None  # {path: (k, ...)} plants added to the training batch
    members: tuple[Problem, ...] = ()  # the problems a `combine`d one is made of

    @property
    def n_train(self) -> int:
        """Plants of the training set (1: the nominal plant alone)."""
        ov = self.objective.overrides
        return len(next(iter(ov.values()))) if ov else 1

    @property
    def n_params(self) -> int:
        return self.selection.size(self.setup)

    def _mode_desc(self) -> str:
        # "auto" now picks "plants" where it picked forward or reverse mode before: same
        # numbers, so the fingerprint keeps the older choice (older runs still resume)
        if self.mode == "plants" and self.cfg.optimizer.gradient == "auto":
            return choose_gradient("auto", self.n_params, self.objective.batch_size)
        return self.mode

    def describe(self) -> dict:
        """JSON-able description; its fingerprint must match to resume."""
        opt = dataclasses.asdict(self.cfg.optimizer)
        for k in ("steps", "time_limit", "patience", "max_rejections", "save_interval",
                  "decay_steps", "regrow", "shrink", "min_delta", "restarts"):
            opt.pop(k)
        if opt["name"] not in SEARCHES or not line_points(self.cfg.optimizer):
            opt.pop("line_generations")  # no line: it changes nothing
        return {
            "setup": dconfig.to_dict(self.setup, self.options),
            "params": [ck.drop_defaults(dataclasses.asdict(t), NEW_OPTIONS["params"])
                       for t in self.selection.items],
            "objective": ck.drop_defaults(dataclasses.asdict(self.cfg.objective),
                                          NEW_OPTIONS["objective"]),
            "optimizer": ck.drop_defaults(opt, NEW_OPTIONS["optimizer"]),
            "robust": _batch_desc(self.cfg.robust, self.setup),
            "requirements": dict(self.cfg.requirements),
            "sim": dataclasses.asdict(self.objective.sim),
            "mode": self._mode_desc(),
        } | ({"extra_plants": {k: np.asarray(v).tolist() for k, v in self.extra_plants.items()}}
             if self.extra_plants else {}) | (
            {"members": [m.describe() for m in self.members], "combine": self.objective.how}
            if self.members else {})


def _batch_desc(b, setup):
    d = dataclasses.asdict(b)
    d["ranges"] = [r.resolve(setup).spec() for r in b.ranges]
    return d


def default_freeze(setup, tune) -> tuple[str, ...]:
    if isinstance(setup.plant, PaperPlant) and "controller.gamma_g" in tune:
        return tuple(p for p in PAPER_PLANT_FREEZE if p.split("[")[0] in tune)
    return ()


def model_default_ranges(cfg: TuningConfig, setup) -> TuningConfig:
    """Batches left at the default ranges vary the setup's own hysteresis model's numbers
    (`default_ranges(setup)`: alpha, lam, psi only for the backlash-like model)."""
    from dscjax.ranges import default_ranges

    for key in ("robust", "heldout"):
        b = getattr(cfg, key)
        if b.ranges == default_ranges():
            cfg = dataclasses.replace(cfg, **{key: dataclasses.replace(
                b, ranges=default_ranges(setup))})
    return cfg


def build_problem(setup, options: SimOptions, cfg: TuningConfig,
                  extra_plants: dict | None = None) -> Problem:
    """Validate the tuning settings against the setup and build the objective.

    `extra_plants` ({path: (k, ...)}, e.g. the worst cases of `tuning.adversarial`) join the
    training batch (or the nominal plant, without one). Raises ConfigError (naming the field)
    on any bad setting.
    """
    from dscjax.metrics import default_window
    from dscjax.validation import validate_run, validate_setup

    cfg.validate()
    validate_setup(setup)
    cfg = model_default_ranges(cfg, setup)
    notes = []
    window = cfg.objective.window_start
    if window is None:
        window = default_window(options.t_final, options.window_start)
    validate_run(setup, options.t_final, options.dt, 1, window)
    freeze = cfg.freeze if cfg.freeze is not None else default_freeze(setup, cfg.params)
    if cfg.freeze is None and freeze:
        notes.append(f"frozen by default on the paper's plant (no effect, f_2 = 0): "
                     f"{', '.join(freeze)}")
    bounds = dict(cfg.bounds)
    if "controller.tau" in cfg.params and not any(k.startswith("controller.tau")
                                                   for k in bounds):
        bounds["controller.tau"] = (TAU_MIN_STEPS * options.dt, None)
        notes.append(f"controller.tau >= {TAU_MIN_STEPS:g} dt = {TAU_MIN_STEPS * options.dt:g} "
                     f"s by default (RK4 stability of the filters)")
    selection = Selection.build(setup, cfg.params, freeze, bounds, cfg.transforms)
    n_params = selection.size(setup)
    n_extra = len(next(iter(extra_plants.values()))) if extra_plants else 0
    mode = choose_gradient(cfg.optimizer.gradient, n_params,
                           (cfg.robust.batch if cfg.robust.batch > 0 else 1) + n_extra,
                           cfg.robust.aggregate, cfg.robust.cvar_level)
    ce = cfg.optimizer.checkpoint_every if mode == "reverse" else None
    sim = SimSpec(t_final=options.t_final, dt=options.dt, window_start=float(window),
                  state_bound=options.state_bound, checkpoint_every=ce, solver=options.solver)
    batches = {}
    for key in ("robust", "heldout"):
        b = getattr(cfg, key)
        if b.batch > 0:
            batches[key] = _sample(setup, b, f"tuning.{key}.ranges", options)
    train, heldout = batches.get("robust"), batches.get("heldout")
    if extra_plants:
        train = join_plants(setup, train, extra_plants)
    requirements = build_requirements(setup, cfg.requirements)
    scales = start_scales(setup, sim, cfg.objective, train)
    if scales.per_plant:
        n = len(next(iter(train.values())))
        notes.append(f"effort bounds per training plant: the start gains' own max|u| and "
                     f"{cfg.objective.tv_max_factor:g} x TV(u) on each of the {n} plants"
                     + (f" ({scales.n_train_fallback} on which the start gains diverge keep "
                        f"the nominal plant's)" if scales.n_train_fallback else ""))
    objective = Objective(setup=setup, selection=selection, spec=cfg.objective, sim=sim,
                          scales=scales, requirements=requirements, overrides=train,
                          aggregate=cfg.robust.aggregate if train else "mean",
                          cvar_level=cfg.robust.cvar_level)
    return Problem(setup=setup, options=options, cfg=cfg, selection=selection,
                   objective=objective, heldout=heldout, mode=mode,
                   z0=selection.init(setup), notes=tuple(notes), extra_plants=extra_plants)


def join_plants(setup, first: dict | None, then: dict) -> dict:
    """{path: (n1 + n2, ...)}: the plants of `first` (None: the nominal plant alone), then
    those of `then`; where one side does not vary a leaf, its plants keep the setup's value."""
    from dscjax import params

    def size(d):
        return len(next(iter(d.values()))) if d else 1

    out = {}
    for path in dict.fromkeys([*(first or {}), *then]):
        leaf = np.asarray(params.get(setup, path))
        cols = [np.asarray(d[path]) if d and path in d
                else np.broadcast_to(leaf, (size(d), *leaf.shape)) for d in (first, then)]
        out[path] = np.concatenate(cols).astype(leaf.dtype)
    return out


def combine(problems, how: str = "mean") -> Problem:
    """One problem whose loss is the mean (or max) of the problems' losses (`Combined`): the
    same tuned gains over setups of different structure, e.g. `build_problem` once per
    hysteresis kind, each with its own robust batch. The problems must tune the same
    parameters (same names and sizes) with the same settings, and start from the same
    values; the result's setup, gains.json and report are the first problem's.

        probs = [build_problem(hysteresis_example(k), options, cfg) for k in ("pi", "gpi")]
        result = run(combine(probs, "max"))
    """
    first = problems[0]
    if first.cfg.optimizer.name in SEARCHES:
        # (the search methods simulate one batch of one structure per generation)
        raise ConfigError(f"combine: tuning.optimizer.name must be one of the gradient rules "
                          f"(adam, adamw, sgd, lion), not the search method "
                          f"{first.cfg.optimizer.name!r}; e.g. name = \"adam\"")
    for p in problems[1:]:
        if (p.selection.names != first.selection.names or p.cfg.optimizer != first.cfg.optimizer
                or p.objective.sim != first.objective.sim or p.n_params != first.n_params):
            raise ConfigError("combine: every problem must tune the same parameters with the "
                              "same optimizer and simulation settings")
        for k in first.z0:
            if not np.array_equal(np.asarray(p.z0[k]), np.asarray(first.z0[k])):
                raise ConfigError(f"combine: the problems start from different values of {k}")
    objective = Combined(tuple(p.objective for p in problems), how)
    gradient = first.cfg.optimizer.gradient
    if gradient == "plants":
        raise ConfigError("tuning.optimizer.gradient = \"plants\" differentiates one batch "
                          "plant by plant; combine objectives with \"auto\", \"forward\" or "
                          "\"reverse\"")
    # each member's own choice (forward over a batch, reverse for one plant) if they agree;
    # not "plants" (the members' batches differ): then the choice for the whole
    modes = {p.mode for p in problems}
    mode = (next(iter(modes)) if len(modes) == 1 and "plants" not in modes else
            choose_gradient(gradient, first.n_params, objective.batch_size))
    return dataclasses.replace(first, objective=objective, heldout=None, mode=mode,
                               members=tuple(problems), extra_plants=None,
                               notes=first.notes + (f"{how} of {len(problems)} objectives",))


def _sample(setup, b, field, options) -> dict:
    """{path: (batch, ...)}: the plants of a [tuning.robust] or [tuning.heldout] table."""
    ranges = rg.check(b.ranges, setup, field, t_final=options.t_final, dt=options.dt)
    return rg.sample_overrides(setup, ranges, b.batch, b.seed, b.method)


def build_requirements(setup, table) -> tuple:
    out = []
    dtype = jnp.result_type(setup.plant.x0)
    for name, values in table.items():
        values = dict(values)
        if name == "step":
            ref = setup.reference
            if "final" not in values or "height" not in values:
                if not isinstance(ref, SmoothStep):
                    raise ConfigError("tuning.requirements.step needs a step reference "
                                      "(reference.kind = \"smooth_step\") or both 'final' and "
                                      "'height'")
                values.setdefault("height", float(ref.height))
                values.setdefault("final", float(ref.initial) + float(ref.height))
            if values["height"] == 0:
                raise ConfigError("tuning.requirements.step.height must be != 0")
        out.append(KINDS[name](**{k: jnp.asarray(v, dtype) for k, v in values.items()}))
    return tuple(out)


# -- the loop ------------------------------------------------------------------------------------


@dataclasses.dataclass
class Result:
    problem: Problem
    state: Any
    history: list[dict]
    stop_reason: str
    wall_s: float  # this invocation
    compile_s: float
    resumed_from: int
    method: str = "optax"
    evaluations: int | None = None  # loss evaluations (None: one per iteration)
    gradient_evaluations: int | None = None

    @property
    def best_z(self):
        return self.state.best_z

    @property
    def best_setup(self):
        return self.problem.selection.apply(self.problem.setup, self.state.best_z)


def history_columns(problem: Problem) -> list[str]:
    terms = list(_term_names(problem))
    return (["iteration", "loss", "accepted", "feasible", "best_loss", "lr", "grad_norm",
             "linf_window", "max_abs_u", "n_diverged"] + terms + ["wall_s"])


def _term_names(problem):
    spec, obj = problem.cfg.objective, problem.objective
    names = [n for n in ("linf", "l2", "effort_l2", "effort_max", "effort_tv")
             if getattr(spec, n)]
    if obj.scales.u_max is not None and spec.u_max_weight:
        names.append("u_bound")
    if obj.scales.tv_max is not None and spec.tv_max_weight:
        names.append("tv_bound")
    names += [f"req{i}" for i in range(len(obj.requirements))]
    return names


def check_out_dir(out: Path, resume: bool, overwrite: bool) -> None:
    """ConfigError unless the directory's state fits: --resume needs a checkpoint, and an
    existing run is only replaced with --overwrite."""
    out = Path(out)
    has = (out / "checkpoint.json").exists()
    if resume and not has:
        raise ConfigError(f"--resume: nothing to resume in {out} (checkpoint.json is missing); "
                          f"run without --resume to start afresh")
    if has and not resume and not overwrite:
        raise ConfigError(f"{out} already holds a tuning run; use --resume to continue it or "
                          f"--overwrite to start afresh")


def _prepare_dir(out: Path, resume: bool, overwrite: bool) -> None:
    check_out_dir(out, resume, overwrite)
    files.mkdir(out)
    if overwrite:
        for name in ck.FILES:
            (out / name).unlink(missing_ok=True)


def run(problem: Problem, out_dir: str | Path | None = None, *, resume: bool = False,
        overwrite: bool = False, progress: Callable[[dict], None] | None = None,
        step_hook: Callable | None = None, z_init: dict | None = None) -> Result:
    """Iterate until steps, time limit, early stopping or too many rejections.

    Args:
        out_dir: where checkpoints go (None: nothing is written).
        resume: continue from the checkpoint in out_dir (the problem must be the same; the
            stopping settings steps/time_limit/patience may differ).
        z_init: the first point (default `problem.z0`, the start gains; the report still
            compares against `problem.z0`); ignored on resume.
        progress: called with each iteration's row (dict) for a progress display.
        step_hook: test hook, (state, report) -> report, applied to every report on the host.
    """
    if problem.cfg.optimizer.name in SEARCHES:
        return _run_search(problem, None if out_dir is None else Path(out_dir), resume,
                           overwrite, progress, z_init)
    loop = _Loop.open(problem, None if out_dir is None else Path(out_dir), resume, overwrite,
                      z_init)
    try:
        while (reason := loop.limit_reached()) is None:
            # a Ctrl-C waits for the iteration, its row and its checkpoint (dscjax.progress)
            with critical():
                row = loop.iterate(step_hook)
                loop.checkpoint(every=loop.spec.save_interval)
            if progress is not None:
                progress(row | {"steps": loop.spec.max_steps, "terms": loop.terms,
                                "n_rejected": int(loop.state.n_rejected)})
            if (reason := loop.stalled()) is not None:
                break
    except KeyboardInterrupt:
        loop.save(stop_reason="interrupted")
        raise
    loop.save(stop_reason=reason)
    if not np.isfinite(float(loop.state.best_loss)):
        raise ConfigError("no iteration produced a finite loss: the start point is not usable "
                          "(see the divergence report of `dscjax simulate`)")
    return Result(problem=problem, state=loop.state, history=loop.history, stop_reason=reason,
                  wall_s=time.perf_counter() - loop.t_start, compile_s=loop.compile_s,
                  resumed_from=loop.resumed_from)


def _run_search(problem: Problem, out: Path | None, resume: bool, overwrite: bool,
                progress, z_init: dict | None = None) -> Result:
    """The cma / cma_grad loop (tuning/search.py) under the same stopping rules and files."""
    from tuning.search import STATE_FILE, Search

    t_start = time.perf_counter()
    if out is not None:
        _prepare_dir(out, resume, overwrite)
        if overwrite:
            (out / STATE_FILE).unlink(missing_ok=True)
    loop = Search.open(problem, out, resume, t_start, z_init)
    spec = loop.spec
    # a Ctrl-C waits for the compilation too: one that cuts XLA's ahead-of-time compilation
    # short makes the process crash as it exits
    with critical():
        loop.compile()
    reason = None
    try:
        while True:
            elapsed = time.perf_counter() - t_start
            if spec.max_steps is not None and loop.state.iteration >= spec.max_steps:
                reason = f"reached {spec.max_steps} generations"
                break
            # at least one generation, so that a slow compilation never leaves no result
            if (spec.time_limit is not None and loop.state.iteration > loop.resumed_from
                    and elapsed + loop.last_iter_s > spec.time_limit):
                reason = f"time limit {spec.time_limit:g} s"
                break
            # a Ctrl-C waits for the generation (ask, simulate, tell, inject, counters), a
            # restart and the checkpoint (dscjax.progress): the state saved is a whole one
            with critical():
                row = loop.generation()
                # before the checkpoint: a file written at this generation holds the restart
                stopped = loop.state.es.stop()
                if stopped and loop.state.restarts >= spec.restarts:
                    reason = f"CMA-ES stopped: {dict(stopped)}"
                elif stopped:
                    loop.restart()  # budget left: a fresh CMA-ES from the start point
                if reason is None and loop.state.iteration % spec.save_interval == 0:
                    loop.save()
            if progress is not None:
                progress(row | {"steps": spec.max_steps, "terms": _term_names(problem),
                                "n_rejected": 0})
            if reason is not None:
                break
            if spec.patience and loop.state.stall >= spec.patience:
                reason = (f"no improvement of the best loss by more than {spec.min_delta:g} "
                          f"(relative) in {spec.patience} generations")
                break
    except KeyboardInterrupt:
        loop.save(stop_reason="interrupted")
        raise
    loop.save(stop_reason=reason)
    if not np.isfinite(loop.state.best_loss):
        raise ConfigError("no generation produced a finite loss: the start point is not usable "
                          "(see the divergence report of `dscjax simulate`)")
    return Result(problem=problem, state=loop.state, history=loop.history, stop_reason=reason,
                  wall_s=time.perf_counter() - t_start, compile_s=loop.compile_s,
                  resumed_from=loop.resumed_from, method=spec.name,
                  evaluations=loop.state.evaluations,
                  gradient_evaluations=loop.state.gradient_evaluations)


def finished(problem: Problem, out_dir: str | Path) -> Result:
    """The `Result` of the run whose checkpoint is in `out_dir`, without iterating (a phase
    of `tuning.adversarial` that has finished)."""
    out = Path(out_dir)
    if problem.cfg.optimizer.name in SEARCHES:
        from tuning.search import Search

        search = Search.open(problem, out, True, 0.0)
        meta = files.read_json(out / "checkpoint.json")
        return Result(problem=problem, state=search.state, history=search.history,
                      stop_reason=meta.get("stop_reason") or "finished", wall_s=0.0,
                      compile_s=0.0, resumed_from=search.resumed_from,
                      method=problem.cfg.optimizer.name,
                      evaluations=search.state.evaluations,
                      gradient_evaluations=search.state.gradient_evaluations)
    loop = _Loop.open(problem, out, True, False)
    meta = files.read_json(out / "checkpoint.json")
    return Result(problem=problem, state=loop.state, history=loop.history,
                  stop_reason=meta.get("stop_reason") or "finished", wall_s=0.0,
                  compile_s=0.0, resumed_from=loop.resumed_from)


@dataclasses.dataclass
class _Loop:
    """One invocation of the tuning loop: the state, its history and its files."""

    problem: Problem
    out: Path | None
    spec: Any  # OptimizerSpec with the run's decay_steps (kept from the first invocation)
    step: Any  # the jitted step (compiled on first use)
    state: Any  # TuneState
    history: list[dict]
    resumed_from: int = 0
    elapsed_before: float = 0.0  # wall time of earlier invocations of the same run
    t_start: float = dataclasses.field(default_factory=time.perf_counter)
    compile_s: float = 0.0
    last_iter_s: float = 0.0
    last_best_write: float = 0.0

    @classmethod
    def open(cls, problem: Problem, out: Path | None, resume: bool, overwrite: bool,
             z_init: dict | None = None) -> _Loop:
        """A fresh start, or the state, history and schedule of the checkpoint in `out`."""
        t_start = time.perf_counter()
        spec = problem.cfg.optimizer
        meta = None
        if out is not None:
            _prepare_dir(out, resume, overwrite)
        if resume:
            meta = files.read_json(out / "checkpoint.json")
            files.check_same(meta.get("problem"), problem.describe(),
                             where=f"the checkpoint in {out}",
                             fix="start afresh with --overwrite or another --out")
        decay_steps = int(meta["decay_steps"]) if meta else spec.schedule_steps
        spec = dataclasses.replace(spec, decay_steps=decay_steps)
        optimizer, step = compiled_step(problem, spec)
        z_init = problem.z0 if z_init is None else jax.tree.map(jnp.asarray, z_init)
        loop = cls(problem, out, spec, step, init_state(z_init, optimizer), [],
                   t_start=t_start)
        if meta:
            state = ck.load_state(out / "checkpoint.npz", loop.state, meta["state"])
            loop.history = [r for r in ck.read_history(out / "history.csv")
                            if r["iteration"] < int(state.iteration)]
            loop.state = _best_from_file(out, state, problem)
            loop.resumed_from = int(loop.state.iteration)
            loop.elapsed_before = float(meta.get("elapsed_total_s", 0.0))
        return loop

    @functools.cached_property
    def terms(self) -> list[str]:
        return _term_names(self.problem)

    @functools.cached_property
    def schedule(self):
        return self.spec.schedule_fn()

    @functools.cached_property
    def desc(self) -> dict:
        return self.problem.describe()

    @functools.cached_property
    def rates(self) -> tuple:
        """(shrink, min_delta, regrow) as arrays: traced arguments of the step."""
        dtype = self.state.lr_scale.dtype
        return tuple(jnp.asarray(getattr(self.spec, k), dtype)
                     for k in ("shrink", "min_delta", "regrow"))

    # -- stopping ---------------------------------------------------------------------------
    def limit_reached(self) -> str | None:
        """Why to stop before the next iteration (steps, time limit), or None."""
        spec, elapsed = self.spec, time.perf_counter() - self.t_start
        if spec.max_steps is not None and int(self.state.iteration) >= spec.max_steps:
            return f"reached {spec.max_steps} iterations"
        if spec.time_limit is not None and elapsed + self.last_iter_s > spec.time_limit:
            return f"time limit {spec.time_limit:g} s"
        return None

    def stalled(self) -> str | None:
        """Why to stop after an iteration (rejections, no improvement), or None."""
        spec, state = self.spec, self.state
        if int(state.streak) >= spec.max_rejections:
            return (f"{spec.max_rejections} rejected steps in a row (non-finite or "
                    f"diverging); the learning rate is now x{float(state.lr_scale):.3g}")
        if spec.patience and int(state.stall) >= spec.patience:
            return (f"no improvement of the best loss by more than {spec.min_delta:g} "
                    f"(relative) in {spec.patience} iterations")
        return None

    # -- one iteration ------------------------------------------------------------------------
    def iterate(self, step_hook=None) -> dict:
        """One jitted step (compiled on first use: a finished run resumes at once); returns
        its row of the history."""
        if self.step.executable is None:
            t0 = time.perf_counter()
            self.step.compile(self.state, *self.rates)
            self.compile_s = time.perf_counter() - t0
        t_it = time.perf_counter()
        before = self.state
        self.state, rep = self.step.executable(self.state, *self.rates)
        rep = jax.device_get(rep)
        if step_hook is not None:
            rep = step_hook(self.state, rep)
        self.last_iter_s = time.perf_counter() - t_it
        row = self._row(int(before.iteration), rep)
        self.history.append(row)
        if float(self.state.best_loss) != float(before.best_loss):
            self._best_improved()
        return row

    def _row(self, it: int, rep: dict) -> dict:
        state = self.state
        accepted_steps = int(state.iteration) - int(state.n_rejected)
        lr = float(self.schedule(max(accepted_steps - 1, 0))) * float(rep["lr_scale"])
        return {
            "iteration": it, "loss": float(rep["loss"]), "accepted": bool(rep["accepted"]),
            "feasible": bool(rep["feasible"]), "best_loss": float(state.best_loss), "lr": lr,
            "grad_norm": float(rep["grad_norm"]),
            "linf_window": float(rep["linf_window"]), "max_abs_u": float(rep["max_abs_u"]),
            "n_diverged": int(rep["n_diverged"]),
            **{k: float(rep["terms"][k]) for k in self.terms},
            "wall_s": self.elapsed_before + time.perf_counter() - self.t_start,
            "best_iteration": int(state.best_iteration),
            "best_feasible": bool(state.best_feasible),
        }

    # -- files --------------------------------------------------------------------------------
    def _best_improved(self) -> None:
        """Write the new best point at once (at most once a second): a run killed before its
        next checkpoint keeps it."""
        now = time.perf_counter()
        if self.out is not None and now - self.last_best_write > 1:
            write_best(self.out, self.problem, self.state)
            self.last_best_write = now

    def checkpoint(self, every: int) -> None:
        """The checkpoint files, after every `every`-th iteration."""
        if int(self.state.iteration) % every == 0:
            self.save()

    def save(self, stop_reason: str | None = None) -> None:
        """Write every checkpoint file (stop_reason: the run ends here), a Ctrl-C waiting for
        them. The history and the best point first, then the state, then checkpoint.json: a
        save cut short (a full disk) leaves a state whose history and best point are on disk
        (a resume reads the history up to the state's iteration)."""
        if self.out is None:
            return
        with critical():
            self._save(stop_reason)

    def _save(self, stop_reason: str | None) -> None:
        out, state, desc = self.out, self.state, self.desc
        ck.write_history(out / "history.csv", self.history, history_columns(self.problem))
        write_best(out, self.problem, state)
        meta_state = ck.save_state(out / "checkpoint.npz", state)
        files.write_json(out / "checkpoint.json", {
            "version": ck.FORMAT_VERSION, "fingerprint": ck.fingerprint(desc),
            "iteration": int(state.iteration), "best_loss": float(state.best_loss),
            "best_iteration": int(state.best_iteration),
            "best_feasible": bool(state.best_feasible), "decay_steps": self.spec.decay_steps,
            "elapsed_total_s": self.elapsed_before + time.perf_counter() - self.t_start,
            "stop_reason": stop_reason, "state": meta_state, "problem": desc})


def compiled_step(problem: Problem, spec):
    """The optax transformation and the jitted step for the problem and update rule.

    Kept in the objective's cache (`Objective.compiled`), so that a run resumed in the same
    process (tests, experiments) does not compile again; it lives as long as the objective.
    """
    rule = (spec.name, spec.learning_rate, spec.schedule, spec.final_lr_fraction,
            spec.decay_steps, spec.clip_norm)
    key = ("tuning step", problem.mode, rule)
    cache = problem.objective.compiled
    if key not in cache:
        optimizer = spec.make()
        cache[key] = (optimizer, _AheadOfTime(make_step(
            problem.objective, optimizer, problem.selection, problem.mode,
            problem.objective.sim.checkpoint_every)))
    return cache[key]


class _AheadOfTime:
    """A jitted step compiled ahead of time once (so compilation can be timed apart)."""

    def __init__(self, step):
        self.step = step
        self.executable = None

    def compile(self, *args) -> None:
        self.executable = self.step.lower(*args).compile()


def gains_config(problem: Problem, z) -> dict:
    """The tuned setup as a dscjax config dict (all sections, the config's names)."""
    setup = problem.selection.apply(problem.setup, z)
    setup = jax.tree.map(np.asarray, setup)
    return dconfig.to_dict(setup, problem.options)


def write_best(out: Path, problem: Problem, state) -> None:
    """best.json and gains.json of the state's best point (nothing before a finite loss)."""
    if not np.isfinite(float(state.best_loss)):
        return
    z = jax.device_get(state.best_z)
    values = jax.device_get(problem.selection.values(z))
    files.write_json(out / "best.json", {
        "iteration": int(state.best_iteration), "loss": float(state.best_loss),
        "feasible": bool(state.best_feasible),
        "values": {k: np.asarray(v).tolist() for k, v in values.items()},
        "z": {k: np.asarray(v).tolist() for k, v in z.items()},
    })
    files.write_json(out / "gains.json", gains_config(problem, z))


def _best_from_file(out: Path, state, problem: Problem):
    """A best point written after the last checkpoint (best.json) replaces the state's."""
    path = out / "best.json"
    if not path.exists():
        return state
    b = files.read_json(path)
    loss, feas = float(b["loss"]), bool(b["feasible"])
    better = (feas and not bool(state.best_feasible)) or (
        feas == bool(state.best_feasible) and loss < float(state.best_loss))
    if not better or set(b["z"]) != set(problem.selection.names):
        return state
    dtype = state.best_loss.dtype
    z = {k: jnp.asarray(np.asarray(b["z"][k]), dtype).reshape(np.shape(state.best_z[k]))
         for k in state.best_z}
    return state._replace(best_z=z, best_loss=jnp.asarray(loss, dtype),
                          best_feasible=jnp.asarray(feas),
                          best_iteration=jnp.asarray(int(b["iteration"]), jnp.int32))


def format_progress(row: dict, step: str = "lr") -> str:
    """The figures of one iteration's row, for a progress display (dscjax.progress). `step`
    names the row's "lr" column: "lr" for the optax rules, "sigma" for the CMA-ES methods
    (whose rows hold CMA-ES's step size there)."""
    terms = " ".join(f"{k} {row[k]:.3g}" for k in row["terms"])
    return (f"loss {row['loss']:.4g}{'' if row['accepted'] else ' (rejected)'}  best "
            f"{row['best_loss']:.4g}  [{terms}]  Linf[t0,T] {row['linf_window']:.4g}  max|u| "
            f"{row['max_abs_u']:.4g}  {step} {row['lr']:.3g}")
