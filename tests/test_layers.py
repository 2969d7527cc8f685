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
