"""Reader for robomimic HDF5 files.

Layout: ``data/demo_N/actions`` [T, A], ``data/demo_N/obs/<key>`` (images
uint8 [T, H, W, 3] and low-dimensional float arrays), ``mask/<filter>`` lists
of demo names (``train``/``valid`` become democheck's train/val split), and
``data.attrs["env_args"]`` (JSON).  One task per file, named by a ``task``
attribute of the demo or of ``data``, by ``--task``, or else by the
environment's name.  Frames are sliced from HDF5 directly, so a cue reads two
frames, not the episode.  ``obs/object`` (the objects' poses, in robomimic's low-dimensional datasets) is the
demo's environment state (``Demo.env_state``), not part of its state.
"""

from __future__ import annotations

import json
import re
from typing import Any, Callable
from pathlib import Path

import numpy as np
import pandas as pd

from democheck.data.demo import (NO_CAMERA, NO_CAMERA_KEY, OTHER_CAMERA, Demo, check_arrays, check_episodes, no_frames,
                                 readable_frames, repair_non_finite)
from democheck.errors import DatasetError


def _decode(x) -> str:
    return x.decode() if isinstance(x, bytes) else str(x)


class Robomimic:
    format = "robomimic"
    strict = False  # a broken recording raises instead of being repaired and reported (``DemoSet.strict``)

    def __init__(self, path: Path, camera: str | None = None, state_key: str | None = None,
                 action_key: str | None = None, task: str | None = None):
        import h5py

        self.root = path
        self._h5 = h5py
        self._keys = {"state_key": state_key, "action_key": action_key, "task": task}
        try:
            f = h5py.File(path, "r")
        except OSError as exc:
            raise DatasetError(f"{path}: not a readable HDF5 file ({exc})") from None
        with f:
            if "data" not in f or not isinstance(f["data"], h5py.Group):
                raise DatasetError(f"{path}: no 'data' group; not a robomimic file")
            data = f["data"]
            names = sorted((k for k in data.keys() if re.fullmatch(r"demo_\d+", k)), key=lambda k: int(k[5:]))
            if not names:
                raise DatasetError(f"{path}: no data/demo_N groups")
            first = data[names[0]]
            # What the file records is read from every demo's keys, not the first's alone: a demo whose images were
            # lost is a broken demo (``_frames``), not a file without a camera.  robomimic's raw files (demo.hdf5)
            # have no obs group: the simulator's flattened state is the state.
            groups = [data[n]["obs"] for n in names if "obs" in data[n]]
            obs = groups[0] if groups else None
            if obs is None and "states" not in first:
                raise DatasetError(f"{path}: {names[0]} has no obs group (nor states)")
            obs_keys = list(obs) if obs is not None else []
            images = {k: g[k] for g in groups for k in g if g[k].ndim == 4 and g[k].shape[-1] == 3}
            cams = sorted(images)
            self.cameras = cams
            if camera == NO_CAMERA_KEY:
                self.camera = None
            elif camera is None:
                self.camera = cams[0] if cams else None  # none: robomimic's low-dimensional files (``NO_CAMERA``)
            else:
                matches = [c for c in (camera, f"{camera}_image") if c in cams]
                if not matches:
                    raise DatasetError(f"{path}: no camera {camera!r}; "
                                       + (f"choose one of {', '.join(cams)}" if cams else "it records no images"))
                self.camera = matches[0]
            low = sorted(k for k in obs_keys if obs[k].ndim == 2 and k not in cams)
            self._widths = {**{k: str(obs[k].shape[1]) for k in low},
                            **{k: "x".join(str(v) for v in images[k].shape[1:]) for k in cams}}
            self.obs = obs is not None
            if state_key is not None:
                self.state_keys = [k.strip() for k in state_key.split(",")]
                missing = [k for k in self.state_keys if k not in (obs if self.obs else first)]
                if missing:
                    raise DatasetError(f"{path}: no {'obs ' if self.obs else ''}key {missing[0]!r} (--state-key)")
            elif not self.obs:
                self.state_keys = ["states"]
            else:
                robot = [k for k in low if k.startswith("robot")]
                self.state_keys = robot or low
            # robomimic's low-dimensional datasets keep the objects' poses under obs/object: the environment's state.
            self.env_key = "object" if "object" in low and "object" not in self.state_keys else None
            self.action_key = action_key or "actions"
            if not self.obs and "states" in first:
                self._widths["states"] = str(first["states"].shape[1])
            if self.action_key in first:
                self._widths[self.action_key] = str(first[self.action_key].shape[1])
            if self.action_key not in first:
                raise DatasetError(f"{path}: {names[0]} has no {self.action_key!r}")
            self.image_shape = tuple(int(v) for v in images[self.camera].shape[1:]) if self.camera else NO_CAMERA
            self.state_dim = int(sum((obs if self.obs else first)[k].shape[1] for k in self.state_keys))
            self.action_dim = int(first[self.action_key].shape[1])
            self.env_state_dim = int(obs["object"].shape[1]) if self.env_key else 0
            try:
                env_args = json.loads(_decode(data.attrs.get("env_args", "{}")))
            except json.JSONDecodeError:
                env_args = {}
            self.fps = float(env_args.get("env_kwargs", {}).get("control_freq", 20))
            default_task = task or _decode(data.attrs.get("task", "")) or env_args.get("env_name") or path.stem
            split = {}
            for mask, name in (("train", "train"), ("valid", "val"), ("val", "val"), ("test", "test")):
                if "mask" in f and mask in f["mask"]:
                    for d in f["mask"][mask][()]:
                        split[_decode(d)] = name
            rows = []
            for n in names:
                g = data[n]
                t = _decode(g.attrs.get("task", "")) or default_task  # a demo naming its task wins
                rows.append({"episode_index": int(n[5:]), "task": t, "length": int(g[self.action_key].shape[0]),
                             "split": split.get(n), "name": n})
        eps = pd.DataFrame(rows).set_index("episode_index")
        if eps["split"].isna().all():
            eps = eps.drop(columns="split")
        self.episodes = eps
        check_episodes(path, eps)

    def with_camera(self, camera: str) -> "Robomimic":
        """The same file read through another of its cameras."""
        other = Robomimic(self.root, camera=camera, **self._keys)
        other.strict = self.strict
        return other

    def streams(self) -> list[tuple[str, str, str]]:
        """Every recorded stream of the first demo: (name, width or frame shape, what the audit reads it as)."""
        def role(k: str) -> str:
            if k == self.camera:
                return "the camera"
            if k in self.state_keys:
                return "the state (part)" if len(self.state_keys) > 1 else "the state"
            if k == self.action_key:
                return "the actions"
            if k == self.env_key:
                return "the environment state (where the objects are)"
            return OTHER_CAMERA if "x" in self._widths[k] else "not read"

        return [(k, w, role(k)) for k, w in self._widths.items()]

    def _group(self, f, episode_index: int):
        return f["data"][self.episodes.loc[episode_index, "name"]]

    def _camera(self, g, read: Callable[[Any], np.ndarray]) -> np.ndarray:
        """``read`` of a demo's camera dataset, the HDF5 file's errors as one ``DatasetError`` (a corrupt chunk, a
        dataset that is missing): what ``demo.readable_frames`` turns into black frames and a broken demo."""
        try:
            return read(g["obs"][self.camera])
        except (OSError, KeyError, ValueError, IndexError) as exc:
            raise DatasetError(f"{self.root}: {g.name}: obs/{self.camera}: {exc}") from None

    def _frames(self, g, n: int) -> tuple[np.ndarray, list[tuple[int, str]]]:
        """A demo's ``n`` frames, or black frames and what went wrong (``demo.readable_frames``)."""
        def whole(img) -> np.ndarray:
            frames = np.asarray(img[()], dtype=np.uint8)
            if frames.shape != (n, *self.image_shape):
                raise DatasetError(f"{self.root}: {g.name}: obs/{self.camera}: frames that do not match its steps: "
                                   f"{frames.shape[0]} of {frames.shape[1:]} for {n} of {self.image_shape}")
            return frames

        return readable_frames(lambda: self._camera(g, whole), n, self.image_shape, self.strict, self.root)

    def _state_group(self, g):
        """Where a demo's state keys are: its obs group, or the demo itself in a raw file (its ``states``)."""
        return g["obs"] if self.obs else g

    def load(self, episode_index: int, arena: object = None) -> Demo:
        """One demo (``arena``: LeRobot's video reuse, unused for images in the file)."""
        with self._h5.File(self.root, "r") as f:
            g = self._group(f, episode_index)
            actions = np.asarray(g[self.action_key][()], np.float32)
            n = len(actions)
            frames, unreadable = (self._frames(g, n) if self.camera else (no_frames(n), []))
            where_state = self._state_group(g)
            state = np.concatenate([np.asarray(where_state[k][()], np.float32).reshape(n, -1)
                                    for k in self.state_keys], axis=1) if self.state_keys else np.zeros((n, 0), np.float32)
            env_state = (np.asarray(g["obs"][self.env_key][()], np.float32).reshape(n, -1)
                         if self.env_key else None)
        where = f"{self.root}: data/{self.episodes.loc[episode_index, 'name']}"
        check_arrays(where, "obs (state keys)", state, self.state_dim)
        check_arrays(where, self.action_key, actions, self.action_dim)
        state, bad_state = repair_non_finite(state, "obs (state keys)")
        actions, bad_actions = repair_non_finite(actions, self.action_key)
        if self.strict and (bad_state or bad_actions):
            raise DatasetError(f"{where}: holds {[*bad_state.values(), *bad_actions.values()][0][1]}")
        row = self.episodes.loc[episode_index]
        split = row.get("split") if "split" in row else None
        return Demo(episode_index=episode_index, task=str(row["task"]), frames=frames, state=state, actions=actions,
                    split=split if isinstance(split, str) else None, env_state=env_state,
                    damaged=[*unreadable, *bad_state.values(), *bad_actions.values()])

    def end_state(self, episode_index: int, at: float = 1.0) -> np.ndarray:
        """The state at an episode's last step (``at``: that share of the way from its first), float32 [S],
        reading one row of each state key."""
        with self._h5.File(self.root, "r") as f:
            obs = self._state_group(self._group(f, episode_index))
            parts = [np.asarray(obs[k][int(round(at * (obs[k].shape[0] - 1)))], np.float32).reshape(-1)
                     for k in self.state_keys]
        return np.concatenate(parts) if parts else np.zeros(0, np.float32)

    def cue_frames(self, episode_index: int) -> np.ndarray:
        if self.camera is None:
            return no_frames(2)
        with self._h5.File(self.root, "r") as f:
            g = self._group(f, episode_index)

            def ends(img) -> np.ndarray:
                return np.stack([img[0], img[img.shape[0] - 1]]).astype(np.uint8)

            # Black where unreadable: the decoding pass reports it (``_frames``).
            return readable_frames(lambda: self._camera(g, ends), 2, self.image_shape, self.strict, self.root)[0]
