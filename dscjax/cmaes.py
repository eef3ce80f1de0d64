"""CMA-ES of the `cma` package, shared by the tuner (tuning/search.py, tuning/baselines.py)
and the worst-case search (dscjax/worst.py): `require_cma`, and `ReplayCMA`, whose state is
saved as plain arrays (no pickle) and restored exactly by replaying ask/tell/inject."""

from __future__ import annotations

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

    It records what it was told: the fitness values of every generation, the point injected
    after it (if any) and the population of the last generation told. `replay` rebuilds the
    same strategy from a fresh one with the same x0, sigma0 and options (so the same seed:
    cma's samples come from the `randn` option or NumPy's generator seeded by `seed`) by
    repeating ask/tell/inject with the stored values, no simulation needed, and checks the last
    population told against the stored one. A population asked but not yet told is not part
    of the record: a strategy saved between ask and tell replays to its last told generation,
    and asks that population again.

        es = ReplayCMA(x0, 0.3, {"seed": 1, "verbose": -9})
        x = es.ask(); es.tell(x, f(x)); es.inject(best)     # as with cma
        saved = es.arrays()                                 # plain float arrays (npz)
        again = ReplayCMA(x0, 0.3, {"seed": 1, "verbose": -9}); again.replay(saved)
    """

    def __init__(self, x0, sigma0: float, opts: dict):
        cma = require_cma()
        self.es = cma.CMAEvolutionStrategy(x0, sigma0, opts)
        self.n = int(np.size(x0))
        self.fitness: list[np.ndarray] = []  # (popsize,) per generation, as told
        self.injected: list[np.ndarray] = []  # (n,) per generation, NaN: none
        self.asked = np.zeros((0, self.n))  # the last population asked (told or not)
        self.told = np.zeros((0, self.n))  # the population of the last generation told

    def ask(self) -> np.ndarray:
        self.asked = np.asarray(self.es.ask(), dtype=float)
        return self.asked

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

    def arrays(self) -> dict[str, np.ndarray]:
        """{"fitness": (G, popsize), "injected": (G, n), "asked": (popsize, n)}: "asked" is
        the population of generation G, the last told (the key the files have always used)."""
        pop = self.es.popsize
        return {"fitness": np.asarray(self.fitness).reshape(-1, pop),
                "injected": np.asarray(self.injected).reshape(-1, self.n),
                "asked": self.told}

    def replay(self, arrays: dict[str, np.ndarray]) -> None:
        """Repeat the stored generations (`arrays()`; "injected" may be left out: none).
        ValueError if the replay does not meet the stored population of the last generation
        (another cma version or other options)."""
        fitness = np.asarray(arrays["fitness"])
        injected = arrays.get("injected", np.full((len(fitness), self.n), np.nan))
        for f, x in zip(fitness, injected, strict=True):
            self.tell(self.ask(), f)
            if np.all(np.isfinite(x)):
                self.inject(x)
        if len(fitness) and not np.array_equal(self.told, arrays["asked"]):
            raise ValueError("CMA-ES could not replay its stored generations")


__all__ = ["ReplayCMA", "require_cma"]
