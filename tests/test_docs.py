"""The shell examples of README.md and docs/*.md run as printed (with small sizes; see
tests/doc_examples.py for exactly what changes). One subprocess a document (xdist spreads
them), each in its own directory; the outputs that several documents read (my.toml, the
README's tune run) are made once per session (`shared_docs`) and copied in. JAX's persistent
compilation cache lives in pytest's cache directory, so a program one document compiles is
not compiled again by another, nor by a second run of the suite (without pytest's cache: a
directory of this session)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import doc_examples
import pytest

HERE = Path(__file__).parent
PLAN = doc_examples.plan()
# the longest first, those that wait for `shared_docs` between those that do not (xdist hands
# the first two to the two workers)
ORDER = ("README.md", "reproduction.md", "tuning.md", "theory.md", "sweeps.md",
         "worst-case.md", "hysteresis.md")
DOCS = sorted((name for name, steps in PLAN.items() if name != "shared" and steps),
              key=lambda name: ORDER.index(name) if name in ORDER else len(ORDER))


def _run(group: str, work: Path, cache_dir: Path) -> list[dict]:
    """The report of `doc_examples.py WORK GROUP`, asserting that every command succeeded."""
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache_dir),
           "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
           "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "-1"}
    proc = subprocess.run([sys.executable, str(HERE / "doc_examples.py"), str(work), group],
                          env=env, capture_output=True, text=True, timeout=3600)
    assert proc.stdout.strip(), proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    failed = [r for r in report if r["code"]]
    assert not failed, "\n".join(f"{r['doc']}: {r['printed']}\n  ran: {r['ran']}\n  exit "
                                 f"{r['code']}: {r['stderr']}" for r in failed)
    assert proc.returncode == 0
    assert [r["printed"] for r in report] == [s[1] for s in PLAN[group] if s[0] == "run"]
    return report


@pytest.fixture(scope="session")
def doc_cache(request, once):
    cache = getattr(request.config, "cache", None)
    return (cache.mkdir("jax-compilation-cache") if cache is not None
            else once("jax-cache", lambda work: work.mkdir()))


@pytest.fixture(scope="session")
def shared_docs(once, doc_cache):
    """The directory in which the commands of doc_examples.SHARED ran (once per session)."""
    return once("doc-examples-shared", lambda work: _run("shared", work, doc_cache))


@pytest.mark.parametrize("doc", DOCS)
def test_shell_examples_of_the_document_run(doc, tmp_path, request, doc_cache):
    work = tmp_path / "w"
    if doc in doc_examples.READS_SHARED:
        shutil.copytree(request.getfixturevalue("shared_docs"), work)
    _run(doc, work, doc_cache)


def test_every_document_with_examples_is_run_and_the_key_examples_are_among_them():
    printed = {s[1] for steps in PLAN.values() for s in steps if s[0] == "run"}
    assert set(doc_examples.SHARED) <= {s[1] for s in PLAN["shared"]}
    for example in ("dscjax simulate --print-config > my.toml",
                    "dscjax tune --resume --steps 600 --time-limit none",
                    "dscjax reproduce --complexity --resume",
                    "dscjax sweep --resume --samples 100000 --out results/big",
                    "dscjax worst-case --config envelope.toml --metric requirement:envelope "
                    "--range hysteresis.alpha=30% --disturbance fourier:4:0.5 --out "
                    "results/worst-envelope",
                    "dscjax tune --adversarial 2 --disturbance fourier:16:0.5 --batch 8 "
                    "--aggregate cvar --cvar-level 0.25 --out results/adversarial --resume"):
        assert example in printed, example
    assert set(DOCS) >= {"README.md", "reproduction.md", "sweeps.md", "tuning.md"}
    # a document reads the shared outputs only through a copy: those that do are declared
    for name in DOCS:
        text = " ".join(" ".join(map(str, s[2])) for s in PLAN[name] if s[0] == "run")
        if "my.toml" in text or "results/tune/" in text:
            assert name in doc_examples.READS_SHARED, name
