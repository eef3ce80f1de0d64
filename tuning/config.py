"""The [tuning] table of a config file -> `TuningConfig` (validated, naming the bad field).

    [tuning]
    params = ["controller.k", "controller.tau", ...]   # tuned; everything else is frozen
    freeze = ["controller.gamma_g[1]"]                  # elements or leaves left out of params
    [tuning.bounds]                                     # on values, [lower, upper]
    [tuning.transforms]                                 # "log" (default) or "linear"
    [tuning.objective], [tuning.optimizer], [tuning.adversarial]
    [tuning.robust], [tuning.heldout]                   # batches; .ranges as [sweep.ranges]
    [tuning.requirements.envelope]                      # time-domain requirements

Unknown keys and bad values are errors that name the field (docs/tuning.md lists them all).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from dscjax import validation, worst
from dscjax.params import default_ranges, flatten, from_table
from dscjax.validation import ConfigError
from tuning.objective import AGGREGATES, ObjectiveSpec
from tuning.optimize import OptimizerSpec
from tuning.params import DSC_GAINS

METHODS = ("uniform", "lhs")  # a batch of plants is sampled, never a grid


@dataclasses.dataclass(frozen=True)
class BatchSpec:
    """A batch of plants drawn from ranges with a seed ([tuning.robust] or [tuning.heldout]);
    batch = 0: the nominal plant only."""

    batch: int = 0
    seed: int = 0
    method: str = "uniform"
    ranges: tuple = dataclasses.field(default_factory=default_ranges)
    aggregate: str = "mean"
    cvar_level: float = 0.2

    def validate(self, field: str) -> None:
        validation.integer(self.batch, f"{field}.batch", 0)
        validation.integer(self.seed, f"{field}.seed", 0)
        validation.one_of(self.method, f"{field}.method", METHODS)
        validation.one_of(self.aggregate, f"{field}.aggregate", AGGREGATES)
        lv = self.cvar_level
        if isinstance(lv, bool) or not isinstance(lv, int | float) or not (0 < lv <= 1):
            raise ConfigError(f"{field}.cvar_level must be in (0, 1] (got {lv!r}); 1 is the "
                              f"mean, small levels average only the worst plants")


@dataclasses.dataclass(frozen=True)
class AdversarialSpec:
    """Min-max tuning ([tuning.adversarial], `tuning.adversarial`; rounds = 0: off): each
    round's search (`method`, `search_time` seconds or `search_evals` evaluations) over the box
    `ranges` (None: [tuning.robust]'s) and the waveform `disturbance` adds `add` worst points."""

    rounds: int = 0
    disturbance: str | None = None
    ranges: tuple | None = None
    method: str = "gradient"
    metric: str = "linf_error_window"
    search_time: float = 30.0
    starts: int = 4
    batch: int = 32
    add: int = 4
    seed: int = 0
    search_evals: int | None = None  # None: search_time alone ends a search

    def validate(self, field: str = "tuning.adversarial") -> None:
        validation.integer(self.rounds, f"{field}.rounds", 0)
        for key in ("starts", "batch", "add"):
            validation.integer(getattr(self, key), f"{field}.{key}", 1)
        validation.integer(self.seed, f"{field}.seed", 0)
        if self.search_evals is not None:
            validation.integer(self.search_evals, f"{field}.search_evals", 1)
        validation.one_of(self.method, f"{field}.method", worst.METHODS)
        validation.one_of(self.metric, f"{field}.metric", worst.METRICS)
        t = self.search_time
        if isinstance(t, bool) or not isinstance(t, int | float) or not (0 < t < float("inf")):
            raise ConfigError(f"{field}.search_time must be a number of seconds > 0 (got "
                              f"{t!r})")
        if self.disturbance is not None:
            worst.DisturbanceSpec.parse(self.disturbance, field=f"{field}.disturbance")


@dataclasses.dataclass(frozen=True)
class TuningConfig:
    """Everything `dscjax tune` needs beyond the Setup and [simulation]."""

    params: tuple[str, ...] = DSC_GAINS
    freeze: tuple[str, ...] | None = None  # None: the default for the plant
    bounds: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    transforms: Mapping[str, str] = dataclasses.field(default_factory=dict)
    objective: ObjectiveSpec = ObjectiveSpec()
    optimizer: OptimizerSpec = OptimizerSpec()
    robust: BatchSpec = BatchSpec()
    heldout: BatchSpec = BatchSpec(batch=256, seed=12345)
    requirements: Mapping[str, Mapping[str, float]] = dataclasses.field(default_factory=dict)
    adversarial: AdversarialSpec = AdversarialSpec()
    # the deployable constraint: the loop with the controller sampled (ZOH) at this period
    sample_time: float | None = 1e-3

    def validate(self) -> None:
        if self.sample_time is not None:
            validation.finite_positive(self.sample_time, "tuning.sample_time")
        self.objective.validate()
        self.optimizer.validate()
        self.robust.validate("tuning.robust")
        self.heldout.validate("tuning.heldout")
        self.adversarial.validate()


TOP_KEYS = ("params", "freeze", "bounds", "transforms", "objective", "optimizer", "robust",
            "heldout", "requirements", "adversarial", "sample_time")
REQUIREMENT_KEYS = {
    "envelope": ("b0", "b_inf", "decay", "weight"),
    "step": ("overshoot", "settling_time", "band", "final", "height", "weight"),
    "u_bound": ("max", "weight"),
    "u_rate": ("max", "weight"),
}
REQUIRED = {"envelope": ("b0", "b_inf", "decay"), "step": (), "u_bound": ("max",),
            "u_rate": ("max",)}


def from_dict(table: Mapping[str, Any], base: TuningConfig | None = None) -> TuningConfig:
    """The [tuning] table laid over `base` (default: `TuningConfig()`)."""
    cfg = base or TuningConfig()
    if not isinstance(table, Mapping):
        raise ConfigError("'tuning' must be a table ([tuning])")
    _known(table, TOP_KEYS, "tuning")
    changes: dict[str, Any] = {}
    for key in ("params", "freeze"):
        if key in table:
            v = table[key]
            if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
                raise ConfigError(f"tuning.{key} must be a list of parameter paths (got {v!r})")
            changes[key] = tuple(v)
    for key in ("bounds", "transforms"):
        if key in table:
            sub = _table(table[key], f"tuning.{key}")
            changes[key] = dict(flatten(sub))
    if "objective" in table:
        changes["objective"] = _spec(cfg.objective, table["objective"], "tuning.objective",
                                     _objective_value)
    if "optimizer" in table:
        changes["optimizer"] = _spec(cfg.optimizer, table["optimizer"], "tuning.optimizer",
                                     _optimizer_value)
    for key in ("robust", "heldout"):
        if key in table:
            changes[key] = _spec(getattr(cfg, key), table[key], f"tuning.{key}", _batch_value)
    if "requirements" in table:
        changes["requirements"] = _requirements(table["requirements"])
    if "adversarial" in table:
        changes["adversarial"] = _spec(cfg.adversarial, table["adversarial"],
                                       "tuning.adversarial", _adversarial_value)
    if "sample_time" in table:
        v = table["sample_time"]
        changes["sample_time"] = (None if isinstance(v, str) and v.lower() == "none" else
                                  validation.number(v, "tuning.sample_time"))
    cfg = dataclasses.replace(cfg, **changes)
    cfg.validate()
    return cfg


def _known(table, allowed, field):
    for key in table:
        if key not in allowed:
            raise ConfigError(f"unknown key '{field}.{key}' (allowed: {', '.join(allowed)})")


def _table(v, field):
    if not isinstance(v, Mapping):
        raise ConfigError(f"{field} must be a table ([{field}])")
    return v


def _objective_value(name, v, field):
    if name == "effort_bounds":
        return v  # checked with its allowed values by ObjectiveSpec.validate
    if name == "window_start" and isinstance(v, str) and v.lower() == "none":
        return None
    if name in ("u_max", "tv_max"):
        if isinstance(v, str):
            if v.lower() == "none":
                return None
            if v == "start":
                return v
            raise ConfigError(f"{field} must be a number > 0, \"start\" or \"none\" (got {v!r})")
        return validation.number(v, field)
    return validation.number(v, field)


def _optimizer_value(name, v, field):
    if name in ("name", "gradient"):
        return validation.string(v, field)
    if name == "steps" and isinstance(v, str) and v.lower() == "none":
        return None
    if name in ("patience", "steps", "checkpoint_every", "save_interval", "popsize", "seed",
                "restarts"):
        return validation.integer(v, field)
    if name == "time_limit" and isinstance(v, str) and v.lower() == "none":
        return None
    return validation.number(v, field)


def _spec(base, table, field, convert):
    table = _table(table, field)
    names = [f.name for f in dataclasses.fields(base)]
    _known(table, names, field)
    return dataclasses.replace(base, **{k: convert(k, v, f"{field}.{k}")
                                        for k, v in table.items()})


def _batch_value(name, v, field):
    if name == "ranges":
        ranges = from_table(v, field)
        if not ranges:
            raise ConfigError(f"{field} is empty")
        return ranges
    if name in ("batch", "seed"):
        return validation.integer(v, field)
    if name in ("method", "aggregate"):
        return validation.string(v, field)
    return validation.number(v, field)


def _adversarial_value(name, v, field):
    if name == "ranges":
        return from_table(v, field) or None
    if name == "disturbance":
        text = validation.string(v, field)
        return None if text.lower() == "none" else text
    if name in ("method", "metric"):
        return validation.string(v, field)
    if name == "search_time":
        return validation.number(v, field)
    if name == "search_evals":
        none = isinstance(v, str) and v.lower() == "none"
        if not none and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"{field} must be an integer >= 1 or \"none\" (got {v!r})")
        return None if none else v
    return validation.integer(v, field)


