"""The checks that need several real devices, in ONE interpreter with 4 forced host devices:

    XLA_FLAGS=--xla_force_host_platform_device_count=4 JAX_PLATFORMS=cpu \
        python tests/four_devices.py OUTDIR

writes OUTDIR/results.json ({check: "ok" or what failed}) and OUTDIR/sweep.npz (the float64
columns of the sweep SWEEP on 4 devices). Run once per session by conftest.py's `four_devices`
fixture; the tests of test_device.py and test_sweep.py read what they need."""

import json
import sys
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import dscjax
from dscjax import device

# the sweep of test_sweep.py's `base_result` (one device), here on four
SWEEP = dict(samples=24, chunk=8, dtype="float64", t_final=0.5, dt=1e-3)


def placement(out: Path) -> None:
    cpus = jax.devices()
    assert len(cpus) == 4, cpus
    choice = device.choose("auto", 10**6)
    assert choice.devices == tuple(cpus) and choice.device == cpus[0], choice
    setup = dscjax.paper_example()
    traj = dscjax.simulate(setup, 0.2, 1e-3, save_every=200, device=cpus[2])
    assert traj.x.devices() == {cpus[2]}, traj.x.devices()
    with jax.default_device(cpus[3]):  # "auto" honours the caller's default
        again = dscjax.simulate(setup, 0.2, 1e-3, save_every=200)
    assert again.x.devices() == {cpus[3]}, again.x.devices()
    np.testing.assert_array_equal(np.asarray(traj.x), np.asarray(again.x))
    batch = dscjax.simulate_batch(setup, {"hysteresis.alpha": jnp.array([0.9, 1.1])},
                                  0.2, 1e-3, device=cpus[1])
    assert batch.metrics["linf_error"].devices() == {cpus[1]}


def sweep(out: Path) -> None:
    from dscjax.sweep import SweepSettings, run_sweep

    assert jax.device_count() == 4, jax.devices()
    s = dict(SWEEP)
    t_final, dt = s.pop("t_final"), s.pop("dt")
    res = run_sweep(dscjax.paper_example(), SweepSettings(**s), t_final=t_final, dt=dt)
    assert res.info["devices"] == 4
    np.savez(out / "sweep.npz", **res.columns)


def main(out: Path) -> int:
    jax.config.update("jax_enable_x64", True)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for check in (placement, sweep):
        try:
            check(out)
            results[check.__name__] = "ok"
        except Exception:
            results[check.__name__] = traceback.format_exc()[-3000:]
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
