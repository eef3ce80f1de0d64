"""What a search has done (`Trace`, the one record of every method), the one ranking (feasible
first, then lower loss) and the one resume format: a single atomic npz per search with the
method's arrays ("m_*"), the trace's arrays ("t_*", history columns "h_*") and a JSON string
of metadata ("meta": the version, the method, the caller's fingerprint)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from dscjax import files
from dscjax.validation import ConfigError

VERSION = 1
TOP = 8  # best distinct points a trace keeps
DIVERGED = 8  # diverged candidates a trace keeps (for a re-check)
_FLOATS = ("best_loss", "start_loss", "seconds", "compile_seconds")
_ARRAYS = ("top_z", "top_loss", "top_feasible", "diverged_z")  # saved as "t_<name>"
_INTS = ("iterations", "evaluations", "gradients", "best_iteration", "best_feasible", "stall",
         "restarts")


class Evaluation(NamedTuple):
    """A batch of candidates evaluated (host arrays)."""

    loss: np.ndarray  # (B,) float64, lower is better; a non-finite loss is never the best
    feasible: np.ndarray  # (B,) bool
    diverged: np.ndarray  # (B,) bool: the evaluation broke down (kept for a re-check)
    info: dict  # {name: (B,)} figures for the history

    @classmethod
    def of(cls, loss, feasible=None, diverged=None, info=None) -> Evaluation:
        loss = np.array(loss, dtype=np.float64).reshape(-1)

        def flags(v, fill):
            return np.full(loss.shape, fill) if v is None else np.array(v, bool).reshape(-1)

        return cls(loss, flags(feasible, True), flags(diverged, False),
                   {k: np.asarray(v).reshape(-1) for k, v in (info or {}).items()})

    def rows(self, index) -> Evaluation:
        return Evaluation(self.loss[index], self.feasible[index], self.diverged[index],
                          {k: v[index] for k, v in self.info.items()})

    @staticmethod
    def join(evs) -> Evaluation:
        return Evaluation(*(np.concatenate([getattr(e, f) for e in evs])
                            for f in ("loss", "feasible", "diverged")),
                          {k: np.concatenate([e.info[k] for e in evs]) for k in evs[0].info})


class Incumbent(NamedTuple):
    """The best point so far (z None before any)."""

    z: np.ndarray | None = None  # (n,)
    loss: float = math.inf
    feasible: bool = False
    iteration: int = -1


class Step(NamedTuple):
    """One iteration's outcome: the candidates evaluated (the first iteration's first: the
    start point) and the method's next state."""

    z: np.ndarray  # (B, n) every candidate evaluated, in order
    ev: Evaluation
    state: Any
    first: int = 0  # the first row of the iteration's own candidates (rows before: the start)
    scale: float = math.nan  # CMA-ES's sigma, the gradient's step
    notes: dict | None = None  # per-iteration figures for the history row
    gradients: int = 0  # points whose gradient was taken
    restarts: int = 0  # restarts in this iteration (the stall count starts again)
    done: str | None = None  # the method's own end


def order(ev: Evaluation) -> np.ndarray:
    """The candidates best first: feasible, then lower loss, then earlier; non-finite last."""
    finite = np.isfinite(ev.loss)
    return np.lexsort((np.arange(len(ev.loss)), np.where(finite, ev.loss, np.inf),
                       ~(ev.feasible & finite), ~finite))


def take(best: Incumbent, z: np.ndarray, ev: Evaluation, iteration: int,
         min_delta: float) -> tuple[Incumbent, int | None]:
    """The incumbent after the candidates z (one or more): the best of them if it ranks above
    `best`; and the index of that candidate if it improved on `best` by more than `min_delta`
    (relative), else None (a new incumbent that improved by less still replaces it)."""
    i = int(order(ev)[0])
    loss, feas = float(ev.loss[i]), bool(ev.feasible[i])
    if not math.isfinite(loss) or not ((feas and not best.feasible) or (
            feas == best.feasible and loss < best.loss)):
        return best, None
    margin = min_delta * abs(best.loss) if math.isfinite(best.loss) else 0.0
    real = (feas and not best.feasible) or loss < best.loss - margin
    return Incumbent(np.array(z[i], dtype=np.float64), loss, feas, iteration), i if real else None


