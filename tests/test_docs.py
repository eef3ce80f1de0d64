"""The shell examples of README.md and docs/*.md run as printed (with small sizes; see
tests/doc_examples.py for exactly what changes). Each document's commands run through
`dscjax.cli.main.main` in the test's process (xdist spreads the documents), in its own
directory; the outputs that several documents read (my.toml, the README's tune run) are made
once per session (`shared_docs`) and copied in. A program that the worker has compiled already,
for another document or another test, is not compiled again (the tests that share a
document's programs run on its worker: conftest's groups)."""

import os
import shutil
from pathlib import Path

import doc_examples
import pytest

PLAN = doc_examples.plan()
# the longest first, those that wait for `shared_docs` between those that do not (xdist hands
# the first two to the two workers)
ORDER = ("README.md", "reproduction.md", "tuning.md", "theory.md", "sweeps.md",
         "worst-case.md", "hysteresis.md")
DOCS = sorted((name for name, steps in PLAN.items() if name != "shared" and steps),
              key=lambda name: ORDER.index(name) if name in ORDER else len(ORDER))


def _run(group: str, work: Path) -> list[dict]:
    """The report of doc_examples' GROUP run in `work`, asserting that every command
    succeeded."""
    here = os.getcwd()
    try:
        report = doc_examples.run_group(work, group, PLAN[group])
    finally:
        os.chdir(here)
    failed = [r for r in report if r["code"]]
    assert not failed, "\n".join(f"{r['doc']}: {r['printed']}\n  ran: {r['ran']}\n  exit "
                                 f"{r['code']}: {r['stderr']}" for r in failed)
    assert [r["printed"] for r in report] == [s[1] for s in PLAN[group] if s[0] == "run"]
    return report


@pytest.fixture(scope="session")
def shared_docs(once):
    """The directory in which the commands of doc_examples.SHARED ran (once per session)."""
    return once("doc-examples-shared", lambda work: _run("shared", work))


@pytest.mark.parametrize("doc", DOCS)
def test_shell_examples_of_the_document_run(doc, tmp_path, request):
    work = tmp_path / "w"
    if doc in doc_examples.READS_SHARED:
        shutil.copytree(request.getfixturevalue("shared_docs"), work)
    _run(doc, work)
    if doc == "README.md":  # `dscjax reproduce --no-plot`: the summaries, no figure
        paper = work / "results" / "paper"
        assert (paper / "summary.md").is_file() and not list(paper.glob("fig*"))
        assert "Figures:" not in (paper / "summary.md").read_text()


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


def _python_blocks():
    """(document, block) for every ```python block of README.md and docs/*.md."""
    import re

    for doc in doc_examples.documents():
        for block in re.findall(r"```python\n(.*?)```", doc.read_text(), flags=re.S):
            yield doc.name, block


def test_every_call_of_the_python_examples_binds_to_the_api_it_names():
    """Each call in the documents' Python blocks to a function or class of dscjax, tuning or
    their modules (by the names the block imports) passes arguments its signature accepts:
    none missing, no unknown keyword. Checked without running the blocks (the README's optax
    loop runs in test_objective)."""
    import ast
    import importlib
    import inspect

    checked, bad = 0, []
    for doc, block in _python_blocks():
        tree = ast.parse(block)
        names = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names |= {a.asname or a.name: importlib.import_module(a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module.split(".")[0] in ("dscjax",
                                                                                     "tuning"):
                for a in node.names:  # a name of the module, or a submodule
                    module = importlib.import_module(node.module)
                    names[a.asname or a.name] = (getattr(module, a.name) if hasattr(
                        module, a.name) else importlib.import_module(f"{node.module}.{a.name}"))
        for call in (n for n in ast.walk(tree) if isinstance(n, ast.Call)):
            chain, f = [], call.func
            while isinstance(f, ast.Attribute):
                chain, f = [f.attr, *chain], f.value
            if not isinstance(f, ast.Name) or f.id not in names:
                continue  # a call on a value the block computed
            target = names[f.id]
            for attr in chain:
                target = getattr(target, attr)
            root = getattr(inspect.getmodule(target), "__name__", "").split(".")[0]
            if root not in ("dscjax", "tuning") or any(
                    isinstance(a, ast.Starred) for a in call.args) or any(
                    k.arg is None for k in call.keywords):
                continue
            try:
                inspect.signature(target).bind(*call.args, **{k.arg: k for k in call.keywords})
            except TypeError as err:
                bad.append(f"{doc}: {ast.unparse(call)}: {err}")
            checked += 1
    assert not bad, "\n".join(bad)
    assert checked >= 20, checked  # the blocks' calls were found
