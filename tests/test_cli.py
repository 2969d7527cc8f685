import json
import subprocess
import sys
from pathlib import Path

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
    # What the audit will rely on: the tasks and their sizes, the lengths, each stream and its width.
    assert "demos per task" in res.output and "3-3 (median 3)" in res.output and "12-12 steps" in res.output
    assert "observation.environment_state" in res.output and "the environment state" in res.output
    assert "observation.state" in res.output and "the actions" in res.output
    res = runner.invoke(app, ["info", str(tmp_path / "missing")])
    assert res.exit_code == 2 and "no such file" in res.output


def test_brackets_survive_help_and_errors(tmp_path):
    """Rich reads [word] as markup: the install hint 'democheck[ray]' and a path with brackets must print as written."""
    for command in ("audit", "synth", "probe"):
        res = runner.invoke(app, [command, "--help"], env={"COLUMNS": "400"})
        assert res.exit_code == 0 and "'democheck[ray]'" in res.output, command
    res = runner.invoke(app, ["info", str(tmp_path / "run[2]")])
    assert res.exit_code == 2 and "run[2]" in res.output


@pytest.mark.parametrize("moment", ["loading", "importing the simulator", "workers running"])
def test_ctrl_c_at_any_moment_prints_one_line_and_leaves_nothing(tmp_path, moment):
    """Ctrl-C reaches the whole process group: while the CLI loads, while a command imports its libraries (a GL
    library turns the interrupt into an error of its own) and while workers run, the answer is one line, exit
    status 130, no traceback from any process, no output folder and no process left behind.  The job is long
    enough (64 episodes) that it is still running at every moment."""
    import os
    import signal
    import threading
    import time

    out = tmp_path / "d"
    proc = subprocess.Popen([sys.executable, "-m", "democheck", "synth", "push-mini", "--out", str(out),
                             "--workers", "2", "--tasks", "8", "--demos", "8"],
                            stdout=open(tmp_path / "stdout.txt", "w"), stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    lines, first_episode = [], threading.Event()

    def read_stderr():
        for line in proc.stderr:
            lines.append(line)
            if "1/64" in line or "episodes" in line:
                first_episode.set()

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    if moment == "workers running":
        assert first_episode.wait(timeout=120), "".join(lines)
    else:
        time.sleep({"loading": 0.15, "importing the simulator": 0.6}[moment])
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=60)
    reader.join(timeout=10)
    text = (tmp_path / "stdout.txt").read_text() + "".join(lines)
    assert proc.returncode == 130, text
    assert "Traceback" not in text and "SpawnPoolWorker" not in text and "KeyboardInterrupt" not in text, text
    assert text.count("interrupted; nothing was written") == 1, text
    assert not out.exists() and not list(tmp_path.glob(".d*")), list(tmp_path.iterdir())
    # An exited worker not yet reaped (Z) holds nothing; multiprocessing's resource tracker leaves a moment after the
    # process it served, on a busy machine a little later.
    for _ in range(50):
        ps = subprocess.run(["ps", "-o", "stat=,pid=", "-g", str(proc.pid)], capture_output=True, text=True).stdout
        running = [line for line in ps.splitlines() if line.strip() and not line.strip().startswith("Z")]
        if not running:
            break
        time.sleep(0.1)
    assert not running, f"processes left behind: {running}"


def test_ctrl_c_taken_by_another_thread_while_workers_start_is_answered_after_they_have_started():
    """The signal mask holds only the starting thread; a press that another thread takes is held too, and raised
    once the workers have started (else it would stop the pool half-built, its workers left to nobody)."""
    import os
    import signal
    import threading
    import time

    from democheck.pool import _workers_ignore_ctrl_c

    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)  # started before the mask: takes what the main blocks
    other.start()
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # whatever an earlier test left
    starting_done = False
    try:
        with pytest.raises(KeyboardInterrupt):
            with _workers_ignore_ctrl_c():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.2)
                starting_done = True
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        stop.set()
        signal.signal(signal.SIGINT, before)
    assert starting_done


def test_info_says_before_any_long_work_that_the_video_files_are_not_where_the_metadata_says(tmp_path):
    import shutil

    from typer.testing import CliRunner

    from democheck.cli import app

    data = tmp_path / "d"
    shutil.copytree(Path(__file__).parent / "data" / "mw-tiny", data)
    res = CliRunner().invoke(app, ["info", str(data)])
    assert res.exit_code == 0 and "every one there; a sample decodes" in res.output, res.output
    (data / "videos").rename(data / "video")  # where info.json does not say they are
    res = CliRunner().invoke(app, ["info", str(data)])
    said = " ".join(res.output.split())
    assert res.exit_code == 0 and "1 problem(s)" in said and "file-000.mp4: missing (21 episodes)" in said, said
    (data / "video").rename(data / "videos")
    (data / "videos" / "observation.images.corner" / "chunk-000" / "file-000.mp4").write_bytes(b"not a video")
    said = " ".join(CliRunner().invoke(app, ["info", str(data)]).output.split())
    assert "episode 0's first and last frame do not decode" in said, said
