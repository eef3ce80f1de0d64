"""The one run specification: how a closed loop is simulated, as one `eqx.Module`.

    spec = RunSpec.make(t_final=20.0, dt=1e-3)                      # every default rule applied
    spec = RunSpec.from_table({"dt": 5e-4, "sample_time": 1e-3})     # the [simulation] table
    traj = dscjax.simulate(setup, spec=spec)

Static fields shape the compiled program: `n_steps`, `save_every`, `solver`, `gradient`,
`sampled` (the controller sampled, or continuous), `line` (the input delay line's length: the
delay, or longer where several delays are to share a program), `discretisation` (how the
sampled controller advances its states), `skip_diverged` and whether `substeps` is given (a
refinement level's). Traced fields change without recompiling: `dt`, `window_start`,
`state_bound`, `sample_every` (steps per controller sample), `delay` (input delay in samples,
up to `line`), `noise`, `noise_seed` and `substeps` (so that one program serves every
refinement level); `refine`, `dtype`, `device` and `rules` are host-side, never part of a compiled
program: `program()` sets them to fixed values before a spec enters a jitted function, so specs
differing only there share one compiled program. The [simulation] table and its command-line
flags (both from `Simulation`'s declarations) and a run's fingerprint (`describe`) all derive
from it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from dscjax import settings, validation
from dscjax.closed_loop import SCHEME, ExponentialEuler, ForwardEuler, check_delay
from dscjax.integrate import SOLVERS, Gradient, Solver, TimeParallel
from dscjax.integrate import solver as as_solver
from dscjax.metrics import default_window
from dscjax.rules import AtLeast, Choice, Maybe, Number, Numbers, Positive
from dscjax.settings import setting
from dscjax.validation import ConfigError

# A saved trajectory keeps at most this many points unless save_every says otherwise (20 s at
# the default dt = 1e-3 is 20,001 points: every step).
MAX_SAVED_POINTS = 20_001
DEFAULT_REFINE = 6  # halvings of dt tried before a run counts as diverged: down to dt/64


@dataclasses.dataclass(frozen=True)
class Simulation:
    """The [simulation] table as a person writes it, each key declared once
    (`dscjax.settings`); `RunSpec.make` builds the spec from these keys. A key whose default
    is a rule (save_every, window_start) is None, written "none", until given."""

    t_final: float = setting(20.0, "horizon T [s] (the paper does not give it)", Positive(),
                             flag="--t-final")
    dt: float = setting(1e-3, "integration step [s]; RK4 needs dt/min(tau) <= 2.785",
                        Positive(), flag="--dt")
    save_every: int | None = setting(
        None, "keep every k-th step in saved trajectories (metrics use every step); none: "
        f"automatic, at most {MAX_SAVED_POINTS:,} points", Maybe(AtLeast(1)),
        flag="--save-every")
    window_start: float | None = setting(
        None, "t0 [s] of the windowed metrics on [t0, T]; none: 1 s (0 s if t_final <= 1 s)",
        Maybe(Number(ge=0)), flag="--window-start")
    state_bound: float = setting(1e6, "a state beyond this magnitude counts as divergence",
                                 Positive(), flag="--state-bound")
    dtype: str = setting("float64", "the precision of the run (float32: --float32)",
                         Choice(("float64", "float32")))
    solver: str = setting("rk4", "rk4 (classical RK4, the paper's method) or etdrk4 "
                          "(exponential RK4: integrates the stiff decays alpha |u'| and 1/tau "
                          "exactly)", Choice(("rk4", "etdrk4")), flag="--solver")
    refine: int = setting(DEFAULT_REFINE, "if the run diverges: levels tried (ETDRK4 at dt, "
                          "dt/2, ...) before it counts as diverged; 0: report the divergence at "
                          "once", AtLeast(0), flag="--refine")
    sample_time: float | None = setting(
        None, "the controller sampled every Ts seconds, its input held in between (zero-order "
        "hold), a whole multiple of dt; none: continuous", Maybe(Positive()),
        flag="--sample-time")
    delay: int = setting(0, "sampled controller: input delay in whole samples", AtLeast(0),
                         flag="--delay")
    noise: float | tuple | None = setting(
        None, "sampled controller: std of Gaussian measurement noise on x, one number or one "
        "per state; none: no noise", Maybe(Numbers(Number(ge=0))), flag="--noise")
    noise_seed: int = setting(0, "sampled controller: seed of the measurement noise",
                              AtLeast(0), flag="--noise-seed")
    discretisation: str = setting(
        "exponential-euler", "sampled controller: how its states advance over a sample, "
        "exponential-euler (c += Ts phi(-Ts/tau) c', exact for the filters) or euler (forward "
        "Euler, c += Ts c')", Choice(tuple(SCHEME)), flag="--discretisation")
    device: str = setting("auto", "auto (one trajectory and small batches on the CPU, large "
                          "batches on an accelerator), cpu or gpu", Choice(("auto", "cpu", "gpu")),
                          flag="--device")


class RunSpec(eqx.Module):
    """How a closed loop is simulated (see the module docstring). Build it with `make` or
    `from_table`, which check every field; the constructor checks nothing."""

    dt: Any
    window_start: Any
    state_bound: Any = 1e6
    noise: Any = None  # () or (n,) std of the sampled controller's measurement noise
    noise_seed: Any = 0
    n_steps: int = eqx.field(static=True, default=20_000)
    save_every: int = eqx.field(static=True, default=1)
    solver: Solver = eqx.field(static=True, default_factory=lambda: SOLVERS["rk4"]())
    gradient: Gradient = eqx.field(static=True, default_factory=TimeParallel)
    sample_every: Any = 0  # steps per controller sample (0: continuous); traced
    sampled: bool = eqx.field(static=True, default=False)
    delay: Any = 0  # input delay in whole samples; traced, at most `line`
    line: int = eqx.field(static=True, default=0)  # the delay line's length: the delay's
    discretisation: ExponentialEuler | ForwardEuler = eqx.field(  # closed_loop.SCHEME
        static=True, default=ExponentialEuler())
    refine: int = eqx.field(static=True, default=DEFAULT_REFINE)
    dtype: str = eqx.field(static=True, default="float64")
    device: str = eqx.field(static=True, default="auto")
    rules: tuple[str, ...] = eqx.field(static=True, default=())  # fields set by a default rule
    # a refinement level's (`refined`): no more steps once every member has diverged
    skip_diverged: bool = eqx.field(static=True, default=False)
    # a refinement level's: each of the n_steps steps is this many steps of dt (traced)
    substeps: Any = None

    def __check_init__(self):
        check_delay(self.delay, self.line, "RunSpec")

    # -- building ---------------------------------------------------------------------------
    @classmethod
    def make(cls, t_final: float = 20.0, dt: float = 1e-3, *, gradient: Gradient | None = None,
             prefix: str = "simulation.", names: Mapping[str, str] | None = None,
             **table) -> RunSpec:
        """A checked RunSpec of the [simulation] keys (`Simulation`, whose defaults apply;
        `solver` and `discretisation` also as objects): each key checked by its rule, then the
        rules between keys. Messages name a field `prefix` + key, or `names[key]` (the
        command-line option that gave it)."""
        names = names or {}

        def f(key):
            return names.get(key, prefix + key)

        named = {k: getattr(table[k], "name", table[k]) for k in ("solver", "discretisation")
                 if k in table}
        keys = settings.checked(Simulation(t_final=t_final, dt=dt, **(table | named)), f)
        t_final, dt = keys.t_final, keys.dt
        n_steps = validation.whole_steps(t_final, dt, f("t_final"), f("dt"))
        rules = tuple(k for k in ("save_every", "window_start") if getattr(keys, k) is None)
        save_every = auto_stride(n_steps) if keys.save_every is None else keys.save_every
        window_start = default_window(t_final) if keys.window_start is None else keys.window_start
        validation.in_horizon(window_start, t_final, f("window_start"))
        every = 0
        sample_time = keys.sample_time
        if sample_time is not None:
            every = int(round(sample_time / dt))
            if not (every >= 1 and abs(every * dt - sample_time) <= 1e-9 * sample_time):
                raise ConfigError(
                    f"{f('sample_time')} must be a whole multiple > 0 of {f('dt')} (got "
                    f"sample_time={sample_time:.6g}, dt={dt:.6g}, ratio {sample_time / dt:.6g})")
            if every > n_steps:
                raise ConfigError(f"{f('sample_time')} must be <= {f('t_final')} = "
                                  f"{t_final:.6g} (got {sample_time:.6g})")
        elif keys.delay or keys.noise is not None:
            which = "delay" if keys.delay else "noise"
            raise ConfigError(f"{f(which)} applies to a sampled controller: give "
                              f"{f('sample_time')} too")
        noise = None if keys.noise is None else np.asarray(keys.noise, dtype=float)
        return cls(dt=dt, window_start=float(window_start), state_bound=keys.state_bound,
                   noise=noise, noise_seed=keys.noise_seed, n_steps=n_steps,
                   save_every=int(save_every), solver=as_solver(table.get("solver", keys.solver)),
                   gradient=gradient or TimeParallel(), sample_every=every, sampled=every > 0,
                   delay=keys.delay, line=keys.delay,
                   discretisation=SCHEME[keys.discretisation],
                   refine=keys.refine, dtype=keys.dtype, device=keys.device, rules=rules)

    @classmethod
    def from_table(cls, table: Mapping[str, Any], base: RunSpec | None = None,
                   prefix: str = "simulation.", names: Mapping[str, str] | None = None
                   ) -> RunSpec:
        """The [simulation] table laid over `base` (default: the defaults), each key read by
        its rule (`Simulation`). A key of the table replaces the base's value; a rule-derived
        value of the base (save_every, window_start) is derived again from the new horizon and
        step; the base's `gradient` and `skip_diverged`, which no table holds, are kept."""
        values = Simulation(**base.to_table()) if base is not None else Simulation()
        values = settings.from_table(Simulation, table, prefix, base=values)
        spec = cls.make(**dataclasses.asdict(values), prefix=prefix, names=names,
                        gradient=base.gradient if base is not None else None)
        return spec if base is None else dataclasses.replace(spec,
                                                             skip_diverged=base.skip_diverged)

    @classmethod
    def given(cls, spec: RunSpec | None, fields: Mapping[str, Any], caller: str) -> RunSpec:
        """The spec of a function that takes a spec or its fields as keywords: `spec`, else one
        made of `fields` (`make`); both given is refused (TypeError naming `caller`)."""
        if spec is not None and fields:
            raise TypeError(f"{caller}: give spec or its fields, not both")
        return cls.make(**fields) if spec is None else spec

    def replace(self, names: Mapping[str, str] | None = None, **table) -> RunSpec:
        """This spec with some [simulation] keys changed (checked again; `names`: how the
        changed keys are named in messages, e.g. by their command-line options)."""
        return type(self).from_table(table, base=self, names=names)

    # -- reading --------------------------------------------------------------------------------
    @property
    def t_final(self) -> float:
        return self.n_steps * self._substeps * float(self.dt)

    @property
    def _substeps(self) -> int:
        return 1 if self.substeps is None else int(self.substeps)

    @property
    def sample_time(self) -> float | None:
        return int(self.sample_every) * float(self.dt) if self.sampled else None

    @property
    def n_saved(self) -> int:
        """Points of a saved trajectory: steps 0, s, 2s, ... below N, and N."""
        return -(-self.n_steps // self.save_every) + 1

    def to_table(self) -> dict[str, Any]:
        """The [simulation] table of this spec (rule-derived keys given as None)."""
        noise = None if self.noise is None else np.asarray(self.noise, float).tolist()
        short = validation.shortest
        return {"t_final": short(self.t_final), "dt": short(float(self.dt)),
                "save_every": self.save_every * self._substeps,
                "window_start": short(float(self.window_start)),
                "state_bound": short(float(self.state_bound)), "dtype": self.dtype,
                "solver": self.solver.name, "refine": self.refine,
                "sample_time": None if not self.sampled else short(self.sample_time),
                "delay": self.delay, "noise": noise, "noise_seed": int(self.noise_seed),
                "discretisation": self.discretisation.name,
                "device": self.device} | dict.fromkeys(self.rules)

    def describe(self) -> dict[str, Any]:
        """What determines a run's numbers (a resumable run's fingerprint): the table with
        every rule applied, without the host-side device."""
        out = dataclasses.replace(self, rules=()).to_table()
        out.pop("device")
        if isinstance(self.discretisation, ExponentialEuler):  # the default
            out.pop("discretisation")  # the fingerprints of runs made before the key existed
        if not isinstance(self.gradient, TimeParallel) or self.gradient.every != 100:
            out["gradient"] = [self.gradient.name, self.gradient.every]
        return out

    def for_dtype(self, dtype) -> RunSpec:
        """The traced fields as arrays of `dtype` (the setup's), strongly typed, so that
        jit's cache does not depend on how they were written (the noise seed and the sample
        period too: an integer leaf would be a constant of the time-parallel derivative's
        trace; the noise None without noise)."""
        traced = ("dt", "window_start", "state_bound", "sample_every", "delay")
        return dataclasses.replace(
            self, **{k: jnp.asarray(getattr(self, k), dtype) for k in traced},
            noise=None if self.noise is None else jnp.asarray(self.noise, dtype),
            noise_seed=None if self.noise is None else jnp.asarray(self.noise_seed, dtype),
            substeps=None if self.substeps is None else jnp.asarray(self.substeps, jnp.int32))

    def program(self) -> RunSpec:
        """This spec with its host-side fields at fixed values: what a jitted
        function takes, so that specs differing only in refinement, dtype, device or rules
        hit the same compiled program."""
        return dataclasses.replace(self, refine=0, dtype="float64", device="auto", rules=())

    def grouped(self, m: int) -> RunSpec:
        """The same run with every m of its steps taken as one (`substeps` m, a traced count),
        so that runs of one horizon at steps dt / m share one compiled program whatever m: the
        same steps, states and saved points (n_steps and save_every must be multiples of m)."""
        if self.n_steps % m or self.save_every % m:
            raise ValueError(f"RunSpec.grouped: m = {m} must divide n_steps = {self.n_steps} "
                             f"and save_every = {self.save_every}")
        return dataclasses.replace(self, n_steps=self.n_steps // m,
                                   save_every=self.save_every // m, substeps=m)

    def refined(self, halvings: int, solver: Solver) -> RunSpec:
        """The same run at dt / 2^halvings with another solver, on the same saved times and
        the same controller sample time (a refinement level of `simulate`): each of its
        n_steps steps is 2^halvings times its `substeps`, a traced count, so that every level
        of a run is one compiled program; it steps no more once every member has diverged
        (`skip_diverged`: it re-runs runs that diverged, most of which diverge again)."""
        m = 2 ** halvings
        return dataclasses.replace(self, dt=self.dt / m, sample_every=self.sample_every * m,
                                   solver=solver, skip_diverged=True,
                                   substeps=self._substeps * m)


def step_for(sample_time: float, dt: float) -> float:
    """The largest integration step <= dt that divides `sample_time` a whole number of times
    (dt itself when it does)."""
    return sample_time / math.ceil(sample_time / dt * (1 - 1e-12))


def auto_stride(n_steps: int) -> int:
    """The smallest stride s that keeps at most MAX_SAVED_POINTS points of N steps: the steps
    0, s, 2s, ... and always N (s need not divide N)."""
    return max(-(-n_steps // (MAX_SAVED_POINTS - 1)), 1)


__all__ = ["DEFAULT_REFINE", "MAX_SAVED_POINTS", "RunSpec", "Simulation", "auto_stride"]


def loop_words(sim: RunSpec) -> str:
    """The loop of a RunSpec in words: continuous, or sampled (Ts, ZOH, discretisation of the
    controller's states, the plant's step, delay and noise)."""
    plant = f"{sim.solver.name.upper()} at dt = {float(sim.dt):g} s"
    if not sim.sampled:
        return f"the continuous loop ({plant})"
    noise = ("no measurement noise" if sim.noise is None else "measurement noise std "
             + ", ".join(f"{v:g}" for v in np.atleast_1d(np.asarray(sim.noise, float)))
             + f" (seed {int(sim.noise_seed)})")
    return (f"the controller sampled every Ts = {sim.sample_time:g} s with a zero-order hold, "
            f"its states advanced by {sim.discretisation.words}, the plant by {plant}; "
            f"input delay {int(sim.delay)} sample(s); {noise}")
