"""Slow checks (run with `pytest benchmarks -m slow`): the whole demo, and random SIGKILLs of every writing command."""

import json
import time

import pytest
from typer.testing import CliRunner

from democheck.cli import app


@pytest.mark.slow
def test_demo_runs_in_under_three_minutes(tmp_path):
    t0 = time.perf_counter()
    res = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "demo")])
    wall = time.perf_counter() - t0
    assert res.exit_code == 0, res.output
    assert wall < 180, wall
    summary = json.loads((tmp_path / "demo" / "report" / "summary.json").read_text())
    assert summary["labels"] == {"clean": 160, "idle": 4, "random": 4}
    assert (tmp_path / "demo" / "report" / "report.rrd").stat().st_size > 0
    print(f"demo: {wall:.0f} s; planted ranks: {res.output.splitlines()[-3]}")


@pytest.mark.slow
def test_random_kills_never_leave_an_accepted_half_result():
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parent / "kill_test.py"
    res = subprocess.run([sys.executable, str(script), "--kills", "2", "--seed", "1"], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    print(res.stdout)
