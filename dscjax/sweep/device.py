"""Running blocks of a sweep on the devices: one compiled single-device program of a fixed
tile width (`tile_rows`) per device; a block of any size runs as tiles of that width
(`xla.tiles`: the last padded with copies of a valid row), so a row's result does not depend
on the block size."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, SingleDeviceSharding
from jax.sharding import PartitionSpec as P

from dscjax import device as dscjax_device
from dscjax import params, xla
from dscjax.runspec import RunSpec
from dscjax.simulate import counted_levels, level_spec, refine_rows, refinement_level, run_reported

# the tracking error, and the effort with the chattering index (docs/numerics.md): every
# verdict of a sweep says both
METRICS = ("linf_error", "linf_error_window", "l2_error", "l2_error_window", "rms_error",
           "rms_error_window", "max_abs_u", "l2_u", "tv_u", "max_abs_w", "max_abs_u_window",
           "tv_u_window", "chattering_index")


def _block_body(setup, spec, table, *, columns):
    """The metrics and status of every row of a (chunk, d) table of parameter values."""
    traj = run_reported(setup, spec, overrides=params.overrides(setup, columns, table))
    return {**{k: traj.metrics[k] for k in METRICS}, "status": traj.status.code,
            "bad_step": traj.status.step}


# One compiled program per shape: every block runs it on tiles of the same width, so one
# program serves every block size; 512-bit vectors on AVX-512 CPUs, or lean for a sweep whose
# whole work is small (dscjax.xla.lean_work).
_block = xla.jit(_block_body, static_argnames=("columns",))
_block_lean = xla.jit(_block_body, lean=True, static_argnames=("columns",))
# Rows per tile: XLA compiles each width differently (the fused loop of two widths can differ in
# the last bits of some rows), so the width never follows the chunk. It is a multiple of 64, so
# every row sits in a full vector (no scalar remainder loop with code of its own).
CPU_TILE_ROWS = 1024
ACCELERATOR_TILE_ROWS = 262144  # a GPU needs wide batches: a narrow tile idles most of it


def tile_rows(platform: str, n: int) -> int:
    """The tile width of the block program of a sweep of `n` rows on `platform` ("cpu",
    "gpu", ...): the platform's maximum (`CPU_TILE_ROWS`, `ACCELERATOR_TILE_ROWS`), or n
    rounded up to 64 (to 256 beyond 256 rows, the alignment of `dscjax.device.auto_chunk`)
    where that is less, so a small sweep does not pay for a wide tile."""
    most = CPU_TILE_ROWS if platform == "cpu" else ACCELERATOR_TILE_ROWS
    align = 256 if n > 256 else 64
    return min(most, -(-max(n, 1) // align) * align)


class Runner:
    """Runs rounds of blocks, one block per device of the mesh, and returns host arrays;
    `tile`: rows per compiled tile (a sweep passes its `tile_rows`)."""

    def __init__(self, setup, columns, spec: RunSpec, devices, tile: int, lean: bool = False):
        self.devices = list(devices)
        # the whole sweep's compiled programs alike: the tiles and the refinements
        self.block = _block_lean if lean else _block
        self.tile = tile
        self.n_dev = len(self.devices)
        self.columns = tuple(columns)
        self.dtype = np.dtype(np.asarray(setup.plant.x0).dtype)
        # metrics only: the first and last points saved
        self.spec = spec.replace(save_every=spec.n_steps).for_dtype(self.dtype)
        # block b of a round on devices[b]
        self.out_sharding = NamedSharding(Mesh(np.array(self.devices), ("batch",)), P("batch"))
        self._compiled = False
        self.local = [d for d in self.devices if d.process_index == jax.process_index()]
        self.setup_on = {d: jax.device_put(setup, d) for d in self.local}

    def default_chunk(self, n: int) -> int:
        """Rows per block of a sweep of `n` rows (`dscjax.device.auto_chunk`): on an
        accelerator from the first local device's free memory and the tile program's memory
        per row (`per_row_bytes`, compiled, nothing run; process 0's, so that every host
        agrees)."""
        first = self.local[0]
        if first.platform == "cpu":
            return dscjax_device.auto_chunk(n)
        table = jax.ShapeDtypeStruct((self.tile, len(self.columns)), self.dtype,
                                     sharding=SingleDeviceSharding(first))
        compiled = _block.top.lower(self.setup_on[first], self.spec.program(), table,
                                    columns=self.columns).compile()
        chunk = dscjax_device.auto_chunk(n, first, dscjax_device.free_bytes(first),
                                         dscjax_device.per_row_bytes(compiled, self.tile),
                                         self.n_dev)
        return int(from_process_0(np.int64(chunk)))

    def __call__(self, blocks: list[np.ndarray], chunk: int) -> dict[str, np.ndarray]:
        """blocks: a round's blocks of rows, at most one per device and at most `chunk` rows
        each, identical on every process. Returns each metric's rows, `chunk` per block (past
        a short block's rows: zeros): of the blocks given with one process; of one block per
        device with several (the devices past the blocks run the last one again: garbage)."""
        single = jax.process_count() == 1
        # one process: padding blocks need not run
        jobs = {b: dev for b, dev in enumerate(self.devices)
                if dev in self.local and not (single and b >= len(blocks))}

        def dispatch(block):
            rows = np.asarray(blocks[min(block, len(blocks) - 1)], self.dtype)
            return self._tiles_on(jobs[block], self.spec, rows)

        if self._compiled or len(jobs) == 1:
            # asynchronous: the devices overlap
            outs = [dispatch(b) for b in jobs]
        else:
            # The first call compiles the program once per device: do that concurrently.
            with ThreadPoolExecutor(len(jobs)) as pool:
                outs = list(pool.map(dispatch, jobs))
        self._compiled = True
        # each job's tile outputs, in block order (that of the local devices)
        if single:
            return {k: np.concatenate([_join(o, k, chunk) for o in outs]) for k in outs[0][0]}
        return {k: _to_host(jax.make_array_from_single_device_arrays(
            (self.n_dev * chunk,), self.out_sharding,
            [_join(o, k, chunk, jax.numpy) for o in outs])) for k in outs[0][0]}

    def _tiles_on(self, device, spec, rows) -> list[dict]:
        """The tile program's outputs (device arrays, dispatched asynchronously) for `rows`
        split into tiles (`xla.tiles`) on `device`, with the setup placed there."""
        # (host-side fields of the spec never recompile the tile program)
        setup, program = self.setup_on[device], spec.program()
        return [self.block(setup, program, jax.device_put(t, device), columns=self.columns)
                for t in xla.tiles(rows, self.tile)]

    def refine(self, table: np.ndarray, part: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """`part` with its diverged rows re-run at the spec's refinement levels
        (`counted_levels`, `refine_rows`) on the first local device, and the columns
        "refinements" and "dt_used" added (every process computes the same rows: no gather)."""
        rows = np.asarray(table, self.dtype)
        levels = counted_levels(self.spec)

        def level(j, idx):  # the same tile program as the blocks: independent of the chunk
            out = self._tiles_on(self.local[0], level_spec(self.spec, j), rows[idx])
            return {k: _join(out, k, len(idx)) for k in out[0]}

        out, level_of = refine_rows(part, lambda p: np.asarray(p["status"]) != 0, level, levels)
        halvings = np.array([refinement_level(j, self.spec.solver)[1] for j in range(levels + 1)])
        out["refinements"] = level_of.astype(np.int8)
        out["dt_used"] = float(self.spec.dt) / 2.0**halvings[level_of]
        return out


def _join(outputs: list[dict], key: str, n: int, xp=np):
    """Column `key` of a list of tile outputs, cut or zero-padded to n rows: on the host, or
    with `xp` = `jax.numpy` on the tiles' device (concatenation copies bits, nothing is
    computed)."""
    a = xp.concatenate([xp.asarray(o[key]) for o in outputs])[:n]
    return xp.concatenate([a, xp.zeros(n - a.shape[0], a.dtype)])


def from_process_0(x):
    """x as process 0 has it, on every process (x itself with one process)."""
    if jax.process_count() == 1:
        return x
    from jax.experimental import multihost_utils

    return multihost_utils.broadcast_one_to_all(x)


def _to_host(a) -> np.ndarray:
    if a.is_fully_addressable:
        return np.asarray(a)
    from jax.experimental import multihost_utils  # only with several processes

    return np.asarray(multihost_utils.process_allgather(a, tiled=True))


