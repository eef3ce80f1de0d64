"""A tuning run end to end: build the problem, search (`dscjax.search`), write its files.

    problem = build_problem(setup, options, TuningConfig())
    result = run(problem, out_dir="results/tune")          # or resume=True
    result.best_setup                                       # the tuned Setup

The search saves its state after every iteration, `run` the other files (checkpoint.py) every
`save_interval` iterations, on Ctrl-C and at the end: `resume=True` continues exactly.
"""

from __future__ import annotations

import dataclasses
import shlex
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from dscjax import config as dconfig
from dscjax import files, params, search, settings
from dscjax.integrate import TimeParallel
from dscjax.params import default_ranges
from dscjax.plant import PaperPlant
from dscjax.runspec import RunSpec, loop_words
from dscjax.selection import Selection
from dscjax.simulate import check
from dscjax.validation import ConfigError, shortest
from tuning import checkpoint as ck
from tuning.config import SIGNED, TuningConfig
from tuning.objective import Objective, check_loops, plant_count
from tuning.optimize import Forward, Mean
from tuning.requirements import build_requirements
from tuning.scales import start_scales
from tuning.search import STATE_FILE, TuneProblem

# no effect on the paper's plant (f_2 = 0 in eq. 73: they act on theta_hat_2 only): frozen
PAPER_PLANT_FREEZE = ("controller.gamma_g[1]", "controller.eta[1]")
# [tuning.optimizer]'s keys of where to stop, no part of a run's fingerprint: a resumed run
# may change them
STOPPING = ("steps", "time_limit", "patience", "save_interval", "min_delta")
# the record of a tuning run in its directory: a plain run's, an adversarial run's (its MANIFEST)
MANIFEST = "adversarial.json"
RECORDS = (ck.RECORD, MANIFEST)
TAU_MIN_STEPS = 2.0  # default lower bound of tau: 2 dt (RK4 is stable for dt/tau <= 2.785)


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Everything a run needs, built and validated (see `build_problem`)."""

    setup: Any
    options: RunSpec  # the [simulation] table of the config (dtype float64)
    cfg: TuningConfig
    selection: Selection
    objective: Objective
    heldout: dict | None
    mode: Forward  # the AD mode of the exact gradient (`tuning.optimize`)
    z0: dict
    notes: tuple[str, ...] = ()
    extra_plants: dict | None = None  # {path: (k, ...)} plants added to the training batch
    # the continuous loop, a check in the report (None: tuned as given, `--sample-time`)
    continuous: RunSpec | None = None
    # the compiled programs of the search ({name: (objective, `search.Batched`)})
    programs: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def n_train(self) -> int:
        """Plants of the training set (1: the nominal plant alone), padding apart."""
        obj = self.objective
        return obj.batch_size if obj.mask is None else int(np.sum(obj.mask))

    @property
    def scales(self):
        """The objective's `Scales` with the per-plant bounds of the real training plants."""
        sc, n = self.objective.scales, self.n_train
        return dataclasses.replace(sc, **{k: getattr(sc, k)[:n] for k in (
            "u_max_train", "tv_max_train") if getattr(sc, k) is not None})

    @property
    def n_params(self) -> int:
        return self.selection.size(self.setup)

    def setup_at(self, z):
        """The setup with the tuned numbers at z, as host arrays."""
        return jax.tree.map(np.asarray, self.selection.apply(self.setup, z))

    def values_at(self, z) -> dict[str, list | float]:
        """The tuned numbers' values at z by name, as JSON data."""
        return {k: np.asarray(v).tolist() for k, v in
                jax.device_get(self.selection.values(z)).items()}

    def describe(self) -> dict:
        """JSON-able description; its fingerprint must match to resume."""
        return _description(self.setup, self.options, self.cfg, self.selection,
                            self.objective.sim, self.objective.checks, self.mode, self.extra_plants)