@dataclasses.dataclass(frozen=True)
class Trace:
    """A search's record: counters, the incumbent, the history (one row per iteration: its best
    candidate's loss, feasibility and info, the best so far, CMA-ES's sigma or the gradient's
    step as "scale", the search seconds at its end), the TOP best distinct points and the
    first DIVERGED diverged candidates. `record` returns a new trace; none is changed."""

    method: str
    start_z: np.ndarray  # (n,) the start point
    iterations: int = 0
    evaluations: int = 0
    gradients: int = 0  # points whose gradient was taken
    seconds: float = 0.0  # search seconds (compilation in or out: `run`'s count_compile)
    compile_seconds: float = 0.0
    best: Incumbent = Incumbent()
    start_loss: float = math.nan
    stall: int = 0  # iterations since the best improved by more than min_delta
    restarts: int = 0
    done: str | None = None  # the method's own end (e.g. CMA-ES stopped, its restarts spent)
    history: tuple[dict, ...] = ()
    top_z: np.ndarray | None = None  # (k <= TOP, n)
    top_loss: np.ndarray | None = None  # (k,)
    top_feasible: np.ndarray | None = None  # (k,)
    diverged_z: np.ndarray | None = None  # (j <= DIVERGED, n)

    def __post_init__(self):
        n = len(self.start_z)
        for name, shape, dtype in (("top_z", (0, n), float), ("top_loss", (0,), float),
                                   ("top_feasible", (0,), bool), ("diverged_z", (0, n), float)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(shape, dtype))

    best_z = property(lambda self: self.best.z)
    best_loss = property(lambda self: self.best.loss)
    best_feasible = property(lambda self: self.best.feasible)
    best_iteration = property(lambda self: self.best.iteration)

    def record(self, step: Step, seconds: float, compile_seconds: float,
               min_delta: float) -> Trace:
        """The trace after one iteration (`Step`) of `seconds` search seconds."""
        z, ev, it, k = step.z, step.ev, self.iterations, step.first
        best = self.best
        start_loss = self.start_loss if it else float(ev.loss[0])
        if k:  # the start point, evaluated before the iteration's own candidates
            best, _ = take(best, z[:k], ev.rows(slice(0, k)), it, min_delta)
        own = ev.rows(slice(k, None))
        best, improved = take(best, z[k:], own, it, min_delta)
        i = int(order(own)[0])
        row = {"iteration": it, "loss": float(own.loss[i]), "feasible": bool(own.feasible[i]),
               **{name: np.asarray(v[i]).item() for name, v in own.info.items()},
               **(step.notes or {}), "scale": float(step.scale), "best_loss": best.loss,
               "best_feasible": best.feasible, "best_iteration": best.iteration,
               "seconds": self.seconds + seconds}
        finite = np.isfinite(ev.loss)
        zs = np.concatenate([self.top_z, z[finite]])
        ls = np.concatenate([self.top_loss, ev.loss[finite]])
        fs = np.concatenate([self.top_feasible, ev.feasible[finite]])
        # a point kept keeps its entry (its first)
        first = np.sort(np.unique(zs, axis=0, return_index=True)[1])
        keep = first[order(Evaluation.of(ls[first], fs[first]))[:TOP]]
        diverged = np.concatenate([self.diverged_z, z[ev.diverged]])[:DIVERGED]
        return dataclasses.replace(
            self, iterations=it + 1, evaluations=self.evaluations + len(ev.loss),
            gradients=self.gradients + step.gradients, seconds=self.seconds + seconds,
            compile_seconds=self.compile_seconds + compile_seconds, best=best,
            start_loss=start_loss, restarts=self.restarts + step.restarts,
            stall=0 if (improved is not None or step.restarts) else self.stall + 1,
            done=step.done, history=(*self.history, row), top_z=zs[keep], top_loss=ls[keep],
            top_feasible=fs[keep], diverged_z=diverged)


class Saved(NamedTuple):
    trace: Trace
    arrays: dict  # the method's state arrays
    fingerprint: Any  # as stored


def save(path: str | Path, trace: Trace, arrays: dict, fingerprint: Any) -> None:
    """Write the search's state file (atomically; plain arrays, no pickle)."""
    columns = list(trace.history[0]) if trace.history else []
    meta = {"version": VERSION, "method": trace.method, "fingerprint": fingerprint,
            "done": trace.done, "columns": columns}
    out = {"meta": np.frombuffer(files.dumps(meta).encode(), dtype=np.uint8),
           "t_start_z": trace.start_z,
           "t_best_z": trace.best_z if trace.best_z is not None else np.zeros(0),
           "t_floats": np.array([getattr(trace, k) for k in _FLOATS], dtype=np.float64),
           "t_ints": np.array([int(getattr(trace, k)) for k in _INTS], dtype=np.int64),
           **{f"t_{k}": getattr(trace, k) for k in _ARRAYS}}
    out |= {f"h_{c}": np.asarray([row[c] for row in trace.history]) for c in columns}
    out |= {f"m_{k}": np.asarray(v) for k, v in arrays.items()}
    files.write_npz(path, out)


def load(path: str | Path) -> Saved | None:
    """The state saved in `path`, or None if there is none (a missing or partial file);
    ConfigError for a file of another dscjax version."""
    a = files.read_npz(path)
    if a is None:
        return None
    meta = json.loads(bytes(a["meta"]).decode()) if "meta" in a else {}
    if meta.get("version") != VERSION:
        raise ConfigError(f"{path} was written by another version of dscjax and cannot be "
                          f"resumed; start afresh with --overwrite")
    floats = dict(zip(_FLOATS, a["t_floats"].tolist(), strict=True))
    ints = dict(zip(_INTS, a["t_ints"].tolist(), strict=True))
    columns = [a[f"h_{c}"].tolist() for c in meta["columns"]]
    history = tuple(dict(zip(meta["columns"], values, strict=True))
                    for values in zip(*columns, strict=True))
    best = Incumbent(a["t_best_z"] if a["t_best_z"].size else None, floats.pop("best_loss"),
                     bool(ints.pop("best_feasible")), ints.pop("best_iteration"))
    trace = Trace(meta["method"], a["t_start_z"], best=best, done=meta["done"],
                  history=history, **{k: a[f"t_{k}"] for k in _ARRAYS}, **floats, **ints)
    return Saved(trace, {k[2:]: v for k, v in a.items() if k.startswith("m_")}, meta["fingerprint"])


__all__ = ["DIVERGED", "TOP", "Evaluation", "Incumbent", "Saved", "Trace", "load", "order",
           "save", "take"]
