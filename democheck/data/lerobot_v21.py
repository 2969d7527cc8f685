"""Reader for LeRobotDataset v2.0/v2.1: the base reader of ``democheck.data.lerobot`` with the older layout's
metadata -- ``meta/episodes.jsonl`` and ``meta/tasks.jsonl`` -- and one data and one video file per episode,
found through ``info.json``'s path templates.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from democheck.data.demo import check_episodes
from democheck.data.lerobot import CHUNKS_SIZE, LeRobotBase, inside_root, path_template
from democheck.errors import DatasetError


class LeRobotV21(LeRobotBase):
    """Reader for LeRobotDataset v2.0/v2.1 (one data and one video file per episode)."""

    format = "lerobot-v2.1"

    def __init__(self, root: Path, info: dict[str, Any], **keys: str | None):
        super().__init__(root, info, **keys)
        self.chunks_size = int(info.get("chunks_size", CHUNKS_SIZE))
        tasks_path = root / "meta" / "tasks.jsonl"
        ep_path = root / "meta" / "episodes.jsonl"
        task_names = {int(t["task_index"]): t["task"] for t in _read_jsonl(tasks_path)}
        rows = []
        for ep in _read_jsonl(ep_path):
            try:
                tasks = ep.get("tasks") or [task_names.get(int(ep.get("task_index", 0)), "")]
                rows.append({"episode_index": int(ep["episode_index"]), "task": str(tasks[0]), "length": int(ep["length"])})
            except (KeyError, TypeError, ValueError):
                raise DatasetError(f"{ep_path}: malformed episode line {ep!r:.80}") from None
        if not rows:
            raise DatasetError(f"{ep_path}: no episodes")
        self.episodes = self._attach_sidecar(pd.DataFrame(rows).set_index("episode_index"))
        check_episodes(root / "meta/episodes.jsonl", self.episodes)

    def _path(self, template_key: str, episode_index: int) -> Path:
        chunk = episode_index // self.chunks_size
        # The chunk by either of LeRobot's names for it: v2.1's episode_chunk, or chunk_index as later writers put it.
        rel = path_template(self.info, template_key, None, self.root, episode_chunk=chunk, chunk_index=chunk,
                            episode_index=episode_index, video_key=self.camera)
        return inside_root(self.root, rel)

    def _data_path(self, episode_index: int) -> Path:
        return self._path("data_path", episode_index)

    def _video_span(self, episode_index: int, frames: int) -> tuple[Path, int, int]:
        return self._path("video_path", episode_index), 0, frames


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                raise DatasetError(f"{path}:{n}: not valid JSON") from None
    return out
