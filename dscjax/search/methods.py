"""The methods of a search, each a frozen dataclass of settings: `CMA` (CMA-ES; path=True adds
the line along its evolution path, `dscjax tune`'s default), `Random` (random sampling) and
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
from dscjax.search.trace import Evaluation, Incumbent, Step, order, take
from dscjax.validation import ConfigError

# cma_path's line: LINE_POINTS step sizes sigma sqrt(n) geomspace(LINE_MIN, LINE_MAX) from the
# incumbent, in the first LINE_GENERATIONS generations of a run (restarts included)
LINE_POINTS, LINE_MIN, LINE_MAX, LINE_GENERATIONS = 6, 0.02, 1.0, 50
BAD = 1e30  # what CMA-ES is told for a non-finite loss


class Context(NamedTuple):
    """What a step reads besides its state."""

    iteration: int  # iterations done before this one
    seed: int
    x0: np.ndarray  # (n,) the start point
    best: Incumbent  # the incumbent before this iteration
    min_delta: float


def generator(seed: int, name: str, iteration: int) -> np.random.Generator:
    """A generator that depends only on (seed, method, iteration): a resumed search draws
    what an uninterrupted one would have drawn."""
    return np.random.default_rng([seed, zlib.crc32(name.encode()), iteration])


def _words(rng: np.random.Generator) -> np.ndarray:
    """PCG64's state as uint64 words: state and increment (high word first), has_uint32,
    uinteger."""
    st = rng.bit_generator.state
    words = [w for k in ("state", "inc") for v in [int(st["state"][k])]
             for w in (v >> 64, v & (2**64 - 1))]
    return np.asarray(words + [st["has_uint32"], st["uinteger"]], dtype=np.uint64)


def _generator(words) -> np.random.Generator:
    w = [int(x) for x in words]
    rng = np.random.default_rng()
    rng.bit_generator.state = rng.bit_generator.state | {
        "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
        "has_uint32": w[4], "uinteger": w[5]}
    return rng


def path_direction(es, cov) -> np.ndarray | None:
    """CMA-ES's evolution path p_c (its smoothed recent mean shift), scaled to unit
    Mahalanobis length under C; None while it is still zero or not finite."""
    pc = np.asarray(es.pc, float)
    q = float(pc @ np.linalg.solve(cov, pc)) if np.all(np.isfinite(pc)) else 0.0
    return pc / math.sqrt(q) if np.isfinite(q) and q > 0 else None


class CMAState(NamedTuple):
    es: ReplayCMA  # the current instance (of restart `restarts`) and what it was told
    restarts: int
    line_rng: np.ndarray  # (6,) uint64: the generator of the line's random directions


@dataclasses.dataclass(frozen=True)
class CMA:
    """CMA-ES (`cma`) from x0 with step sigma0, one batch per generation, told a non-finite
    loss as BAD; its seed is seed + 1, restart r's SeedSequence([seed, r]). When its own
    criteria stop it, a fresh instance starts from x0 (at most `restarts` times; the incumbent
    is kept) with `growth` times the population (IPOP-CMA-ES: 2). path=True ("cma_path") adds LINE_POINTS points from the incumbent along the
    evolution path p_c (a random direction while p_c is zero, from seed + 2) in the first
    LINE_GENERATIONS generations, simulated in the same batch; a line point that improves on
    the incumbent is injected into the next generation."""

    sigma0: float = 0.3
    popsize: int = 0  # 0: cma's default, 4 + floor(3 ln n)
    path: bool = False
    restarts: int = 9
    growth: int = 1  # the population's factor at each restart

    @property
    def name(self) -> str:
        return "cma_path" if self.path else "cma"

    def _new(self, problem, x0, seed: int, restart: int = 0) -> ReplayCMA:
        seed = (seed + 1 if not restart else
                int(np.random.SeedSequence([seed, restart]).generate_state(1)[0]))
        opts = {"seed": seed, "verbose": -9, "randn": np.random.RandomState(seed).randn,
                "bounds": [[x if np.isfinite(x) else None for x in problem.lower],
                           [x if np.isfinite(x) else None for x in problem.upper]]}
        if self.popsize or (restart and self.growth > 1):
            base = self.popsize or 4 + int(3 * math.log(len(x0)))
            opts["popsize"] = base * self.growth ** restart
        return ReplayCMA(np.asarray(x0, dtype=np.float64), self.sigma0, opts)

    def init(self, problem, x0, seed: int) -> CMAState:
        return CMAState(self._new(problem, x0, seed), 0, _words(np.random.default_rng(seed + 2)))

    def step(self, problem, state: CMAState, ctx: Context) -> Step:
        es, rng = state.es.copy(), state.line_rng
        pop = es.ask()
        parts = [problem.project(pop)]
        line = self.path and ctx.iteration < LINE_GENERATIONS
        if line:
            n = len(ctx.x0)
            cov = es.covariance
            d = path_direction(es, cov)
            if d is None:  # a random direction of unit Mahalanobis length under C
                g = _generator(rng)
                xi = g.standard_normal(n)
                rng = _words(g)
                d = np.linalg.cholesky(cov + 1e-300 * np.eye(n)) @ (xi / np.linalg.norm(xi))
            base = ctx.x0 if ctx.best.z is None else ctx.best.z
            steps = math.sqrt(n) * np.geomspace(LINE_MIN, LINE_MAX, LINE_POINTS)
            parts.append(problem.project(base[None, :] + es.sigma * steps[:, None] * d))
        z = np.concatenate(parts)
        ev = problem.evaluate(z)
        best, first, start = ctx.best, 0, None
        if ctx.iteration == 0:  # the start point (evaluated after: padded to this batch)
            ev0 = problem.evaluate(ctx.x0[None, :])
            best, _ = take(best, ctx.x0[None, :], ev0, 0, ctx.min_delta)
            z, ev, first, start = np.concatenate([ctx.x0[None, :], z]), Evaluation.join(
                [ev0, ev]), 1, 0
        k = len(pop)
        best, improved = take(best, z[first:], ev.rows(slice(first, None)), ctx.iteration,
                              ctx.min_delta)
        loss = ev.loss[first:first + k]
        es.tell(pop, np.where(np.isfinite(loss), loss, BAD))
        if line and improved is not None and improved >= k:
            es.inject(best.z)
        sigma, stop = es.sigma, es.stop()
        restarts, done = state.restarts, None
        if stop and restarts < self.restarts:
            restarts += 1
            es = self._new(problem, ctx.x0, ctx.seed, restarts)
        elif stop:
            done = f"CMA-ES stopped: {dict(stop)}"
        return Step(z, ev, CMAState(es, restarts, rng), start, first, sigma,
                    restarts=restarts - state.restarts, done=done)

    def arrays(self, state: CMAState) -> dict:
        return state.es.arrays() | {"restarts": np.int64(state.restarts),
                                    "line_rng": state.line_rng}

    def restore(self, problem, x0, seed: int, arrays: dict) -> CMAState:
        restarts = int(arrays["restarts"])
        es = self._new(problem, x0, seed, restarts)
        try:
            es.replay(arrays)
        except ValueError as e:
            raise ConfigError(f"--resume: {e} (another cma version?); start afresh with "
                              f"--overwrite") from None
        return CMAState(es, restarts, np.asarray(arrays["line_rng"], np.uint64))


@dataclasses.dataclass(frozen=True)
class Random:
    """`batch` points of `problem.sample` per iteration, from `generator(seed, "random",
    iteration)`; the first iteration's first point is x0."""

    batch: int = 32
    name: ClassVar[str] = "random"

    def init(self, problem, x0, seed: int) -> None:
        return None

    def step(self, problem, state: None, ctx: Context) -> Step:
        z = np.array(problem.sample(generator(ctx.seed, self.name, ctx.iteration), self.batch))
        start = 0 if ctx.iteration == 0 else None
        if start == 0:
            z[0] = ctx.x0
        return Step(z, problem.evaluate(z), None, start)

    def arrays(self, state: None) -> dict:
        return {}

    def restore(self, problem, x0, seed: int, arrays: dict) -> None:
        return None


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


