import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from democheck.data import open_dataset
from democheck.data.video import VideoWriter, read_frames
from democheck.errors import DatasetError
from democheck.sim.catalog import OBJECTS
from democheck.sim.env import PushEnv
from democheck.sim.expert import ScriptedExpert
from democheck.sim.variants import record_demo


def psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def test_lerobot_v3_layout(tiny_dataset):
    root, summary = tiny_dataset
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 20
    assert info["total_episodes"] == 12 and info["total_frames"] == 12 * 12
    assert info["features"]["observation.images.main"]["dtype"] == "video"
    assert set(info["splits"]) == {"train", "val", "test"}
    tasks = pd.read_parquet(root / "meta/tasks.parquet")
    assert tasks.index.name == "task" and len(tasks) == 4
    eps = pd.read_parquet(root / "meta/episodes/chunk-000/file-000.parquet")
    for col in ("episode_index", "tasks", "length", "dataset_from_index", "dataset_to_index",
                "videos/observation.images.main/from_timestamp", "videos/observation.images.main/to_timestamp"):
        assert col in eps
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert {"observation.state", "action", "timestamp", "frame_index", "episode_index", "index", "task_index"} <= set(
        data.column_names)
    stats = json.loads((root / "meta/stats.json").read_text())
    assert np.array(stats["observation.images.main"]["mean"]).shape == (3, 1, 1)
    assert (root / "videos/observation.images.main/chunk-000/file-000.mp4").exists()


def test_round_trip_matches_resimulation(tiny_dataset):
    """Write -> open_dataset -> compare with the episode re-simulated from its sim record."""
    root, _ = tiny_dataset
    ds = open_dataset(root)
    assert len(ds) == 12 and len(ds.by_task()) == 4 and all(len(v) == 3 for v in ds.by_task().values())
    for e in (0, 7, 11):
        demo = ds[e]
        assert demo.frames.shape == (12, 16, 16, 3) and demo.state.shape == (12, 17) and demo.actions.shape == (12, 7)
        assert demo.label == "clean" and demo.split in ("train", "val", "test") and demo.sim is not None
        env = PushEnv((OBJECTS[demo.sim["target"]], OBJECTS[demo.sim["distractor"]]), image_size=16)
        actions = iter(demo.actions)
        rec = record_demo(env, lambda: next(actions), len(demo), layout=demo.sim["layout"])
        np.testing.assert_array_equal(rec["state"], demo.state)
        np.testing.assert_array_equal(rec["env_state"], demo.env_state)
        assert psnr(rec["frames"], demo.frames) >= 30  # 16x16 frames; the 64x64 bound is checked below
        cue = ds.cue_frames(e)
        np.testing.assert_array_equal(cue[0], demo.frames[0])
        np.testing.assert_array_equal(cue[1], demo.frames[-1])
    eps = ds.episode_indices
    np.testing.assert_array_equal(ds.end_states(eps), np.stack([ds[e].state[-1] for e in eps]))
    np.testing.assert_array_equal(ds.end_states(eps, at=0.0), np.stack([ds[e].state[0] for e in eps]))


def test_video_quality_at_64(tmp_path):
    env = PushEnv((OBJECTS["block-yellow-small"], OBJECTS["ell-blue-large"]), image_size=64)
    env.reset(seed=4)
    rec = record_demo(env, ScriptedExpert(env).act, 40, seed=4)
    with VideoWriter(tmp_path / "v.mp4", 20, 64) as vw:
        vw.write(rec["frames"])
    decoded = read_frames(tmp_path / "v.mp4", np.arange(40), 20)
    assert psnr(rec["frames"], decoded) >= 35
    assert min(psnr(a, b) for a, b in zip(rec["frames"], decoded)) >= 33


def test_sparse_read_does_not_decode_everything(tmp_path):
    frames = np.random.default_rng(0).integers(0, 255, (200, 16, 16, 3), dtype=np.uint8)
    with VideoWriter(tmp_path / "v.mp4", 20, 16, crf=0) as vw:
        vw.write(frames[:100])
        vw.write(frames[100:])
    got = read_frames(tmp_path / "v.mp4", [0, 99, 100, 199], 20)
    assert got.shape == (4, 16, 16, 3)
    assert psnr(got, frames[[0, 99, 100, 199]]) > 30


