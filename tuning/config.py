"""The [tuning] table of a config file -> `TuningConfig`, each setting declared once
(`dscjax.settings`: default, meaning, rule and command-line option on its field).

    [tuning]
    params = ["controller.k", "controller.tau", ...]   # tuned; everything else is frozen
    freeze = ["controller.gamma_g[1]"]                  # elements or leaves left out of params
    [tuning.bounds]                                     # on values, [lower, upper]
    [tuning.transforms]                                 # "log" (default) or "linear"
    [tuning.objective], [tuning.optimizer], [tuning.adversarial]
    [tuning.robust], [tuning.heldout]                   # batches; .ranges as [sweep.ranges]
    [tuning.requirements.envelope]                      # time-domain requirements

The loop tuned is the config's [simulation] (`dscjax tune` samples the controller at 1 ms
unless the config says otherwise). Unknown keys and bad values are errors that name the field;
docs/tuning.md's key table is generated from these declarations.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from dscjax import params, settings, validation, worst
from dscjax.params import default_ranges, flatten, from_table
from dscjax.rules import AtLeast, Choice, Custom, Either, Maybe, Number, Positive, Strings
from dscjax.search.methods import cma_population
from dscjax.settings import group, setting
from dscjax.validation import ConfigError
from tuning import optimize
from tuning.optimize import AGGREGATES, EFFORT_BOUNDS, GRADIENTS, OPTIMIZERS
from tuning.requirements import KINDS

# the design parameters of the DSC (Section 2 of the paper), tuned by default
DSC_GAINS = ("controller.k", "controller.tau", "controller.gamma_g", "controller.gamma_phi",
             "controller.gamma_zeta", "controller.gamma_d", "controller.eta", "controller.sigma",
             "controller.eta_zeta", "controller.eta_d", "controller.eps", "controller.sat_width")
# tuned in linear coordinates by default (`dscjax.selection.Linear`): signed numbers
SIGNED = ("controller.theta_hat0", "controller.c", "plant.x0", "hysteresis.w0")
# the trajectories a CMA-ES generation runs by default: a batched simulation costs far less per
# trajectory in a batch of this size than in one of the 11 of cma's own population
ROWS = 64
OPTAX_STEPS = 300  # adam's iterations when `steps` is not given
METHODS = {k: v for k, v in params.METHODS.items() if not v.grid}  # plants are drawn
# `dscjax tune`'s own defaults of [simulation]: the controller that runs, sampled at 1 kHz
SIMULATION = {"sample_time": 1e-3}
WEIGHT = Number(ge=0)
BOUND = Maybe(Either((Choice(("start",)), Positive())))
# the objective's terms by their weight's key: (the figure the loss reads, the start gains'
# figure that normalises it, the `Scales` field holding that figure, the term in words)
TERMS = {"linf": ("smooth_linf_window", "linf_error_window", "linf", "the L-inf tracking error"),
         "l2": ("l2_error_window", "l2_error_window", "l2", "the L2 tracking error"),
         "effort_l2": ("l2_u", "l2_u", "l2_u", "L2(u)"),
         "effort_max": ("smooth_max_abs_u", "max_abs_u", "max_u", "max|u|"),
         "effort_tv": ("tv_u", "tv_u", "tv_u", "TV(u)")}


def _ranges(value, field):
    ranges = from_table(value, field)
    if not ranges:
        raise ConfigError(f"{field} is empty")
    return ranges


def _ranges_table(ranges) -> dict:
    return {r.name: f"{r.rel * 100:g}%" if r.rel is not None else [r.low, r.high]
            for r in ranges or ()}


RANGES = Custom(_ranges, "a table of ranges, \"PATH\" = [low, high] or \"P%\"", _ranges_table)
# the rules of a [tuning.requirements.NAME] table's keys but its bounds and times (> 0)
REQUIREMENT_RULES = {"final": Number(), "height": Number(), "weight": WEIGHT, "overshoot": WEIGHT}


@dataclasses.dataclass(frozen=True)
class ObjectiveSpec:
    """[tuning.objective]: the weights and settings of the per-plant objective
    (`tuning.objective`, docs/tuning.md)."""

    linf: float = setting(1.0, "weight of the smooth windowed L-inf of e (over the start's)",
                          WEIGHT)
    l2: float = setting(0.0, "weight of L2(e) on the window (over the start's)", WEIGHT)
    effort_l2: float = setting(0.0, "weight of L2(u) (over the start's)", WEIGHT)
    effort_max: float = setting(0.0, "weight of the smooth max|u| (over the start's)", WEIGHT)
    effort_tv: float = setting(0.0, "weight of TV(u) (over the start's)", WEIGHT)
    u_max: float | str | None = setting("start", "bound on max|u|: a number, start (the start "
                                        "gains' on the nominal plant) or none", BOUND)
    u_max_weight: float = setting(100.0, "weight of the max|u| bound's penalty", WEIGHT)
    tv_max: float | str | None = setting("start", "bound on TV(u): a number, start (tv_max_factor "
                                         "x the start gains' on the nominal plant) or none", BOUND)
    tv_max_factor: float = setting(1.5, "the TV(u) bound \"start\" over the start's TV(u)",
                                   Positive())
    tv_max_weight: float = setting(100.0, "weight of the TV(u) bound's penalty", WEIGHT)
    sampled_factor: float = setting(
        2.0, "the second loop (the other discretisation of the sampled controller): its "
        "windowed L-inf at most this x the first's, and the effort bounds", Positive())
    sampled_weight: float = setting(100.0, "weight of the second loop's penalty; 0: no second "
                                    "loop", WEIGHT)
    delay_samples: int = setting(
        1, "the delayed loop (a sampled loop's input delayed this many more samples) must "
        "track without a limit cycle; 0: no delayed loop", AtLeast(0))
    delay_factor: float = setting(2.0, "the delayed loop's windowed L-inf at most this x the "
                                  "loop tuned's", Positive())
    delay_tv_factor: float = setting(1.4, "the delayed loop's TV(u) at most this x the TV(u) "
                                     "bound", Positive())
    delay_weight: float = setting(100.0, "weight of the delayed loop's penalty; 0: no delayed "
                                  "loop", WEIGHT)
    effort_bounds: optimize.Nominal | optimize.PerPlant = setting(
        optimize.Nominal(), "the start bounds measured on the nominal plant, or per_plant: on each "
        "training plant its own", Choice(EFFORT_BOUNDS), flag="--effort-bounds")
    sharpness: float = setting(
        1000.0, "s x L-inf(start) of the smooth L-inf: large, so that it stays close to the max "
        "where the tuned error is 20-50 times smaller", Positive())
    u_sharpness: float = setting(300.0, "r x max|u|(start) of the smooth max|u|", Positive())
    divergence_penalty: float = setting(1000.0, "the loss of a plant that diverges", Positive())
    window_start: float | None = setting(None, "t0 [s] of the window; none: the run's",
                                         Maybe(Number(ge=0)))

    def validate(self, prefix: str = "tuning.objective") -> None:
        if sum(getattr(self, k) for k in TERMS) == 0:
            raise ConfigError(f"{prefix}: every weight is 0 (set one of {', '.join(TERMS)} > 0)")


@dataclasses.dataclass(frozen=True)
class OptimizerSpec:
    """[tuning.optimizer]: the search method, its settings and limits. An iteration of the
    CMA-ES methods is a generation: one batched simulation."""

    name: optimize.CMAES | optimize.Adam = setting(
        optimize.CMAES(), "cma (CMA-ES with IPOP restarts) or adam (projected descent on exact "
        "gradients)", Choice(OPTIMIZERS), flag="--method")
    learning_rate: float = setting(0.1, "adam's initial step in z; x1.2 after a gain, /2 "
                                   "after a loss", Positive(), flag="--lr")
    patience: int = setting(60, "stop after this many iterations without a min_delta "
                            "(relative) gain", AtLeast(0))
    min_delta: float = setting(1e-4, "the relative gain that counts", Number(ge=0))
    steps: int | None = setting(None, f"at most this many iterations; none: none for CMA-ES, "
                                f"{OPTAX_STEPS} for adam", Maybe(AtLeast(1)), flag="--steps")
    time_limit: float | None = setting(200.0, "seconds of search in this invocation, "
                                       "compilation included; none: no limit",
                                       Maybe(Positive()), flag="--time-limit")
    gradient: optimize.Auto | optimize.Forward = setting(
        optimize.Auto(), "adam's AD mode: forward, reverse, plants (a batch's weighed plants one "
        "by one) or auto (for one plant forward up to 6 tuned numbers, else reverse; plants where "
        "the aggregate weighs at most a quarter of a batch; else forward up to 64 tuned numbers)",
        Choice(GRADIENTS), flag="--gradient")
    checkpoint_every: int = setting(100, "reverse mode's jax.checkpoint segment in steps",
                                    AtLeast(1))
    save_interval: int = setting(10, "iterations between writes of history.csv, best.json, "
                                 "gains.json", AtLeast(1))
    sigma0: float = setting(0.3, "CMA-ES's initial step in z", Positive())
    popsize: int = setting(0, f"CMA-ES's population; 0: sized to a batched simulation's "
                           f"throughput, about {ROWS} trajectories a generation (ceil({ROWS} / "
                           f"the training plants), at least cma's 4 + 3 ln n)", AtLeast(0))
    growth: int = setting(2, "the population's factor at each restart (IPOP-CMA-ES; 1: the "
                          "same)", AtLeast(1))
    seed: int = setting(0, "CMA-ES's seed (adam: a restarted start's random point)", AtLeast(0))
    restarts: int = setting(9, "fresh CMA-ES runs from the start point after CMA-ES's own "
                            "stop or a stall", AtLeast(0))
    stall: int = setting(20, "CMA-ES has stalled when its best loss fell by less than the share "
                         "stall_gain over this many generations (0: only its own stop)", AtLeast(0))
    stall_gain: float = setting(0.1, "the share of the best loss that counts as progress over "
                                "stall generations", Number(gt=0, lt=1))

    def population(self, plants: int, n: int) -> int:
        """CMA-ES's first population for `plants` training plants and n tuned numbers."""
        return self.popsize or max(cma_population(n), -(-ROWS // plants))

    @property
    def max_steps(self) -> int | None:
        """The iteration limit: `steps`, or by default OPTAX_STEPS for adam and none (None)
        for the CMA-ES methods."""
        if self.steps is not None:
            return self.steps
        return None if self.name.generations else OPTAX_STEPS

    def method(self, plants: int = 1, n: int = 1):
        """The `dscjax.search` method for `plants` training plants and n tuned numbers."""
        return self.name.method(self, plants, n)


@dataclasses.dataclass(frozen=True)
class BatchSpec:
    """A batch of plants drawn from ranges with a seed ([tuning.robust] or [tuning.heldout]);
    batch = 0: the nominal plant only."""

    batch: int = setting(0, "plants drawn (0: the nominal plant only)", AtLeast(0))
    seed: int = setting(0, "seed of the plants", AtLeast(0))
    method: params.Uniform | params.LatinHypercube = setting(
        params.Uniform(), "uniform or lhs (Latin hypercube)", Choice(METHODS))
    ranges: tuple = setting((), "what varies; empty: the hysteresis model's defaults, +-30 %",
                            RANGES, factory=default_ranges)
    aggregate: optimize.CVaR = setting(optimize.Mean(), "over the plants: mean, cvar (the mean "
                                       "of the worst cvar_level share) or max", Choice(AGGREGATES))
    cvar_level: float = setting(0.2, "CVaR's share of the worst plants: 1 is the mean",
                                Number(gt=0, le=1))

    @property
    def over(self) -> optimize.CVaR:
        """The aggregate over the plants, CVaR at cvar_level."""
        return self.aggregate.at(self.cvar_level)


@dataclasses.dataclass(frozen=True)
class AdversarialSpec:
    """[tuning.adversarial]: min-max tuning (`tuning.adversarial`; rounds = 0: off): each
    round's search (`method`, `search_time` seconds or `search_evals` evaluations) over the box
    `ranges` (none: [tuning.robust]'s) and the waveform `disturbance` adds `add` worst points."""

    rounds: int = setting(0, "rounds of worst-case search and re-tuning (0: off)", AtLeast(0),
                          flag="--adversarial")
    disturbance: str | None = setting(
        None, "a searched waveform KIND:K:D (fourier or spline, K, max|dbar| <= D); none",
        Maybe(Custom(worst.check_disturbance, "fourier:K:D or spline:K:D", metavar="KIND:K:D")),
        flag="--disturbance")
    ranges: tuple | None = setting(None, "the searched box; none: [tuning.robust]'s ranges",
                                   Maybe(RANGES))
    method: str = setting("gradient", "each round's search method", Choice(worst.METHODS),
                          flag="--search-method")
    metric: str = setting("linf_error_window", "the metric each round maximises",
                          Choice(worst.METRICS))
    search_time: float = setting(30.0, "seconds of each round's search", Positive(),
                                 flag="--search-time")
    starts: int = setting(4, "gradient starts of each search", AtLeast(1))
    batch: int = setting(32, "candidates per batch of each search", AtLeast(1))
    add: int = setting(4, "worst points each round adds to the training batch", AtLeast(1))
    seed: int = setting(0, "seed of the searches", AtLeast(0))
    search_evals: int | None = setting(None, "evaluations of each round's search; none: "
                                       "search_time alone ends it", Maybe(AtLeast(1)),
                                       flag="--search-evals")


def _requirements(table, field) -> dict[str, dict[str, float]]:
    validation.known_keys(table, field, tuple(KINDS))
    out = {}
    for name, sub in table.items():
        where = f"{field}.{name}"
        # a requirement's keys are its fields, weight last; those without a default are required
        keys = sorted((f for f in dataclasses.fields(KINDS[name]) if f.name != "n_steps"),
                      key=lambda f: f.name == "weight")
        validation.known_keys(sub, where, tuple(f.name for f in keys))
        for f in keys:
            if f.default is dataclasses.MISSING and not f.kw_only and f.name not in sub:
                raise ConfigError(f"{where}.{f.name} is required")
        out[name] = {k: validation.by_rule(REQUIREMENT_RULES.get(k, Positive()), v, f"{where}.{k}")
                     for k, v in sub.items()}
    return out


def _paths_table(value, field) -> dict:
    return dict(flatten(validation.table(value, field)))


@dataclasses.dataclass(frozen=True)
class TuningConfig:
    """Everything `dscjax tune` needs beyond the Setup and [simulation]."""

    params: tuple[str, ...] = setting(DSC_GAINS, "the tuned numbers (config paths); "
                                      "everything else is frozen", Strings())
    freeze: tuple[str, ...] | None = setting(
        None, "elements or leaves left out of params; none: the plant's default", Maybe(Strings()))
    bounds: Mapping[str, Any] = setting(
        None, "box bounds on values, \"PATH\" = [lower, upper]",
        Custom(_paths_table, "a table of \"PATH\" = [lower, upper]"), factory=dict)
    transforms: Mapping[str, str] = setting(
        None, "coordinates of a tuned number, \"PATH\" = \"log\" (default) or \"linear\"",
        Custom(_paths_table, "a table of \"PATH\" = \"log\" or \"linear\""), factory=dict)
    objective: ObjectiveSpec = group(ObjectiveSpec)
    optimizer: OptimizerSpec = group(OptimizerSpec)
    robust: BatchSpec = group(BatchSpec, flags={"batch": "--batch", "aggregate": "--aggregate",
                                                "cvar_level": "--cvar-level", "seed": "--seed"})
    heldout: BatchSpec = group(
        BatchSpec, factory=lambda: BatchSpec(batch=256, seed=12345), flags={"batch": "--heldout"},
        docs={"batch": "held-out plants that check the tuned gains (0: skip the check, the "
                       "margins and the constraints' sensitivities)"})
    requirements: Mapping[str, Mapping[str, float]] = setting(
        None, "time-domain requirements: [tuning.requirements.NAME], NAME one of envelope, "
        "step, u_bound, u_rate (docs/tuning.md)",
        Custom(_requirements, "a table of requirement tables"), factory=dict)
    adversarial: AdversarialSpec = group(AdversarialSpec)

    def validate(self, prefix: str = "tuning") -> None:
        """Every setting by its rule, and the rules between them (a config built in code is
        checked as one read from a file)."""
        settings.checked(self, lambda key: f"{prefix}.{key}")
        for key in settings.groups(type(self)):
            part = getattr(self, key)
            settings.checked(part, lambda k, key=key: f"{prefix}.{key}.{k}")
            if hasattr(part, "validate"):
                part.validate(f"{prefix}.{key}")


def from_dict(table: Mapping[str, Any], base: TuningConfig | None = None) -> TuningConfig:
    """The [tuning] table laid over `base` (default: `TuningConfig()`)."""
    return settings.from_table(TuningConfig, table, "tuning.", base)


def to_table(cfg: TuningConfig, setup=None) -> dict[str, Any]:
    """The effective [tuning] table as data (ranges resolved against `setup` if given)."""
    if setup is not None:
        cfg = dataclasses.replace(cfg, **{key: dataclasses.replace(
            getattr(cfg, key), ranges=tuple(r.resolve(setup) for r in getattr(cfg, key).ranges))
            for key in ("robust", "heldout")})
    table = settings.to_table(cfg)
    for key in ("bounds", "transforms", "requirements"):
        if not table[key]:
            del table[key]
    if cfg.adversarial.ranges is None:
        del table["adversarial"]["ranges"]
    return table


__all__ = ["AGGREGATES", "AdversarialSpec", "BatchSpec", "EFFORT_BOUNDS", "GRADIENTS",
           "OPTIMIZERS", "ObjectiveSpec", "OptimizerSpec", "SIMULATION", "TuningConfig",
           "from_dict", "to_table"]
