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

import numpy as np

from democheck import __version__


def train_model(dataset: str | Path, out: str | Path, tc, model_type: str = "petnet", resume: bool = False,
                force: bool = False, camera: str | None = None, cache_dir: Path | None = None,
                on_decode: Callable[[int, int], None] | None = None,
                on_step: Callable[[int, int, dict], None] | None = None, stop_after: int | None = None):
    """Open ``dataset``, decode it into the frame cache, train, and write the model folder ``out``."""
    import torch

    from democheck.audit.scores import reference
    from democheck.data import open_dataset
    from democheck.data.cache import build_cache
    from democheck.errors import DatasetError
    from democheck.petnet.card import git_commit, model_card
    from democheck.petnet.train import resolve_device, train

    ds = open_dataset(dataset, camera=camera)
    if ds.episodes.groupby("task").size().max() < 2:
        raise DatasetError(f"{ds.root}: every task has a single demo; training needs two or more per task (a cue and "
                           "a trajectory to imitate); democheck audit can still score these demos with a trained model")
    arrays = build_cache(ds, cache_dir, on_progress=on_decode)
    data: dict[str, Any] = {"path": str(dataset), "episodes": len(ds), "tasks": len(ds.tasks), "camera": ds.camera,
                            "fps": ds.fps, "format": ds.format}
    suite = Path(dataset) / "meta" / "democheck" / "suite.json"
    if suite.exists():
        data["recipe"] = json.loads(suite.read_text())["recipe"]
    meta = {"data": data, "command": _command_line(), "commit": git_commit(Path(__file__).parent), "democheck_version": __version__,
            "torch_version": torch.__version__, "device": str(resolve_device(tc.device))}
    return train(arrays, Path(out), tc, model_type=model_type, resume=resume, force=force, meta=meta,
                 on_progress=on_step, card=lambda m: model_card(Path(out).name, m), stop_after=stop_after,
                 reference=reference, task_groups=object_pair_groups(ds))


def refit_novelty(model: str | Path, dataset: str | Path, out: str | Path, camera: str | None = None,
                  cache_dir: Path | None = None, device: str = "auto", force: bool = False,
                  on_decode: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Fit (or refit) a trained PETNet model's novelty density on ``dataset`` -- its training data -- and write
    the model, weights unchanged, to ``out`` with the card's numbers and the audit's reference redone."""
    from democheck.audit.run import check_compatible
    from democheck.audit.scores import reference
    from democheck.data import open_dataset
    from democheck.data.cache import build_cache
    from democheck.errors import DemocheckError
    from democheck.fsutil import atomic_output_dir, refuse_existing
    from democheck.petnet.card import git_commit, model_card
    from democheck.petnet.checkpoint import load_checkpoint, save_checkpoint
    from democheck.petnet.train import finish_petnet, resolve_device, task_rows

    out = Path(out)
    refuse_existing(out, force)  # before the decoding, not only when writing
    dev = resolve_device(device)
    ckpt = load_checkpoint(model, device=dev)
    ds = open_dataset(dataset, camera=camera)
    check_compatible(ds, ckpt)
    arrays = build_cache(ds, cache_dir, on_progress=on_decode)
    trained_on = ckpt.meta.get("data", {}).get("fingerprint")
    if trained_on is not None and trained_on != arrays.fingerprint:
        raise DemocheckError(f"{ds.root}: not the data {ckpt.path} was trained on (fingerprint {arrays.fingerprint}, "
                             f"the model's {trained_on}); the density must describe what the model saw")
    seed = int(ckpt.meta.get("training", {}).get("seed", 0))
    train_rows, val_rows = task_rows(arrays, "train", seed), task_rows(arrays, "val", seed)
    if not train_rows:
        raise DemocheckError(f"{ds.root}: no training tasks with two or more demos")
    held = np.concatenate(list(val_rows.values())) if val_rows else None
    extra = finish_petnet(ckpt.model, arrays, np.concatenate(list(train_rows.values())), held, seed, dev,
                          novelty=True, reference=reference)
    meta = dict(ckpt.meta)
    meta["metrics"] = {**meta.get("metrics", {}), "task_sigma": extra.pop("task_sigma")}
    meta.update(extra)
    meta["novelty"].update(command=_command_line(), commit=git_commit(Path(__file__).parent))
    with atomic_output_dir(out, force=force) as tmp:
        save_checkpoint(tmp, ckpt.model, ckpt.config, ckpt.norm, meta, model_card(out.name, meta))
    return meta


def _command_line() -> str:
    """The command that is running, as the user would type it."""
    return "democheck " + shlex.join(sys.argv[1:]) if sys.argv[0].endswith("democheck") else shlex.join(sys.argv)


def object_pair_groups(ds) -> dict[str, str]:
    """Task -> its unordered object pair, from a democheck suite's sim records (empty for other datasets)."""
    eps = ds.episodes
    if "sim" not in eps:
        return {}
    out = {}
    for task, sim in eps.groupby("task")["sim"].first().items():
        try:
            rec = json.loads(sim)
            out[str(task)] = "|".join(sorted((rec["target"], rec["distractor"])))
        except (TypeError, ValueError, KeyError):
            continue
    return out


def audit_dataset(dataset: str | Path, out: str | Path, model: str | Path | None = None, top: int = 20,
                  camera: str | None = None, task: str | None = None, device: str = "auto", force: bool = False,
                  on_progress: Callable[[int, int], None] | None = None, actions: bool = True) -> dict[str, Any]:
    """Open ``dataset``, load the model (default: the shipped one), audit, write the report folder ``out``."""
    import time

    from democheck.audit.run import audit
    from democheck.data import open_dataset
    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.petnet.train import resolve_device

    ds = open_dataset(dataset, camera=camera, task=task)
    dev = resolve_device(device)
    t0 = time.perf_counter()
    ckpt = load_checkpoint(model, device=dev)
    load_s = time.perf_counter() - t0
    return audit(ds, ckpt, Path(out), top=top, device=str(dev), force=force, on_progress=on_progress,
                 timings={"model_load_s": load_s}, actions=actions)


DEMO_PLANT = {"idle": 4, "random": 4}


def run_demo(out: str | Path, model: str | Path | None = None, workers: int = 2, force: bool = False,
             on_stage: Callable[[str], None] | None = None,
             on_progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """The main job, small: push-mini with planted idle and random demos, audited with the shipped model."""
    import pandas as pd

    from democheck.audit.metrics import by_label
    from democheck.fsutil import refuse_existing
    from democheck.sim.suite import generate, load_recipe

    out = Path(out)
    refuse_existing(out, force)
    recipe = load_recipe("push-mini").with_overrides(defects=DEMO_PLANT)
    if on_stage:
        on_stage(f"generating {recipe.n_episodes} demos of push-mini ({sum(DEMO_PLANT.values())} planted bad ones)")
    synth = generate(recipe, out / "data", workers=workers, force=True, on_progress=on_progress)
    if on_stage:
        on_stage("auditing with the model")
    summary = audit_dataset(out / "data", out / "report", model=model, force=True, on_progress=on_progress)
    table = pd.read_parquet(out / "report" / "scores.parquet")
    summary["planted"] = DEMO_PLANT
    summary["detection"] = {col: by_label(table, col) for col in ("suspicion", "score", "consistency", "action_error")}
    summary["synth"] = {k: synth[k] for k in ("episodes", "wall_s", "frames_per_s")}
    planted = table[table["label"] != "clean"]
    summary["planted_ranks"] = planted[["episode_index", "label", "rank"]].to_dict(orient="records")
    from democheck.audit.run import to_json

    return to_json(summary)
