"""Nothing global changes on `import dscjax`; the 512-bit vector preference of the batched
programs (dscjax/xla.py) is asked for only when wanted, and no vector width changes a result
(checked on every machine at each width its CPU runs)."""

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
from dscjax.runspec import RunSpec
from dscjax.simulate import run_reported


@pytest.mark.parametrize("env,avx512,wide", [
    ({}, True, True),
    ({}, False, False),
    ({"XLA_FLAGS": "--xla_cpu_prefer_vector_width=256"}, True, False),  # the user's choice wins
    ({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}, True, True),
])
def test_wide_vectors_only_when_wanted(env, avx512, wide):
    assert xla.compiler_options(env, has_avx512=avx512) == (xla.WIDE if wide else {})


@pytest.mark.parametrize("env,lean", [
    ({}, True),
    ({"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}, False),  # the user's choice wins
    ({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}, True),
])
def test_lean_emitters_unless_the_user_chose(env, lean):
    assert xla.lean_options(env) == (xla.LEAN if lean and xla.emitter_choice() else {})


@pytest.mark.parametrize("version,choice", [("0.10.2", True), ("0.10.0.dev20260101", True),
                                            ("0.9.2", True), ("0.11.2", False), ("1.0.0", False)])
def test_no_emitter_option_where_jaxlib_has_no_choice(version, choice):
    assert xla.emitter_choice(version) is choice


@pytest.mark.parametrize("member_steps,lean", [
    (None, False),  # a time limit alone: the run may be long
    (0.0, True),
    (5e6, True),  # LEAN_WORK: half the break-even of docs/benchmarks.md
    (5e6 + 1, False),
])
def test_a_batched_program_compiles_lean_only_when_its_whole_work_is_small(member_steps, lean):
    assert xla.lean_work(member_steps) is lean


def test_a_lean_program_called_inside_a_trace_joins_the_callers_program():
    """JAX refuses compiler options on a nested jit, also when its arguments are concrete."""
    f = xla.jit(lambda x: jnp.sin(x) * 2.0, lean=True)
    assert float(jax.jit(lambda x: f(2.0) + f(x))(1.0)) == pytest.approx(
        2 * (np.sin(2.0) + np.sin(1.0)), rel=1e-15)
    assert float(jax.grad(f)(1.0)) == pytest.approx(2 * np.cos(1.0), rel=1e-15)


def test_lean_emitters_change_no_result_beyond_rounding(paper_setup):
    """One trajectory, continuous and sampled, compiled as dscjax compiles it (lean: the loop
    emitters) and with XLA's default emitters: the same trajectories and metrics to rounding
    (1e-10 of each quantity's scale; RK4's own error at this step is orders larger)."""
    setup = dscjax.canonical(paper_setup)
    for sample_time in (None, 2e-3):
        spec = RunSpec.make(0.5, 1e-3, save_every=50, window_start=0.25,
                            sample_time=sample_time).program()
        runs = [jax.jit(run_reported, compiler_options=o)(setup, spec, None, None)
                for o in (xla.LEAN, {xla.EMITTERS: True})]
        for a, b in zip(*(jax.tree.leaves(r) for r in runs), strict=True):
            a, b = np.asarray(a), np.asarray(b)
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.max(np.abs(b)))


def test_cpuinfo_parsing(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n")
    assert xla.cpu_has_avx512(str(info)) == sys.platform.startswith("linux")
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512_vnni\n")
    assert not xla.cpu_has_avx512(str(info))
    assert not xla.cpu_has_avx512(str(tmp_path / "missing"))


def _vector_widths(cpuinfo: str = "/proc/cpuinfo") -> tuple[int, ...]:
    """The vector widths [bits] this CPU runs: 128 (SSE2, every x86-64), 256 with AVX2, 512
    with AVX-512 (the width dscjax's batched programs ask for there)."""
    try:
        with open(cpuinfo) as f:
            flags = next((line.split() for line in f if line.startswith("flags")), [])
    except OSError:
        flags = []
    return (128,) + ((256,) if "avx2" in flags else ()) + ((512,) if "avx512f" in flags else ())


# Every machine compiles the batch at each width it runs: on the CI machine (AVX2) 128 and 256
# bits, on an AVX-512 machine also 512, the width of `xla.compiler_options()` there.
WIDTHS = _vector_widths()

_DUMP = """
import sys, jax, jax.numpy as jnp
x = jnp.ones(4096, jnp.float32)
for w in sys.argv[1:]:
    jax.jit(lambda x: jnp.sin(x) * x + 1.0,
            compiler_options={"xla_cpu_prefer_vector_width": int(w)}).lower(x).compile()
"""


def test_the_vector_width_reaches_the_code_generator(tmp_path):
    """The premise of the next test: XLA:CPU emits vectors of the width asked for (LLVM IR
    dumps of one elementwise kernel compiled at each width this CPU runs), so that each width
    is different machine code."""
    env = dict(os.environ, XLA_FLAGS=f"--xla_dump_to={tmp_path}", JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, "-c", _DUMP, *map(str, WIDTHS)], env=env, check=True,
                   capture_output=True, timeout=300)
    # the kernels, in the order compiled (module numbers grow)
    modules = sorted({f.name.split(".")[0] for f in tmp_path.glob("*lambda*ir-with-opt.ll")})
    assert len(modules) == len(WIDTHS), sorted(f.name for f in tmp_path.iterdir())
    for width, module in zip(WIDTHS, modules, strict=True):
        ir = "".join(f.read_text() for f in tmp_path.glob(f"{module}.*ir-with-opt.ll"))
        floats = width // 32
        assert f"<{floats} x float>" in ir, (width, module)
        assert f"<{2 * floats} x float>" not in ir, (width, module)


def test_vector_widths_change_no_result(paper_setup):
    """The same float64 batch compiled for every vector width this CPU runs (different machine
    code, see above), dscjax's own choice included: bitwise equal trajectories and metrics."""
    setup = dscjax.canonical(paper_setup)
    overrides = {"hysteresis.alpha": jnp.linspace(0.7, 1.3, 64),
                 "hysteresis.lam": jnp.linspace(1.0, 1.8, 64)}
    spec = RunSpec.make(0.5, 1e-3, save_every=50, window_start=0.25)
    runs = [jax.jit(run_reported, compiler_options={xla.OPTION: w})(setup, spec, overrides)
            for w in WIDTHS]
    # what simulate_batch and sweeps run: the 512-bit program above on AVX-512, else JAX's own
    assert xla.compiler_options() in ({}, xla.WIDE)
    if xla.compiler_options() == xla.WIDE:
        assert 512 in WIDTHS
    else:
        runs.append(xla.jit(run_reported)(setup, spec, overrides))
    for other in runs[1:]:
        for a, b in zip(jax.tree.leaves(runs[0]), jax.tree.leaves(other), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


_IMPORT_ALL = """
import gc, json, os, signal, sys, tempfile
import matplotlib
env, thresholds = dict(os.environ), gc.get_threshold()
# read without resolving: rcParams["backend"] would import pyplot and pick a backend
backend = repr(dict.__getitem__(matplotlib.rcParams, "backend"))
rc = {k: repr(v) for k, v in dict.items(matplotlib.rcParams)}
import dscjax, dscjax.cli.main, dscjax.reproduce.complexity, dscjax.plotting, dscjax.reproduce
import dscjax.sweep, dscjax.sweep.plots, tuning, tuning.report, tuning.search, dscjax.progress
with tempfile.TemporaryDirectory() as d, dscjax.plotting.saved(os.path.join(d, "f.png"), 100,
                                                                figsize=(2, 2)):
    pass
print(json.dumps({
    "env": dict(os.environ) == env,
    "backend": repr(dict.__getitem__(matplotlib.rcParams, "backend")) == backend,
    "rc": {k: repr(v) for k, v in dict.items(matplotlib.rcParams)} == rc,
    "pyplot": "matplotlib.pyplot" in sys.modules,
    "sigint": signal.getsignal(signal.SIGINT) is signal.default_int_handler,
    "gc": gc.get_threshold() == thresholds,
}))
"""


def test_import_changes_nothing_global():
    """`import dscjax` (and every module that plots, the CLI and the tuner) leaves the
    environment (XLA_FLAGS included), matplotlib's backend and its rcParams as they were, never
    loads pyplot, installs no signal handler (issue 25: only a command's run does) and leaves
    the garbage collector's thresholds as they were."""
    out = subprocess.run([sys.executable, "-c", _IMPORT_ALL], capture_output=True, text=True,
                         check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {
        "env": True, "backend": True, "rc": True, "pyplot": False, "sigint": True, "gc": True}
