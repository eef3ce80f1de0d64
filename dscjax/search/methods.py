"""The methods of a search, each a frozen dataclass of settings: `CMA` (CMA-ES with IPOP
restarts, `dscjax tune`'s default), `Random` (random sampling) and
`Gradient` (projected gradient descent from one or more starts). `step` computes the next
state from the current one without changing it; states are plain arrays (CMA-ES: a
`ReplayCMA`, rebuilt by replay), saved by `arrays` and rebuilt by `restore`."""

from __future__ import annotations

import dataclasses
import functools
import math
import zlib
from typing import ClassVar, NamedTuple

import numpy as np

from dscjax.search.cma import ReplayCMA
from dscjax.search.trace import Evaluation, Step, order
from dscjax.validation import ConfigError

BAD = 1e30  # what CMA-ES is told for a non-finite loss


class Context(NamedTuple):
    """What a step reads besides its state."""

    iteration: int  # iterations done before this one
    seed: int
    x0: np.ndarray  # (n,) the start point


def generator(seed: int, name: str, iteration: int) -> np.random.Generator:
    """A generator that depends only on (seed, method, iteration): a resumed search draws
    what an uninterrupted one would have drawn."""
    return np.random.default_rng([seed, zlib.crc32(name.encode()), iteration])


def cma_population(n: int) -> int:
    """cma's own population in n dimensions, 4 + floor(3 ln n) (a search of one dimension runs
    in two: `ReplayCMA`)."""
    return 4 + int(3 * math.log(max(n, 2)))


class CMAState(NamedTuple):
    es: ReplayCMA  # the current instance (of restart `restarts`) and what it was told
    restarts: int


@dataclasses.dataclass(frozen=True)
class CMA:
    """CMA-ES (`cma`) from x0 with step sigma0 and `popsize` candidates (0: cma's 4 + 3 ln n),
    one batch per generation, told a non-finite loss as BAD; its seed is seed + 1, restart r's
    SeedSequence([seed, r]). When its own criteria stop it, or when it stalls (its best loss
    fell by less than the share `stall_gain` over the last `stall` generations; 0: never), a
    fresh instance starts from x0 with `growth` times the population (IPOP-CMA-ES: 2), at
    most `restarts` times; the incumbent is kept."""

    sigma0: float = 0.3
    popsize: int = 0
    restarts: int = 9
    growth: int = 1
    stall: int = 0
    stall_gain: float = 0.1
    name: ClassVar[str] = "cma"

    def _new(self, problem, x0, seed: int, restart: int = 0) -> ReplayCMA:
        seed = (seed + 1 if not restart else
                int(np.random.SeedSequence([seed, restart]).generate_state(1)[0]))
        opts = {"seed": seed, "verbose": -9, "randn": np.random.RandomState(seed).randn,
                "bounds": [[x if np.isfinite(x) else None for x in bound]
                           for bound in (problem.lower, problem.upper)]}
        if self.popsize or restart:
            opts["popsize"] = (self.popsize or cma_population(len(x0))) * self.growth ** restart
        return ReplayCMA(np.asarray(x0, dtype=np.float64), self.sigma0, opts)

    def init(self, problem, x0, seed: int) -> CMAState:
        return CMAState(self._new(problem, x0, seed), 0)

    def step(self, problem, state: CMAState, ctx: Context) -> Step:
        es = state.es.copy()
        pop = es.ask()
        z = problem.project(pop)
        ev = problem.evaluate(z)
        first = 0
        if ctx.iteration == 0:  # the start point (evaluated after: padded to this batch)
            ev = Evaluation.join([problem.evaluate(ctx.x0[None, :]), ev])
            z, first = np.concatenate([ctx.x0[None, :], z]), 1
        loss = ev.loss[first:]
        es.tell(pop, np.where(np.isfinite(loss), loss, BAD))
        sigma, stop = es.sigma, es.stop() or self._stalled(es)
        restarts, done = state.restarts, None
        if stop and restarts < self.restarts:
            restarts += 1
            es = self._new(problem, ctx.x0, ctx.seed, restarts)
        elif stop:
            done = f"CMA-ES stopped: {dict(stop)}"
        return Step(z, ev, CMAState(es, restarts), first, sigma,
                    restarts=restarts - state.restarts, done=done)

    def _stalled(self, es: ReplayCMA) -> dict:
        """{"stall": generations} when the instance's best loss fell by less than the share
        stall_gain over its last `stall` generations, else {}."""
        if not self.stall or len(es.fitness) <= self.stall:
            return {}
        best = np.minimum.accumulate([np.min(f) for f in es.fitness])
        then, now = best[-1 - self.stall], best[-1]
        return {"stall": self.stall} if then - now <= self.stall_gain * abs(then) else {}

    def arrays(self, state: CMAState) -> dict:
        return state.es.arrays() | {"restarts": np.int64(state.restarts)}

    def restore(self, problem, x0, seed: int, arrays: dict) -> CMAState:
        restarts = int(arrays["restarts"])
        es = self._new(problem, x0, seed, restarts)
        try:
            es.replay(arrays)
        except ValueError as e:
            raise ConfigError(f"--resume: {e} (another cma version?); start afresh with "
                              f"--overwrite") from None
        return CMAState(es, restarts)


class _BuiltByStep:
    """The state handling of a method whose state is None until its first step builds it (if
    it has one: a NamedTuple of arrays, `state_type`)."""

    state_type: ClassVar[type | None] = None

    def init(self, problem, x0, seed: int) -> None:
        return None

    def arrays(self, state) -> dict:
        return {} if state is None else state._asdict()

    def restore(self, problem, x0, seed: int, arrays: dict):
        return self.state_type(**arrays) if arrays else None


