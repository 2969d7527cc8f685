"""Writing a LeRobotDataset v3.0 (the layout in ``democheck.data.lerobot``): data and video files of a shard of
episodes (``write_shard``, one call per worker), then ``meta/`` for all of them (``write_meta``)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from democheck.data import video
from democheck.data.demo import Demo
from democheck.data.lerobot import (ACTION_KEY, CHUNKS_SIZE, CODEBASE_VERSION, DATA_PATH, ENV_STATE_KEY, EPISODES_PATH,
                                    IMAGE_KEY, INDEX_FEATURES, SIDECAR_PATH, STATE_KEY, SUITE_PATH, VIDEO_PATH)


@dataclass
class VideoOptions:
    pix_fmt: str = video.DEFAULT_PIX_FMT
    crf: int = video.DEFAULT_CRF
    camera: str = IMAGE_KEY  # the image feature's name
    # Lossless RGB (H.264 in RGB at quantiser 0, ``video.LOSSLESS_CODEC``): frames decode bit-exactly as written.
    # Probes use it, so a probe differs from its source only where the probe changes it.
    lossless: bool = False


def _fixed_list(arr: np.ndarray) -> pa.FixedSizeListArray:
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    return pa.FixedSizeListArray.from_arrays(pa.array(arr.reshape(-1)), arr.shape[1])


def _moments(x: np.ndarray) -> dict[str, np.ndarray]:
    x = x.astype(np.float64)
    return {"sum": x.sum(0), "sumsq": (x * x).sum(0), "min": x.min(0), "max": x.max(0), "count": np.array([len(x)])}


def write_shard(root: Path, file_index: int, demos: list[Demo], task_index: dict[str, int], first_index: int,
                fps: int, video_opts: VideoOptions) -> list[dict[str, Any]]:
    """Write one data file and one video file holding ``demos`` back to back.

    ``first_index`` is the global frame index of the first frame.  Returns one
    metadata row per episode (for the episodes table and the sidecar) with the
    per-episode moments used for stats.json.
    """
    chunk = file_index // CHUNKS_SIZE
    data_path = root / DATA_PATH.format(chunk_index=chunk, file_index=file_index)
    video_path = root / VIDEO_PATH.format(video_key=video_opts.camera, chunk_index=chunk, file_index=file_index)
    data_path.parent.mkdir(parents=True, exist_ok=True)
    video_path.parent.mkdir(parents=True, exist_ok=True)
    rows, tables = [], []
    size = demos[0].frames.shape[1:3]
    index = first_index
    with video.VideoWriter(video_path, fps, size, video_opts.pix_fmt, video_opts.crf, video_opts.lossless) as vw:
        for demo in demos:
            T = len(demo)
            start, end = vw.write(demo.frames)
            env = {} if demo.env_state is None else {ENV_STATE_KEY: demo.env_state}  # none recorded: no column
            cols = {
                STATE_KEY: _fixed_list(demo.state),
                **{k: _fixed_list(v) for k, v in env.items()},
                ACTION_KEY: _fixed_list(demo.actions),
                "timestamp": pa.array(np.arange(T, dtype=np.float32) / np.float32(fps)),
                "frame_index": pa.array(np.arange(T, dtype=np.int64)),
                "episode_index": pa.array(np.full(T, demo.episode_index, dtype=np.int64)),
                "index": pa.array(np.arange(index, index + T, dtype=np.int64)),
                "task_index": pa.array(np.full(T, task_index[demo.task], dtype=np.int64)),
            }
            tables.append(pa.table(cols))
            # Sub-sample frames for image stats: every 20th is plenty for a mean and a std.
            img = demo.frames[::20].reshape(-1, 3).astype(np.float64) / 255.0
            rows.append({
                "episode_index": demo.episode_index, "task": demo.task, "length": T,
                "data/chunk_index": chunk, "data/file_index": file_index,
                "dataset_from_index": index, "dataset_to_index": index + T,
                f"videos/{video_opts.camera}/chunk_index": chunk, f"videos/{video_opts.camera}/file_index": file_index,
                f"videos/{video_opts.camera}/from_timestamp": start / fps, f"videos/{video_opts.camera}/to_timestamp": end / fps,
                "split": demo.split, "success": demo.success, "label": demo.label or "clean",
                "source_episode": -1 if demo.source_episode is None else int(demo.source_episode),
                "sim": json.dumps(demo.sim, sort_keys=True) if demo.sim is not None else "",
                "_moments": {STATE_KEY: _moments(demo.state), ACTION_KEY: _moments(demo.actions),
                             **{k: _moments(v) for k, v in env.items()}, video_opts.camera: _moments(img)},
            })
            index += T
    pq.write_table(pa.concat_tables(tables), data_path, compression="zstd")
    return rows


def _stats_entry(moments: list[dict[str, np.ndarray]], image: bool = False) -> dict[str, Any]:
    n = sum(float(m["count"][0]) for m in moments)
    s = sum(m["sum"] for m in moments)
    ss = sum(m["sumsq"] for m in moments)
    mean = s / n
    std = np.sqrt(np.maximum(ss / n - mean * mean, 0.0))
    out = {"mean": mean, "std": std, "min": np.min([m["min"] for m in moments], 0),
           "max": np.max([m["max"] for m in moments], 0)}
    # LeRobot keeps image stats per channel with shape [3, 1, 1].
    res = {k: (v.reshape(3, 1, 1) if image else v).tolist() for k, v in out.items()}
    res["count"] = [int(n)]
    return res


def write_meta(root: Path, rows: list[dict[str, Any]], tasks: list[str], fps: int, image_size: int | tuple[int, int],
               state_names: list[str], action_names: list[str], env_state_names: list[str],
               video_opts: VideoOptions, suite: dict[str, Any] | None = None, robot_type: str = "democheck_arm7") -> None:
    """Write meta/: info.json, tasks.parquet, episodes table, stats.json and democheck's sidecar.  ``image_size``:
    the camera's side (square) or (height, width); no ``env_state_names``: the episodes record no environment
    state (``Demo.env_state`` None)."""
    height, width = video.frame_size(image_size)
    rows = sorted(rows, key=lambda r: r["episode_index"])
    meta = root / "meta"
    (meta / "democheck").mkdir(parents=True, exist_ok=True)
    (root / EPISODES_PATH).parent.mkdir(parents=True, exist_ok=True)

    # Tasks: the task string is the index, as LeRobot writes it.
    pd.DataFrame({"task_index": np.arange(len(tasks), dtype=np.int64)},
                 index=pd.Index(tasks, name="task")).to_parquet(meta / "tasks.parquet")

    ep_cols = ["episode_index", "length", "data/chunk_index", "data/file_index", "dataset_from_index",
               "dataset_to_index", f"videos/{video_opts.camera}/chunk_index", f"videos/{video_opts.camera}/file_index",
               f"videos/{video_opts.camera}/from_timestamp", f"videos/{video_opts.camera}/to_timestamp"]
    episodes = pd.DataFrame([{c: r[c] for c in ep_cols} for r in rows])
    episodes.insert(1, "tasks", [[r["task"]] for r in rows])
    episodes["meta/episodes/chunk_index"] = 0
    episodes["meta/episodes/file_index"] = 0
    for key in (STATE_KEY, ACTION_KEY):
        per_ep = [_stats_entry([r["_moments"][key]]) for r in rows]
        for stat in ("mean", "std", "min", "max", "count"):
            episodes[f"stats/{key}/{stat}"] = [p[stat] for p in per_ep]
    episodes.to_parquet(root / EPISODES_PATH, index=False)

    sidecar = pd.DataFrame([{c: r[c] for c in ("episode_index", "split", "success", "label", "source_episode", "sim")}
                            for r in rows])
    sidecar.to_parquet(root / SIDECAR_PATH, index=False)

    stats = {key: _stats_entry([r["_moments"][key] for r in rows], image=(key == video_opts.camera))
             for key in (STATE_KEY, ACTION_KEY, ENV_STATE_KEY, video_opts.camera) if key in rows[0]["_moments"]}
    (meta / "stats.json").write_text(json.dumps(stats, indent=2))

    n_frames = int(sum(r["length"] for r in rows))
    splits: dict[str, str] = {}
    for name in ("train", "val", "test"):
        idx = [r["episode_index"] for r in rows if r["split"] == name]
        # LeRobot splits are "start:stop" ranges; ours are contiguous by construction.
        if idx and idx == list(range(idx[0], idx[-1] + 1)):
            splits[name] = f"{idx[0]}:{idx[-1] + 1}"
    if not splits:
        splits = {"train": f"0:{len(rows)}"}
    n_files = len({r["data/file_index"] for r in rows})
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": len(rows),
        "total_frames": n_frames,
        "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 500,
        "fps": fps,
        "splits": splits,
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH,
        "features": {
            video_opts.camera: {
                "dtype": "video", "shape": [height, width, 3], "names": ["height", "width", "channels"],
                "info": {"video.height": height, "video.width": width, "video.codec": "h264",
                         "video.pix_fmt": "gbrp" if video_opts.lossless else video_opts.pix_fmt, "video.is_depth_map": False, "video.fps": fps,
                         "video.channels": 3, "has_audio": False},
            },
            STATE_KEY: {"dtype": "float32", "shape": [len(state_names)], "names": state_names},
            **({ENV_STATE_KEY: {"dtype": "float32", "shape": [len(env_state_names)], "names": env_state_names}}
               if env_state_names else {}),
            ACTION_KEY: {"dtype": "float32", "shape": [len(action_names)], "names": action_names},
            **INDEX_FEATURES,
        },
        "democheck": {"files": n_files, "sidecar": SIDECAR_PATH},
    }
    (meta / "info.json").write_text(json.dumps(info, indent=2))
    if suite is not None:
        (root / SUITE_PATH).write_text(json.dumps(suite, indent=2, sort_keys=True))
