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
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dscjax import config as dconfig
from dscjax.config import SimOptions
from dscjax.plant import PaperPlant
from dscjax.reference import SmoothStep
from dscjax.validation import ConfigError
from tuning import checkpoint as ck
from tuning.config import TuningConfig
from tuning.objective import Objective, SimSpec, sample_overrides, start_scales
from tuning.optimize import choose_gradient, init_state, make_step
from tuning.params import Selection
from tuning.requirements import KINDS

# Elements with no effect on the paper's plant (f_2 = 0 in eq. 73): gamma_g2 and eta_2 only
# act on theta_hat_2, which multiplies f_2. Frozen by default on that plant: tuning them would
# cost a tangent each for a zero gradient.
PAPER_PLANT_FREEZE = ("controller.gamma_g[1]", "controller.eta[1]")
TAU_MIN_STEPS = 2.0  # default lower bound of tau: 2 dt (RK4 is stable for dt/tau <= 2.785)


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

    @property
    def n_params(self) -> int:
        return self.selection.size(self.setup)

    def describe(self) -> dict:
        """JSON-able description; its fingerprint must match to resume."""
        opt = dataclasses.asdict(self.cfg.optimizer)
        for k in ("steps", "time_limit", "patience", "max_rejections", "save_interval",
                  "decay_steps", "regrow", "shrink", "min_delta"):
            opt.pop(k)
        return {
            "setup": dconfig.to_dict(self.setup, self.options),
            "params": [dataclasses.asdict(t) for t in self.selection.items],
            "objective": dataclasses.asdict(self.cfg.objective),
            "optimizer": opt,
            "robust": _batch_desc(self.cfg.robust, self.setup),
            "requirements": dict(self.cfg.requirements),
            "sim": dataclasses.asdict(self.objective.sim),
            "mode": self.mode,
        }


def _batch_desc(b, setup):
    d = dataclasses.asdict(b)
    d["ranges"] = [r.resolve(setup).spec() for r in b.ranges]
    return d


def default_freeze(setup, tune) -> tuple[str, ...]:
    if isinstance(setup.plant, PaperPlant) and "controller.gamma_g" in tune:
        return tuple(p for p in PAPER_PLANT_FREEZE if p.split("[")[0] in tune)
    return ()


def build_problem(setup, options: SimOptions, cfg: TuningConfig) -> Problem:
    """Validate the tuning settings against the setup and build the objective.

    Raises ConfigError (naming the field) on any bad setting.
    """
    from dscjax.simulate import default_window
    from dscjax.validation import validate_run, validate_setup

    cfg.validate()
    validate_setup(setup)
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
    mode = choose_gradient(cfg.optimizer.gradient, n_params,
                           cfg.robust.batch if cfg.robust.batch > 0 else 1)
    ce = cfg.optimizer.checkpoint_every if mode == "reverse" else None
    sim = SimSpec(t_final=options.t_final, dt=options.dt, window_start=float(window),
                  state_bound=options.state_bound, checkpoint_every=ce)
    batches = {}
    for key in ("robust", "heldout"):
        b = getattr(cfg, key)
        if b.batch > 0:
            batches[key] = _sample(setup, b, f"tuning.{key}.ranges")
    train, heldout = batches.get("robust"), batches.get("heldout")
    requirements = build_requirements(setup, cfg.requirements)
    scales = start_scales(setup, sim, cfg.objective)
    objective = Objective(setup=setup, selection=selection, spec=cfg.objective, sim=sim,
                          scales=scales, requirements=requirements, overrides=train,
                          aggregate=cfg.robust.aggregate if train else "mean",
                          cvar_level=cfg.robust.cvar_level)
    return Problem(setup=setup, options=options, cfg=cfg, selection=selection,
                   objective=objective, heldout=heldout, mode=mode,
                   z0=selection.init(setup), notes=tuple(notes))


def _sample(setup, b, field) -> dict:
    from dscjax.sweep import _check_lam_psi

    ranges = []
    for r in b.ranges:
        try:
            ranges.append(r.resolve(setup))
            r.param.nominal(setup)
        except KeyError:
            raise ConfigError(f"{field}: unknown parameter {r.param.path!r}") from None
        except IndexError:
            raise ConfigError(f"{field}: index of {r.name!r} out of range") from None
        if not ranges[-1].low < ranges[-1].high:
            raise ConfigError(f"{field}.{r.name}: empty range [{ranges[-1].low:g}, "
                              f"{ranges[-1].high:g}]")
    _check_lam_psi(ranges, setup, field)
    return sample_overrides(setup, ranges, b.batch, b.seed, b.method)


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
    out.mkdir(parents=True, exist_ok=True)
    if overwrite:
        for name in ck.FILES:
            (out / name).unlink(missing_ok=True)


