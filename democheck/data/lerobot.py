"""LeRobotDataset layouts: their names and the base reader that v3.0 (``lerobot_v3``) and v2.1 (``lerobot_v21``)
share (``lerobot_write`` writes v3.0).

v3.0 layout written by democheck (LeRobot and the tools built for it open it)::

    meta/info.json                      codebase_version, fps, features, path templates, totals, splits
    meta/tasks.parquet                  task string (index) -> task_index
    meta/episodes/chunk-000/file-000.parquet   one row per episode: length, data/video file and ranges
    meta/stats.json                     per-feature mean/std/min/max/count
    meta/democheck/episodes.parquet     democheck's sidecar: split, success, label, source, sim record
    meta/democheck/suite.json           the recipe and generation summary (synthetic datasets)
    data/chunk-000/file-NNN.parquet     one row per frame: state, action, timestamps, indices
    videos/observation.images.main/chunk-000/file-NNN.mp4

Several episodes share one data file and one video file; the episodes table
says where each one lies.  The layout's names (paths, feature keys) are here,
for the readers and the writer alike.  Each reader is the base class with its
layout's metadata: v3.0's episodes table (``lerobot_v3``), v2.1's JSON lines and
one file per episode (``lerobot_v21``).
"""

from __future__ import annotations

import json
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

import democheck.data.video as video
from democheck.data.demo import (NO_CAMERA, NO_CAMERA_KEY, OTHER_CAMERA, Damage, Demo, check_arrays, no_frames,
                                 readable_frames, repair_non_finite)
from democheck.errors import DatasetError

MAX_FPS = 100_000.0  # frames a second: no recorder runs faster; a larger number is not a frame rate

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000
IMAGE_KEY = "observation.images.main"
STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
ACTION_KEY = "action"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
SIDECAR_PATH = "meta/democheck/episodes.parquet"
SUITE_PATH = "meta/democheck/suite.json"

INDEX_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


