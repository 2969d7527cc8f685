"""democheck's layers (DESIGN.md, pyproject.toml's import-linter contract) only point down, and the check bites."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(project: Path) -> subprocess.CompletedProcess:
    # PYTHONPATH puts this copy of the package first, ahead of any installed democheck.
    return subprocess.run([str(LINT), "--config", str(project / "pyproject.toml"), "--no-cache"], cwd=project,
                          capture_output=True, text=True, env={"PYTHONPATH": str(project), "PATH": "/usr/bin:/bin"})


@pytest.fixture(scope="module")
def lint_available():
    if not LINT.exists():
        pytest.skip("import-linter is not installed (pip install -e '.[test]')")


def test_the_layers_contract_is_kept(lint_available):
    res = _lint(ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "1 kept, 0 broken" in res.stdout


def test_an_upward_import_breaks_the_contract(lint_available, tmp_path):
    copy = tmp_path / "project"
    copy.mkdir()
    shutil.copy(ROOT / "pyproject.toml", copy)
    shutil.copytree(ROOT / "democheck", copy / "democheck", ignore=shutil.ignore_patterns("models", "__pycache__"))
    demo = copy / "democheck" / "data" / "demo.py"
    demo.write_text(demo.read_text() + "\n\ndef _upward():\n    from democheck.audit import scores  # noqa: F401\n")
    res = _lint(copy)
    assert res.returncode != 0 and "BROKEN" in res.stdout
    assert "democheck.data.demo -> democheck.audit.scores" in res.stdout


def test_no_module_imports_another_packages_private_names():
    import re

    private = re.compile(r"from democheck[\w.]* import [^#\n]*\b_[a-z]\w*")
    hits = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in (ROOT / "democheck").rglob("*.py")
            for m in private.finditer(p.read_text())]
    assert not hits, hits


def _import_graph() -> dict[str, set[str]]:
    """Which democheck modules each democheck module imports, at any depth of its code (function-level imports
    included)."""
    import ast

    graph: dict[str, set[str]] = {}
    for path in (ROOT / "democheck").rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        package = name if parts[-1] == "__init__" else name.rsplit(".", 1)[0]
        out = graph.setdefault(name, set())
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                out |= {a.name for a in node.names if a.name.startswith("democheck")}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                if base.startswith("democheck"):
                    out |= {f"{base}.{a.name}" for a in node.names} | {base}
    return {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}


# The import circles the tree has today: none.  A new one fails the test below.
KNOWN_CIRCLES: set[frozenset[str]] = set()


def test_no_new_import_circle_between_modules():
    graph = _import_graph()

    def reaches(a: str, b: str) -> bool:
        seen, todo = set(), [a]
        while todo:
            m = todo.pop()
            if m == b:
                return True
            if m not in seen:
                seen.add(m)
                todo.extend(graph.get(m, ()))
        return False

    def family(a: str, b: str) -> bool:  # a package and its own modules (an __init__ that re-exports them)
        return a.startswith(b + ".") or b.startswith(a + ".")

    circles = {frozenset({a, b}) for a in graph for b in graph[a] if not family(a, b) and reaches(b, a)}
    assert circles <= KNOWN_CIRCLES, sorted(map(sorted, circles - KNOWN_CIRCLES))
    assert circles == KNOWN_CIRCLES  # the search sees the known ones (drop one here when the code loses it)
    assert "democheck.data.lerobot" in graph["democheck.data.lerobot_v21"]  # ... and would see one: the v2.1 reader
    assert "democheck.data.lerobot_v21" not in graph["democheck.data.lerobot"]  # builds on v3.0's, not back
    assert graph["democheck.audit.trust"] == set()  # a leaf: the ranking's tests read no registry
    assert "democheck.audit.scorers" not in graph["democheck.audit.ranking"]  # the ranking knows no check by name
