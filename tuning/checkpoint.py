"""Checkpoint files of a tuning run: plain arrays (npz, no pickle) and JSON, written atomically.

    search.npz       the search's state (`dscjax.search`'s one format), saved every iteration
    checkpoint.json  what the run is (fingerprint of the problem) and where it is
    best.json        the best point so far (values and z by name, its loss and iteration)
    gains.json       the best gains as a dscjax config (loadable by `dscjax simulate --config`)
    history.csv      one row per iteration (`history_row`; its columns `history_columns`)

Each is written atomically (`dscjax.files`): a run killed mid-write leaves the previous file.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dscjax import files
from tuning.config import TERMS
from tuning.objective import bound_terms

FORMAT_VERSION = 2
RECORD = "checkpoint.json"  # what the run is and where it is (the record --resume needs)
FILES = ("search.npz", RECORD, "best.json", "gains.json", "history.csv")


# the search's names of history.csv's columns lr and wall_s
RENAMED = {"scale": "lr", "seconds": "wall_s"}


def history_row(row: dict) -> dict:
    """A search trace's history row as history.csv and the progress display give it: the
    search's keys (two renamed), its figures and terms."""
    return ({"grad_norm": float("nan")} | {RENAMED.get(k, k): v for k, v in row.items()}
            | {"accepted": bool(row.get("accepted", True))})


def history_columns(problem) -> list[str]:
    """history.csv's columns: the search's, the figures and the problem's terms."""
    return (["iteration", "loss", "accepted", "feasible", "best_loss", "lr", "grad_norm",
             "linf_window", "max_abs_u", "n_diverged"] + term_names(problem) + ["wall_s"])


def term_names(problem) -> list[str]:
    """The names of the problem's loss terms (its aux terms' keys), in their order."""
    spec, obj = problem.cfg.objective, problem.objective
    return ([n for n in TERMS if getattr(spec, n)]
            + [t[0] for t in bound_terms(spec, obj.scales.u_max, obj.scales.tv_max)]
            + [f"req{i}" for i in range(len(obj.requirements))] + [c.name for c in obj.checks])


def format_progress(row: dict, step: str = "lr") -> str:
    """The figures of one iteration's row for the progress display; `step` names the step
    size (sigma for the CMA-ES methods)."""
    terms = " ".join(f"{k} {row[k]:.3g}" for k in row["terms"])
    return (f"loss {row['loss']:.4g}{'' if row['accepted'] else ' (rejected)'}  best "
            f"{row['best_loss']:.4g}  [{terms}]  Linf[t0,T] {row['linf_window']:.4g}  max|u| "
            f"{row['max_abs_u']:.4g}  {step} {row['lr']:.3g}")


def write_history(path: Path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> None:
    """history.csv: the header `columns`, then a line per row (a figure it lacks left empty)."""
    lines = [",".join(columns), *(",".join(_fmt(r.get(k)) for k in columns) for r in rows)]
    files.write_text(path, "\n".join(lines) + "\n")


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool | np.bool_):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return repr(float(v))
    return str(v)
