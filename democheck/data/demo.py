"""Demo and DemoSet: one vocabulary for every dataset format.

A ``Demo`` is one episode.  A ``DemoSet`` is indexed by ``episode_index``,
never by frame, and loads lazily: iterating or ``demos[e]`` decodes one
episode at a time, and ``cue_frames(e)`` reads only the first and last frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple, Protocol

import cv2
import numpy as np
import pandas as pd

from democheck.errors import DatasetError


# The frame shape of a dataset that records no camera (robomimic's low-dimensional files, a state-only LeRobot
# dataset): its demos' frames are [T, 0, 0, 3].  The model-free checks of states and actions read it; those of
# the frames need frames and are left out (``evidence.NEEDS``); the model, which reads a demo by its frames, cannot.
NO_CAMERA = (0, 0, 3)


def no_frames(n: int) -> np.ndarray:
    """The frames of ``n`` steps of a dataset without a camera (``NO_CAMERA``)."""
    return np.zeros((n, *NO_CAMERA), np.uint8)


class Damage(NamedTuple):
    """What a reader found broken in one stream of a recording: the frames affected, what and where in words, and
    for frames that could not be decoded the file and why."""

    frames: int
    what: str
    file: str = ""
    why: str = ""


@dataclass
class Demo:
    """One demonstration: frames uint8 [T,H,W,3] ([T,0,0,3] where no camera is recorded: ``NO_CAMERA``), state
    float32 [T,S], actions float32 [T,A]."""

    episode_index: int
    task: str
    frames: np.ndarray
    state: np.ndarray
    actions: np.ndarray
    success: bool | None = None
    label: str | None = None
    split: str | None = None
    sim: dict[str, Any] | None = None
    env_state: np.ndarray | None = None
    source_episode: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    # What the reader found broken in the recording and repaired so that it can be read, one ``Damage`` per broken
    # stream -- the state's or the actions' NaN or infinite values (``repair_non_finite``), frames that could not
    # be decoded (given as black).
    damaged: list[Damage] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.actions)


def readable_frames(read: Callable[[], np.ndarray], n: int, shape: tuple[int, int, int], strict: bool,
                    file: str | Path = "") -> tuple[np.ndarray, list[Damage]]:
    """The frames ``read`` decodes, or -- where they cannot be decoded (``read`` raises ``DatasetError``: a
    truncated or corrupt file, a missing one, frames that do not match the steps) -- ``n`` black frames of
    ``shape`` and what went wrong (a ``Demo.damaged`` entry, naming ``file``, the file ``read`` reads): a broken
    demo the audit reports (``modelfree.broken``), not a dataset it refuses; ``strict`` (``DemoSet.strict``): the
    error."""
    try:
        return read(), []
    except DatasetError as exc:
        if strict:
            raise
        why = str(exc).removeprefix(f"{file}: ") if file else str(exc)
        return np.zeros((n, *shape), np.uint8), [Damage(n, f"unreadable frames ({exc})", str(file), why)]


def check_arrays(where: str | Path, key: str, x: np.ndarray, dim: int) -> None:
    """One clear line when a state/action matrix has the wrong width."""
    if x.ndim != 2 or x.shape[1] != dim:
        raise DatasetError(f"{where}: {key!r} has {x.shape[1] if x.ndim == 2 else x.shape} values per frame, "
                           f"the metadata says {dim}")


def repair_non_finite(x: np.ndarray, key: str, episode: np.ndarray | None = None
                      ) -> tuple[np.ndarray, dict[int, Damage]]:
    """A recording with NaN or infinite values is a broken demo to report, not a dataset to refuse: ``x`` [T, D]
    (its rows grouped by ``episode``, each episode's in frame order; one episode 0 when None) with every such
    value replaced by the last finite value of its column before it in the same episode (the first after it
    where none is before, 0 where the episode has none), so that every check can still read the demo; and, for
    each episode that held any, (how many of its frames, where in words: "NaN or infinite values in 'action' at
    3 of 100 frames, 40-42")."""
    bad = ~np.isfinite(x)
    if not bad.any():
        return x, {}
    episode = np.zeros(len(x), np.int64) if episode is None else np.asarray(episode)
    frame = pd.Series(np.arange(len(x))).groupby(episode).cumcount().to_numpy()
    length = pd.Series(episode).map(pd.Series(episode).value_counts()).to_numpy()
    filled = pd.DataFrame(np.where(bad, np.nan, x)).groupby(episode).ffill()
    filled = filled.groupby(episode).bfill().fillna(0.0).to_numpy(x.dtype)
    rows = bad.any(1)
    found: dict[int, tuple[int, str]] = {}
    for e in np.unique(episode[rows]):
        at = frame[rows & (episode == e)]
        span = (f"{at[0]}" if len(at) == 1 else f"{at[0]}-{at[-1]}" if at[-1] - at[0] + 1 == len(at)
                else f"between {at[0]} and {at[-1]}")
        of = int(length[np.argmax(episode == e)])
        found[int(e)] = Damage(len(at), f"NaN or infinite values in {key!r} at {len(at)} of {of} frames, {span}")
    return filled, found


def check_episodes(where: str | Path, episodes: pd.DataFrame) -> None:
    """A dataset must have episodes, each at least one frame long."""
    if not len(episodes):
        raise DatasetError(f"{where}: the dataset has no episodes")
    if not episodes.index.is_unique:
        dup = episodes.index[episodes.index.duplicated()][0]
        raise DatasetError(f"{where}: episode {dup} is listed more than once")
    short = episodes.index[episodes["length"].to_numpy() < 1]
    if len(short):
        raise DatasetError(f"{where}: episode {int(short[0])} has no frames (length 0)")


class DemoSource(Protocol):
    """What a format reader provides to ``DemoSet``."""

    root: Path
    format: str
    fps: float
    camera: str | None  # None: no camera (``NO_CAMERA``)
    image_shape: tuple[int, int, int]
    state_dim: int
    action_dim: int
    episodes: pd.DataFrame  # index: episode_index; columns: task, length (+ split, success, label when known)

    def load(self, episode_index: int, arena: Any = None) -> Demo: ...

    def cue_frames(self, episode_index: int) -> np.ndarray: ...


def resize_frames(frames: np.ndarray, size: int) -> np.ndarray:
    """uint8 frames [..., H, W, 3] as size x size images: OpenCV's area interpolation when shrinking (each output
    pixel the mean of the pixels it covers), bilinear when enlarging.  A non-square camera is squeezed square."""
    h, w = frames.shape[-3:-1]
    if (h, w) == (size, size):
        return frames
    flat = frames.reshape(-1, h, w, frames.shape[-1])
    how = cv2.INTER_AREA if size < max(h, w) else cv2.INTER_LINEAR
    out = np.stack([cv2.resize(f, (size, size), interpolation=how) for f in flat]) if len(flat) else \
        np.zeros((0, size, size, frames.shape[-1]), np.uint8)
    return out.reshape(*frames.shape[:-3], size, size, frames.shape[-1])


NO_CAMERA_KEY = ""  # the camera a reader is asked for to read none (``DemoSet.without_camera``)
# What ``democheck info`` says of a camera other than the one read first: the checks of the pictures alone read it.
OTHER_CAMERA = "another camera: its pictures checked too"


def camera_name(key: str) -> str:
    """A camera's short name, as the audit's columns and words give it: LeRobot's ``observation.images.wrist`` is
    ``wrist``, robomimic's ``agentview_image`` is ``agentview``."""
    key = key.rpartition("observation.images.")[2] if "observation.images." in key else key
    return key[:-len("_image")] if key.endswith("_image") and len(key) > len("_image") else key


class DemoSet:
    """A lazily loaded collection of Demos, indexed by episode.

    ``image_size``: every frame it hands out (demos and cues) is resized to that square size
    (``resize_frames``), the way a model trained at that size reads them; None keeps the camera's size.
    """

    def __init__(self, source: DemoSource, image_size: int | None = None):
        self._src = source
        self._arena = None  # where its demos' frames are decoded to, in a set that ``reuses`` memory
        native = source.image_shape
        self.image_size = (None if image_size is None or native[:2] in ((image_size, image_size), NO_CAMERA[:2])
                           else int(image_size))

    def strict(self) -> "DemoSet":
        """Make a broken recording (NaN or infinite states or actions, frames that cannot be decoded) an error
        instead of a demo repaired to be read and reported (``Demo.damaged``): for reads that no decoding pass
        reports, such as an audit of the cues alone.  The source is shared: every set over it turns strict."""
        if hasattr(self._src, "strict"):
            self._src.strict = True
        return self

    def reusing(self) -> "DemoSet":
        """The same demos, each one's frames decoded into the memory of the one before (``video.FrameArena``):
        for a pass that is done with a demo before it reads the next, and keeps none of its frames."""
        from democheck.data.video import FrameArena  # PyAV: not at import, so that --help stays light

        out = DemoSet(self._src, self.image_size)
        out._arena = FrameArena()
        return out

    def resized(self, image_size: int | None) -> "DemoSet":
        """The same demos, frames at ``image_size`` (None: the camera's own)."""
        return DemoSet(self._src, image_size)

    @property
    def native_shape(self) -> tuple[int, int, int]:
        """The camera's own frame shape, before any resizing."""
        return self._src.image_shape

    # metadata
    @property
    def root(self) -> Path:
        return self._src.root

    @property
    def format(self) -> str:
        return self._src.format

    @property
    def fps(self) -> float:
        return self._src.fps

    @property
    def camera(self) -> str | None:
        """The camera read (None: the dataset records none, ``NO_CAMERA``)."""
        return self._src.camera

    @property
    def cameras(self) -> list[str]:
        """Every camera the dataset records, the one read (``camera``) among them."""
        return list(getattr(self._src, "cameras", [self.camera] if self.camera else []))

    def other_cameras(self) -> dict[str, "DemoSet"]:
        """Each camera but the one read, by its short name (``camera_name``), as a set that reads it at its own
        size: for the checks that read every camera."""
        return {camera_name(c): DemoSet(self._src.with_camera(c)) for c in self.cameras if c != self.camera}

    def without_camera(self) -> "DemoSet":
        """The same demos, their states and actions alone (``NO_CAMERA``): for a dataset whose frames cannot be
        read at all."""
        return DemoSet(self._src.with_camera(NO_CAMERA_KEY))

    @property
    def has_camera(self) -> bool:
        return self._src.image_shape[:2] != NO_CAMERA[:2]

    def require_camera(self, what: str) -> "DemoSet":
        """This set, or one clear line where the dataset records no camera and ``what`` reads demos by frames."""
        if not self.has_camera:
            raise DatasetError(f"{self.root}: records no camera images, and {what} reads a demo by its frames; "
                               "democheck audit --no-model checks its states and actions")
        return self

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """The shape of the frames this set hands out."""
        if self.image_size is None:
            return self._src.image_shape
        return self.image_size, self.image_size, self._src.image_shape[2]

    def video_files(self) -> dict[Path, list[int]]:
        """Each video file the metadata names for the camera, and the episodes it holds ({} for a camera that is not
        a video)."""
        files: dict[Path, list[int]] = {}
        if not hasattr(self._src, "video_file") or not self.has_camera:
            return files
        for e in self.episodes.index:
            path = self._src.video_file(int(e))
            if path is not None:
                files.setdefault(path, []).append(int(e))
        return files

    def camera_files(self) -> tuple[int, list[str]]:
        """Before any long work: how many video files the metadata names for the camera, and what is wrong with
        them -- each file that is missing (with how many episodes it holds), and a sample that does not decode
        (the first and last frame of the first episode in a file that is there, read strictly).  (0, []) for a
        camera that is not a video."""
        files = self.video_files()
        there = {path: path.exists() for path in files}
        problems = [f"{path}: missing ({len(eps)} episode{'s' * (len(eps) > 1)})" for path, eps in files.items()
                    if not there[path]]
        present = [eps[0] for path, eps in files.items() if there[path]]
        if present:
            was = getattr(self._src, "strict", False)
            self._src.strict = True
            try:
                self._src.cue_frames(present[0])
            except DatasetError as exc:
                problems.append(f"episode {present[0]}'s first and last frame do not decode: {exc}")
            finally:
                self._src.strict = was
        return len(files), problems

    def streams(self) -> list[tuple[str, str, str]]:
        """What the dataset records, stream by stream: (name, width or frame shape, what the audit reads it as)."""
        return self._src.streams() if hasattr(self._src, "streams") else []

    @property
    def state_dim(self) -> int:
        return self._src.state_dim

    @property
    def action_dim(self) -> int:
        return self._src.action_dim

    def names(self, what: str) -> list[str]:
        """Names of the ``state``, ``action`` or ``env_state`` dimensions: the dataset's own where it gives them,
        else ``state[0]``, ``state[1]``, ...; no environment state's where the dataset records none."""
        dim = {"state": self.state_dim, "action": self.action_dim,
               "env_state": int(getattr(self._src, "env_state_dim", 0) or 0)}[what]
        given = getattr(self._src, f"{what}_names", None)
        return list(given) if given and len(given) == dim else [f"{what}[{i}]" for i in range(dim)]

    @property
    def episodes(self) -> pd.DataFrame:
        """One row per episode (index: episode_index): task, length, and split/success/label when known."""
        return self._src.episodes

    @property
    def episode_indices(self) -> list[int]:
        return [int(e) for e in self._src.episodes.index]

    @property
    def tasks(self) -> list[str]:
        return sorted(self._src.episodes["task"].unique())

    def __len__(self) -> int:
        return len(self._src.episodes)

    def __contains__(self, episode_index: int) -> bool:
        return episode_index in self._src.episodes.index

    def _load(self, episode_index: int) -> Demo:
        demo = self._src.load(episode_index, arena=self._arena)
        if self.image_size is not None:
            demo.frames = resize_frames(demo.frames, self.image_size)
        return demo

    def _sized(self, frames: np.ndarray) -> np.ndarray:
        return frames if self.image_size is None else resize_frames(frames, self.image_size)

    def __getitem__(self, episode_index: int) -> Demo:
        if episode_index not in self._src.episodes.index:
            raise KeyError(f"no episode {episode_index} in {self.root}")
        return self._load(int(episode_index))

    def __iter__(self) -> Iterator[Demo]:
        for e in self.episode_indices:
            yield self._load(e)

    def cue_frames(self, episode_index: int) -> np.ndarray:
        """First and last frame of one episode, uint8 [2, H, W, 3], without decoding the rest."""
        return self._sized(self._src.cue_frames(int(episode_index)))

    def cue_frames_many(self, episode_indices: list[int], at: float = 1.0) -> np.ndarray:
        """Cues of several episodes, uint8 [N, 2, H, W, 3]; opens each video file once where the format allows.
        ``at`` < 1: the second frame is that share of the way from the first, not the last."""
        many = getattr(self._src, "cues", None)
        if many is not None:
            return self._sized(many([int(e) for e in episode_indices], at=at) if at < 1.0
                               else many([int(e) for e in episode_indices]))
        if at < 1.0:
            return self._sized(np.stack([f[[0, int(round(at * (len(f) - 1)))]]
                                         for f in (self._src.load(int(e)).frames for e in episode_indices)]))
        return self._sized(np.stack([self._src.cue_frames(int(e)) for e in episode_indices]))

    def end_states(self, episode_indices: list[int], at: float = 1.0) -> np.ndarray:
        """The state at each episode's last step (``at``: that share of the way from its first), float32 [N, S],
        without decoding frames where the format allows (a reader's ``end_state``; otherwise the whole demo is
        read)."""
        reader = getattr(self._src, "end_state", None)

        def whole(e: int) -> np.ndarray:
            state = self._src.load(e).state
            return state[int(round(at * (len(state) - 1)))]

        one = (lambda e: reader(e, at=at)) if reader else whole
        out = np.zeros((len(episode_indices), self.state_dim), np.float32)
        for i, e in enumerate(episode_indices):
            out[i] = one(int(e))
            if not np.isfinite(out[i]).all():  # read as the whole demo is: repaired, or refused when strict
                out[i] = whole(int(e))
        return out

    def by_task(self) -> dict[str, list[int]]:
        """Episode indices grouped by task string (demos with the same string are the same task)."""
        groups = self._src.episodes.groupby("task", sort=True).groups
        return {task: sorted(int(e) for e in idx) for task, idx in groups.items()}

    def split(self, name: str) -> list[int]:
        """Episode indices of one split (train/val/test) when the dataset records splits."""
        if "split" not in self._src.episodes:
            return []
        return [int(e) for e in self._src.episodes.index[self._src.episodes["split"] == name]]

    def __repr__(self) -> str:
        h, w, _ = self.image_shape
        return (f"DemoSet({self.root}, format={self.format}, episodes={len(self)}, tasks={len(self.tasks)}, "
                f"camera={self.camera}, image={h}x{w}" + (" resized" if self.image_size else "") + ")")
