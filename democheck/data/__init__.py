"""Datasets on disk: Demo, DemoSet, format readers and writers, ``open_dataset``."""

from __future__ import annotations

from pathlib import Path

from democheck.data.demo import Demo, DemoSet
from democheck.errors import DatasetError

__all__ = ["Demo", "DemoSet", "open_dataset"]


def open_dataset(path: str | Path, camera: str | None = None, state_key: str | None = None,
                 action_key: str | None = None, task: str | None = None, image_size: int | None = None) -> DemoSet:
    """Open a dataset, sniffing its format: a LeRobot v3.0/v2.1 folder or a robomimic HDF5 file.

    ``camera`` picks the image feature when there are several (full key or the
    part after ``observation.images.``); ``state_key``/``action_key`` override
    the features found in the metadata; ``task`` names the task of a robomimic
    file that does not name it; ``image_size`` resizes every frame to that square size (``DemoSet``).
    """
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"{root}: no such file or directory")
    if root.is_file() and root.suffix.lower() in (".hdf5", ".h5"):
        from democheck.data.robomimic import Robomimic

        return DemoSet(Robomimic(root, camera=camera, state_key=state_key, action_key=action_key, task=task),
                       image_size)
    if root.is_dir() and (root / "meta").is_dir() and not (root / "meta" / "info.json").exists():
        raise DatasetError(f"{root / 'meta' / 'info.json'}: missing; a LeRobot dataset describes itself there")
    if root.is_dir() and (root / "meta" / "info.json").exists():
        return DemoSet(open_lerobot(root, camera=camera, state_key=state_key, action_key=action_key), image_size)
    raise DatasetError(f"{root}: not a dataset democheck knows (a LeRobot folder with meta/info.json, "
                       "or a robomimic .hdf5 file)")


def open_lerobot(root: Path, camera: str | None = None, state_key: str | None = None,
                 action_key: str | None = None):
    """The reader of a LeRobot folder's codebase version: v3.x (``lerobot_v3.LeRobotV3``) or v2.x
    (``lerobot_v21.LeRobotV21``)."""
    from democheck.data.lerobot import read_json
    from democheck.data.lerobot_v3 import LeRobotV3

    info = read_json(root / "meta" / "info.json")
    if not isinstance(info, dict):
        raise DatasetError(f"{root / 'meta/info.json'}: not a JSON object")
    version = str(info.get("codebase_version", ""))
    keys = dict(camera=camera, state_key=state_key, action_key=action_key)
    if version.startswith("v3"):
        return LeRobotV3(root, info, **keys)
    if version.startswith("v2"):
        from democheck.data.lerobot_v21 import LeRobotV21

        return LeRobotV21(root, info, **keys)
    raise DatasetError(f"{root / 'meta/info.json'}: unsupported LeRobot codebase_version {version!r} (v2.x, v3.x)")