def _write_v21(root, n_eps=3, T=5, size=8, image_path=None, videos=False):
    """A LeRobot v2.1 dataset with PNG image features (or one MP4 per episode), as LeRobot writes one."""
    from io import BytesIO

    from PIL import Image

    (root / "meta").mkdir(parents=True)
    info = {
        "codebase_version": "v2.1", "fps": 10, "chunks_size": 1000,
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4" if videos else None,
        "features": {
            "observation.images.top": {"dtype": "image", "shape": [size, size, 3], "names": ["height", "width", "channel"]},
            "observation.images.wrist": {"dtype": "image", "shape": [size, size, 3], "names": ["height", "width", "channel"]},
            "observation.state": {"dtype": "float32", "shape": [4], "names": None},
            "action": {"dtype": "float32", "shape": [2], "names": None},
            "episode_index": {"dtype": "int64", "shape": [1]}, "frame_index": {"dtype": "int64", "shape": [1]},
        },
    }
    if videos:
        for key in ("observation.images.top", "observation.images.wrist"):
            info["features"][key]["dtype"] = "video"
    (root / "meta/info.json").write_text(json.dumps(info))
    (root / "meta/tasks.jsonl").write_text('{"task_index": 0, "task": "stack"}\n{"task_index": 1, "task": "pour"}\n')
    lines, truth = [], {}
    rng = np.random.default_rng(1)
    for e in range(n_eps):
        task = ["stack", "pour"][e % 2]
        lines.append(json.dumps({"episode_index": e, "tasks": [task], "length": T}))
        imgs = rng.integers(0, 255, (T, size, size, 3), dtype=np.uint8)
        state = rng.normal(size=(T, 4)).astype(np.float32)
        action = rng.normal(size=(T, 2)).astype(np.float32)
        truth[e] = (imgs, state, action, task)

        def png(a):
            buf = BytesIO()
            Image.fromarray(a).save(buf, format="PNG")
            return {"bytes": buf.getvalue(), "path": image_path}

        table = pa.table({
            "observation.images.top": [png(a) for a in imgs],
            "observation.images.wrist": [png(255 - a) for a in imgs],
            "observation.state": [list(s) for s in state], "action": [list(a) for a in action],
            "episode_index": [e] * T, "frame_index": list(range(T)),
        })
        if videos:
            table = table.drop_columns(["observation.images.top", "observation.images.wrist"])
            for key, clip in (("observation.images.top", imgs), ("observation.images.wrist", 255 - imgs)):
                vpath = root / f"videos/chunk-000/{key}/episode_{e:06d}.mp4"
                vpath.parent.mkdir(parents=True, exist_ok=True)
                with VideoWriter(vpath, 10, size, crf=0) as vw:
                    vw.write(clip)
        path = root / f"data/chunk-000/episode_{e:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
    (root / "meta/episodes.jsonl").write_text("\n".join(lines) + "\n")
    return truth


def test_lerobot_v21_images(tmp_path):
    truth = _write_v21(tmp_path / "v21")
    ds = open_dataset(tmp_path / "v21")
    assert ds.format == "lerobot-v2.1" and ds.camera == "observation.images.top" and len(ds) == 3
    for e, (imgs, state, action, task) in truth.items():
        demo = ds[e]
        np.testing.assert_array_equal(demo.frames, imgs)  # PNG is lossless
        np.testing.assert_allclose(demo.state, state)
        np.testing.assert_allclose(demo.actions, action)
        assert demo.task == task
    wrist = open_dataset(tmp_path / "v21", camera="wrist")
    np.testing.assert_array_equal(wrist.cue_frames(1)[1], 255 - truth[1][0][-1])
    assert wrist.by_task() == {"pour": [1], "stack": [0, 2]}