def read_json(path: Path) -> Any:
    """A JSON file's content; a missing or unreadable file is a one-line DatasetError naming it."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None


def _read_parquet(path: Path, columns: list[str] | None = None, schema_only: bool = False):
    """A parquet table (or only its column names), with unreadable files as one-line DatasetErrors."""
    try:
        return pq.read_schema(path).names if schema_only else pq.read_table(path, columns=columns)
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise DatasetError(f"{path}: unreadable parquet ({str(exc).splitlines()[0]})") from None


def metadata_frame(path: Path) -> pd.DataFrame:
    """A metadata parquet file as a DataFrame, text decoded now (not on first access), per-episode stats left out.

    The ``stats/*`` columns are skipped: democheck never reads them, and as Python objects they cost ~4 KB a
    row (200 MB at 60,000 episodes).
    """
    names = [c for c in _read_parquet(path, schema_only=True) if not c.startswith("stats/")]
    table = _read_parquet(path, names)
    out = {}
    try:
        for c in table.column_names:
            col = table.column(c)
            text = pa.types.is_string(col.type) or pa.types.is_large_string(col.type) or (
                pa.types.is_list(col.type) and pa.types.is_string(col.type.value_type))
            out[c] = col.to_pylist() if text else col.to_pandas().to_numpy()
        return pd.DataFrame(out)
    except (pa.ArrowException, UnicodeDecodeError, ValueError, OverflowError) as exc:
        raise DatasetError(f"{path}: unreadable values ({str(exc).splitlines()[0][:80]})") from None


def feature_names(feature: dict[str, Any], dim: int) -> list[str] | None:
    """A vector feature's per-dimension names from ``info.json``, in every form LeRobot datasets write them: a list,
    a list nested in lists (``[["j1", "j2"]]``), LeRobot's older ``{"motors": [...]}``, or a dict of parts whose
    lists together name every dimension (``{"left_arm": [...], "right_arm": [...]}``: 'left_arm.j1' where two
    parts name a dimension alike).  None when it names none or not one per dimension."""
    names = feature.get("names")
    if isinstance(names, dict):
        parts = {k: _flat(v) for k, v in names.items() if isinstance(v, (list, tuple))}
        whole = next((v for v in parts.values() if len(v) == dim), None)
        if whole is None:
            joined = [n for v in parts.values() for n in v]
            clash = len(set(joined)) < len(joined)
            whole = [f"{k}.{n}" if clash else n for k, v in parts.items() for n in v]
        names = whole
    elif isinstance(names, (list, tuple)):
        names = _flat(names)
    if isinstance(names, list) and len(names) == dim and all(isinstance(n, str) for n in names):
        return names
    return None


def _flat(names: Any) -> list:
    """Names nested in lists, in order."""
    if isinstance(names, (list, tuple)):
        return [n for part in names for n in _flat(part)]
    return [names]


def path_template(info: dict[str, Any], key: str, default: str | None, root: Path, **fields: Any) -> str:
    """A file path from one of info.json's path templates, with a malformed template as a DatasetError."""
    tpl = info.get(key, default)
    try:
        if not isinstance(tpl, str):
            raise TypeError(type(tpl).__name__)
        return tpl.format(**fields)
    except (KeyError, IndexError, ValueError, TypeError, AttributeError) as exc:
        raise DatasetError(f"{root / 'meta/info.json'}: {key} {tpl!r:.60} is not a usable path template ({exc})") from None


def inside_root(root: Path, rel: str) -> Path:
    """A path from the dataset's metadata, refused if it escapes the dataset folder or cannot be a path."""
    if "\0" in rel:
        raise DatasetError(f"{root / 'meta/info.json'}: path {rel!r} holds a NUL character")
    path = (root / rel).resolve()
    if not path.is_relative_to(root.resolve()):
        raise DatasetError(f"{root / 'meta/info.json'}: path {rel!r} points outside the dataset")
    return path


def _column_matrix(table: pa.Table, key: str, path: Path) -> np.ndarray:
    if key not in table.column_names:
        raise DatasetError(f"{path}: no column {key!r}")
    col = table.column(key).combine_chunks()
    try:
        if pa.types.is_fixed_size_list(col.type) or pa.types.is_list(col.type) or pa.types.is_large_list(col.type):
            flat = col.flatten().to_numpy(zero_copy_only=False)
            n = len(col)
            if n and flat.size % n:
                raise DatasetError(f"{path}: column {key!r} has rows of different lengths")
            return flat.reshape(n, -1 if n else 0).astype(np.float32)
        return col.to_numpy(zero_copy_only=False).astype(np.float32).reshape(len(col), -1)
    except (ValueError, TypeError, pa.ArrowException):
        raise DatasetError(f"{path}: column {key!r} is {col.type}, not numbers") from None


class LeRobotBase:
    """What v2.1 and v3.0 readers share: info.json, feature keys, episode table, sidecar."""

    strict = False  # a broken recording raises instead of being repaired and reported (``DemoSet.strict``)

    format = "lerobot"

    def __init__(self, root: Path, info: dict[str, Any], camera: str | None, state_key: str | None,
                 action_key: str | None):
        self.root = root
        self.info = info
        try:
            self.fps = float(info["fps"])
            self.features: dict[str, Any] = dict(info["features"])
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{root / 'meta/info.json'}: needs 'fps' and 'features'") from None
        if not (np.isfinite(self.fps) and 0 < self.fps <= MAX_FPS):
            raise DatasetError(f"{root / 'meta/info.json'}: fps must be a positive number up to {MAX_FPS:g}, not "
                               f"{info['fps']!r}")
        self.cameras = [k for k, f in self.features.items()
                        if isinstance(f, dict) and f.get("dtype") in ("video", "image")]
        self.camera = self._pick_camera(camera)
        self._keys = {"state_key": state_key, "action_key": action_key}
        feat = self.features[self.camera] if self.camera else {}
        self.camera_dtype = feat.get("dtype")  # None: the dataset records no camera (``NO_CAMERA``)
        self.image_shape = self._hwc(feat.get("shape", []), feat.get("names")) if self.camera else NO_CAMERA
        self.state_key = self._pick_key(state_key, [STATE_KEY, "state", "observation.qpos"], "state", "--state-key")
        self.action_key = self._pick_key(action_key, [ACTION_KEY, "actions"], "action", "--action-key")
        self.state_dim = int(np.prod(self.features[self.state_key].get("shape", [1])))
        self.action_dim = int(np.prod(self.features[self.action_key].get("shape", [1])))
        self.state_names = feature_names(self.features[self.state_key], self.state_dim)
        self.action_names = feature_names(self.features[self.action_key], self.action_dim)
        env = self.features.get(ENV_STATE_KEY)
        self.env_state_dim = int(np.prod(env.get("shape", [1]))) if isinstance(env, dict) else 0
        self.env_state_names = feature_names(env, self.env_state_dim) if isinstance(env, dict) else None
        self._cache: OrderedDict[Path, dict[str, Any]] = OrderedDict()

    def streams(self) -> list[tuple[str, str, str]]:
        """Every recorded feature but the index columns: (name, width or frame shape, what the audit reads it as)."""
        index = {"timestamp", "frame_index", "episode_index", "index", "task_index"}
        roles = {self.state_key: "the state", self.action_key: "the actions",
                 ENV_STATE_KEY: "the environment state (where the objects are)"}
        out = []
        for key, f in self.features.items():
            if key in index or not isinstance(f, dict):
                continue
            shape = [int(v) for v in f.get("shape", [1])]
            if f.get("dtype") in ("video", "image"):
                h, w, c = self._hwc(shape, f.get("names"))
                out.append((key, f"{h}x{w}x{c}", "the camera" if key == self.camera else OTHER_CAMERA))
            else:
                out.append((key, str(int(np.prod(shape))), roles.get(key, "not read")))
        return out

    def with_camera(self, camera: str) -> "LeRobotBase":
        """The same dataset read through another of its cameras."""
        other = type(self)(self.root, self.info, camera=camera, **self._keys)
        other.strict = self.strict
        return other

    def _pick_camera(self, camera: str | None) -> str | None:
        cams = self.cameras
        if camera == NO_CAMERA_KEY:
            return None
        if not cams and camera is not None:
            raise DatasetError(f"{self.root / 'meta/info.json'}: no camera {camera!r}: no image or video feature")
        if camera is None:
            return cams[0] if cams else None
        for key in (camera, f"observation.images.{camera}"):
            if key in cams:
                return key
        raise DatasetError(f"{self.root / 'meta/info.json'}: no camera {camera!r}; choose one of {', '.join(cams)}")

    def _pick_key(self, given: str | None, candidates: list[str], what: str, option: str) -> str:
        if given is not None:
            if given not in self.features:
                raise DatasetError(f"{self.root / 'meta/info.json'}: no feature {given!r} ({option})")
            return given
        for key in candidates:
            if key in self.features:
                return key
        raise DatasetError(f"{self.root / 'meta/info.json'}: no {what} feature found; name it with {option}")

    def _hwc(self, shape: list[int], names: list[str] | None) -> tuple[int, int, int]:
        if len(shape) != 3:
            raise DatasetError(f"{self.root / 'meta/info.json'}: camera {self.camera!r} has shape {shape}, not 3-D")
        if names and list(names)[0] in ("channel", "channels") or shape[0] == 3 and shape[2] != 3:
            return int(shape[1]), int(shape[2]), int(shape[0])
        return int(shape[0]), int(shape[1]), int(shape[2])

    def _attach_sidecar(self, episodes: pd.DataFrame) -> pd.DataFrame:
        path = self.root / SIDECAR_PATH
        if path.exists():
            side = metadata_frame(path)
            if "episode_index" not in side:
                raise DatasetError(f"{path}: no column 'episode_index'")
            side = side.set_index("episode_index")
            if not side.index.is_unique:
                raise DatasetError(f"{path}: an episode is listed more than once")
            episodes = episodes.join(side, how="left")
        return episodes

    def _frame_table(self, path: Path) -> dict[str, Any]:
        """Columns of one data file as arrays, with each episode's row range; two files cached."""
        if path in self._cache:
            self._cache.move_to_end(path)
            return self._cache[path]
        cols = [self.state_key, self.action_key, "episode_index", "frame_index", "timestamp"]
        if ENV_STATE_KEY in self.features:
            cols.append(ENV_STATE_KEY)
        if self.camera_dtype == "image":
            cols.append(self.camera)
        schema = _read_parquet(path, schema_only=True)
        table = _read_parquet(path, [c for c in cols if c in schema])
        eps = table.column("episode_index").to_numpy() if "episode_index" in table.column_names else None
        if eps is None:
            raise DatasetError(f"{path}: no column 'episode_index'")
        order = np.argsort(eps, kind="stable")
        uniq, starts, counts = np.unique(eps[order], return_index=True, return_counts=True)
        state = _column_matrix(table, self.state_key, path)[order]
        actions = _column_matrix(table, self.action_key, path)[order]
        check_arrays(path, self.state_key, state, self.state_dim)
        check_arrays(path, self.action_key, actions, self.action_dim)
        damaged: dict[int, list[Damage]] = {}
        # The environment state may be NaN where an object is not in the scene (democheck's no-objects probes):
        # only the robot's state and actions are repaired (``repair_non_finite``) and reported.
        for key, x in ((self.state_key, state), (self.action_key, actions)):
            filled, found = repair_non_finite(x, key, eps[order])
            if found and self.strict:
                e, damage = next(iter(found.items()))
                raise DatasetError(f"{path}: episode {e} holds {damage.what}")
            x[:] = filled
            for e, damage in found.items():
                damaged.setdefault(e, []).append(damage)
        entry = {
            "state": state,
            "actions": actions,
            "env_state": _column_matrix(table, ENV_STATE_KEY, path)[order] if ENV_STATE_KEY in table.column_names else None,
            "timestamp": (table.column("timestamp").to_numpy().astype(np.float64)[order]
                          if "timestamp" in table.column_names else None),
            "images": table.column(self.camera).to_pylist() if self.camera_dtype == "image" else None,
            "order": order,
            "damaged": damaged,
            "ranges": {int(e): (int(s), int(s + c)) for e, s, c in zip(uniq, starts, counts)},
        }
        self._cache[path] = entry
        while len(self._cache) > 2:
            self._cache.popitem(last=False)
        return entry

    def _rows(self, path: Path, episode_index: int) -> tuple[dict[str, Any], int, int]:
        entry = self._frame_table(path)
        if episode_index not in entry["ranges"]:
            raise DatasetError(f"{path}: episode {episode_index} has no rows")
        s, e = entry["ranges"][episode_index]
        return entry, s, e

    def _data_path(self, episode_index: int) -> Path:
        raise NotImplementedError

    def _video_span(self, episode_index: int, frames: int) -> tuple[Path, int, int]:
        """The video file of the episode's camera, and the frames [start, stop) of it that are the episode's;
        ``frames``: how many it holds, for a layout whose episodes table records no span."""
        raise NotImplementedError

    def video_file(self, episode_index: int) -> Path | None:
        """The video file that holds the episode's camera frames (None where the camera is not a video)."""
        if self.camera is None or self.camera_dtype != "video":
            return None
        return self._video_span(episode_index, int(self.episodes.loc[episode_index, "length"]))[0]

    def load(self, episode_index: int, arena: video.FrameArena | None = None) -> Demo:
        path = self._data_path(episode_index)
        entry, s, e = self._rows(path, episode_index)
        if self.camera is None:
            frames, unreadable = no_frames(e - s), []
        elif self.camera_dtype == "video":
            vpath, start, stop = self._video_span(episode_index, e - s)
            frames, unreadable = self._readable(lambda: video.read_range(vpath, start, stop, self.fps, arena), e - s,
                                                vpath)
        else:
            frames, unreadable = self._readable(lambda: self._decode_images(entry, s, e, path), e - s, path)
        return self._make_demo(episode_index, frames, entry, s, e, unreadable)

    def cue_frames(self, episode_index: int) -> np.ndarray:
        if self.camera is None:
            return no_frames(2)
        if self.camera_dtype == "video":
            vpath, start, stop = self._video_span(episode_index, int(self.episodes.loc[episode_index, "length"]))
            return self._readable(lambda: video.read_frames(vpath, [start, stop - 1], self.fps), 2, vpath)[0]
        return self._image_cues(episode_index)

    def end_state(self, episode_index: int, at: float = 1.0) -> np.ndarray:
        """The state at an episode's last step (``at``: that share of the way from its first), float32 [S], from
        its data file without decoding any frame."""
        path = self._data_path(episode_index)
        entry, s, e = self._rows(path, episode_index)
        return entry["state"][s + int(round(at * (e - 1 - s)))]

    def _decode_images(self, entry: dict[str, Any], s: int, e: int, path: Path) -> np.ndarray:
        from io import BytesIO

        from PIL import Image

        out = []
        for i in entry["order"][s:e]:
            cell = entry["images"][i]
            data = cell.get("bytes") if isinstance(cell, dict) else cell
            if not data and isinstance(cell, dict) and cell.get("path"):
                data = inside_root(self.root, cell["path"]).read_bytes()
            try:
                out.append(np.asarray(Image.open(BytesIO(data)).convert("RGB")))
            except Exception as exc:  # PIL raises many types for bad bytes
                raise DatasetError(f"{path}: unreadable image in {self.camera!r} ({exc})") from None
        return np.stack(out)

    def _readable(self, read: Callable[[], np.ndarray], n: int, file: Path) -> tuple[np.ndarray, list[Damage]]:
        """``demo.readable_frames`` of ``file`` with this reader's frame shape and strictness."""
        return readable_frames(read, n, self.image_shape, self.strict, file)

    def _image_cues(self, episode_index: int) -> np.ndarray:
        """First and last frame of an episode stored as images (not video), black where they cannot be read."""
        path = self._data_path(episode_index)
        entry, s, e = self._rows(path, episode_index)
        return self._readable(lambda: np.stack([self._decode_images(entry, s, s + 1, path)[0],
                                                 self._decode_images(entry, e - 1, e, path)[0]]), 2,
                              path)[0]

    def _make_demo(self, episode_index: int, frames: np.ndarray, entry: dict[str, Any], s: int, e: int,
                   unreadable: list[Damage] | None = None) -> Demo:
        row = self.episodes.loc[episode_index]
        sim = row.get("sim") if "sim" in row else None
        src = row.get("source_episode") if "source_episode" in row else None
        success = row.get("success") if "success" in row else None
        return Demo(
            episode_index=episode_index, task=str(row["task"]), frames=frames,
            state=entry["state"][s:e], actions=entry["actions"][s:e],
            success=None if success is None or pd.isna(success) else bool(success),
            label=row.get("label") if "label" in row and isinstance(row.get("label"), str) else None,
            split=row.get("split") if "split" in row and isinstance(row.get("split"), str) else None,
            sim=_sim_record(sim, self.root, episode_index),
            env_state=None if entry["env_state"] is None else entry["env_state"][s:e],
            source_episode=None if src is None or pd.isna(src) or int(src) < 0 else int(src),
            damaged=[*(unreadable or []), *entry["damaged"].get(episode_index, [])],
            extra={**({} if entry["timestamp"] is None else {"timestamp": entry["timestamp"][s:e], "fps": self.fps}),
                   "state_names": self.state_names, "action_names": self.action_names,
                   "env_state_names": self.env_state_names},
        )


def _sim_record(text: Any, root: Path, episode_index: int) -> dict[str, Any] | None:
    if not isinstance(text, str) or not text:
        return None
    try:
        sim = json.loads(text)
    except json.JSONDecodeError:
        sim = None
    if not isinstance(sim, dict):
        raise DatasetError(f"{root / SIDECAR_PATH}: episode {episode_index}: malformed sim record")
    return sim
