"""Test configuration: float64 everywhere (references and gradient checks need it).

x64 is switched on here, once, before any test module imports jax.numpy arrays; tests that
need float32 say so and cast their setups (dscjax.cast) instead of flipping the flag.
"""

import jax

jax.config.update("jax_enable_x64", True)

import pytest  # noqa: E402

import dscjax  # noqa: E402


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