def test_lerobot_v21_videos(tmp_path):
    truth = _write_v21(tmp_path / "v21v", size=16, T=12, videos=True)
    ds = open_dataset(tmp_path / "v21v", camera="observation.images.wrist")
    for e, (imgs, state, _, _) in truth.items():
        demo = ds[e]
        assert demo.frames.shape == (12, 16, 16, 3)
        assert psnr(demo.frames, 255 - imgs) > 30  # CRF 0 on noise: near lossless
        np.testing.assert_allclose(demo.state, state)
        np.testing.assert_array_equal(ds.cue_frames(e), demo.frames[[0, -1]])
        np.testing.assert_array_equal(ds.end_states([e])[0], demo.state[-1])
    # A v2.1 dataset whose templates name the chunk as later writers do ({chunk_index}) reads the same.
    info_path = tmp_path / "v21v" / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    for key in ("data_path", "video_path"):
        info[key] = info[key].replace("{episode_chunk", "{chunk_index")
    info_path.write_text(json.dumps(info))
    again = open_dataset(tmp_path / "v21v", camera="observation.images.wrist")
    np.testing.assert_array_equal(again[0].frames, ds[0].frames)


def test_cue_frames_do_not_decode_whole_episodes(tiny_dataset, tmp_path):
    from democheck.data import video
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    # Long episodes make the point: 60 steps each, cues need 2 frames.
    root = tmp_path / "long"
    generate(TINY.with_overrides(steps=60, demos=2), root, workers=1)
    ds = open_dataset(root)
    before = video.frames_decoded
    for e in ds.episode_indices:
        ds.cue_frames(e)
    per_demo = (video.frames_decoded - before) / len(ds)
    assert per_demo <= 2 + video.GOP, per_demo  # at most one GOP before the last frame, never 60
    before = video.frames_decoded
    ds.end_states(ds.episode_indices)  # where each demo ended: its data file alone
    assert video.frames_decoded == before


def test_bad_inputs_are_one_line_errors(tmp_path):
    _write_v21(tmp_path / "v21")
    with pytest.raises(DatasetError, match="no camera 'side'"):
        open_dataset(tmp_path / "v21", camera="side")
    with pytest.raises(DatasetError, match="no such file"):
        open_dataset(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="not a dataset"):
        open_dataset(tmp_path / "empty")
    (tmp_path / "v21/meta/info.json").write_text("{not json")
    with pytest.raises(DatasetError, match="info.json: not valid JSON"):
        open_dataset(tmp_path / "v21")


def test_paths_cannot_escape_the_dataset(tmp_path):
    _write_v21(tmp_path / "v21")
    info = json.loads((tmp_path / "v21/meta/info.json").read_text())
    info["data_path"] = "../../etc/episode_{episode_index:06d}.parquet"
    (tmp_path / "v21/meta/info.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError, match="outside the dataset"):
        open_dataset(tmp_path / "v21")[0]


def test_a_video_whose_metadata_is_not_utf8_is_one_clear_error(tmp_path):
    # Found by the byte-flipping fuzz test: PyAV decodes the container's tags as UTF-8 when it opens the file.
    path = tmp_path / "v.mp4"
    with VideoWriter(path, 20, 16) as w:
        w.write(np.zeros((5, 16, 16, 3), np.uint8))
    data = bytearray(path.read_bytes())
    data[data.find(b"Lavf")] = 0xCC  # the encoder tag's first byte: no longer UTF-8
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="not valid UTF-8"):
        read_frames(path, [0], 20)


