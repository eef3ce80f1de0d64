"""One sweep end to end: the table of samples, rounds of blocks over the devices, chunk files
written as blocks finish, resume, and the columns of the result."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from dscjax import config, device, files, params, validation, xla
from dscjax.progress import critical
from dscjax.runspec import RunSpec, loop_words
from dscjax.simulate import check
from dscjax.sweep.device import METRICS, Runner, from_process_0, tile_rows
from dscjax.sweep.settings import DTYPES, SweepSettings, check_settings
from dscjax.validation import ConfigError

# 2: the metrics of diverged rows are NaN (were the frozen values); 3: rows that diverged are
# re-run with ETDRK4 at smaller steps ("refinements", "dt_used"); 4: the effort on the window
# and the chattering index are columns (a chunk of 3 lacks them)
FORMAT_VERSION = 4
MANIFEST = "sweep.json"  # the record of a sweep: what was run, what --resume continues
STATUS_COLUMNS = ("diverged", "t_diverged", "status", "refinements", "dt_used")
# the run's settings in a result's info besides t_final and dt (a row re-simulated reads them)
RUN_KEYS = ("window_start", "state_bound", "solver", "refine", "sample_time", "delay", "noise",
            "noise_seed", "discretisation")


@dataclasses.dataclass
class SweepResult:
    """A finished sweep.

    columns: one array per column, one row per sample: "sample", the parameter columns
        (`Range.name`), the metrics (`METRICS`), "diverged" (after every refinement level),
        "t_diverged" (+inf if not), "status", "refinements" (`refinement_level` of the run
        reported) and "dt_used" (its step).
    param_names: the parameter columns, in table order.
    info: sizes, timing and settings (what `summary.json` reports under "run").
    """

    columns: dict[str, np.ndarray]
    param_names: tuple[str, ...]
    info: dict[str, Any]

    @property
    def n(self) -> int:
        return int(self.columns["sample"].shape[0])


def fingerprint(setup, settings: SweepSettings, ranges, spec: RunSpec,
                chunk: int, tile: int | None) -> dict[str, Any]:
    """Everything that determines the rows of a sweep (and how they are split into files)."""
    setup_dict = {k: v for k, v in config.to_dict(setup).items() if k != "simulation"}
    # the run without its dtype (the sweep's own) and save_every (metrics only)
    run = {k: v for k, v in spec.describe().items() if k not in ("dtype", "save_every")}
    return {
        "format": FORMAT_VERSION, "setup": setup_dict,
        "ranges": [[r.name, r.low, r.high, r.num] for r in ranges],
        "method": settings.method.name, "samples": settings.n_samples(), "seed": settings.seed,
        "dtype": settings.dtype, "run": run, "chunk": int(chunk),
        "tile": tile,  # the compiled width decides the last bits (dscjax.sweep.device)
    }


def run_sweep(setup, settings: SweepSettings | None = None, spec: RunSpec | None = None, *,
              out_dir: str | Path | None = None, resume: bool = False, overwrite: bool = False,
              progress: Callable[[dict[str, Any]], None] | None = None, devices=None,
              tile: int | None = None, **run) -> SweepResult:
    """Run a sweep of `setup` (gains fixed) over `settings`; see the module docstring.

    Args:
        setup: the nominal Setup; it is cast to `settings.dtype`.
        settings: what to sample and how (validated here); default `SweepSettings()`.
        spec: how each plant is simulated; or its fields as keywords (`run`).
        out_dir: write chunk files and results.npz there (None: in memory only).
        resume: skip the blocks already in out_dir (written by the same settings).
        overwrite: start afresh even if out_dir holds a sweep's chunk files.
        progress: called after every round with a dict: done (samples, the resumed ones
            too), total and steps_per_s (without compilation, once a round was timed alone).
        devices: default those of `device.choose(spec.device, n)`.
        tile: rows of the one compiled block program (a multiple of 64); default
            `dscjax.sweep.device.tile_rows(platform, n)`. Blocks of any chunk run as tiles of
            this width, so the results do not depend on the chunk.

    Returns:
        SweepResult; nothing is raised for diverged samples.

    Example:
        >>> import dscjax, numpy as np
        >>> from dscjax.sweep import SweepSettings, run_sweep
        >>> res = run_sweep(dscjax.paper_example(dtype=np.float32), SweepSettings(samples=8),
        ...                 t_final=0.5, dt=1e-3)
        >>> res.columns["linf_error_window"].shape
        (8,)
    """
    settings = settings or SweepSettings()
    spec = RunSpec.given(spec, run, "run_sweep")
    validation.one_of(settings.dtype, "sweep.dtype", DTYPES)
    dtype = np.dtype(settings.dtype)
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise ConfigError("sweep.dtype = 'float64' needs JAX's x64 mode: "
                          "jax.config.update('jax_enable_x64', True) before anything else")
    setup = params.cast(setup, dtype)
    ranges = check_settings(settings, setup, spec)
    check(setup, spec)
    n = settings.n_samples()
    columns = tuple(r.param for r in ranges)
    if devices is None:
        choice = device.choose(spec.device, n)
        devices, placement = choice.devices, str(choice)
    else:
        placement = "the devices given"
    if tile is not None and (not isinstance(tile, int) or tile < 1):
        raise ConfigError(f"tile must be an integer >= 1 (got {tile!r})")
    tile = tile or tile_rows(devices[0].platform, n)
    runner = Runner(setup, columns, spec, devices, tile, lean=xla.lean_work(n * spec.n_steps))
    chunk = settings.chunk or (_started_chunk(out_dir) if resume and out_dir is not None else None)
    if not chunk:  # the default, in whole tiles where that keeps the number of blocks
        chunk = runner.default_chunk(n)
        whole = -(-chunk // tile) * tile
        chunk = whole if -(-n // whole) == -(-n // chunk) else chunk
    names = tuple(r.name for r in ranges)
    # the values actually simulated: rounded to the sweep's dtype
    table = settings.method.draw(ranges, n, settings.seed).astype(dtype).astype(np.float64)
    n_blocks = -(-n // chunk)
    fp = fingerprint(setup, settings, ranges, spec, chunk, tile)
    digest = files.digest(fp)

    out = Path(out_dir) if out_dir is not None else None
    main = jax.process_index() == 0
    done = (np.zeros(n_blocks, dtype=bool) if out is None
            else _prepare_dir(out, fp, digest, n_blocks, resume, overwrite, main))
    kept: dict[int, dict[str, np.ndarray]] = {}

    todo = [b for b in range(n_blocks) if not done[b]]
    t_start = time.perf_counter()
    n_done_before = int(sum(_block_len(b, chunk, n) for b in range(n_blocks) if done[b]))
    n_run, t_first_round = 0, None
    for r in range(0, len(todo), runner.n_dev):
        group = todo[r:r + runner.n_dev]
        host = runner([table[b * chunk:(b + 1) * chunk] for b in group], chunk)
        for k, b in enumerate(group):
            lo = b * chunk
            m = _block_len(b, chunk, n)
            part = {key: v[k * chunk:k * chunk + m] for key, v in host.items()}
            part = runner.refine(table[lo:lo + m], part)
            data = _columns(np.arange(lo, lo + m, dtype=np.int64), names, table[lo:lo + m], part)
            if out is None:
                kept[b] = data
            elif main:
                with critical():  # a Ctrl-C waits for the chunk file (dscjax.progress)
                    files.write_npz(_chunk_path(out, b), {**data, "_fingerprint": np.array(digest)})
            n_run += m
        now = time.perf_counter()
        t_first_round = t_first_round or (now, n_run)
        if progress is not None:
            t_first, n_first = t_first_round
            # the rate after the first round excludes compilation
            t0, n0 = (t_first, n_first) if n_run > n_first and now > t_first else (t_start, 0)
            rate = (n_run - n0) / (now - t0) if now > t0 else 0.0
            progress(dict(done=n_done_before + n_run, total=n, steps_per_s=rate * spec.n_steps))
    elapsed = time.perf_counter() - t_start

    if out is not None and main:  # every block from its file (the resumed ones too)
        kept = {b: _read_chunk(_chunk_path(out, b), digest) for b in range(n_blocks)}
        if missing := [b for b, data in kept.items() if data is None]:
            raise ConfigError(f"{_chunk_path(out, missing[0])} is missing or unreadable after "
                              f"the sweep; run again with --resume")
    columns_out = ({k: np.concatenate([kept[b][k] for b in range(n_blocks)]) for k in kept[0]}
                   if kept else {})
    if out is not None and main:
        with critical():
            files.write_npz(out / "results.npz", columns_out)
    info = dict(n_samples=n, n_params=len(names), n_blocks=n_blocks, chunk=chunk,
                devices=runner.n_dev, processes=jax.process_count(),
                platform=runner.devices[0].platform, placement=placement,
                n_steps=spec.n_steps, **scope(settings, spec, ranges), samples_run=n_run,
                samples_resumed=n_done_before, wall_s=elapsed,
                steps_per_s=(n_run * spec.n_steps / elapsed) if n_run and elapsed > 0 else None)
    return SweepResult(columns=columns_out, param_names=names, info=info)


def scope(settings: SweepSettings, spec: RunSpec, ranges) -> dict[str, Any]:
    """What a sweep runs, as its result's info says it, the loop in words too
    (`runspec.loop_words`; `summary.scope_text` words the whole, given "n_samples" too)."""
    return dict(dtype=settings.dtype, t_final=spec.t_final, dt=float(spec.dt),
                window_start=float(spec.window_start), state_bound=float(spec.state_bound),
                method=settings.method.name, seed=settings.seed, solver=spec.solver.name,
                refine=spec.refine, sample_time=spec.sample_time, delay=spec.delay,
                noise=None if spec.noise is None else np.asarray(spec.noise, float).tolist(),
                noise_seed=int(spec.noise_seed), discretisation=spec.discretisation.name,
                ranges={r.name: [r.low, r.high] + ([r.num] if r.num else []) for r in ranges},
                loop=loop_words(spec))


def _started_chunk(out_dir) -> int | None:
    """The chunk of the sweep in `out_dir` (its sweep.json), which a resume without a chunk of
    its own continues with; None if there is none."""
    try:
        chunk = files.read_json(Path(out_dir) / MANIFEST)["fingerprint"]["chunk"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return int(chunk) if isinstance(chunk, int) and chunk > 0 else None


def check_resumable(out: str | Path, setup, settings: SweepSettings, spec: RunSpec) -> None:
    """ConfigError unless `out` holds a sweep to resume (its sweep.json) made with the sweep's
    setup, settings and run (naming the old and new values), so that a command refuses before
    it prints or runs anything."""
    manifest = files.resume_file(out, MANIFEST)
    chunk = settings.chunk or _started_chunk(out)
    if chunk is None:
        return
    setup = params.cast(setup, np.dtype(settings.dtype))
    ranges = check_settings(settings, setup, spec)
    old = files.read_json(manifest).get("fingerprint")
    # the tile follows the devices, known only once placed: run_sweep checks it again
    tile = old.get("tile") if isinstance(old, dict) else None
    files.check_same(old, fingerprint(setup, settings, ranges, spec, chunk, tile),
                     where=f"--resume: {manifest}")


def _prepare_dir(out: Path, fp, digest, n_blocks, resume, overwrite, main) -> np.ndarray:
    manifest = files.resume_file(out, MANIFEST) if resume else out / MANIFEST
    done = np.zeros(n_blocks, dtype=bool)
    if main:
        files.mkdir(out / "chunks")
        existing = sorted((out / "chunks").glob("chunk_*.npz"))
        if resume:
            files.check_record(out, MANIFEST, fp)
            done = np.array([_read_chunk(_chunk_path(out, b), digest) is not None
                             for b in range(n_blocks)])
        elif existing and not overwrite:
            raise ConfigError(f"{out} already holds a sweep ({len(existing)} chunk files); "
                              f"use --resume to continue it or --overwrite to start afresh")
        else:
            for f in existing:
                f.unlink()
            (out / "results.npz").unlink(missing_ok=True)
        with critical():
            files.write_text(manifest, files.dumps({"fingerprint": fp, "digest": digest}) + "\n")
    return np.asarray(from_process_0(done))


def _block_len(b, chunk, n):
    return min(chunk, n - b * chunk)


def _columns(sample, names, values, part) -> dict[str, np.ndarray]:
    code, step = part["status"].astype(np.int8), part["bad_step"].astype(np.int64)
    return {"sample": sample, **{name: values[:, j] for j, name in enumerate(names)},
            **{k: part[k] for k in METRICS}, "diverged": code != 0,
            "t_diverged": np.where(step >= 0, step * part["dt_used"], np.inf), "status": code,
            "refinements": part["refinements"].astype(np.int8),
            "dt_used": part["dt_used"].astype(np.float64)}


def _read_chunk(path: Path, fingerprint: str) -> dict[str, np.ndarray] | None:
    """A finished chunk file, or None if missing, unreadable or from another sweep."""
    data = files.read_npz(path)
    if data is None or str(data.pop("_fingerprint", "")) != fingerprint:
        return None
    return data


def _chunk_path(out_dir: Path, b: int) -> Path:
    return out_dir / "chunks" / f"chunk_{b:06d}.npz"
