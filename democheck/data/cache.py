"""Decode a dataset once into flat arrays, so training is never bound by video decoding.

Frames of every episode go into one uint8 memmap ``[total_frames, H, W, 3]``
(episodes back to back; ``offsets[i]`` is where episode ``i`` starts), states
and actions into float32 arrays.  The cache lives outside the dataset (inputs
are read-only), keyed by the dataset's fingerprint and camera, and is written
under a temporary name and renamed, so an interrupted build is never reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from democheck.data.demo import DemoSet
from democheck.errors import DatasetError

DEFAULT_CACHE = Path(os.environ.get("DEMOCHECK_CACHE", Path.home() / ".cache" / "democheck"))


def dataset_fingerprint(ds: DemoSet) -> str:
    """sha256 over the dataset's metadata files and the names and sizes of its data and video files."""
    h = hashlib.sha256()
    root = ds.root
    for path in sorted(p for p in (root / "meta").rglob("*") if p.is_file()):
        if path.name == "suite.json":  # records run timing; not part of the data
            continue
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    for sub in ("data", "videos"):
        for path in sorted(p for p in (root / sub).rglob("*") if p.is_file()):
            h.update(f"{path.relative_to(root)}:{path.stat().st_size}".encode())
    h.update((ds.camera or "").encode())
    return h.hexdigest()[:16]


@dataclass
class EpisodeArrays:
    """Every episode of a dataset decoded: frames (memmap), state, actions, with per-episode offsets."""

    frames: np.ndarray  # uint8 [F, H, W, 3]
    state: np.ndarray  # float32 [F, S]
    actions: np.ndarray  # float32 [F, A]
    offsets: np.ndarray  # int64 [N]
    lengths: np.ndarray  # int64 [N]
    episodes: pd.DataFrame  # index aligned with rows: episode_index, task, split (when known), label
    fingerprint: str
    env_state: np.ndarray | None = None  # float32 [F, E]: the recorded environment state, where the data has one

    def cue(self, rows: np.ndarray, end: np.ndarray | None = None) -> np.ndarray:
        """First and last frame of each row's episode: uint8 [len(rows), 2, H, W, 3].

        ``end`` (a timestep per row) cuts each episode short there: the cue of the demo seen only up to ``end``.
        """
        first, last = self.cue_index(rows, end)
        return np.stack([self.frames[first], self.frames[last]], axis=1)

    def cue_index(self, rows: np.ndarray, end: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frame indices of each row's cue: its episode's first frame, and its last (or the one at ``end``)."""
        first = self.offsets[rows]
        return first, first + (self.lengths[rows] - 1 if end is None else np.minimum(end, self.lengths[rows] - 1))

    def last_index(self, rows: np.ndarray) -> np.ndarray:
        """Frame index of each row's episode's last step."""
        return self.offsets[rows] + self.lengths[rows] - 1

    def end_state(self, rows: np.ndarray) -> np.ndarray:
        """The state at each row's episode's last step: float32 [len(rows), S]."""
        return self.state[self.last_index(rows)]


def build_cache(ds: DemoSet, cache_dir: Path | None = None,
                on_progress: Callable[[int, int], None] | None = None) -> EpisodeArrays:
    """Decode ``ds`` into the cache (or reuse a complete one) and map it."""
    fp = dataset_fingerprint(ds)
    folder = (cache_dir or DEFAULT_CACHE) / (f"frames2-{fp}" + (f"-{ds.image_size}px" if ds.image_size else ""))
    eps = ds.episodes.reset_index()
    keep = [c for c in ("episode_index", "task", "length", "split", "label") if c in eps]
    eps = eps[keep].sort_values("episode_index").reset_index(drop=True)
    lengths = eps["length"].to_numpy(np.int64)
    if (lengths < 1).any():
        bad = int(eps.loc[lengths < 1, "episode_index"].iloc[0])
        raise DatasetError(f"{ds.root}: episode {bad} has no frames")
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    total = int(lengths.sum())
    h, w, c = ds.image_shape
    if not (folder / "complete").exists():
        tmp = folder.with_name(folder.name + f".tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            frames = np.lib.format.open_memmap(tmp / "frames.npy", mode="w+", dtype=np.uint8, shape=(total, h, w, c))
            state = np.zeros((total, ds.state_dim), np.float32)
            actions = np.zeros((total, ds.action_dim), np.float32)
            env_state: np.ndarray | None = None
            for i, e in enumerate(eps["episode_index"]):
                demo = ds[int(e)]
                n, o = lengths[i], offsets[i]
                if demo.frames.shape != (n, h, w, c) or len(demo.state) != n or len(demo.actions) != n:
                    raise DatasetError(f"{ds.root}: episode {e} has {len(demo.frames)} frames, {len(demo.state)} "
                                       f"states, {len(demo.actions)} actions; its metadata says {n}")
                if demo.damaged:
                    raise DatasetError(f"{ds.root}: episode {e} holds {demo.damaged[0].what}: a model must not learn "
                                       "from it (democheck audit --no-model flags every such episode; for a "
                                       "LeRobot v3.0 dataset democheck clean then writes it without them)")
                frames[o:o + n] = demo.frames
                state[o:o + n] = demo.state
                actions[o:o + n] = demo.actions
                env_state = _put_env_state(env_state, demo.env_state, o, n, total)
                if on_progress:
                    on_progress(i + 1, len(eps))
            frames.flush()
            del frames
            np.save(tmp / "state.npy", state)
            np.save(tmp / "actions.npy", actions)
            if env_state is not None:
                np.save(tmp / "env_state.npy", env_state)
            (tmp / "complete").write_text(json.dumps({"episodes": len(eps), "frames": total}))
            if folder.exists():
                shutil.rmtree(folder)
            os.replace(tmp, folder)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    frames = np.load(folder / "frames.npy", mmap_mode="r")
    state = np.load(folder / "state.npy")
    actions = np.load(folder / "actions.npy")
    if frames.shape != (total, h, w, c):
        raise DatasetError(f"{folder}: cache does not match the dataset; delete it and retry")
    env_state = np.load(folder / "env_state.npy") if (folder / "env_state.npy").exists() else None
    return EpisodeArrays(frames, state, actions, offsets, lengths, eps, fp, env_state)


def _put_env_state(env_state: np.ndarray | None, demo_env: np.ndarray | None, o: int, n: int, total: int
                   ) -> np.ndarray | None:
    """Episode rows ``o:o+n`` of the environment state, its array made at the first demo that records one (NaN
    where a demo records none, or one of another width)."""
    if demo_env is None or np.ndim(demo_env) != 2 or len(demo_env) != n:
        return env_state
    if env_state is None:
        env_state = np.full((total, demo_env.shape[1]), np.nan, np.float32)
    if demo_env.shape[1] == env_state.shape[1]:
        env_state[o:o + n] = demo_env
    return env_state
