"""Test configuration: float64 everywhere (references and gradient checks need it).

x64 is switched on here, once, before any test module imports jax.numpy arrays; tests that
need float32 say so and cast their setups (dscjax.cast) instead of flipping the flag.
"""

import gc
import os
import shutil
import signal
import tempfile

# The tests' programs (and those of the commands they start) compile as cheaply as XLA:CPU
# allows: the suite's time is compiling programs that each run a few short horizons once. No
# backend optimisation, and every program with the loop emitters that dscjax gives its
# run-once programs (`xla.LEAN`; test_xla compares both emitters explicitly).
# Python's cyclic garbage collector seldom: a worker traces thousands of programs, tracing
# allocates short-lived objects by the million, and at CPython's thresholds the collector
# re-walks the worker's whole heap (every jaxpr and program it keeps) again and again
# (docs/benchmarks.md, "The test suite").
gc.set_threshold(50_000, 20, 100)
os.environ["XLA_FLAGS"] = " ".join(
    [os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0",
     "--xla_cpu_use_fusion_emitters=false"]).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Commands run through dscjax.cli.main.main in this process must not switch JAX's persistent
# cache on in the user's home (test_cli tests that cache in a subprocess; the tests' own cache
# is set up by pytest_configure below).
os.environ.setdefault("DSCJAX_NO_COMPILATION_CACHE", "1")

import pytest  # noqa: E402

import dscjax  # noqa: E402
from dscjax import xla  # noqa: E402

_TEMPORARY_CACHE = pytest.StashKey[str]()


def pytest_configure(config):
    """SIGINT delivered as KeyboardInterrupt, as in a user's terminal: a pytest started in the
    background of a non-interactive shell (`pytest &` in a script) inherits SIGINT ignored,
    Python then installs no handler, and the Ctrl-C tests (test_out_dir) would see nothing.

    JAX's persistent compilation cache in pytest's cache directory, for the processes tests
    start (through JAX's variables): a command a test interrupts and resumes, or two
    processes of one sweep, compile each program once. Without pytest's cache
    (`-p no:cacheprovider`): a temporary directory of the session, removed at its end (the
    workers inherit the one the main process configured). The workers themselves compile
    without it: what they share is shared in memory (the groups below), and over a whole
    suite their reads and writes cost more CPU than their hits spared (docs/benchmarks.md,
    "The test suite")."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    cache = getattr(config, "cache", None)
    if cache is not None:
        directory = cache.mkdir("jax-compilation-cache")
    elif jax.config.jax_compilation_cache_dir:
        directory = None  # configured already (a worker: the main process's)
    else:
        directory = config.stash[_TEMPORARY_CACHE] = tempfile.mkdtemp(prefix="dscjax-jax-cache-")
    path = xla.enable_compilation_cache(directory)
    if path is not None:
        os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
        # the processes tests start: the same cache, size (locked) and least compile time
        for name in ("jax_compilation_cache_max_size",
                     "jax_persistent_cache_min_compile_time_secs"):
            os.environ[name.upper()] = str(getattr(jax.config, name))
    jax.config.update("jax_enable_compilation_cache", False)


def pytest_unconfigure(config):
    """The session's temporary cache directory, if it made one, removed."""
    directory = config.stash.get(_TEMPORARY_CACHE, None)
    if directory is not None:
        shutil.rmtree(directory, ignore_errors=True)


# The longest files first (the scheduler below hands the groups out in this order,
# --no-loadscope-reorder): a long file started last would leave the other worker idle.
LONGEST_FIRST = ("test_docs.py", "test_out_dir.py", "test_tuning_adversarial.py",
                 "test_tuning_loop.py", "test_sweep.py", "test_gradients.py",
                 "test_tuning_gradients.py", "test_identify.py", "test_refine.py")
# Files whose parametrized tests xdist may hand to different workers, one group a parameter
# (each test runs alone, whatever is shared comes from `once`); every other file is one group.
SPLIT = ("test_docs.py",)
# Files that share compiled programs run on one worker, in one group: `search_problem`
# (test_out_dir, test_tuning_search), `traj20` (test_paper_reference, test_dsc), the tuning
# report's elasticities of test_tuning_loop's run (test_tuning_report), the reverse-mode
# Jacobian of the README's `dscjax sensitivity` example (test_sensitivity) and the stability
# map of its `dscjax stability` example (test_validation), the runs of
# reproduction.md's `dscjax reproduce --theory` and `--complexity` (test_lyapunov,
# test_reproduce).
DOC = "tests/test_docs.py::test_shell_examples_of_the_document_run[{}]"
TOGETHER = {"test_tuning_search.py": "test_out_dir.py", "test_dsc.py": "test_paper_reference.py",
            "test_tuning_report.py": "test_tuning_loop.py",
            "test_sensitivity.py": DOC.format("README.md"),
            "test_validation.py": DOC.format("README.md"),
            "test_lyapunov.py": DOC.format("reproduction.md"),
            "test_reproduce.py": DOC.format("reproduction.md")}


