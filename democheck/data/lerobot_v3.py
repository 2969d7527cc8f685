"""Reader for LeRobotDataset v3.0: the base reader of ``democheck.data.lerobot`` with v3.0's episodes table, which
says where in the shared data and video files each episode lies (several episodes per file).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from democheck.data import video
from democheck.data.demo import check_episodes
from democheck.data.lerobot import DATA_PATH, VIDEO_PATH, LeRobotBase, inside_root, metadata_frame, path_template
from democheck.errors import DatasetError


class LeRobotV3(LeRobotBase):
    """Reader for LeRobotDataset v3.0 (several episodes per data and video file)."""

    format = "lerobot-v3.0"

    def __init__(self, root: Path, info: dict[str, Any], **keys: str | None):
        super().__init__(root, info, **keys)
        ep_dir = root / "meta" / "episodes"
        files = sorted(ep_dir.glob("chunk-*/file-*.parquet"))
        if not files:
            raise DatasetError(f"{ep_dir}: no episode metadata files")
        eps = pd.concat([metadata_frame(f) for f in files], ignore_index=True)
        need = ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index"]
        missing = [c for c in need if c not in eps.columns]
        if missing:
            raise DatasetError(f"{files[0]}: episode table lacks {', '.join(missing)}")
        eps["task"] = [t[0] if len(t) else "" for t in eps["tasks"]]
        self._eps = eps.set_index("episode_index", drop=False)
        self.episodes = self._attach_sidecar(eps.set_index("episode_index")[["task", "length"]])
        check_episodes(files[0], self.episodes)

    def _data_path(self, episode_index: int) -> Path:
        r = self._eps.loc[episode_index]
        rel = path_template(self.info, "data_path", DATA_PATH, self.root, chunk_index=int(r["data/chunk_index"]),
                        file_index=int(r["data/file_index"]))
        return inside_root(self.root, rel)

    def _video_span(self, episode_index: int, frames: int) -> tuple[Path, int, int]:
        # v3.0's episodes table says where in the shared file the episode starts; its length, how many frames.
        r = self._eps.loc[episode_index]
        pre = f"videos/{self.camera}/"
        try:
            rel = path_template(self.info, "video_path", VIDEO_PATH, self.root, video_key=self.camera,
                            chunk_index=int(r[pre + "chunk_index"]), file_index=int(r[pre + "file_index"]))
            start = int(round(float(r[pre + "from_timestamp"]) * self.fps))
        except KeyError as exc:
            raise DatasetError(f"{self.root / 'meta/episodes'}: no {exc} for camera {self.camera!r}") from None
        return inside_root(self.root, rel), start, start + int(r["length"])

    def cues(self, episode_indices: list[int], at: float = 1.0) -> np.ndarray:
        """First and last frames of many episodes (``at``: the second frame that share of the way from the first),
        decoding each video file in one pass."""
        if self.camera_dtype != "video":  # images, or no camera
            if at < 1.0:
                frames = (self.load(e).frames for e in episode_indices)
                return np.stack([f[[0, int(round(at * (len(f) - 1)))]] for f in frames])
            return np.stack([self.cue_frames(e) for e in episode_indices])
        h, w, c = self.image_shape
        out = np.empty((len(episode_indices), 2, h, w, c), np.uint8)
        by_file: dict[Path, list[tuple[int, int, int]]] = {}
        for i, e in enumerate(episode_indices):
            vpath, start, stop = self._video_span(e, int(self.episodes.loc[e, "length"]))
            by_file.setdefault(vpath, []).append((i, start, start + int(round(at * (stop - 1 - start)))))
        for vpath, items in by_file.items():
            wanted = sorted({f for _, a, b in items for f in (a, b)})
            try:
                frames = dict(zip(wanted, video.read_frames(vpath, wanted, self.fps)))
            except DatasetError:  # a file that cannot be read whole: each episode's own, black where it fails
                for i, a, b in items:
                    out[i] = self._readable(lambda: video.read_frames(vpath, [a, b], self.fps), 2, vpath)[0]
                continue
            for i, a, b in items:
                out[i, 0], out[i, 1] = frames[a], frames[b]
        return out
