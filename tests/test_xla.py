"""Nothing global changes on `import dscjax`; the 512-bit vector preference of the batched
programs (dscjax/xla.py) is asked for only when wanted and changes no result."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscjax
from dscjax import xla
from dscjax.simulate import _run_reported


@pytest.mark.parametrize("env,avx512,wide", [
    ({}, True, True),
    ({}, False, False),
    ({"XLA_FLAGS": "--xla_cpu_prefer_vector_width=256"}, True, False),  # the user's choice wins
    ({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}, True, True),
])
def test_wide_vectors_only_when_wanted(env, avx512, wide):
    assert xla.compiler_options(env, has_avx512=avx512) == (xla.WIDE if wide else {})


def test_cpuinfo_parsing(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n")
    assert xla.cpu_has_avx512(str(info)) == sys.platform.startswith("linux")
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512_vnni\n")
    assert not xla.cpu_has_avx512(str(info))
    assert not xla.cpu_has_avx512(str(tmp_path / "missing"))


# Without AVX-512 (or with a width already set in XLA_FLAGS) both compilations below are the
# same program, and comparing their results would prove nothing.
wide_differs = pytest.mark.skipif(
    not xla.cpu_has_avx512() or jax.default_backend() != "cpu"
    or xla.OPTION in os.environ.get("XLA_FLAGS", ""),
    reason="512-bit vectors change the code only on a CPU with AVX-512 and no width set in "
           "XLA_FLAGS")

_DUMP = f"""
import jax, jax.numpy as jnp
x = jnp.ones(4096, jnp.float32)
jax.jit(lambda x: jnp.sin(x) * x + 1.0, compiler_options={xla.WIDE!r}).lower(x).compile()
jax.jit(lambda x: jnp.sin(x) * x + 2.0).lower(x).compile()
"""


@wide_differs
def test_the_option_reaches_the_code_generator(tmp_path):
    """The premise of the next test: compiled with the option, XLA:CPU emits 16-float vectors
    (512 bits), without it 8-float ones, for the same elementwise kernel (LLVM IR dumps)."""
    env = dict(os.environ, XLA_FLAGS=f"--xla_dump_to={tmp_path}", JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, "-c", _DUMP], env=env, check=True, capture_output=True,
                   timeout=300)

    def widths(module):
        ir = "".join(f.read_text() for f in tmp_path.glob(f"{module}.*ir-with-opt.ll"))
        return "<16 x float>" in ir, "<8 x float>" in ir

    # the two lambdas, in the order compiled (module numbers grow)
    modules = sorted({f.name.split(".")[0] for f in tmp_path.glob("*lambda*ir-with-opt.ll")})
    assert len(modules) == 2, sorted(f.name for f in tmp_path.iterdir())
    wide, narrow = (widths(m) for m in modules)
    assert wide == (True, False) and narrow == (False, True)


@wide_differs
def test_wide_vectors_change_no_result(paper_setup):
    """The same float64 batch compiled with and without 512-bit vectors (different machine
    code on this CPU, see above): bitwise equal trajectories and metrics."""
    setup = dscjax.canonical(paper_setup)
    overrides = {"hysteresis.alpha": jnp.linspace(0.7, 1.3, 64),
                 "hysteresis.lam": jnp.linspace(1.0, 1.8, 64)}
    args = (setup, jnp.asarray(1e-3), jnp.asarray(0.25), jnp.asarray(1e6))
    kw = dict(n_steps=500, save_every=50, overrides=overrides)
    static = ("n_steps", "save_every", "checkpoint_every")
    wide = jax.jit(_run_reported, static_argnames=static, compiler_options=xla.WIDE)(*args, **kw)
    narrow = jax.jit(_run_reported, static_argnames=static)(*args, **kw)
    assert xla.compiler_options() == xla.WIDE  # what simulate_batch and sweeps compile with
    for a, b in zip(jax.tree.leaves(wide), jax.tree.leaves(narrow), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


_IMPORT_ALL = """
import json, os, sys
import matplotlib
env = dict(os.environ)
# read without resolving: rcParams["backend"] would import pyplot and pick a backend
backend = repr(dict.__getitem__(matplotlib.rcParams, "backend"))
rc = {k: repr(v) for k, v in dict.items(matplotlib.rcParams)}
import dscjax, dscjax.cli.main, dscjax.reproduce.complexity, dscjax.plotting, dscjax.reproduce
import dscjax.sweep, dscjax.sweep.plots, tuning, tuning.report
fig, ax = dscjax.plotting.subplots(figsize=(2, 2))
fig.savefig(os.devnull, format="png")
print(json.dumps({
    "env": dict(os.environ) == env,
    "backend": repr(dict.__getitem__(matplotlib.rcParams, "backend")) == backend,
    "rc": {k: repr(v) for k, v in dict.items(matplotlib.rcParams)} == rc,
    "pyplot": "matplotlib.pyplot" in sys.modules,
}))
"""


def test_import_changes_nothing_global():
    """`import dscjax` (and every module that plots) leaves the environment (XLA_FLAGS
    included), matplotlib's backend and its rcParams as they were, and never loads pyplot."""
    out = subprocess.run([sys.executable, "-c", _IMPORT_ALL], capture_output=True, text=True,
                         check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {
        "env": True, "backend": True, "rc": True, "pyplot": False}