def _requirements(table) -> dict[str, dict[str, float]]:
    table = _table(table, "tuning.requirements")
    _known(table, tuple(REQUIREMENT_KEYS), "tuning.requirements")
    out = {}
    for name, sub in table.items():
        field = f"tuning.requirements.{name}"
        sub = _table(sub, field)
        _known(sub, REQUIREMENT_KEYS[name], field)
        for key in REQUIRED[name]:
            if key not in sub:
                raise ConfigError(f"{field}.{key} is required")
        values = {k: validation.number(v, f"{field}.{k}") for k, v in sub.items()}
        for k, v in values.items():
            if k in ("b0", "b_inf", "decay", "max", "band", "settling_time") and not v > 0:
                raise ConfigError(f"{field}.{k} must be > 0 (got {v:g})")
            if k in ("weight", "overshoot") and v < 0:
                raise ConfigError(f"{field}.{k} must be >= 0 (got {v:g})")
        out[name] = values
    return out


def to_table(cfg: TuningConfig, setup=None) -> dict[str, Any]:
    """The effective [tuning] table as data (ranges resolved against `setup` if given)."""
    def ranges(spec):
        out = {}
        for r in spec.ranges or ():
            r = r.resolve(setup) if setup is not None else r
            out[r.name] = f"{r.rel * 100:g}%" if r.rel is not None else [r.low, r.high]
        return out

    table: dict[str, Any] = {"params": list(cfg.params), "sample_time": cfg.sample_time}
    if cfg.freeze is not None:
        table["freeze"] = list(cfg.freeze)
    for key in ("bounds", "transforms"):
        if getattr(cfg, key):
            table[key] = dict(getattr(cfg, key))
    for key in ("objective", "optimizer", "robust", "heldout", "adversarial"):
        spec = getattr(cfg, key)
        table[key] = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec)
                      if f.name != "ranges"}
        if getattr(spec, "ranges", None):
            table[key]["ranges"] = ranges(spec)
    if cfg.requirements:
        table["requirements"] = {name: dict(v) for name, v in cfg.requirements.items()}
    return table