def group(nodeid: str) -> str:
    """The xdist work unit of a test: its file (see SPLIT and TOGETHER)."""
    path, _, rest = nodeid.partition("::")
    name = path.rsplit("/", 1)[-1]
    if name in SPLIT and "[" in rest:
        return nodeid
    return TOGETHER.get(name, name)


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: each file keeps its own order


@pytest.hookimpl(optionalhook=True)  # (a hook of xdist's)
def pytest_xdist_make_scheduler(config, log):
    """xdist's scheduling by scope (as --dist loadfile), the scopes being `group`'s."""
    from xdist.scheduler import LoadScopeScheduling

    class ByGroup(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group(nodeid)

    return ByGroup(config, log)


@pytest.fixture(scope="session")
def once(tmp_path_factory):
    """f(NAME, MAKE) -> a directory that MAKE(directory) filled once in this pytest session,
    whichever xdist worker asked first (the others wait for it, then read it). A MAKE that
    failed fails every later f(NAME, ...) with its message, without running again."""
    import fcntl
    import shutil

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's directory, above the workers' own

    def get(name: str, make):
        work, done, failed = root / name, root / f"{name}.done", root / f"{name}.failed"
        with open(root / f"{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if failed.exists():
                pytest.fail(f"{name} failed in another test: {failed.read_text()}")
            if not done.exists():
                shutil.rmtree(work, ignore_errors=True)
                try:
                    make(work)
                except BaseException as err:
                    failed.write_text(str(err)[-3000:])
                    raise
                done.touch()
        return work

    return get


@pytest.fixture(scope="session")
def four_devices(once):
    """The directory of tests/four_devices.py's results: the checks that need several real
    devices, run once per session in one interpreter with 4 forced host devices."""
    import subprocess
    import sys
    from pathlib import Path

    def make(work):
        env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=os.environ["XLA_FLAGS"]
                   + " --xla_force_host_platform_device_count=4")
        proc = subprocess.run([sys.executable, str(Path(__file__).parent / "four_devices.py"),
                               str(work)], env=env, capture_output=True, text=True,
                              timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]

    return once("four-devices", make)


# The size policy of the tests that run a command: the horizon SHORT (200 RK4 steps at the
# default dt = 1 ms) unless the test is about a longer one, the same in every file, so that
# the program one test compiles serves the others of its worker (and, through the persistent
# cache, the processes tests start); the documents' examples run as many steps
# (tests/doc_examples.py).
SHORT = "0.2"


@pytest.fixture(scope="session")
def short() -> tuple[str, str]:
    """("--t-final", SHORT): the horizon of a test's command (see SHORT)."""
    return ("--t-final", SHORT)


@pytest.fixture(scope="session")
def paper_setup():
    """The paper's example in float64."""
    return dscjax.paper_example()


def _run_with_config(directory, toml: str, *argv: str):
    from dscjax.cli.main import main

    cfg = directory / "config.toml"
    cfg.write_text(toml)
    out = directory / "out"
    return main([*argv, "--config", str(cfg), "--out", str(out)]), out


@pytest.fixture(scope="session")
def run_with_config():
    """f(DIR, TOML, *ARGV) -> (exit code, DIR/out): `dscjax ARGV --config DIR/config.toml
    --out DIR/out`, the config holding TOML."""
    return _run_with_config


@pytest.fixture(scope="session")
def traj20(paper_setup):
    """The paper's example over its 20 s at dt = 1 ms, every step saved."""
    return dscjax.simulate(paper_setup, 20.0, 1e-3)


@pytest.fixture(scope="session")
def search_problem():
    """The tuning problem of the search tests (test_tuning_search, test_out_dir): controller.k
    by cma (population 10, the same at a restart, 4 generations, each saved), forward-mode
    gradients, over 1 s
    at dt = 2 ms, window from 0.5 s; no sampled loop (a 1 ms controller cannot be sampled on
    the 2 ms step). A test changes its optimizer by `dataclasses.replace` of `cfg`: the same
    objective, so the same compiled programs."""
    import tuning
    from dscjax.runspec import RunSpec

    spec = tuning.OptimizerSpec(name=tuning.CMAES(), steps=4, save_interval=1, popsize=10, growth=1,
                                time_limit=None, gradient=tuning.Forward())
    cfg = tuning.TuningConfig(params=("controller.k",), optimizer=spec,
                              objective=tuning.ObjectiveSpec(window_start=0.5),
                              heldout=tuning.BatchSpec(batch=0))
    return tuning.build_problem(dscjax.paper_example(), RunSpec.make(t_final=1.0, dt=2e-3), cfg)