def run(problem: Problem, out_dir: str | Path | None = None, *, resume: bool = False,
        overwrite: bool = False, progress: Callable[[dict], None] | None = None,
        step_hook: Callable | None = None) -> Result:
    """Iterate until steps, time limit, early stopping or too many rejections.

    Args:
        out_dir: where checkpoints go (None: nothing is written).
        resume: continue from the checkpoint in out_dir (the problem must be the same; the
            stopping settings steps/time_limit/patience may differ).
        progress: called with each iteration's row (dict) for a progress display.
        step_hook: test hook, (state, report) -> report, applied to every report on the host.
    """
    t_start = time.perf_counter()
    opt_spec = problem.cfg.optimizer
    out = Path(out_dir) if out_dir is not None else None
    desc = problem.describe()
    fp = ck.fingerprint(desc)
    decay_steps = opt_spec.decay_steps or opt_spec.steps
    history: list[dict] = []
    resumed_from = 0
    elapsed_before = 0.0
    if out is not None:
        _prepare_dir(out, resume, overwrite)
    if resume:
        meta = ck.read_json(out / "checkpoint.json")
        if meta.get("fingerprint") != fp:
            raise ConfigError(f"the checkpoint in {out} was made for a different problem "
                              f"(setup, parameters, objective or optimiser differ); start "
                              f"afresh with --overwrite or another --out")
        decay_steps = int(meta["decay_steps"])
    spec = dataclasses.replace(opt_spec, decay_steps=decay_steps)
    optimizer, step = _step_for(problem, spec)
    state = init_state(problem.z0, optimizer)
    if resume:
        state = ck.load_state(out / "checkpoint.npz", state, meta["state"])
        history = ck.read_history(out / "history.csv")
        history = [r for r in history if r["iteration"] < int(state.iteration)]
        state = _best_from_file(out, state, problem)
        resumed_from = int(state.iteration)
        elapsed_before = float(meta.get("elapsed_total_s", 0.0))
    shrink = jnp.asarray(spec.shrink, state.lr_scale.dtype)
    min_delta = jnp.asarray(spec.min_delta, state.lr_scale.dtype)
    regrow = jnp.asarray(spec.regrow, state.lr_scale.dtype)
    compiled, compile_s = None, 0.0
    schedule = spec.schedule_fn()
    columns = history_columns(problem)
    terms = _term_names(problem)
    last_best_write = 0.0
    last_iter_s = 0.0
    reason = "steps"

    def save(final=False):
        if out is None:
            return
        elapsed_total = elapsed_before + time.perf_counter() - t_start
        meta_state = ck.save_state(out / "checkpoint.npz", state)
        _write_best(out, problem, state)
        ck.write_history(out / "history.csv", history, columns)
        ck.write_json(out / "checkpoint.json", {
            "version": ck.FORMAT_VERSION, "fingerprint": fp, "iteration": int(state.iteration),
            "best_loss": float(state.best_loss), "best_iteration": int(state.best_iteration),
            "best_feasible": bool(state.best_feasible), "decay_steps": decay_steps,
            "elapsed_total_s": elapsed_total, "stop_reason": reason if final else None,
            "state": meta_state, "problem": desc})

    try:
        while True:
            it = int(state.iteration)
            elapsed = time.perf_counter() - t_start
            if it >= spec.steps:
                reason = f"reached {spec.steps} iterations"
                break
            if spec.time_limit is not None and elapsed + last_iter_s > spec.time_limit:
                reason = f"time limit {spec.time_limit:g} s"
                break
            if compiled is None:  # compiled on first use: a finished run resumes instantly
                t0 = time.perf_counter()
                compiled = step.compiled(state, shrink, min_delta, regrow)
                compile_s = time.perf_counter() - t0
            t_it = time.perf_counter()
            prev_best = float(state.best_loss)
            state, rep = compiled(state, shrink, min_delta, regrow)
            rep = jax.device_get(rep)
            if step_hook is not None:
                rep = step_hook(state, rep)
            last_iter_s = time.perf_counter() - t_it
            accepted_steps = int(state.iteration) - int(state.n_rejected)
            row = {
                "iteration": it, "loss": float(rep["loss"]), "accepted": bool(rep["accepted"]),
                "feasible": bool(rep["feasible"]), "best_loss": float(state.best_loss),
                "lr": float(schedule(max(accepted_steps - 1, 0))) * float(rep["lr_scale"]),
                "grad_norm": float(rep["grad_norm"]),
                "linf_window": float(rep["linf_window"]), "max_abs_u": float(rep["max_abs_u"]),
                "n_diverged": int(rep["n_diverged"]),
                **{k: float(rep["terms"][k]) for k in terms},
                "wall_s": elapsed_before + time.perf_counter() - t_start,
                "best_iteration": int(state.best_iteration),
            }
            history.append(row)
            if progress is not None:
                progress(row | {"steps": spec.steps, "terms": terms, "n_rejected":
                                int(state.n_rejected)})
            now = time.perf_counter()
            improved = float(state.best_loss) != prev_best
            if out is not None and improved and now - last_best_write > 1:
                _write_best(out, problem, state)
                last_best_write = now
            if (it + 1) % spec.save_interval == 0:
                save()
            if int(state.streak) >= spec.max_rejections:
                reason = (f"{spec.max_rejections} rejected steps in a row (non-finite or "
                          f"diverging); the learning rate is now x{float(state.lr_scale):.3g}")
                break
            if spec.patience and int(state.stall) >= spec.patience:
                reason = (f"no improvement of the best loss by more than {spec.min_delta:g} "
                          f"(relative) in {spec.patience} iterations")
                break
    except KeyboardInterrupt:
        reason = "interrupted"
        save(final=True)
        raise
    save(final=True)
    if not np.isfinite(float(state.best_loss)):
        raise ConfigError("no iteration produced a finite loss: the start point is not usable "
                          "(see the divergence report of `dscjax simulate`)")
    return Result(problem=problem, state=state, history=history, stop_reason=reason,
                  wall_s=time.perf_counter() - t_start, compile_s=compile_s,
                  resumed_from=resumed_from)