def _description(setup, options, cfg, selection, sim, checks, mode, extra_plants) -> dict:
    """`Problem.describe` of these parts (the start gains' evaluation plays no part)."""
    return {
        "setup": dconfig.to_dict(setup, options),
        "params": [t.describe() for t in selection.items],
        "objective": settings.plain(cfg.objective),
        "optimizer": {k: v for k, v in settings.plain(cfg.optimizer).items()
                      if k not in STOPPING},
        "robust": settings.plain(cfg.robust) | {
            "ranges": [r.resolve(setup).spec() for r in cfg.robust.ranges]},
        "requirements": dict(cfg.requirements),
        "sim": sim.describe(),
        "checks": {c.name: c.sim.describe() for c in checks},
        "mode": mode.name,
    } | ({"extra_plants": {k: np.asarray(v).tolist() for k, v in extra_plants.items()}}
         if extra_plants else {})


# the held-out batch's default box beyond the hysteresis: the plant's g and theta (one factor
# scaling each vector: g within -+20 %, but not below the controller's g_min, Assumption 4)
# and the amplitude of a disturbance dbar_amp sin(dbar_freq t)
HELDOUT_PLANT = (("plant.g*", (0.8, 1.2)), ("plant.theta*", (0.7, 1.3)),
                 ("plant.dbar_amp", (0.0, 0.2)))


def heldout_ranges(setup) -> tuple:
    """The held-out batch's default box: the hysteresis model's numbers (`default_ranges`)
    and, where the plant has them, `HELDOUT_PLANT`."""
    out = []
    for path, (low, high) in HELDOUT_PLANT:
        name = path.split(".")[1].rstrip("*")
        if not hasattr(setup.plant, name):
            continue
        g_min = getattr(setup.controller, "g_min", None)
        if name == "g" and g_min is not None:
            low = max(low, float(np.max(g_min)) / float(np.min(np.abs(setup.plant.g))))
        out.append(params.Range(params.Param.parse(path), low=low, high=max(high, low)))
    return default_ranges(setup) + tuple(out)


def model_default_ranges(cfg: TuningConfig, setup) -> TuningConfig:
    """Batches left at the default ranges vary the setup's own hysteresis model's numbers;
    the held-out batch also the plant (`heldout_ranges`)."""
    for key, ranges in (("robust", default_ranges), ("heldout", heldout_ranges)):
        b = getattr(cfg, key)
        if b.ranges == default_ranges():
            cfg = dataclasses.replace(cfg, **{key: dataclasses.replace(b, ranges=ranges(setup))})
    return cfg


def build_problem(setup, options: RunSpec, cfg: TuningConfig, extra_plants: dict | None = None,
                  ready: Callable[[], None] | None = None, capacity: int = 0) -> Problem:
    """Validate the tuning settings against the setup (ConfigError naming the field) and
    build the objective; `extra_plants` ({path: (k, ...)}, e.g. `tuning.adversarial`'s worst
    cases) join the training batch (or the nominal plant), padded to `capacity` plants with
    copies of the nominal one that weigh nothing (the objective's mask), so that batches of
    one capacity share their compiled programs. `ready()` is called once every setting is
    validated, before anything runs or compiles (the start scales run the loop): the command
    prepares its --out there."""
    parts = _parts(setup, options, cfg, extra_plants, capacity)
    cfg, notes, selection, mode, sim, checks, train, heldout, continuous = parts
    if ready is not None:
        ready()
    requirements = build_requirements(setup, cfg.requirements)
    n = plant_count(train)
    mask = None
    if train and capacity:  # (a mask even where none is padding: one structure)
        train = join_plants(setup, train, {p: np.repeat(np.asarray(params.get(setup, p))[None],
                                                        max(capacity - n, 0), axis=0)
                                           for p in train})
        mask = np.arange(max(capacity, n)) < n
    scales = start_scales(setup, sim, cfg.objective, train)
    if scales.per_plant:
        notes.append(f"effort bounds per training plant: the start gains' own max|u| and "
                     f"{cfg.objective.tv_max_factor:g} x TV(u) on each of the {n} plants"
                     + (f" ({scales.n_train_fallback} on which the start gains diverge keep "
                        f"the nominal plant's)" if scales.n_train_fallback else ""))
    objective = Objective(setup=setup, selection=selection, spec=cfg.objective, sim=sim,
                          scales=scales, requirements=requirements, overrides=train, mask=mask,
                          aggregate=cfg.robust.over if train else Mean(), checks=checks)
    notes.append(f"the loop tuned: {loop_words(sim)}")
    for c in checks:
        kept = [f"windowed L-inf within {c.linf_factor:g} x the loop tuned's",
                *(f"{what} within {f:g} x its bound" for what, _, _, f in c.bounded((1, 1)))]
        notes.append(f"checked too, in the search: the same loop with {c.label} must keep its "
                     f"{' and '.join(kept)} (penalty weight tuning.objective.{c.weight_key} = "
                     f"{c.weight:g}; 0 turns this check off)")
    if continuous is not None:
        notes.append(f"the continuous loop (RK4 at dt = {float(continuous.dt):g} s, refined "
                     f"where stiff) is a check in the report, not part of the objective")
    return Problem(setup=setup, options=options, cfg=cfg, selection=selection, objective=objective,
                   heldout=heldout, mode=mode, z0=selection.init(setup), notes=tuple(notes),
                   extra_plants=extra_plants, continuous=continuous)