@dataclasses.dataclass(frozen=True)
class Gradient:
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

    def init(self, problem, x0, seed: int) -> None:
        return None  # built by the first step

    def _fresh(self, z: np.ndarray) -> GradientState:
        m, a = len(z), z.shape[1] - self.coupled
        return GradientState(z, z.copy(), np.full(m, np.inf), np.zeros_like(z),
                             np.full(m, float(self.lr)), np.zeros(m, np.int32),
                             np.zeros((m, a)), np.zeros((m, a)))

    def step(self, problem, state: GradientState | None, ctx: Context) -> Step:
        start = None
        if state is None:
            size = max(self.screen, self.starts)
            pts = np.concatenate([ctx.x0[None, :], problem.sample(
                generator(ctx.seed, self.name, 0), size - 1)]) if size > 1 else ctx.x0[None, :]
            if self.screen:
                ev = problem.evaluate(pts)
                return Step(pts, ev, self._fresh(pts[order(ev)[:self.starts]]), 0,
                            scale=self.lr, notes={"grad_norm": math.nan, "accepted": True})
            state, start = self._fresh(pts), 0
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
        b = better[:, None]
        lr = np.where(better, np.minimum(state.lr * 1.2, 8 * self.lr), state.lr * 0.5)
        nxt = GradientState(
            z=np.asarray(problem.project(np.where(b, z + lr[:, None] * step, state.good_z
                                                  + lr[:, None] * state.good_dir)),
                         dtype=np.float64),
            good_z=np.where(b, z, state.good_z),
            good_loss=np.where(better, ev.loss, state.good_loss),
            good_dir=np.where(b, -np.concatenate([scaled, coupled], axis=1), state.good_dir),
            lr=lr, count=np.where(better, count, state.count), mu=np.where(b, mu, state.mu),
            nu=np.where(b, nu, state.nu))
        again = ev.diverged | (lr < self.lr / 64)
        if again.any():  # a fresh start from a random point
            fresh = self._fresh(np.asarray(problem.sample(
                generator(ctx.seed, self.name, ctx.iteration + 1), len(z)), dtype=np.float64))
            nxt = GradientState(*(np.where(again.reshape((-1,) + (1,) * (np.ndim(x) - 1)), y, x)
                                  for x, y in zip(nxt, fresh, strict=True)))
        i = int(order(ev)[0])
        return Step(z, ev, nxt, start, scale=float(lr[i]), gradients=len(z),
                    notes={"grad_norm": float(np.linalg.norm(g[i])), "accepted": bool(better[i])},
                    restarts=int(again.sum()))

    def arrays(self, state: GradientState | None) -> dict:
        return {} if state is None else state._asdict()

    def restore(self, problem, x0, seed: int, arrays: dict) -> GradientState | None:
        return GradientState(**arrays) if arrays else None


__all__ = ["BAD", "CMA", "LINE_GENERATIONS", "LINE_MAX", "LINE_MIN", "LINE_POINTS", "CMAState",
           "Context", "Gradient", "GradientState", "Random", "generator",
           "path_direction"]
