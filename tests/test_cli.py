import json
import subprocess
import sys

import numpy as np
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
