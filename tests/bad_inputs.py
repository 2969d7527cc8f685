"""Bad inputs and the one line democheck answers each with (exit status 2, no traceback, nothing written).

Each case builds its broken input from a good tiny dataset and model, and
names the command to run.  ``tests/test_bad_inputs.py`` runs them all;
``python -m tests.bad_inputs docs/bad-inputs.md`` writes the table of
observed messages.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

DATA_FILE = "data/chunk-000/file-000.parquet"
EPISODES_FILE = "meta/episodes/chunk-000/file-000.parquet"
VIDEO_FILE = "videos/observation.images.main/chunk-000/file-000.mp4"


@dataclass
class Case:
    name: str  # what is wrong, as the table says it
    build: Callable[[Path, Path, Path], list[str]]  # (tmp, good dataset, good model) -> argv after "democheck"
    expect: str  # a piece of the message
    # Found only once the demos are decoded: the progress of that work comes before the one line.
    after_progress: bool = False


def _copy(src: Path, tmp: Path, name: str = "ds") -> Path:
    dst = tmp / name
    shutil.copytree(src, dst)
    return dst


def _audit(ds: Path | str, tmp: Path, model: Path, *extra: str) -> list[str]:
    return ["audit", str(ds), "--out", str(tmp / "out"), "--model", str(model), *extra]


def _train(ds: Path, tmp: Path) -> list[str]:
    return ["train", str(ds), "--out", str(tmp / "out"), "--steps", "2", "--set", "batch_tasks=2", "--set",
            "timesteps=2", "--device", "cpu", "--cache-dir", str(tmp / "cache")]


def _rewrite_column(path: Path, key: str, fn) -> None:
    t = pq.read_table(path)
    t = t.set_column(t.column_names.index(key), key, fn(t.column(key)))
    pq.write_table(t, path)


def _edit_json(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def missing_path(tmp, ds, model):
    return _audit(tmp / "no-such-dataset", tmp, model)


def not_a_dataset(tmp, ds, model):
    (tmp / "photos").mkdir()
    (tmp / "photos" / "a.txt").write_text("hello")
    return _audit(tmp / "photos", tmp, model)


def info_missing(tmp, ds, model):
    d = _copy(ds, tmp)
    (d / "meta/info.json").unlink()
    return _audit(d, tmp, model)


def info_malformed(tmp, ds, model):
    d = _copy(ds, tmp)
    (d / "meta/info.json").write_text('{"codebase_version": "v3.0", "fps": ')
    return _audit(d, tmp, model)


def episodes_parquet_truncated(tmp, ds, model):
    d = _copy(ds, tmp)
    _truncate(d / EPISODES_FILE)
    return _audit(d, tmp, model)


def data_parquet_truncated(tmp, ds, model):
    d = _copy(ds, tmp)
    _truncate(d / DATA_FILE)
    return _train(d, tmp)


def video_garbage(tmp, ds, model):
    d = _copy(ds, tmp)
    (d / VIDEO_FILE).write_bytes(np.random.default_rng(0).bytes(5000))
    return _audit(d, tmp, model)


def state_wrong_shape(tmp, ds, model):
    d = _copy(ds, tmp)
    _edit_json(d / "meta/info.json", lambda doc: doc["features"]["observation.state"].update(shape=[12]))
    return _train(d, tmp)


def action_wrong_dtype(tmp, ds, model):
    d = _copy(ds, tmp)
    _rewrite_column(d / DATA_FILE, "action", lambda c: pa.array([f"a{i}" for i in range(len(c))]))
    return _train(d, tmp)


def _poison(tmp, ds, key: str, row: int, col: int, value: float) -> list[str]:
    """A copy of the dataset with one value of a state/action column replaced (NaN, inf), and train on it."""
    d = _copy(ds, tmp)

    def poisoned(column):
        x = np.stack(column.to_pylist()).astype(np.float32)
        x[row, col] = value
        return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])

    _rewrite_column(d / DATA_FILE, key, poisoned)
    return _train(d, tmp)


def action_nan(tmp, ds, model):
    return _poison(tmp, ds, "action", 5, 2, np.nan)


def state_inf(tmp, ds, model):
    return _poison(tmp, ds, "observation.state", 7, 0, np.inf)


def zero_length_episode(tmp, ds, model):
    d = _copy(ds, tmp)
    _rewrite_column(d / EPISODES_FILE, "length", lambda c: pa.array([0] + c.to_pylist()[1:], pa.int64()))
    return _audit(d, tmp, model)


def empty_dataset(tmp, ds, model):
    d = _copy(ds, tmp)
    t = pq.read_table(d / EPISODES_FILE)
    pq.write_table(t.slice(0, 0), d / EPISODES_FILE)
    return _audit(d, tmp, model)


def single_demo_tasks(tmp, ds, model):
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    d = tmp / "one-each"
    generate(replace(TINY, demos_per_task=1), d, workers=1)
    return _train(d, tmp)


def unknown_camera(tmp, ds, model):
    return _audit(ds, tmp, model, "--camera", "wrist")


def checkpoint_mismatch(tmp, ds, model):
    m = _copy(model, tmp, "model")
    _edit_json(m / "config.json", lambda doc: doc["model"].update(fc_units=64))
    return _audit(ds, tmp, m)


def checkpoint_pickle(tmp, ds, model):
    m = _copy(model, tmp, "model")
    (m / "model.safetensors").write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    return _audit(ds, tmp, m)


def checkpoint_random_bytes(tmp, ds, model):
    m = _copy(model, tmp, "model")
    (m / "config.json").write_bytes(np.random.default_rng(1).bytes(300))
    return _audit(ds, tmp, m)


def checkpoint_is_a_torch_file(tmp, ds, model):
    f = tmp / "model.pt"
    f.write_bytes(pickle.dumps({"state_dict": {"w": [0.0, 1.0]}, "epoch": 3}))
    return _audit(ds, tmp, f)


def state_width_mismatch(tmp, ds, model):
    from tests.test_audit import _write_robomimic

    path = tmp / "narrow.hdf5"
    _write_robomimic(path, joints=10)  # 10 joint positions + 3 end-effector: 13 state dimensions, not 17
    return _audit(path, tmp, model)


def path_escape(tmp, ds, model):
    d = _copy(ds, tmp)
    _edit_json(d / "meta/info.json", lambda doc: doc.update(video_path="../../{video_key}/file-{file_index:03d}.mp4"))
    return _audit(d, tmp, model)


def path_nul(tmp, ds, model):
    d = _copy(ds, tmp)
    _edit_json(d / "meta/info.json", lambda doc: doc.update(video_path="\0"))
    return _audit(d, tmp, model)


CASES = [
    Case("path does not exist", missing_path, "no such file or directory"),
    Case("a directory that is no dataset", not_a_dataset, "not a dataset democheck knows"),
    Case("meta/info.json missing", info_missing, "info.json: missing"),
    Case("meta/info.json malformed", info_malformed, "not valid JSON"),
    Case("episodes parquet truncated", episodes_parquet_truncated, "unreadable parquet"),
    Case("data parquet truncated", data_parquet_truncated, "unreadable parquet"),
    Case("every episode's video unreadable (random bytes)", video_garbage, "every episode is broken", True),
    Case("state feature of the wrong shape", state_wrong_shape, "the metadata says 12"),
    Case("action feature of the wrong dtype", action_wrong_dtype, "not numbers"),
    Case("NaN in actions", action_nan, "NaN or infinite values in 'action'"),
    Case("infinite value in states", state_inf, "NaN or infinite values in 'observation.state'"),
    Case("zero-length episode", zero_length_episode, "has no frames"),
    Case("empty dataset", empty_dataset, "no episodes"),
    Case("every task has a single demo (train)", single_demo_tasks, "training needs two or more per task"),
    Case("unknown --camera", unknown_camera, "no camera 'wrist'"),
    Case("checkpoint config does not match its tensors", checkpoint_mismatch, "do not match config.json"),
    Case("a pickle where model.safetensors should be", checkpoint_pickle, "not a safetensors file"),
    Case("random bytes where config.json should be", checkpoint_random_bytes, "not valid JSON"),
    Case("a torch pickle file given as the model", checkpoint_is_a_torch_file, "not a file"),
    Case("state width the model was not trained for", state_width_mismatch, "states have 13 dimensions"),
    Case("a ../../ video path in the metadata", path_escape, "points outside the dataset"),
    Case("a NUL character in a metadata path", path_nul, "holds a NUL character"),
]


def run_case(case: Case, tmp: Path, ds: Path, model: Path):
    """Run one case through the CLI in-process; returns (argv, exit code, output, exception)."""
    from typer.testing import CliRunner

    from democheck.cli import app

    argv = case.build(tmp, ds, model)
    res = CliRunner().invoke(app, argv)
    return argv, res.exit_code, res.output.strip(), res.exception


def _fixtures(tmp: Path) -> tuple[Path, Path]:
    from democheck.petnet.train import TrainConfig
    from democheck.sim.suite import generate
    from democheck.workflows import train_model
    from tests.conftest import TINY

    ds, model = tmp / "good", tmp / "model"
    generate(TINY, ds, workers=1)
    train_model(ds, model, TrainConfig(steps=4, batch_tasks=2, timesteps=2, val_every=2, device="cpu"),
                cache_dir=tmp / "cache")
    return ds, model


def main(out: str) -> None:  # pragma: no cover - documentation generator
    import tempfile

    os.environ.setdefault("MUJOCO_GL", "egl")
    lines = ["# Bad inputs and what democheck says", "",
             "Generated by `python -m tests.bad_inputs docs/bad-inputs.md` (each case is also a test in "
             "`tests/test_bad_inputs.py`). Every row: exit status 2, one line on stderr (after the progress of "
             "the decoding where only that finds it), no traceback, no output folder written. Paths are shortened to the part inside the temporary folder.", "",
             "| input | command | message |", "|---|---|---|"]
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        ds, model = _fixtures(tmp)
        for i, case in enumerate(CASES):
            work = tmp / f"case{i}"
            work.mkdir()
            argv, code, output, exc = run_case(case, work, ds, model)
            output = output.splitlines()[-1] if case.after_progress and output else output
            msg = output.replace(str(work) + "/", "").replace(str(tmp) + "/", "").replace("|", "\\|")
            ok = code == 2 and case.expect in output and "\n" not in output
            lines.append(f"| {case.name} | `democheck {argv[0]}` | {msg if ok else 'UNEXPECTED: ' + msg} (exit {code}) |")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/bad-inputs.md")