def test_synth_and_probe_on_ray_write_the_local_engines_files(tmp_path):
    """``democheck synth --engine ray`` and ``probe --engine ray`` on a local 2-CPU Ray instance: the same shards
    rendered by Ray Data actors, every file byte for byte the local workers' (the records' timings apart)."""
    import hashlib
    from dataclasses import replace

    pytest.importorskip("ray.data")
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    import ray

    from democheck.sim.probes import make_probes

    recipe = replace(TINY, seed=5)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")  # one start for both
    try:
        generate(recipe, tmp_path / "local", workers=2)
        generate(recipe, tmp_path / "ray", workers=2, engine="ray")
        for engine in ("local", "ray"):
            make_probes(tmp_path / "local", tmp_path / f"probes-{engine}", ["no-action", "hidden"], per_kind=2,
                        seed=3, workers=2, engine=engine)
    finally:
        ray.shutdown()

    def digests(root):
        out = {}
        for f in sorted(root.rglob("*")):
            if f.is_file():
                data = f.read_bytes()
                if f.name == "suite.json":
                    doc = json.loads(data)
                    for record in (doc, doc.get("probes", {})):
                        record.pop("wall_s", None), record.pop("frames_per_s", None)
                    data = json.dumps(doc, sort_keys=True).encode()
                out[str(f.relative_to(root))] = hashlib.sha256(data).hexdigest()
        return out

    local, on_ray = digests(tmp_path / "local"), digests(tmp_path / "ray")
    assert local == on_ray and any(k.endswith(".mp4") for k in local)
    probes, probes_on_ray = digests(tmp_path / "probes-local"), digests(tmp_path / "probes-ray")
    assert probes == probes_on_ray and any(k.endswith(".mp4") for k in probes)


def test_dimension_names_are_read_in_every_form_lerobot_writes_them():
    from democheck.data.lerobot import feature_names

    assert feature_names({"names": ["a", "b"]}, 2) == ["a", "b"]
    assert feature_names({"names": [["a", "b"]]}, 2) == ["a", "b"]  # a list nested in a list
    assert feature_names({"names": {"motors": ["a", "b"]}}, 2) == ["a", "b"]
    assert feature_names({"names": {"axes": ["x", "y", "z"]}}, 3) == ["x", "y", "z"]
    assert feature_names({"names": {"left": ["j1", "j2"], "right": ["j1", "j2"]}}, 4) == \
        ["left.j1", "left.j2", "right.j1", "right.j2"]  # parts together, told apart where they name alike
    assert feature_names({"names": {"arm": ["a"], "gripper": ["g"]}}, 2) == ["a", "g"]
    assert feature_names({"names": None}, 2) is None and feature_names({"names": ["a"]}, 2) is None


def test_a_dataset_is_found_by_its_hub_id_offline_in_lerobots_home_and_in_the_hubs_cache(tmp_path, monkeypatch):
    """``ORG/NAME`` reads LeRobot's copy under HF_LEROBOT_HOME, else the hub's snapshot cache (a revision picks its
    snapshot), with no network; a missing id is one line saying what to do."""
    import shutil

    from typer.testing import CliRunner

    from democheck.cli import app
    from democheck.data.hub import resolve
    from democheck.errors import DatasetError

    tiny = Path(__file__).parent / "data" / "mw-tiny"
    home, cache = tmp_path / "lerobot", tmp_path / "hub"
    shutil.copytree(tiny, home / "someone" / "tiny")
    snapshot = cache / "datasets--someone--other" / "snapshots" / ("a" * 40)
    shutil.copytree(tiny, snapshot)
    (cache / "datasets--someone--other" / "refs").mkdir()
    (cache / "datasets--someone--other" / "refs" / "main").write_text("a" * 40)
    (cache / "datasets--someone--other" / "refs" / "v1.0").write_text("a" * 40)
    monkeypatch.setenv("HF_LEROBOT_HOME", str(home))
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    import huggingface_hub.constants as constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    assert resolve("someone/tiny") == home / "someone" / "tiny"
    assert resolve("someone/other") == snapshot and resolve("someone/other", revision="v1.0") == snapshot
    assert resolve(tiny) == tiny  # a path is itself
    with pytest.raises(DatasetError, match="not on this machine.*huggingface-cli download --repo-type dataset"):
        resolve("someone/missing")
    res = CliRunner().invoke(app, ["info", "someone/other"])
    assert res.exit_code == 0 and "lerobot-v3.0" in res.output, res.output
    res = CliRunner().invoke(app, ["audit", "someone/missing", "--out", str(tmp_path / "r"), "--no-model"])
    assert res.exit_code == 2 and "someone/missing: not on this machine" in " ".join(res.output.split())
    # a mistyped path whose folder is here reads as a path first
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    with pytest.raises(DatasetError, match=r"data/typo: no such folder \(data/ is here, without typo\); and as a hub"):
        resolve("data/typo")
