"""Library functions behind the CLI commands that join several parts (data -> petnet -> ...).

Each part stays in its lane (``petnet`` never reads datasets from disk); the
joining happens here, once, so the CLI only parses and prints.
"""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path
from typing import Any, Callable

from democheck import __version__


def train_model(dataset: str | Path, out: str | Path, tc, model_type: str = "petnet", resume: bool = False,
                force: bool = False, camera: str | None = None, cache_dir: Path | None = None,
                on_decode: Callable[[int, int], None] | None = None,
                on_step: Callable[[int, int, dict], None] | None = None, stop_after: int | None = None):
    """Open ``dataset``, decode it into the frame cache, train, and write the model folder ``out``."""
    import torch

    from democheck.data import open_dataset
    from democheck.data.cache import build_cache
    from democheck.petnet.card import git_commit, model_card
    from democheck.petnet.train import resolve_device, train

    ds = open_dataset(dataset, camera=camera)
    arrays = build_cache(ds, cache_dir, on_progress=on_decode)
    data: dict[str, Any] = {"path": str(dataset), "episodes": len(ds), "tasks": len(ds.tasks), "camera": ds.camera,
                            "fps": ds.fps, "format": ds.format}
    suite = Path(dataset) / "meta" / "democheck" / "suite.json"
    if suite.exists():
        data["recipe"] = json.loads(suite.read_text())["recipe"]
    meta = {"data": data, "command": "democheck " + shlex.join(sys.argv[1:]) if sys.argv[0].endswith("democheck")
            else shlex.join(sys.argv), "commit": git_commit(Path(__file__).parent), "democheck_version": __version__,
            "torch_version": torch.__version__, "device": str(resolve_device(tc.device))}
    return train(arrays, Path(out), tc, model_type=model_type, resume=resume, force=force, meta=meta,
                 on_progress=on_step, card=lambda m: model_card(Path(out).name, m), stop_after=stop_after)
