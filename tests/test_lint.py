"""ruff finds nothing in the repository (the rules of pyproject.toml's [tool.ruff])."""

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _ruff() -> list[str] | None:
    if importlib.util.find_spec("ruff") is not None:
        return [sys.executable, "-m", "ruff"]
    exe = shutil.which("ruff")
    return [exe] if exe else None


def test_ruff_check_is_clean():
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed (it is in the test extra: pip install -e '.[test]')")
    proc = subprocess.run([*ruff, "check", "--no-cache", "."], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]


APPLICATIONS = ("dscjax.sweep", "dscjax.worst", "dscjax.reproduce", "dscjax.identify",
                "dscjax.export", "dscjax.cli", "tuning")


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at any depth (a function's lazy imports too)."""
    import ast

    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            # `from dscjax import sweep` imports dscjax.sweep (a name that is not a module
            # counts too: harmless, no application is named like a function)
            names |= {node.module, *(f"{node.module}.{a.name}" for a in node.names)}
    return names


def _within(name: str, packages) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


def test_the_layers_of_docs_architecture():
    """The core (the search too) imports no application, and tuning none but dscjax.worst
    (min-max tuning) (docs/architecture.md, "Modules")."""
    core = [p for p in (ROOT / "dscjax").rglob("*.py")
            if not _within(".".join(p.relative_to(ROOT).with_suffix("").parts), APPLICATIONS)]
    wrong = {f"{p.relative_to(ROOT)} imports {n}" for p in core for n in _imports(p)
             if _within(n, APPLICATIONS)}
    allowed = [a for a in APPLICATIONS if a not in ("dscjax.worst", "tuning")]
    wrong |= {f"{p.relative_to(ROOT)} imports {n}" for p in (ROOT / "tuning").rglob("*.py")
              for n in _imports(p) if _within(n, allowed)}
    assert not wrong, sorted(wrong)