def describe(setup, options: RunSpec, cfg: TuningConfig) -> dict:
    """`build_problem(setup, options, cfg).describe()` without building the objective (nothing
    is run): what a resumed run is checked against before it starts."""
    cfg, _, selection, mode, sim, checks, _, _, _ = _parts(setup, options, cfg, None)
    return _description(setup, options, cfg, selection, sim, checks, mode, None)


def check_resume(out: str | Path, setup, options: RunSpec, cfg: TuningConfig) -> None:
    """ConfigError (one line: what is missing, or the old and new values of what differs)
    unless `out` holds a run made with these settings; checked before anything runs."""
    files.resume_file(out, ck.RECORD)  # a missing run first, then the settings
    files.check_record(out, ck.RECORD, describe(setup, options, cfg), key="problem",
                       where=f"--resume: the checkpoint in {out}")


def _parts(setup, options: RunSpec, cfg: TuningConfig, extra_plants: dict | None,
           capacity: int = 0):
    """The validated settings of `build_problem` before the start gains are evaluated:
    (cfg, notes, selection, mode, sim, checks, train, heldout, continuous): `checks` the
    `CheckLoop`s of the search, `continuous` the report's check loop."""
    cfg.validate()
    check(setup, options)  # the setup's models, and the filters against a continuous loop's dt
    cfg = model_default_ranges(cfg, setup)
    notes = []
    window = cfg.objective.window_start
    # the loop tuned is the one given ([simulation]: `dscjax tune` samples the controller at
    # 1 ms unless told otherwise); the continuous one is a check of a sampled loop
    sim = options.replace(save_every=options.n_steps, window_start=float(
        options.window_start if window is None else window),
        names={"window_start": "tuning.objective.window_start"})
    continuous = sim.replace(sample_time=None, delay=0, noise=None) if options.sampled else None
    freeze = cfg.freeze or ()
    if cfg.freeze is None and isinstance(setup.plant, PaperPlant) and (
            "controller.gamma_g" in cfg.params):
        freeze = tuple(p for p in PAPER_PLANT_FREEZE if p.split("[")[0] in cfg.params)
        notes.append(f"frozen by default on the paper's plant (no effect, f_2 = 0): "
                     f"{', '.join(freeze)}")
    bounds = dict(cfg.bounds)
    if "controller.tau" in cfg.params and not any(k.startswith("controller.tau") for k in bounds):
        # RK4 at dt in the continuous loop; forward Euler at Ts in a sampled one (an
        # embedded controller may advance its filters so: stable for Ts/tau < 2)
        dt, what = float(options.dt), "dt"
        if options.sampled and options.sample_time > dt:
            dt, what = options.sample_time, "Ts"
        bounds["controller.tau"] = (TAU_MIN_STEPS * dt, None)
        notes.append(f"controller.tau >= {TAU_MIN_STEPS:g} {what} = {TAU_MIN_STEPS * dt:g} s "
                     f"by default (stable filters: RK4 at dt, forward Euler at Ts)")
    selection = Selection.build(setup, cfg.params, freeze, bounds, cfg.transforms, signed=SIGNED)
    train, heldout = (_sample(setup, b, f"tuning.{key}.ranges", options) if b.batch > 0 else None
                      for key, b in (("robust", cfg.robust), ("heldout", cfg.heldout)))
    if extra_plants:
        train = join_plants(setup, train, extra_plants)
    # by the plants simulated: a padded batch's capacity (its rounds share one gradient)
    mode = cfg.optimizer.gradient.chosen(selection.size(setup), max(plant_count(train), capacity),
                                         cfg.robust.over, cfg.optimizer.checkpoint_every)
    sim = dataclasses.replace(sim, gradient=TimeParallel(every=mode.every))
    return (cfg, notes, selection, mode, sim, check_loops(sim, cfg.objective), train, heldout,
            continuous)


