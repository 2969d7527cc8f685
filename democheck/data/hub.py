"""Datasets by their hub repository id: ``lerobot/pusht`` resolves to a folder on this machine.

A path that exists is itself.  Otherwise a name of the form ``ORG/NAME`` is looked up as LeRobot looks it up:
first LeRobot's own copy under ``HF_LEROBOT_HOME`` (default ``$HF_HOME/lerobot``, ``~/.cache/huggingface/lerobot``)
at ``ORG/NAME``, then the hub's snapshot cache (``huggingface_hub.snapshot_download`` of the dataset repository),
which downloads what is missing when online and reads the cache alone when offline (``HF_HUB_OFFLINE=1``).  A
``revision`` (a branch, tag or commit) skips LeRobot's copy, which records none.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from democheck.errors import DatasetError

REPO_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")


def lerobot_home() -> Path:
    """Where LeRobot keeps the datasets it downloaded: ``HF_LEROBOT_HOME``, else ``$HF_HOME/lerobot``."""
    if os.environ.get("HF_LEROBOT_HOME"):
        return Path(os.environ["HF_LEROBOT_HOME"]).expanduser()
    hf_home = os.environ.get("HF_HOME") or Path(os.environ.get("XDG_CACHE_HOME", "~/.cache")) / "huggingface"
    return Path(hf_home).expanduser() / "lerobot"


def is_repo_id(name: str) -> bool:
    return bool(REPO_ID.match(str(name)))


def resolve(name: str | Path, revision: str | None = None) -> Path:
    """The local folder of a dataset given by path or by hub repository id (see the module docstring); a name that
    is neither a path here nor an id found is one line saying what to do."""
    path = Path(name).expanduser()
    if path.exists() or not is_repo_id(str(name)):
        return path
    local = lerobot_home() / str(name)
    if revision is None and (local / "meta" / "info.json").exists():
        return local
    try:
        from huggingface_hub import snapshot_download
        from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError, RepositoryNotFoundError
    except ImportError:
        raise DatasetError(f"{name}: no such folder, nor in {local}; to read datasets by their hub id, pip install "
                           "huggingface_hub") from None
    offline = os.environ.get("HF_HUB_OFFLINE", "").lower() in ("1", "true", "yes", "on")
    try:
        return Path(snapshot_download(str(name), repo_type="dataset", revision=revision, local_files_only=offline))
    except LocalEntryNotFoundError:
        raise DatasetError(f"{name}: {_no_folder(path)}not on this machine ({local}, or the hub's cache) and the hub cannot be reached"
                           + (" (HF_HUB_OFFLINE is set)" if offline else "") + "; download it where there is a "
                           f"network (huggingface-cli download --repo-type dataset {name}"
                           + (f" --revision {revision}" if revision else "") + "), or give its folder") from None
    except RepositoryNotFoundError:
        raise DatasetError(f"{name}: {_no_folder(path)}no such dataset on the hub (or it is private: "
                           "huggingface-cli login)") from None
    except (HfHubHTTPError, OSError, ValueError) as exc:
        raise DatasetError(f"{name}: could not be fetched from the hub ({str(exc).splitlines()[0][:120]})") from None


def _no_folder(path: Path) -> str:
    """Where the id's first part is a folder here, the words that say the name was most likely a path, mistyped."""
    return (f"no such folder ({path.parent}/ is here, without {path.name}); and as a hub id, "
            if path.parent.is_dir() and str(path.parent) not in ("", ".") else "")
