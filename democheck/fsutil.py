"""Writing results: atomic output folders (a temporary sibling, renamed at the end) and plain JSON."""

from __future__ import annotations

import json
import math
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from democheck.errors import DemocheckError


def refuse_existing(out: Path, force: bool) -> None:
    """One clear line when ``out`` exists (a non-empty folder, or a file) and ``force`` was not given; called
    before long work starts as well as by ``atomic_output_dir``."""
    if out.exists() and not (out.is_dir() and not any(out.iterdir())) and not force:
        raise DemocheckError(f"{out}: already exists; choose another --out or pass --force to replace it")


def work_dir(out: Path, resume: bool, force: bool, what: str = "run of this model") -> Path:
    """The folder beside ``out`` where a long run keeps what it has done for ``--resume``, after checking ``out``
    and it: refuses an existing ``out`` without ``force``, and an interrupted ``what``'s folder without ``resume``
    (or ``force``, which discards it)."""
    work = out.parent / f".{out.name}.partial"
    refuse_existing(out, force)
    if work.exists() and not resume:
        if not force:
            raise DemocheckError(f"{work}: an interrupted {what} is there; pass --resume to continue it "
                                 "or --force to start over")
        shutil.rmtree(work)
    return work


@contextmanager
def atomic_output_dir(out: str | Path, force: bool = False) -> Iterator[Path]:
    """Yield a temporary folder that becomes ``out`` only if the block finishes.

    An interrupted run leaves ``out`` untouched (absent, or its previous
    content); the temporary folder is a dot-folder beside it, removed on any
    Python-level exit and ignored by every reader.
    """
    out = Path(out)
    refuse_existing(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale(out)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)


def _remove_stale(out: Path) -> None:
    """Temporary folders left beside ``out`` by killed runs (their process is gone) are removed."""
    for stale in out.parent.glob(f".{out.name}.tmp-*"):
        pid = stale.name.rsplit("-", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            shutil.rmtree(stale, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def to_json(x: Any) -> Any:
    """Plain JSON values: numpy scalars unwrapped, NaN and inf as null."""
    if isinstance(x, dict):
        return {str(k): to_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_json(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(path: Path, doc: Any) -> None:
    """``doc`` as indented JSON (``to_json`` first, so NaN never reaches the file)."""
    path.write_text(json.dumps(to_json(doc), indent=2, allow_nan=False))