_STEPS: dict = {}  # (problem, update rule) -> (optimizer, jitted step): one compile per process


def _step_for(problem: Problem, spec):
    """The optax transformation and the jitted step, cached so that a run resumed in the same
    process (tests, experiments) does not compile again."""
    rule = (spec.name, spec.learning_rate, spec.schedule, spec.final_lr_fraction,
            spec.decay_steps, spec.clip_norm)
    key = (id(problem.objective), problem.mode, rule)
    if key not in _STEPS:
        if len(_STEPS) >= 8:
            _STEPS.pop(next(iter(_STEPS)))
        optimizer = spec.make()
        _STEPS[key] = (problem.objective, optimizer, _Compiled(make_step(
            problem.objective, optimizer, problem.selection, problem.mode,
            problem.objective.sim.checkpoint_every)))
    return _STEPS[key][1:]


class _Compiled:
    """A jitted step compiled ahead of time once (so compilation can be timed apart)."""

    def __init__(self, step):
        self.step = step
        self._compiled = None

    def compiled(self, *args):
        if self._compiled is None:
            self._compiled = self.step.lower(*args).compile()
        return self._compiled


def gains_config(problem: Problem, z) -> dict:
    """The tuned setup as a dscjax config dict (all sections, the config's names)."""
    setup = problem.selection.apply(problem.setup, z)
    setup = jax.tree.map(np.asarray, setup)
    return dconfig.to_dict(setup, problem.options)


def _write_best(out: Path, problem: Problem, state) -> None:
    if not np.isfinite(float(state.best_loss)):
        return
    z = jax.device_get(state.best_z)
    values = jax.device_get(problem.selection.values(z))
    ck.write_json(out / "best.json", {
        "iteration": int(state.best_iteration), "loss": float(state.best_loss),
        "feasible": bool(state.best_feasible),
        "values": {k: np.asarray(v).tolist() for k, v in values.items()},
        "z": {k: np.asarray(v).tolist() for k, v in z.items()},
    })
    ck.write_json(out / "gains.json", gains_config(problem, z))


def _best_from_file(out: Path, state, problem: Problem):
    """A best point written after the last checkpoint (best.json) replaces the state's."""
    path = out / "best.json"
    if not path.exists():
        return state
    b = ck.read_json(path)
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


def format_progress(row: dict) -> str:
    terms = " ".join(f"{k} {row[k]:.3g}" for k in row["terms"])
    return (f"iter {row['iteration'] + 1:>4}/{row['steps']}  loss {row['loss']:.4g}"
            f"{'' if row['accepted'] else ' (rejected)'}  best {row['best_loss']:.4g}  "
            f"[{terms}]  Linf[t0,T] {row['linf_window']:.4g}  max|u| {row['max_abs_u']:.4g}  "
            f"lr {row['lr']:.3g}  {row['wall_s']:.1f} s")