@dataclasses.dataclass(frozen=True)
class Random(_BuiltByStep):
    """`batch` points of `problem.sample` per iteration, from `generator(seed, "random",
    iteration)`; the first iteration's first point is x0."""

    batch: int = 32
    name: ClassVar[str] = "random"

    def step(self, problem, state: None, ctx: Context) -> Step:
        z = np.array(problem.sample(generator(ctx.seed, self.name, ctx.iteration), self.batch))
        if ctx.iteration == 0:
            z[0] = ctx.x0
        return Step(z, problem.evaluate(z), None)


class GradientState(NamedTuple):
    """Per start (M rows): the point to evaluate, the last good point, its loss and its
    descent direction (its gradient scaled as Adam scales it, without the momentum), the step
    size, and Adam's state at the last good point."""

    z: np.ndarray  # (M, n)
    good_z: np.ndarray  # (M, n)
    good_loss: np.ndarray  # (M,) +inf: none yet
    good_dir: np.ndarray  # (M, n)
    lr: np.ndarray  # (M,)
    count: np.ndarray  # (M,) int32
    mu: np.ndarray  # (M, n - coupled)
    nu: np.ndarray  # (M, n - coupled)


B2, EPS = 0.999, 1e-8  # Adam's (optax's defaults)


@functools.cache
def _adam():
    """optax's Adam scaling, vmapped over the starts (each start its own count)."""
    import jax
    import optax

    tx = optax.scale_by_adam(b2=B2, eps=EPS)

    @jax.jit
    def update(g, count, mu, nu):
        u, s = jax.vmap(tx.update)(g, optax.ScaleByAdamState(count=count, mu=mu, nu=nu))
        return u, s.count, s.mu, s.nu

    return update


def _rows(take, new: GradientState, old: GradientState) -> GradientState:
    """Per start, its rows of `new` where `take` (M,), else of `old`."""
    return GradientState(*(np.where(take.reshape((-1,) + (1,) * (np.ndim(x) - 1)), x, y)
                           for x, y in zip(new, old, strict=True)))


@dataclasses.dataclass(frozen=True)
class Gradient(_BuiltByStep):
    """Projected gradient descent from `starts` points as one batch: Adam's scaling of the
    gradient (the last `coupled` coordinates: the gradient over its largest entry); each
    start's step grows x1.2 (up to 8 lr) after an improvement and halves after a worse or
    non-finite point (stepping again from the last good one); then `problem.project`.
    `screen` > 0 starts from the best of that many points (x0 and `problem.sample`). A start
    that diverged, or whose step fell below lr/64, restarts from a random point."""

    lr: float = 0.1
    starts: int = 1
    screen: int = 0
    coupled: int = 0
    name: ClassVar[str] = "gradient"
    state_type: ClassVar[type] = GradientState

    def _fresh(self, z: np.ndarray) -> GradientState:
        m, a = len(z), z.shape[1] - self.coupled
        return GradientState(z, z.copy(), np.full(m, np.inf), np.zeros_like(z),
                             np.full(m, float(self.lr)), np.zeros(m, np.int32),
                             np.zeros((m, a)), np.zeros((m, a)))

    def step(self, problem, state: GradientState | None, ctx: Context) -> Step:
        if state is None:
            size = max(self.screen, self.starts)
            pts = np.concatenate([ctx.x0[None, :], problem.sample(
                generator(ctx.seed, self.name, 0), size - 1)]) if size > 1 else ctx.x0[None, :]
            if self.screen:
                ev = problem.evaluate(pts)
                return Step(pts, ev, self._fresh(pts[order(ev)[:self.starts]]), scale=self.lr,
                            notes={"grad_norm": math.nan, "accepted": True})
            state = self._fresh(pts)
        z, a = state.z, state.z.shape[1] - self.coupled
        ev, g = problem.value_and_grad(z)
        g = np.where(np.isfinite(g), g, 0.0)
        better = np.isfinite(ev.loss) & (ev.loss <= state.good_loss)
        u, count, mu, nu = (np.asarray(x) for x in _adam()(g[:, :a], state.count, state.mu,
                                                              state.nu))
        gc = g[:, a:]
        peak = np.max(np.abs(gc), axis=1, keepdims=True) if self.coupled else 1.0
        coupled = gc / np.where(peak > 0, peak, 1.0)
        step = -np.concatenate([u, coupled], axis=1)
        scaled = g[:, :a] / (np.sqrt(nu / (1 - B2 ** count[:, None])) + EPS)
        lr = np.where(better, np.minimum(state.lr * 1.2, 8 * self.lr), state.lr * 0.5)
        # a start that improved: its point is the last good one, with Adam's state there
        nxt = _rows(better, GradientState(z, z, ev.loss, -np.concatenate([scaled, coupled], axis=1),
                                          lr, count, mu, nu), state._replace(lr=lr))
        # it steps from its point; the others step again from their last good one
        nxt = nxt._replace(z=np.asarray(problem.project(np.where(
            better[:, None], z + lr[:, None] * step, state.good_z + lr[:, None] * state.good_dir)),
            dtype=np.float64))
        again = ev.diverged | (lr < self.lr / 64)
        if again.any():  # a fresh start from a random point
            nxt = _rows(again, self._fresh(np.asarray(problem.sample(
                generator(ctx.seed, self.name, ctx.iteration + 1), len(z)), dtype=np.float64)), nxt)
        i = int(order(ev)[0])
        return Step(z, ev, nxt, scale=float(lr[i]), gradients=len(z),
                    notes={"grad_norm": float(np.linalg.norm(g[i])), "accepted": bool(better[i])},
                    restarts=int(again.sum()))


__all__ = ["BAD", "CMA", "CMAState", "Context", "Gradient", "GradientState", "Random",
           "cma_population", "generator"]
