import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from democheck.cli import app
from democheck.data import open_dataset

runner = CliRunner()
TINY_ARGS = ["--tasks", "3", "--demos", "2", "--steps", "10", "--size", "16"]


def test_help_does_not_import_heavy_libraries():
    code = ("import sys; from typer.testing import CliRunner; from democheck.cli import app; "
            "r = CliRunner().invoke(app, ['--help']); assert r.exit_code == 0, r.output; "
            "heavy = [m for m in ('torch', 'mujoco', 'av', 'rerun') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_synth_cli_writes_exact_size_and_is_deterministic(tmp_path):
    runs = []
    for name, workers in (("a", "2"), ("b", "1")):
        res = runner.invoke(app, ["synth", "push-mini", "--out", str(tmp_path / name), "--workers", workers,
                                  "--seed", "7", *TINY_ARGS])
        assert res.exit_code == 0, res.output
        runs.append(open_dataset(tmp_path / name))
    a, b = runs
    assert len(a) == 6 and len(a.tasks) == 3
    for e in a.episode_indices:
        da, db = a[e], b[e]  # two worker counts, same seed: same dataset
        np.testing.assert_array_equal(da.state, db.state)
        np.testing.assert_array_equal(da.actions, db.actions)
        np.testing.assert_array_equal(da.frames, db.frames)
    summary = json.loads((tmp_path / "a/meta/democheck/suite.json").read_text())
    assert summary["episodes"] == 6 and summary["recipe"]["seed"] == 7


def test_synth_refuses_existing_output_and_bad_recipe(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x/keep.txt").write_text("precious")
    res = runner.invoke(app, ["synth", "push-mini", "--out", str(tmp_path / "x"), *TINY_ARGS])
    assert res.exit_code == 2 and "already exists" in res.output
    assert (tmp_path / "x/keep.txt").read_text() == "precious"
    res = runner.invoke(app, ["synth", "no-such-suite", "--out", str(tmp_path / "y")])
    assert res.exit_code == 2 and "push-v1" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "y").exists()


def test_info_cli(tiny_dataset, tmp_path):
    root, _ = tiny_dataset
    res = runner.invoke(app, ["info", str(root)])
    assert res.exit_code == 0 and "lerobot-v3.0" in res.output and "clean: 12" in res.output
    res = runner.invoke(app, ["info", str(tmp_path / "missing")])
    assert res.exit_code == 2 and "no such file" in res.output


def test_brackets_survive_help_and_errors(tmp_path):
    """Rich reads [word] as markup: the install hint 'democheck[ray]' and a path with brackets must print as written."""
    for command in ("audit", "synth", "probe"):
        res = runner.invoke(app, [command, "--help"], env={"COLUMNS": "400"})
        assert res.exit_code == 0 and "'democheck[ray]'" in res.output, command
    res = runner.invoke(app, ["info", str(tmp_path / "run[2]")])
    assert res.exit_code == 2 and "run[2]" in res.output


@pytest.mark.parametrize("delay", [1.0, 2.5])
def test_ctrl_c_while_workers_start_prints_one_line_and_leaves_nothing(tmp_path, delay):
    """Ctrl-C reaches the whole process group: the workers, starting up, must not print a traceback each."""
    import os
    import signal
    import time

    out = tmp_path / "d"
    proc = subprocess.Popen([sys.executable, "-m", "democheck", "synth", "push-mini", "--out", str(out),
                             "--workers", "2", "--tasks", "4", "--demos", "2"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(delay)
    os.killpg(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    text = stdout + stderr
    if proc.returncode == 0:  # finished before the interrupt: nothing to check
        pytest.skip("the command finished before Ctrl-C")
    assert proc.returncode == 130, text
    assert "Traceback" not in text and "SpawnPoolWorker" not in text and "KeyboardInterrupt" not in text, text
    assert text.count("interrupted; nothing was written") == 1, text
    assert not out.exists() and not list(tmp_path.glob(".d*"))
    ps = subprocess.run(["ps", "-o", "stat=,pid=", "-g", str(proc.pid)], capture_output=True, text=True).stdout
    running = [line for line in ps.splitlines() if line.strip() and not line.strip().startswith("Z")]
    assert not running, f"processes left behind: {running}"  # an exited worker not yet reaped (Z) holds nothing
