"""CMA-ES of the `cma` package with a state of plain arrays: `ReplayCMA` records what it was
told and rebuilds the same strategy by replaying ask/tell/inject, so a search resumes
exactly without pickles."""

from __future__ import annotations

import copy

import numpy as np


def require_cma():
    """The `cma` module, or ModuleNotFoundError saying how to install it (it is a dependency
    of dscjax, but an environment may lack it)."""
    try:
        import cma
    except ModuleNotFoundError:
        raise ModuleNotFoundError("CMA-ES needs the `cma` package, a dependency of dscjax: "
                                  "pip install 'cma>=3.4'") from None
    return cma


class ReplayCMA:
    """A `cma.CMAEvolutionStrategy` that can be rebuilt exactly without pickles.

    It records every told generation's fitness, the point injected after it and the last
    population; `replay` repeats ask/tell/inject on a fresh one with the same x0, sigma0 and
    options (no simulation) and checks the last population against the stored one.

        es = ReplayCMA(x0, 0.3, {"seed": 1, "verbose": -9})
        x = es.ask(); es.tell(x, f(x)); es.inject(best)     # as with cma
        saved = es.arrays()                                 # plain float arrays (npz)
        again = ReplayCMA(x0, 0.3, {"seed": 1, "verbose": -9}); again.replay(saved)
    """

    def __init__(self, x0, sigma0: float, opts: dict):
        cma = require_cma()
        self.es = cma.CMAEvolutionStrategy(x0, sigma0, opts)
        self.n = int(np.size(x0))
        self.fitness: list[np.ndarray] = []  # (popsize,) per told generation
        self.injected: list[np.ndarray] = []  # (n,) per told generation, NaN: none
        self.told = np.zeros((0, self.n))  # (popsize, n) the last told population

    def ask(self) -> np.ndarray:
        return np.asarray(self.es.ask(), dtype=float)

    def tell(self, x, fitness) -> None:
        f = np.asarray(fitness, dtype=float)
        self.es.tell(list(x), list(f))
        self.fitness.append(f)
        self.injected.append(np.full(self.n, np.nan))
        self.told = np.array(x, dtype=float)

    def inject(self, x) -> None:
        """Inject x into the next generation (after this generation's tell)."""
        self.es.inject([np.asarray(x, dtype=float)])
        self.injected[-1] = np.asarray(x, dtype=float)

    def copy(self) -> ReplayCMA:
        """An independent copy (its own strategy and random stream), for a step that computes
        a new state without changing this one."""
        new = object.__new__(ReplayCMA)
        new.es, new.n = copy.deepcopy(self.es), self.n
        new.fitness, new.injected, new.told = list(self.fitness), list(self.injected), self.told
        return new

    def arrays(self) -> dict[str, np.ndarray]:
        """{"fitness": (G, popsize), "injected": (G, n), "told": (popsize, n)}."""
        pop = self.es.popsize
        return {"fitness": np.asarray(self.fitness).reshape(-1, pop),
                "injected": np.asarray(self.injected).reshape(-1, self.n),
                "told": self.told}

    def replay(self, arrays: dict[str, np.ndarray]) -> None:
        """Repeat the stored generations (`arrays()`). ValueError if the replay does not meet
        the stored last population (another cma version or other options)."""
        fitness = np.asarray(arrays["fitness"])
        for f, x in zip(fitness, np.asarray(arrays["injected"]), strict=True):
            self.tell(self.ask(), f)
            if np.all(np.isfinite(x)):
                self.inject(x)
        if len(fitness) and not np.array_equal(self.told, arrays["told"]):
            raise ValueError("CMA-ES could not replay its stored generations")


__all__ = ["ReplayCMA", "require_cma"]
