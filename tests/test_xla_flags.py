"""dscjax/_xla.py: the wide-vector XLA:CPU flag is added only when wanted and changes no result."""

import json
import os
import subprocess
import sys

import pytest

from dscjax import _xla


@pytest.mark.parametrize("env,avx512,added", [
    ({}, True, True),
    ({}, False, False),
    ({"XLA_FLAGS": "--xla_cpu_prefer_vector_width=256"}, True, False),  # the user's choice wins
    ({"DSCJAX_NO_XLA_FLAGS": "1"}, True, False),
    ({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}, True, True),
])
def test_flag_added_only_when_wanted(env, avx512, added):
    environ = dict(env)
    before = environ.get("XLA_FLAGS", "")
    assert _xla.prefer_wide_vectors(environ, has_avx512=avx512) is added
    after = environ.get("XLA_FLAGS", "")
    if added:
        assert after.split() == before.split() + [_xla.FLAG]
    else:
        assert after == before


def test_cpuinfo_parsing(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n")
    assert _xla.cpu_has_avx512(str(info)) == sys.platform.startswith("linux")
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512_vnni\n")
    assert not _xla.cpu_has_avx512(str(info))
    assert not _xla.cpu_has_avx512(str(tmp_path / "missing"))


_BATCH = """
import json, jax, numpy as np
jax.config.update("jax_enable_x64", True)
import dscjax, jax.numpy as jnp
setup = dscjax.paper_example()
b = dscjax.simulate_batch(setup, {"hysteresis.alpha": jnp.linspace(0.7, 1.3, 64),
                                  "hysteresis.lam": jnp.linspace(1.0, 1.8, 64)}, 0.5, 1e-3,
                          save_every=50)
print(json.dumps({"flags": __import__("os").environ.get("XLA_FLAGS", ""),
                  "x": np.asarray(b.x).ravel().tolist(), "u": np.asarray(b.u).ravel().tolist(),
                  "m": {k: np.asarray(v).tolist() for k, v in b.metrics.items()}}))
"""


def _run(extra_env):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", _xla.OPT_OUT)}
    env.update(extra_env)
    out = subprocess.run([sys.executable, "-c", _BATCH], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_wide_vectors_change_no_result():
    """A float64 batch with and without the flag: bitwise equal trajectories and metrics."""
    wide = _run({})
    narrow = _run({_xla.OPT_OUT: "1"})
    assert _xla.FLAG not in narrow["flags"]
    assert (_xla.FLAG in wide["flags"]) == _xla.cpu_has_avx512()
    assert wide["x"] == narrow["x"] and wide["u"] == narrow["u"]
    assert wide["m"] == narrow["m"]
