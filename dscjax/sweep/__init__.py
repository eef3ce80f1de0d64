"""Monte-Carlo and grid robustness sweeps: many plants, fixed gains, metrics only.

    settings = SweepSettings(samples=100_000)                  # alpha, lam, psi within +-30 %
    result = run_sweep(paper_example(), settings, t_final=20.0, dt=1e-3,
                       out_dir="results/sweep")                 # chunk files, resumable
    result.columns["linf_error_window"]                         # one row per sample

The parameter table (seeded samples or a full-factorial grid over config paths such as
``plant.g[1]``) is drawn up front, so it does not depend on the chunk size or device count.
Samples run in blocks of `chunk` rows, each block as tiles of a fixed width (one compiled
program whatever the chunk, so results are bitwise independent of it; the last tile padded),
only the metrics and divergence status coming back. The blocks of a round are laid
over every device of `spec.device`'s platform (all hosts after `jax.distributed.initialize()`),
each device running the SAME single-device program, so results are bitwise independent of the
device count (a partitioned program compiles differently). With `out_dir` each finished
block is written atomically as ``chunks/chunk_000123.npz``; `resume=True` skips those and the
final ``results.npz`` is byte-identical. A diverged sample is a row (`diverged`, `t_diverged`, NaN
metrics), never an error.
"""

from dscjax.sweep.device import METRICS
from dscjax.sweep.run import MANIFEST, SweepResult, check_resumable, run_sweep
from dscjax.sweep.settings import SweepSettings, check_settings, settings_from_dict
from dscjax.sweep.summary import (
    FLOAT32_RTOL,
    check_rows,
    float32_trust,
    float64_check,
    markdown,
    outcome,
    random_rows,
    sample_record,
    scope_text,
    simulate_rows,
    summarize,
    trace_rows,
)

__all__ = ["FLOAT32_RTOL", "MANIFEST", "METRICS", "SweepResult", "SweepSettings", "check_resumable",
           "check_rows", "check_settings", "float32_trust", "float64_check",
           "markdown", "outcome", "random_rows", "run_sweep", "sample_record", "scope_text",
           "settings_from_dict", "simulate_rows", "summarize", "trace_rows"]
