"""Every camera: a dataset of several cameras is audited on all of them -- the picture checks per camera, named in
the columns and the words -- while the model and the other checks read the first (``--camera``)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from democheck.data import open_dataset, video
from democheck.data.lerobot import VIDEO_PATH


def add_camera(src: Path, dst: Path, name: str, change: Callable[[int, np.ndarray], np.ndarray]) -> Path:
    """A copy of the LeRobot v3.0 dataset ``src`` at ``dst`` with another camera, ``observation.images.<name>``:
    each episode's frames of the first camera as ``change(episode_index, frames)`` makes them, written as the
    first camera's files are (the same files, spans and keyframes)."""
    shutil.copytree(src, dst)
    info = json.loads((dst / "meta/info.json").read_text())
    ds = open_dataset(dst)
    first, key = ds.camera, f"observation.images.{name}"
    info["features"][key] = dict(info["features"][first])
    (dst / "meta/info.json").write_text(json.dumps(info, indent=2))
    meta = sorted((dst / "meta/episodes").glob("chunk-*/file-*.parquet"))
    for path in meta:
        eps = pd.read_parquet(path)
        for col in [c for c in eps.columns if c.startswith(f"videos/{first}/")]:
            eps[col.replace(first, key)] = eps[col]
        eps.to_parquet(path, index=False)
    eps = pd.concat([pd.read_parquet(p) for p in meta]).sort_values(f"videos/{first}/from_timestamp")
    for (chunk, file), rows in eps.groupby([f"videos/{first}/chunk_index", f"videos/{first}/file_index"]):
        out = dst / VIDEO_PATH.format(video_key=key, chunk_index=int(chunk), file_index=int(file))
        out.parent.mkdir(parents=True, exist_ok=True)
        with video.VideoWriter(out, int(ds.fps), ds.image_shape[0]) as writer:
            for e in rows["episode_index"]:
                writer.write(change(int(e), ds[int(e)].frames))
    return dst


def frozen_from(episode: int, at: int) -> Callable[[int, np.ndarray], np.ndarray]:
    """Frames mirrored left to right (another view), ``episode``'s repeating its picture from step ``at`` on."""
    def change(e: int, frames: np.ndarray) -> np.ndarray:
        frames = np.ascontiguousarray(frames[:, :, ::-1])
        if e == episode:
            frames[at:] = frames[at - 1]
        return frames
    return change


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory):
    """A tiny push set of 24 demos and a second camera, ``wrist``, that stops in one demo."""
    from dataclasses import replace

    from democheck.sim.suite import generate
    from tests.conftest import TINY

    base = tmp_path_factory.mktemp("cams")
    generate(replace(TINY, seed=6, demos_per_task=6, steps=16), base / "one", workers=1)
    stopped = open_dataset(base / "one").episode_indices[5]
    return add_camera(base / "one", base / "two", "wrist", frozen_from(stopped, 4)), stopped


def test_a_dataset_lists_its_cameras_and_reads_each(two_cameras):
    root, _ = two_cameras
    ds = open_dataset(root)
    assert ds.cameras == ["observation.images.main", "observation.images.wrist"] and ds.camera == ds.cameras[0]
    wrist = ds.other_cameras()["wrist"]
    e = ds.episode_indices[0]
    assert wrist.camera == "observation.images.wrist"
    assert np.abs(wrist[e].frames.astype(int) - ds[e].frames[:, :, ::-1].astype(int)).mean() < 3
    assert list(open_dataset(root, camera="wrist").other_cameras()) == ["main"]


def test_a_camera_that_stops_is_found_on_that_camera_and_named(two_cameras):
    """The stopped camera leads its demo's reason, by its column and in words; the first camera's checks read the
    same numbers as an audit of the dataset without the second camera."""
    from democheck.audit.run import audit

    root, stopped = two_cameras
    table, summary = audit(open_dataset(root), None)
    alone, _ = audit(open_dataset(root.parent / "one"), None)
    assert summary["cameras"] == ["main", "wrist"]
    for check in ("frozen_video", "frame_jump", "view", "colours"):
        assert f"{check}@wrist" in table and f"p_{check}@wrist" in table and f"is_{check}@wrist" in table
    by_episode, alone = table.set_index("episode_index"), alone.set_index("episode_index")
    for check in ("frozen_video", "frame_jump", "view", "colours", "idle", "motion"):
        assert np.allclose(by_episode[check], alone.loc[by_episode.index, check], equal_nan=True), check
    assert not any("@" in c for c in alone.columns)
    row = by_episode.loc[stopped]
    assert by_episode["frozen_video@wrist"].idxmax() == stopped
    assert row["rank"] == 1 and row["driven_by"] == "frozen_video@wrist"
    assert row["finding"].startswith("frozen_video:")
    assert row["reason"].startswith("on the wrist camera, the picture stays the same")


