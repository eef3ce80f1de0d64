"""Test configuration: float64 everywhere (references and gradient checks need it).

x64 is switched on here, once, before any test module imports jax.numpy arrays; tests that
need float32 say so and cast their setups (dscjax.cast) instead of flipping the flag.
"""

import os
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
# Commands run through dscjax.cli.main.main in this process must not switch JAX's persistent
# cache on in the user's home (test_cli tests that cache in a subprocess; the tests' own cache
# is set up by pytest_configure below).
os.environ.setdefault("DSCJAX_NO_COMPILATION_CACHE", "1")

import pytest  # noqa: E402

import dscjax  # noqa: E402
from dscjax import xla  # noqa: E402


def pytest_configure(config):
    """JAX's persistent compilation cache in pytest's cache directory (shared by the xdist
    workers and, through JAX_COMPILATION_CACHE_DIR, by the processes tests start): a program
    that several tests or files compile, in whatever process, is compiled once. Without
    pytest's cache: a directory of this process."""
    cache = getattr(config, "cache", None)
    path = xla.enable_compilation_cache(cache.mkdir("jax-compilation-cache") if cache is not None
                                        else tempfile.mkdtemp(prefix="dscjax-jax-cache-"))
    if path is not None:
        os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)


# The longest files first (xdist's --dist loadfile with --no-loadscope-reorder hands files out in
# this order): a long file started last would leave the other worker idle at the end.
LONGEST_FIRST = ("test_docs.py", "test_out_dir.py", "test_sweep.py", "test_gradients.py",
                 "test_tuning_gradients.py", "test_tuning_loop.py", "test_tuning_adversarial.py")


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: each file keeps its own order


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
