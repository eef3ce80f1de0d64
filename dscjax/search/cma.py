"""CMA-ES of the `cma` package with a state of plain arrays: `ReplayCMA` records what it was
told and rebuilds the same strategy by replaying ask/tell, so a search resumes
exactly without pickles. A search of one dimension runs CMA-ES in two, the second a copy of
the first's box that no loss depends on (pycma fails on a bounded box of one dimension)."""

from __future__ import annotations

import copy

import numpy as np


class ReplayCMA:
    """A `cma.CMAEvolutionStrategy` that can be rebuilt exactly without pickles.

    It records every told generation's fitness and the last population; `replay` repeats
    ask/tell on a fresh one with the same x0, sigma0 and options (no simulation) and checks
    the last population against the stored one.

        es = ReplayCMA(x0, 0.3, {"seed": 1, "verbose": -9})
        x = es.ask(); es.tell(x, f(x))                      # as with cma
        saved = es.arrays()                                 # plain float arrays (npz)
        again = ReplayCMA(x0, 0.3, {"seed": 1, "verbose": -9}); again.replay(saved)
    """

    def __init__(self, x0, sigma0: float, opts: dict):
        import cma  # (imported on use: only CMA-ES needs it)
        x0 = np.asarray(x0, dtype=float).reshape(-1)
        self.n = x0.size  # the search's dimension
        if self.n == 1:  # pycma 4.5 cannot bound one dimension: a neutral copy of it
            x0 = np.concatenate([x0, x0])
            opts = dict(opts)
            if "bounds" in opts:
                opts["bounds"] = [list(b) * 2 if np.ndim(b) == 1 and len(b) == 1 else b
                                  for b in opts["bounds"]]
        self.dim = x0.size  # CMA-ES's dimension (n, or 2 when n = 1)
        self.es = cma.CMAEvolutionStrategy(x0, sigma0, opts)
        self.fitness: list[np.ndarray] = []  # (popsize,) per told generation
        self.told = np.zeros((0, self.dim))  # (popsize, dim) the last told population
        self.asked = np.zeros((0, self.dim))  # (popsize, dim) the last asked population

    def ask(self) -> np.ndarray:
        """The next population (popsize, n)."""
        self.asked = np.asarray(self.es.ask(), dtype=float)
        return self.asked[:, :self.n].copy()

    def tell(self, x, fitness) -> None:
        """The losses of the population x (popsize, n) last asked."""
        f = np.asarray(fitness, dtype=float)
        x = np.asarray(x, dtype=float)
        if self.dim > self.n:  # the neutral coordinate as asked
            x = np.concatenate([x, self.asked[:len(x), self.n:]], axis=1)
        self.es.tell(list(x), list(f))
        self.fitness.append(f)
        self.told = np.array(x, dtype=float)

    # what a method reads of the strategy, in the search's n dimensions
    @property
    def sigma(self) -> float:
        return float(self.es.sigma)

    def stop(self) -> dict:
        return self.es.stop()

    def copy(self) -> ReplayCMA:
        """An independent copy (its own strategy and random stream), for a step that computes
        a new state without changing this one."""
        return copy.deepcopy(self)

    def arrays(self) -> dict[str, np.ndarray]:
        """{"fitness": (G, popsize), "told": (popsize, dim)}."""
        return {"fitness": np.asarray(self.fitness).reshape(-1, self.es.popsize),
                "told": self.told}

    def replay(self, arrays: dict[str, np.ndarray]) -> None:
        """Repeat the stored generations (`arrays()`). ValueError if the replay does not meet
        the stored last population (another cma version or other options)."""
        fitness = np.asarray(arrays["fitness"])
        for f in fitness:
            self.tell(self.ask(), f)
        if len(fitness) and not np.array_equal(self.told, arrays["told"]):
            raise ValueError("CMA-ES could not replay its stored generations")


__all__ = ["ReplayCMA"]
