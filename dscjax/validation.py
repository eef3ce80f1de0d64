"""Host-side validation of setups and run settings, before anything is traced.

Every failure is a `ConfigError` naming the field by its config path, the allowed range and the
value received, e.g. ``hysteresis.lam must be > hysteresis.psi (got lam=0.1, psi=0.5)``. Arrays
with a leading batch axis are checked elementwise.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
from collections.abc import Mapping

import jax
import numpy as np

from dscjax.rules import Invalid, Rule

# RK4's stability interval on the negative real axis is about [-2.785, 0].
RK4_REAL_STABILITY = 2.785
# The integrator counts steps in an int32 (t_k = k dt): no run may have more.
MAX_STEPS = 2**31 - 1


class ConfigError(ValueError):
    """A setting out of its allowed range; the message names the field."""


def fmt(v) -> str:
    """A value for a message: a number, a short list, or the shape of a large array."""
    a = np.asarray(v)
    if a.ndim == 0:
        return f"{float(a):.6g}"
    if a.size <= 8:
        return "[" + ", ".join(f"{float(x):.6g}" for x in a.ravel()) + "]"
    return f"array of shape {a.shape}"


def shortest(x, dtype=np.float64) -> float:
    """x as the float whose repr is the shortest decimal that gives back x in `dtype`
    (float32 0.1 prints as 0.1, not 0.10000000149011612)."""
    return float(str(np.dtype(dtype).type(x)))


def floor_sig(x: float, digits: int = 3) -> str:
    """x rounded DOWN to `digits` significant digits (a safe upper bound to print)."""
    if x <= 0 or not np.isfinite(x):
        return f"{x:g}"
    scale = 10.0 ** (np.floor(np.log10(x)) - digits + 1)
    return f"{np.floor(x / scale) * scale:.{digits}g}"


def is_concrete(tree) -> bool:
    """False if any leaf is a tracer (then validation is the caller's job)."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(tree))


def every(value, field: str, ok, must: str) -> None:
    """ConfigError "FIELD must be MUST (got VALUE)" unless `ok` holds for every element."""
    if not np.all(ok(np.asarray(value, dtype=float))):
        raise ConfigError(f"{field} must be {must} (got {fmt(value)})")


def positive(value, field: str) -> None:
    every(value, field, lambda a: a > 0, "> 0")


def nonnegative(value, field: str) -> None:
    every(value, field, lambda a: a >= 0, ">= 0")


def finite_positive(value, field: str) -> float:
    """`value` as a float if it is a finite number > 0; else ConfigError naming `field`."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if isinstance(value, bool) or not (math.isfinite(x) and x > 0):
        raise ConfigError(f"{field} must be a finite number > 0 (got {value!r})")
    return x


def shape(value, field: str, expected: tuple[int, ...], why: str = "") -> None:
    got = tuple(np.shape(value))
    if got != tuple(expected):
        hint = f" {why}" if why else ""
        raise ConfigError(f"{field} must have shape {tuple(expected)}{hint} (got shape {got})")


def got(value) -> str:
    """The "got ..." of a message, saying what kind of value it is where its printed form
    hides that: a string ("got a string, '10'": quoted in the file, it is no number), a
    boolean, a table."""
    if isinstance(value, str):
        return f"got a string, {value!r}"
    if isinstance(value, bool):
        return f"got {str(value).lower()}, a boolean"
    if isinstance(value, dict):
        return f"got a table, {value!r}"
    return f"got {value!r}"


def not_boolean(value, field: str) -> None:
    """ConfigError "FIELD must be a number, not a boolean (got true)" if `value` is one: NumPy
    would read `true` as the number 1.0."""
    if isinstance(value, bool | np.bool_):
        raise ConfigError(f"{field} must be a number, not a boolean (got {str(value).lower()})")


def by_rule(rule: Rule, value, field: str):
    """`value` read by a rule (`dscjax.rules`); ConfigError "FIELD must be RANGE (got VALUE)"."""
    try:
        return rule.parse(value)
    except Invalid as err:
        raise ConfigError(f"{field} must be {err.must} ({got(err.value)})") from None


def string(value, field: str) -> str:
    """`value` if it is a string; else ConfigError."""
    if not isinstance(value, str):
        raise ConfigError(f"{field} must be a string (got {value!r})")
    return value


def table(value, field: str) -> Mapping:
    """`value` if it is a table ([field]); else ConfigError."""
    if not isinstance(value, Mapping):
        raise ConfigError(f"'{field}' must be a table ([{field}])")
    return value


def known_keys(value, field: str, allowed) -> None:
    """ConfigError unless `value` is a table ([field]) of keys among `allowed`."""
    for key in table(value, field):
        if key not in allowed:
            raise ConfigError(f"unknown key '{field}.{key}' (allowed: {', '.join(allowed)})")


def one_of(value, field: str, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{field} must be one of {', '.join(map(repr, allowed))} (got {value!r})")


def validate_setup(setup, check_shapes: bool = True) -> None:
    """Check every model of a Setup; raise ConfigError on the first bad field.

    Range checks are elementwise, so a setup whose leaves carry a leading batch axis can be
    checked with check_shapes=False (its unbatched template checked with shapes).
    """
    n = setup.plant.order
    if n < 2:
        raise ConfigError(f"plant.g must have length n >= 2 (the order; got n={n})")
    if check_shapes:  # every array field has the shape its model expects for the order n
        for f in dataclasses.fields(setup):
            model = getattr(setup, f.name)
            why = f"for a plant of order n={n}" if f.name == "controller" else ""
            for name, expected in model.expected_shapes(n).items():
                shape(getattr(model, name), f"{f.name}.{name}", expected, why)
    for f in dataclasses.fields(setup):  # first: inf or nan is named as such, not as a range
        finite_tree(getattr(setup, f.name), f.name)
    for f in dataclasses.fields(setup):
        getattr(setup, f.name).validate(f.name)


def assumption_warnings(setup) -> list[str]:
    """The paper's assumptions a valid setup violates (Assumption 4: g_min <= |g_i|), one
    sentence each: not errors, but Theorem 1 then does not apply."""
    g_min = getattr(setup.controller, "g_min", None)
    g = getattr(setup.plant, "g", None)
    if g_min is None or g is None or not is_concrete((g_min, g)):
        return []
    g_abs = np.abs(np.asarray(g, dtype=float))
    g_min = float(np.max(np.asarray(g_min, dtype=float)))
    below = np.flatnonzero(g_abs < g_min)
    if not below.size:
        return []
    which = ", ".join(f"|g_{i + 1}| = {g_abs[i]:.6g}" for i in below)
    return [f"Assumption 4 (g_min <= |g_i|) does not hold: controller.g_min = {g_min:.6g} but "
            f"plant.g has {which}; the design's guarantees (Theorem 1) do not apply"]


def _leaves(obj, prefix: str = "") -> list[tuple[str, object]]:
    """(path, value) of every traced leaf (array or float) below obj, in field order (an absent
    optional model, None, has none)."""
    if obj is None:
        return []
    if dataclasses.is_dataclass(obj):
        items = [(f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj)
                 if not f.metadata.get("static")]
    elif isinstance(obj, Mapping):
        items = obj.items()
    else:
        return [(prefix[:-1], obj)]
    return [leaf for k, v in items for leaf in _leaves(v, f"{prefix}{k}.")]


def numeric_paths(obj, prefix: str = "") -> list[str]:
    """Every path to a traced leaf (array or float) below obj, in field order (an absent
    optional model, None, has none)."""
    return [path for path, _ in _leaves(obj, prefix)]


def finite_tree(obj, prefix: str) -> None:
    """Every traced number below obj (a model) finite; ConfigError naming its config path."""
    for path, value in _leaves(obj):
        every(value, f"{prefix}.{path}", np.isfinite, "finite")


def whole_steps(t_final, dt, t_field="simulation.t_final", dt_field="simulation.dt") -> int:
    """N = t_final / dt, the one place a horizon becomes a step count; ConfigError naming the
    fields if either is not finite and > 0, N > MAX_STEPS, or N is not whole."""
    dt = finite_positive(dt, dt_field)
    t_final = finite_positive(t_final, t_field)
    ratio = t_final / dt
    if not ratio < MAX_STEPS + 0.5:
        raise ConfigError(
            f"{t_field} / {dt_field} = {ratio:.4g} steps, more than the {MAX_STEPS:,} the "
            f"integrator's step counter holds (got t_final={t_final:.6g}, dt={dt:.6g}); use a "
            f"shorter {t_field} or a larger {dt_field}")
    n_steps = int(round(ratio))
    if n_steps < 1 or abs(n_steps * dt - t_final) > 1e-9 * max(1.0, t_final):
        raise ConfigError(
            f"{t_field} must be a whole number of steps of {dt_field} "
            f"(got t_final={t_final:.6g}, dt={dt:.6g}, ratio {ratio:.6g})"
        )
    return n_steps


def check_filters(setup, dt) -> None:
    """RK4 on the fastest filter: dt / min(controller.tau) <= 2.785 (a continuous loop
    integrated by classical RK4); ConfigError with the largest dt that passes."""
    tau = getattr(setup.controller, "tau", None)
    # a traced tau (e.g. differentiated by tuning) cannot be checked here: its caller does
    if tau is not None and np.size(tau) and is_concrete(tau):
        ratio = float(dt) / np.min(np.asarray(tau, dtype=float))
        if ratio > RK4_REAL_STABILITY:
            raise ConfigError(
                f"simulation.dt = {float(dt):.6g} is too large for RK4 on the fastest filter: "
                f"dt / min(controller.tau) must be <= {RK4_REAL_STABILITY} "
                f"(got min tau = {float(np.min(tau)):.6g}, ratio {ratio:.3g}); use dt <= "
                f"{floor_sig(RK4_REAL_STABILITY * float(np.min(tau)))}"
            )


def validate_run(setup, t_final, dt, window_start) -> int:
    """Check the run settings against the setup; returns the number of steps N = t_final/dt."""
    n_steps = whole_steps(t_final, dt)
    if window_start is not None:
        in_horizon(window_start, t_final, "simulation.window_start")
    check_filters(setup, dt)
    return n_steps


def in_horizon(t, t_final, field: str) -> None:
    """ConfigError unless 0 <= t < t_final (the start of the metrics' window)."""
    if not 0 <= float(t) < float(t_final):
        raise ConfigError(f"{field} must be in [0, t_final) = [0, {float(t_final):.6g}) "
                          f"(got {float(t):.6g})")


# -- what a command's work needs, checked before any of it runs -----------------------------------

TIME_LIMIT_S = 86_400.0  # work that cannot end within a day is refused before it starts
# The speeds the time check assumes are above any dscjax reaches, so an estimate is a lower
# bound on the time and a run that could finish is never refused.
STEPS_PER_S = 5e6  # consecutive steps of one loop (a scan runs its steps one after another)
MEMBER_STEPS_PER_S_CORE = 1e8  # steps x trajectories of a batch, per CPU core
MEMBER_STEPS_PER_S_DEVICE = 1e11  # the same, per accelerator


@dataclasses.dataclass(frozen=True)
class Work:
    """A command's work, estimated from its settings alone (`check_work`).

    steps: consecutive integration steps (simulations run one after another add up).
    member_steps: steps x trajectories, over all its simulations and batches.
    memory: bytes of its largest single allocation; `memory_what` says what it holds.
    """

    steps: float = 0.0
    member_steps: float = 0.0
    memory: float = 0.0
    memory_what: str = ""

    def __add__(self, other: Work) -> Work:
        big = self if self.memory >= other.memory else other
        return Work(self.steps + other.steps, self.member_steps + other.member_steps,
                    big.memory, big.memory_what)

    def seconds(self) -> float:
        """A lower bound on its time at the optimistic speeds of this machine's devices."""
        return max(self.steps / STEPS_PER_S, self.member_steps / batch_speed())


def cores() -> int:
    """The CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0)) or 1
    return os.cpu_count() or 1


def batch_speed() -> float:
    """The optimistic throughput of a batch (member-steps per second) on JAX's devices."""
    devices = jax.devices()
    if devices[0].platform == "cpu":
        return MEMBER_STEPS_PER_S_CORE * cores()
    return MEMBER_STEPS_PER_S_DEVICE * len(devices)


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable), None if unknown."""
    with contextlib.suppress(OSError, ValueError, IndexError), open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def fmt_bytes(nbytes: float) -> str:
    """1536 -> '1.5 KiB'."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if nbytes < 1024 or unit == "TiB":
            return f"{nbytes:.3g} {unit}" if unit != "B" else f"{int(nbytes)} B"
        nbytes /= 1024


def fmt_seconds(seconds: float) -> str:
    """90 -> '90 s', 5400 -> '1.5 h', 3e5 -> '3.5 days'."""
    for unit, size in (("days", 86_400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= 2 * size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


def check_work(work: Work, *, what: str, fix: str, limit_s: float = TIME_LIMIT_S,
               limit: str = "the limit of 24 h") -> None:
    """Refuse, before any of it runs, work that cannot finish on this machine: its largest
    allocation above the memory available, or its time at optimistic speeds (a lower bound)
    above `limit_s` (default a day; a command's own time limit where one piece of its work
    must fit in it). ConfigError: one line with the estimate, the limit and `fix`."""
    avail = available_memory()
    if avail is not None and work.memory > avail:
        raise ConfigError(f"{what}: {work.memory_what} needs about {fmt_bytes(work.memory)} "
                          f"of memory, more than the {fmt_bytes(avail)} available; {fix}")
    seconds = work.seconds()
    if seconds > limit_s:
        raise ConfigError(f"{what} needs at least {fmt_seconds(seconds)} ({work.steps:,.0f} "
                          f"consecutive RK4 steps, {work.member_steps:.3g} in all, at speeds "
                          f"above any dscjax reaches), more than {limit}; {fix}")
