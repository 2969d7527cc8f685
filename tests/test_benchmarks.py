"""Every benchmark script still imports and explains itself (``--help``): a renamed function or a moved module
fails here rather than the day someone reruns a measurement.  The ones that run on tiny data are smoke-tested
beside the code they measure (``test_robust_checks``: shapes, clean_shapes, ranking/sweep, reasons;
``test_petnet``: controller_speed; ``test_foreign``: the generators)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").rglob("*.py")
                 if p.name not in ("test_slow.py", "record.py", "__init__.py") and "data" not in p.parts)


@pytest.mark.parametrize("path", SCRIPTS, ids=[str(p.relative_to(ROOT / "benchmarks")) for p in SCRIPTS])
def test_every_benchmark_imports_and_explains_itself(path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=180,
                         cwd=ROOT, env=env)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage" in res.stdout.lower() and len(res.stdout) > 100, res.stdout