def simulate_command(problem: Problem, config: str = "gains.json") -> str:
    """The `dscjax simulate` command that runs the loop tuned from `config` (gains.json, whose
    [simulation] is the loop tuned): with --window-start where the objective's differs."""
    sim, given = problem.objective.sim, problem.options
    flags = ([f"--window-start {shortest(float(sim.window_start))}"]
             if float(sim.window_start) != float(given.window_start) else [])
    return " ".join(["dscjax simulate --config", shlex.quote(config), *flags])


def join_plants(setup, first: dict | None, then: dict) -> dict:
    """{path: (n1 + n2, ...)}: the plants of `first` (None: the nominal plant alone), then
    those of `then`; where one side does not vary a leaf, its plants keep the setup's value."""
    out = {}
    for path in dict.fromkeys([*(first or {}), *then]):
        leaf = np.asarray(params.get(setup, path))
        cols = [np.asarray(d[path]) if d and path in d
                else np.broadcast_to(leaf, (plant_count(d), *leaf.shape)) for d in (first, then)]
        out[path] = np.concatenate(cols).astype(leaf.dtype)
    return out


def _sample(setup, b, field, options) -> dict:
    """{path: (batch, ...)}: the plants of a [tuning.robust] or [tuning.heldout] table."""
    ranges = params.check(b.ranges, setup, field, spec=options)
    return params.sample_overrides(setup, ranges, b.batch, b.seed, b.method)


@dataclasses.dataclass
class Result:
    """A tuning run: its problem and the search's record (`dscjax.search.Trace`)."""

    problem: Problem
    trace: search.Trace
    stop_reason: str
    wall_s: float  # this invocation
    compile_s: float  # this invocation
    resumed_from: int  # iterations done before this invocation

    @property
    def history(self) -> list[dict]:
        return history(self.trace)

    @property
    def best_z(self) -> dict:
        return TuneProblem(self.problem).point(self.trace.best_z)

    @property
    def best_setup(self):
        return self.problem.selection.apply(self.problem.setup, self.best_z)

    @property
    def rejected(self) -> int:
        """adam's iterations whose point was worse than its last good one (stepped back)."""
        return sum(not r.get("accepted", True) for r in self.trace.history)


def prepare_dir(out: Path, resume: bool, overwrite: bool) -> None:
    """ConfigError unless --resume finds the run's record (checkpoint.json) in `out`; only
    --overwrite replaces a run there (a record of either kind, `RECORDS`). A fresh start (no
    --resume) removes a tuning run's files: --overwrite's, and any a killed run left without
    its record. --resume wins over --overwrite."""
    if resume:
        files.resume_file(out, ck.RECORD)
    elif not overwrite and any((out / name).exists() for name in RECORDS):
        raise ConfigError(f"{out} already holds a tuning run; use --resume to continue it or "
                          f"--overwrite to start afresh")
    files.mkdir(out)
    if not resume:
        for name in ck.FILES:
            (out / name).unlink(missing_ok=True)


def _saved(out: Path, problem: Problem) -> tuple[dict, search.Saved]:
    """The record (checkpoint.json) and the search state of the run in `out` (the problem
    must be the same)."""
    fix = "start afresh with --overwrite or another --out"
    record = files.read_json(out / ck.RECORD)
    files.check_same(record.get("problem"), problem.describe(), where=f"the checkpoint in {out}",
                     fix=fix)
    saved = search.load(out / STATE_FILE)
    if saved is None:
        raise ConfigError(f"--resume: {out / STATE_FILE} is missing or unreadable; {fix}")
    return record, saved


