"""Monte-Carlo and grid robustness sweeps: many plants, fixed gains, metrics only.

    settings = SweepSettings(samples=100_000)                  # alpha, lam, psi within +-30 %
    result = run_sweep(paper_example(np.float32), settings, t_final=20.0, dt=1e-3,
                       out_dir="results/sweep")                 # chunk files, resumable
    result.columns["linf_error_window"]                         # one row per sample

What a sweep does:

- **Samples** (seeded; i.i.d. uniform or Latin hypercube) or a full-factorial **grid** over any
  numeric leaves of the Setup, addressed by their config paths, with an element index for
  vector leaves: ``hysteresis.alpha``, ``plant.g[1]``, ``plant.x0[0]``, ``plant.dbar_amp``.
  The whole table of parameters is drawn up front from the seed, so it does not depend on the
  chunk size or the device count.
- **Blocks.** Samples are processed in blocks of `chunk` rows (the last one padded with its own
  first row). Every block has the same shape, so one compiled program serves all of them. Per
  sample only the metrics come back (running reductions over every RK4 step, see `metrics.py`),
  with the divergence status and time; memory is O(chunk) on the device.
- **Devices.** `spec.device` picks the platform (`dscjax.device.choose`: "auto" runs a sweep
  below a crossover size on the CPU, a larger one on the accelerators). The blocks of a round
  are laid out over a `jax.sharding.Mesh` of every device of that platform (all hosts after
  `jax.distributed.initialize()`) as one global array with a `NamedSharding`
  along the batch axis; each device then runs the SAME single-device program on its own block.
  This is deliberate: XLA compiles a partitioned (shard_map / GSPMD) program through a
  different pass pipeline from the single-device one, which on XLA:CPU changed float64 results
  by ~1e-11 and doubled the sines per step (measured; see docs/sweeps.md). With a fixed block
  shape per device, results are bitwise independent of the device count. `parallel="spmd"`
  runs one shard_map program instead (one compilation for all devices; results agree to
  round-off but not bitwise).
- **Disk.** With `out_dir`, every finished block is written at once as
  ``chunks/chunk_000123.npz`` (atomically); `resume=True` skips the blocks already there and
  the final ``results.npz`` is byte-identical to that of an uninterrupted run.

Nothing here raises for a bad sample: a diverged trajectory is a row with `diverged = True`,
the time it left the state bound or went non-finite, and NaN for every metric (they were not
measured over the horizon they name; `dscjax.simulate.nan_if_diverged`).
"""

from dscjax.device import auto_chunk
from dscjax.sweep.device import METRICS
from dscjax.sweep.run import SweepResult, check_resumable, run_sweep
from dscjax.sweep.settings import (
    AUTO_BLOCK,
    PARALLEL,
    SweepSettings,
    check_settings,
    settings_from_dict,
)
from dscjax.sweep.summary import (
    random_rows,
    rank_diverged,
    rank_worst,
    sample_record,
    simulate_rows,
    summarize,
    trace_rows,
)

__all__ = ["AUTO_BLOCK", "METRICS", "PARALLEL", "SweepResult", "SweepSettings", "auto_chunk",
           "check_resumable", "check_settings", "random_rows",
           "rank_diverged", "rank_worst", "run_sweep", "sample_record", "settings_from_dict",
           "simulate_rows", "summarize", "trace_rows"]
