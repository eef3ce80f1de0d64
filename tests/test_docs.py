"""The shell examples of README.md and docs/*.md run as printed (with small sizes; see
tests/doc_examples.py for exactly what changes). One subprocess runs them all in order; JAX's
persistent compilation cache lives in pytest's cache directory, so a second run of the suite
compiles almost nothing (without pytest's cache: a temporary directory)."""

import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).parent


def test_shell_examples_of_readme_and_docs_run(tmp_path, request):
    cache = getattr(request.config, "cache", None)
    cache_dir = cache.mkdir("jax-compilation-cache") if cache else tmp_path / "jax-cache"
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache_dir),
           "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
           "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "-1"}
    proc = subprocess.run([sys.executable, str(HERE / "doc_examples.py"), str(tmp_path / "w")],
                          env=env, capture_output=True, text=True, timeout=1200)
    assert proc.stdout.strip(), proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    failed = [r for r in report if r["code"]]
    assert not failed, "\n".join(f"{r['doc']}: {r['printed']}\n  ran: {r['ran']}\n  exit "
                                 f"{r['code']}: {r['stderr']}" for r in failed)
    assert proc.returncode == 0
    printed = {r["printed"] for r in report}
    for example in ("dscjax simulate --print-config > my.toml",
                    "dscjax tune --resume --steps 600 --time-limit 0",
                    "dscjax reproduce --complexity --resume",
                    "dscjax sweep --resume --samples 100000 --out results/big",
                    "dscjax worst-case --config envelope.toml --metric requirement:envelope "
                    "--range hysteresis.alpha=30% --disturbance fourier:4:0.5 --out "
                    "results/worst-envelope",
                    "dscjax tune --adversarial 2 --disturbance fourier:16:0.5 --batch 8 "
                    "--aggregate cvar --cvar-level 0.25 --out results/adversarial --resume"):
        assert example in printed, example
    assert {r["doc"] for r in report} >= {"README.md", "reproduction.md", "sweeps.md",
                                         "tuning.md"}