def run(problem: Problem, out_dir: str | Path | None = None, *, resume: bool = False,
        overwrite: bool = False, progress: Callable[[dict], None] | None = None,
        z_init: dict | None = None) -> Result:
    """Search until steps, time limit, patience or CMA-ES's own end (after its restarts),
    writing into `out_dir` (None: nothing). `resume` continues the run there bitwise (the same
    problem; the stopping settings may differ); `z_init` is the start point (default the start
    gains `problem.z0`, which the report compares against); `progress` gets each row."""
    t_start = time.perf_counter()
    spec = problem.cfg.optimizer
    out = None if out_dir is None else Path(out_dir)
    before, begun = 0.0, 0
    if out is not None:
        prepare_dir(out, resume, overwrite)
        if resume:
            saved = _saved(out, problem)[1].trace
            before, begun = saved.seconds, saved.iterations
    sp = TuneProblem(problem)
    terms = ck.term_names(problem)

    def each(trace, row):
        if out is not None and (trace.iterations % spec.save_interval == 0
                                or trace.iterations == begun + 1):
            write_files(out, problem, trace)
        if progress is not None:
            progress(ck.history_row(row) | {"steps": spec.max_steps, "terms": terms})

    try:
        res = search.run(
            sp, spec.method(problem.objective.batch_size, sp.x0.size),
            x0=sp.x0 if z_init is None else sp.flat(z_init),
            seed=spec.seed, max_iterations=spec.max_steps, patience=spec.patience,
            time_limit=None if spec.time_limit is None else before + spec.time_limit,
            min_delta=spec.min_delta, path=None if out is None else out / STATE_FILE,
            resume=resume, fingerprint={"problem": files.digest(problem.describe())}, progress=each)
    except KeyboardInterrupt:
        saved = None if out is None else search.load(out / STATE_FILE)
        if saved is not None:
            write_files(out, problem, saved.trace, "interrupted")
        raise
    if out is not None:
        write_files(out, problem, res.trace, res.stop_reason)
    if not np.isfinite(res.trace.best_loss):
        raise ConfigError("no iteration produced a finite loss: the start point is not usable "
                          "(see the divergence report of `dscjax simulate`)")
    return Result(problem=problem, trace=res.trace, stop_reason=res.stop_reason,
                  wall_s=time.perf_counter() - t_start, compile_s=res.compile_seconds,
                  resumed_from=res.resumed_from)


def finished(problem: Problem, out_dir: str | Path) -> Result:
    """The `Result` of the finished run whose checkpoint is in `out_dir`, without iterating."""
    record, saved = _saved(Path(out_dir), problem)
    return Result(problem=problem, trace=saved.trace, stop_reason=record.get("stop_reason") or
                  "finished", wall_s=0.0, compile_s=0.0, resumed_from=saved.trace.iterations)


def write_files(out: Path, problem: Problem, trace: search.Trace,
                stop_reason: str | None = None) -> None:
    """best.json, gains.json, history.csv and checkpoint.json of a search's trace."""
    desc = problem.describe()
    write_best(out, problem, trace)
    ck.write_history(out / "history.csv", history(trace), ck.history_columns(problem))
    files.write_json(out / ck.RECORD, {
        "version": ck.FORMAT_VERSION, "fingerprint": files.digest(desc)[:16],
        "iteration": trace.iterations, "best_loss": trace.best_loss,
        "best_iteration": trace.best_iteration, "best_feasible": trace.best_feasible,
        "evaluations": trace.evaluations, "gradient_evaluations": trace.gradients,
        "elapsed_total_s": trace.seconds, "stop_reason": stop_reason,
        "state": {"kind": problem.cfg.optimizer.name.name, "file": STATE_FILE}, "problem": desc})


def history(trace: search.Trace) -> list[dict]:
    """history.csv's rows of a search's trace (`checkpoint.history_row`)."""
    return [ck.history_row(r) for r in trace.history]


def write_best(out: Path, problem: Problem, trace: search.Trace) -> None:
    """best.json and gains.json of the trace's best point (nothing before a finite loss)."""
    if not np.isfinite(trace.best_loss):
        return
    z = TuneProblem(problem).point(trace.best_z)
    files.write_json(out / "best.json", {
        "iteration": int(trace.best_iteration), "loss": float(trace.best_loss),
        "feasible": bool(trace.best_feasible), "values": problem.values_at(z),
        "z": {k: np.asarray(v).tolist() for k, v in z.items()},
    })
    files.write_json(out / "gains.json", dconfig.to_dict(problem.setup_at(z), problem.options))
