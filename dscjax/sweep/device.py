"""Running blocks of a sweep on the devices: one compiled single-device program per device,
each on its own block of a globally sharded table (see the package docstring)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, SingleDeviceSharding
from jax.sharding import PartitionSpec as P

from dscjax import device as dscjax_device
from dscjax import params, xla
from dscjax.runspec import RunSpec
from dscjax.simulate import level_spec, nan_if_diverged, refine_rows, refinement_level, run

METRICS = ("linf_error", "linf_error_window", "l2_error", "l2_error_window", "rms_error",
           "rms_error_window", "max_abs_u", "l2_u", "tv_u", "max_abs_w")


def _block_body(setup, spec, table, *, columns):
    """The metrics and status of every row of a (chunk, d) table of parameter values."""
    traj = run(setup, spec, overrides=params.overrides(setup, columns, table))
    metrics = nan_if_diverged(traj.metrics, traj.diverged)
    return {**{k: metrics[k] for k in METRICS}, "status": traj.status.code,
            "bad_step": traj.status.step}


# One compiled program per block shape; 512-bit vectors on AVX-512 CPUs (dscjax.xla).
_block = xla.jit(_block_body, static_argnames=("columns",))
PROBE_ROWS = 1024  # the block size whose compiled memory gives the footprint of a row


def bytes_per_row(setup, columns, spec: RunSpec, device, rows: int = PROBE_ROWS
                  ) -> float | None:
    """The memory of one row of the block program on `device` (`dscjax.device.per_row_bytes`
    of the program compiled for `rows` rows; nothing is run). None where JAX does not say."""
    dtype = np.dtype(np.asarray(setup.plant.x0).dtype)
    spec = spec.replace(save_every=spec.n_steps).for_dtype(dtype)
    table = jax.ShapeDtypeStruct((rows, len(columns)), dtype,
                                 sharding=SingleDeviceSharding(device))
    compiled = _block.top.lower(jax.device_put(setup, device), spec, table,
                                columns=tuple(columns)).compile()
    return dscjax_device.per_row_bytes(compiled, rows)


class Runner:
    """Runs rounds of blocks, one block per device of the mesh, and returns host arrays."""

    AXIS = "batch"

    def __init__(self, setup, columns, spec: RunSpec, chunk, parallel="per_device",
                 devices=None):
        self.devices = list(devices if devices is not None else jax.devices())
        self.mesh = Mesh(np.array(self.devices), (self.AXIS,))
        self.n_dev = len(self.devices)
        self.chunk = chunk
        self.columns = tuple(columns)
        self.dtype = np.dtype(np.asarray(setup.plant.x0).dtype)
        # metrics only: the first and last points saved
        self.spec = spec.replace(save_every=spec.n_steps).for_dtype(self.dtype)
        self.in_sharding = NamedSharding(self.mesh, P(self.AXIS, None))
        self.out_sharding = NamedSharding(self.mesh, P(self.AXIS))
        self.parallel = parallel
        self._compiled = False
        me = jax.process_index()
        self.local = [d for d in self.devices if d.process_index == me]
        if parallel == "spmd":
            body = jax.shard_map(
                lambda s, sp, t: _block_body(s, sp, t, columns=self.columns),
                mesh=self.mesh, in_specs=(P(), P(), P(self.AXIS, None)),
                out_specs=P(self.AXIS), check_vma=False)
            self._spmd = jax.jit(body, compiler_options=xla.compiler_options())
            self.setup = jax.device_put(setup, NamedSharding(self.mesh, P()))
        else:
            self.setup_on = {d: jax.device_put(setup, d) for d in self.local}
        self._setup = setup

    def __call__(self, table: np.ndarray, n_real: int) -> dict[str, np.ndarray]:
        """table: (n_dev * chunk, d) host array, identical on every process; its first
        `n_real` blocks are real (the others pad the round and their rows are garbage)."""
        table = np.asarray(table, self.dtype)
        arr = jax.make_array_from_callback(table.shape, self.in_sharding, lambda i: table[i])
        if self.parallel == "spmd":
            out = self._spmd(self.setup, self.spec, arr)
            return {k: _to_host(v) for k, v in out.items()}
        single = jax.process_count() == 1
        jobs = {}
        for shard in arr.addressable_shards:
            block = (shard.index[0].start or 0) // self.chunk
            if not (single and block >= n_real):  # one process: padding blocks need not run
                jobs[block] = shard

        def dispatch(shard):
            return shard.device, _block(self.setup_on[shard.device], self.spec, shard.data,
                                        columns=self.columns)

        if self._compiled or len(jobs) == 1:
            per_dev = {b: dispatch(sh) for b, sh in jobs.items()}  # asynchronous: devices overlap
        else:
            # The first call compiles the program once per device: do that concurrently.
            with ThreadPoolExecutor(len(jobs)) as pool:
                per_dev = dict(zip(jobs, pool.map(dispatch, jobs.values()), strict=True))
        self._compiled = True
        if single:
            keys = per_dev[0][1].keys()
            return {k: np.concatenate([np.asarray(per_dev[b][1][k]) for b in sorted(per_dev)]
                                      + [np.zeros(self.chunk * (self.n_dev - len(per_dev)),
                                                  per_dev[0][1][k].dtype)])
                    for k in keys}
        by_device = {dev: res for dev, res in per_dev.values()}
        keys = next(iter(by_device.values())).keys()
        out = {k: jax.make_array_from_single_device_arrays(
            (table.shape[0],), self.out_sharding, [by_device[d][k] for d in self.local])
            for k in keys}
        return {k: _to_host(v) for k, v in out.items()}


    def refine(self, table: np.ndarray, part: dict[str, np.ndarray], levels: int
               ) -> dict[str, np.ndarray]:
        """`part` with its diverged rows re-run at levels 1..levels (`refine_rows`) on the
        first local device, and the columns "refinements" and "dt_used" added (every process
        computes the same rows: no gather)."""
        dt = float(self.spec.dt)
        device = self.local[0] if self.local else self.devices[0]
        setup = jax.device_put(self._setup, device)
        rows = np.asarray(table, self.dtype)

        def level(j, idx):
            return _block(setup, level_spec(self.spec, j), jax.device_put(rows[idx], device),
                          columns=self.columns)

        out, level_of = refine_rows(part, lambda p: np.asarray(p["status"]) != 0, level, levels)
        halvings = np.zeros(level_of.shape, np.int64)
        for j in np.unique(level_of):
            halvings[level_of == j] = refinement_level(int(j), self.spec.solver.name)[1]
        out["refinements"] = level_of.astype(np.int8)
        out["dt_used"] = dt / 2.0**halvings
        return out


def _to_host(a) -> np.ndarray:
    if a.is_fully_addressable:
        return np.asarray(a)
    from jax.experimental import multihost_utils  # only with several processes

    return np.asarray(multihost_utils.process_allgather(a, tiled=True))