def test_the_cameras_of_one_check_count_once(two_cameras):
    """A check read on several cameras is one look (their Sidak minimum): its columns share a look in the ranking
    config, and a dataset of one camera ranks as before."""
    from democheck.audit.scorers import ranking_config

    config = ranking_config(["idle", "frozen_video", "frozen_video@wrist", "view", "view@wrist", "colours"])
    looks = {s.name: s.look for s in config.specs}
    assert looks["frozen_video"] == looks["frozen_video@wrist"] == "frozen_video"
    assert looks["view"] == looks["view@wrist"] == "view" and looks["colours"] == "" and looks["idle"] == ""
    assert ranking_config(["frozen_video", "view"]).specs[0].look == ""


def test_workers_read_every_camera_as_one_process_does(two_cameras, monkeypatch):
    """A small set is cut into small shards (24 demos without a model: three of 8), which two workers share."""
    from democheck import pool
    from democheck.audit import shards
    from democheck.audit.run import audit

    root, _ = two_cameras
    monkeypatch.setattr(shards, "PARALLEL_MIN_PIXELS", 0)  # spread however little they decode
    jobs = []
    monkeypatch.setattr(pool.Workers, "run", lambda self, js, shard, total, on_progress=None, on_result=None,
                        real=pool.Workers.run: (self.workers > 1 and jobs.extend(js))
                        or real(self, js, shard, total, on_progress, on_result))
    one, _ = audit(open_dataset(root), None, workers=1)
    assert not jobs
    two, _ = audit(open_dataset(root), None, workers=2)
    assert [len(j[2]) for j in jobs] == [8, 8, 8]
    for col in one.columns:
        assert one[col].equals(two[col]), col


def test_the_report_shows_every_camera_of_a_suspect(two_cameras, tmp_path):
    """``democheck audit`` on two cameras: the stopped camera's demo first, its reason naming the camera, and its
    tab in the recording holding both cameras' videos."""
    from typer.testing import CliRunner

    from democheck.cli import app
    from democheck.viz.report import suspect_path
    from tests.test_audit import _read_rrd

    root, stopped = two_cameras
    res = CliRunner().invoke(app, ["audit", str(root), "--no-model", "--top", "2", "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    assert table.loc[0, "episode_index"] == stopped and "on the wrist camera" in table.loc[0, "reason"]
    entities = {str(e).strip("/") for e in _read_rrd(tmp_path / "r" / "report.rrd")}
    base = suspect_path(1, stopped)
    assert {f"{base}/video", f"{base}/cameras/wrist"} <= entities


def test_a_camera_whose_files_are_missing_is_left_unread_with_a_warning(two_cameras, tmp_path):
    from democheck.audit.run import audit

    root, _ = two_cameras
    shutil.copytree(root, tmp_path / "d")
    shutil.rmtree(tmp_path / "d" / "videos" / "observation.images.wrist")
    table, summary = audit(open_dataset(tmp_path / "d"), None)
    assert not any("@" in c for c in table.columns) and summary["cameras"] == ["main"]
    assert any(w.startswith("the wrist camera is not read: ") and "missing" in w for w in summary["warnings"])


def test_a_dataset_whose_videos_are_all_missing_is_audited_on_its_states_at_once(two_cameras, tmp_path):
    """Said before any decoding, not after it: the audit reads the states and actions and warns why."""
    from democheck.data import video
    from democheck.workflows import audit_dataset

    root, _ = two_cameras
    shutil.copytree(root, tmp_path / "d")
    shutil.rmtree(tmp_path / "d" / "videos")
    before = video.frames_decoded
    summary = audit_dataset(tmp_path / "d", tmp_path / "r")
    assert video.frames_decoded == before and summary["cameras"] == [] and summary["model"] is None
    assert summary["warnings"][0].startswith("every video file of the camera observation.images.main is missing")
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    assert {"idle", "motion", "jerk"} <= set(table) and "view" not in table
    with pytest.raises(Exception, match="the model reads a demo by its frames"):
        audit_dataset(tmp_path / "d", tmp_path / "r2", model="petnet-push-v1")


def test_a_set_that_reuses_memory_reads_the_same_frames(two_cameras):
    """``DemoSet.reusing`` decodes each demo into the memory of the one before: the same frames, read for read."""
    root, _ = two_cameras
    plain, reused = open_dataset(root), open_dataset(root).reusing()
    for e in plain.episode_indices[:4]:
        frames = reused[e].frames
        assert np.array_equal(frames, plain[e].frames) and frames.base is not None  # a view of the arena
