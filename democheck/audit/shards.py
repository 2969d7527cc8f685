"""The audit's passes in workers: the cue pass and the decoding pass cut into shards, run by spawned processes
or Ray actors (``democheck.pool``), and put back together so that every number is the one a single process
computes.

A shard is a job ``(index, spec, episodes)``: ``spec`` says which pass (``"cues"`` or ``"decode"``) and how a
worker opens the dataset as the calling process reads it (``where``).  Each worker loads the model once
(``_decode_init``) and runs shards of either pass (``_run_shard``).  Numbers stay identical because the shards
cut where one process's own batches end: cue shards hold whole batches of ``CUE_BATCH`` cues, decoding shards
whole batches of the action error's controller and whole blocks of the dynamics check; what a check keeps per
demo (``modelfree.PerDemo``) is merged in shard order before it finishes.
"""

from __future__ import annotations

import json
import os
import pickle
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pandas as pd

from democheck import pool
from democheck.audit import dynamics, modelfree, scorers as registry
from democheck.audit.action_error import ACTION_BATCH
from democheck.audit.evidence import Evidence, Scorer
from democheck.audit.findings import CAMERA_MARK
from democheck.data.demo import Demo, DemoSet
from democheck.errors import DemocheckError
from democheck.fsutil import write_json
from democheck.petnet.encode import encode_demos
from democheck.petnet.posterior import TaskPosterior

CUE_BATCH = 256  # cues encoded at a time, in one process and in a worker alike
# Cues per shard of a parallel cue pass: whole batches of ``CUE_BATCH``, as one process encodes them.
CUE_SHARD = 4 * CUE_BATCH
# Demos per shard of the decoding pass: a multiple of the action error's batch, so that every batch the controller
# sees holds the same demos as in one process (and the numbers are the same), and of the dynamics check's block
# (``dynamics.DYNAMICS_BLOCK``), for the same reason -- a shard then scores its own blocks and hands back no states.
SHARD = 4 * ACTION_BATCH
assert SHARD % dynamics.DYNAMICS_BLOCK == 0 or SHARD < dynamics.DYNAMICS_BLOCK, "see dynamics.DynamicsFit.merged"
# A set of fewer than this many shards is cut into smaller shards instead (the dynamics check's states then wait for
# the merge, a few hundred demos' worth): one action-error batch where a model reads the demos, a quarter of one
# where none does, so that a hub dataset's few dozen long demos keep two workers equally busy and an interruption
# loses little.
FEW_SHARDS = 4


def decode_shard(n_demos: int, model: bool = True) -> int:
    """Demos per shard of a decoding pass over ``n_demos`` (``model``: the action error reads them in batches):
    ``SHARD``, or smaller in a small set."""
    small = ACTION_BATCH if model else ACTION_BATCH // 4
    return SHARD if n_demos >= FEW_SHARDS * SHARD else min(SHARD, small)


# Spreading a pass pays where each worker gets a shard and the pass decodes at least this many pixels (frames
# times their size): starting the workers (each imports torch and loads the model) costs ~2 s, about what one
# core decodes of this many pixels.  On push-v1 (64x64 frames), 168 demos (7e7 pixels) took 2.1 s in one process
# and 3.4 s in two, 768 demos (3e8) 10.1 s and 7.5 s, 6,048 demos 78.6 s and 47.8 s (benchmarks/parallel_audit.py).
PARALLEL_MIN_PIXELS = 2e8


def pays(n_demos: int, shard: int, engine: str, workers: int, pixels: float = float("inf")) -> bool:
    """Whether a pass over ``n_demos`` in shards of ``shard`` that decodes ``pixels`` (frames times their size) is
    worth spreading over ``workers`` (always on Ray: asked for)."""
    shards = -(-n_demos // shard)
    return engine == "ray" or workers > 1 and shards >= workers and pixels >= PARALLEL_MIN_PIXELS


@contextmanager
def runner(parallel: bool, engine: str, workers: int, model: str | None, device: str, address: str | None
           ) -> Iterator[Any]:
    """What runs an audit's shards spread over workers (``run(jobs, _run_shard, total)``), started once for its cue
    pass and its decoding pass: ``pool.workers_for(engine)`` -- spawned processes, each loading the model once, or
    Ray actors, an actor pool per pass -- or None (nothing worth spreading: ``Here`` runs the shards)."""
    if not parallel:
        yield None
        return
    with pool.workers_for(engine, workers, _decode_init, (model, device), address) as workers_:
        yield workers_


class Here(pool.Workers):
    """One worker, this process, holding the model the audit already loaded: it runs the shards its workers would,
    on the datasets it was given (``know``) as this process reads them, so that a ``Journal`` can keep them."""

    def __init__(self, ckpt: Any, device: Any):
        self.sets: dict[str, DemoSet] = {}
        super().__init__(1, _here_init, (ckpt, device, self.sets))

    def know(self, *sets: DemoSet) -> None:
        for ds in sets:
            self.sets[_key(where(ds))] = ds


def _here_init(ckpt: Any, device: Any, sets: dict[str, DemoSet]) -> None:
    pool.state.update(ckpt=ckpt, device=device, sets=sets)


class Journal:
    """The shards of an audit done so far, in a folder beside its output (``fsutil.work_dir``), each written as it
    comes back: ``--resume`` runs only the others, and the audit's numbers are those of a run that never stopped
    (the same shards, merged in the same order).  ``key`` says what was audited and how; a folder of another key
    is refused."""

    def __init__(self, folder: Path, key: dict[str, Any]):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / "journal.json"
        key = json.loads(json.dumps(key))
        if path.exists():
            saved = json.loads(path.read_text())
            differs = sorted(k for k in set(saved) | set(key) if saved.get(k) != key.get(k))
            if differs:
                raise DemocheckError(f"{self.folder}: an interrupted audit of other data or options "
                                     f"({', '.join(differs)}); --force starts over")
        else:
            write_json(path, key)

    def run(self, runner_: Any, name: str, jobs: list, total: int,
            on_progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
        """``runner_.run(jobs, _run_shard, ...)`` for the jobs not done yet; the rows of every job, in order."""
        def path(i: int) -> Path:
            return self.folder / f"{name}-{jobs[i][0]:05d}.pkl"

        done = {i: _load(path(i)) for i in range(len(jobs)) if path(i).exists()}
        todo = [i for i in range(len(jobs)) if i not in done]
        before = sum(len(jobs[i][2]) for i in done)
        if before and on_progress:
            on_progress(before, total)

        def keep(k: int, rows: list[dict[str, Any]]) -> None:
            i = todo[k]
            tmp = path(i).with_suffix(".tmp")
            tmp.write_bytes(pickle.dumps(rows, protocol=pickle.HIGHEST_PROTOCOL))
            os.replace(tmp, path(i))
            done[i] = rows

        if todo:
            runner_.run([jobs[i] for i in todo], _run_shard, total,
                        on_progress and (lambda d, n: on_progress(before + d, n)), keep)
        return [row for i in range(len(jobs)) for row in done[i]]


class _OwnClasses(pickle.Unpickler):
    """Unpickles numpy's and democheck's own classes alone: a shard file names no other code to run."""

    SAFE_BUILTINS = {"list", "dict", "tuple", "set", "frozenset", "slice", "range", "complex", "bytearray"}

    def find_class(self, module: str, name: str) -> Any:
        if module.split(".")[0] in ("numpy", "democheck") or module in ("collections", "copyreg") or (
                module == "builtins" and name in self.SAFE_BUILTINS):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not a class a shard holds")


def _load(path: Path) -> list[dict[str, Any]]:
    """A shard's rows as ``Journal`` wrote them (``_OwnClasses``); one clear line where the file is not one."""
    try:
        with path.open("rb") as f:
            return _OwnClasses(f).load()
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, ValueError) as exc:
        raise DemocheckError(f"{path}: not a shard this audit wrote ({exc}); --force starts over") from None


def where(ds: DemoSet) -> dict[str, Any]:
    """How a worker opens ``ds`` as this process reads it."""
    return {"root": str(ds.root), "camera": ds.camera, "image_size": ds.image_size}


def _key(spec: dict[str, Any]) -> tuple:
    return spec["root"], spec["camera"], spec["image_size"]


# How a pass's shards run: (its name in the journal, jobs, total demos, on_progress) -> the rows of every job.
Run = Callable[[str, list, int, Callable[[int, int], None] | None], list[dict[str, Any]]]


def sharded_cues(ds: DemoSet, run: Run, name: str, batch: int,
                 on_progress: Callable[[int, int], None] | None = None) -> TaskPosterior:
    """The cue pass of ``ds`` by ``run``, in shards of ``CUE_SHARD`` cues encoded in batches of ``batch`` (the
    jobs carry it): what one process encoding in batches of ``batch`` gives."""
    eps = ds.episode_indices
    jobs = [(i, {"pass": "cues", "batch": batch, **where(ds)}, eps[s:s + CUE_SHARD])
            for i, s in enumerate(range(0, len(eps), CUE_SHARD))]
    got = sorted(run(name, jobs, len(eps), on_progress), key=lambda r: r["shard"])
    return TaskPosterior.concat([r["post"] for r in got])


def sharded_decoding(ds: DemoSet, ev: Evidence, rows: slice, decoding: dict[str, Scorer], run: Run, name: str,
                     on_progress: Callable[[int, int], None] | None = None,
                     views: dict[str, DemoSet] | None = None) -> dict[str, Any]:
    """The decoding pass of ``ds`` (its rows ``rows`` of the evidence; ``views``: its other cameras, by short
    name) by ``run``: shards of ``decode_shard`` consecutive demos, each decoded with its worker's copy of the model;
    what a consumer keeps per demo (``modelfree.PerDemo``) is merged before it finishes, what it finishes per demo
    is pooled after."""
    eps = ds.episode_indices
    z = ev.task_variables()[rows] if ev.posterior is not None else None
    cameras = {c: where(v) for c, v in (views or {}).items()}
    size = decode_shard(len(eps), ev.model is not None)
    jobs = [(i, {"pass": "decode", **where(ds), "tasks": ds.episodes.loc[eps[s:s + size], "task"].tolist(),
                 "consumers": {k: x.name for k, x in decoding.items()}, "views": cameras,
                 "z": None if z is None else z[s:s + size]},
             eps[s:s + size])
            for i, s in enumerate(range(0, len(eps), size))]
    got = sorted(run(name, jobs, len(eps), on_progress), key=lambda r: r["shard"])
    out = {}
    for key in decoding:
        parts = [r["parts"][key] for r in got]
        out[key] = (type(parts[0]).merged(parts).finish() if isinstance(parts[0], modelfree.PerDemo)
                    else concat([p[1] for p in parts]))
    return out


def consumers(decoding: dict[str, Scorer], ev: Evidence, rows: slice, device: Any) -> dict[str, Any]:
    """One consumer per behaviour key of ``decoding`` (the scorer that decodes for it), for ``rows``."""
    return {key: s.decode(ev, rows, device) for key, s in decoding.items()}


def feed(demo: Demo, got: dict[str, Any], views: dict[str, DemoSet]) -> None:
    """``demo`` to each consumer of ``got`` (by behaviour key); a key on another camera
    (``findings.camera_column``) gets the same demo with that camera's pictures, read from ``views``."""
    mine: dict[str, list] = {}
    for key, c in got.items():
        mine.setdefault(key.partition(CAMERA_MARK)[2], []).append(c)
    for camera, fed in mine.items():
        seen = demo if not camera else replace(demo, frames=views[camera][demo.episode_index].frames)
        for c in fed:
            c.add(seen)


def concat(parts: list) -> Any:
    """Results of one consumer over several shards or datasets, pooled: arrays, (values, reasons) pairs, or
    consumers that merge."""
    if isinstance(parts[0], modelfree.PerDemo):
        return type(parts[0]).merged(parts)
    if isinstance(parts[0], tuple):
        return np.concatenate([p[0] for p in parts]), [r for p in parts for r in p[1]]
    return np.concatenate(parts)


def _decode_init(model: str | None, device: str) -> None:
    import torch

    from democheck.petnet.checkpoint import load_checkpoint

    torch.set_num_threads(1)  # one core per worker process
    pool.state.update(ckpt=load_checkpoint(model, device=device) if model else None, device=device, sets={})


def _run_shard(job: tuple) -> list[dict[str, Any]]:
    """One shard of either pass, in a worker (``_decode_init`` ran first)."""
    return (_cue_shard if job[1]["pass"] == "cues" else _decode_shard)(job)


def _opened(spec: dict[str, Any]) -> DemoSet:
    """The dataset a shard's ``spec`` names (``where``), opened once per worker."""
    from democheck.data import open_dataset

    key = _key(spec)
    sets = pool.state["sets"]
    if key not in sets:
        sets[key] = open_dataset(spec["root"], camera=spec["camera"]).resized(spec["image_size"])
    return sets[key]


def _cue_shard(job: tuple) -> list[dict[str, Any]]:
    index, spec, eps = job
    ds, ckpt = _opened(spec), pool.state["ckpt"]
    parts, batch = [], spec["batch"]
    for s in range(0, len(eps), batch):
        parts.append(encode_demos(ckpt.model, ds, eps[s:s + batch], pool.state["device"]))
        pool.tick(len(parts[-1]))
    return [{"shard": index, "post": TaskPosterior.concat(parts)}]


def _decode_shard(job: tuple) -> list[dict[str, Any]]:
    index, spec, eps = job
    ds = _opened(spec)
    ev = Evidence(episodes=pd.DataFrame({"episode_index": eps, "task": spec["tasks"]}), model=pool.state["ckpt"])
    ev._z = spec["z"]
    decoding = {k: registry.SCORERS[n] for k, n in spec["consumers"].items()}
    got = consumers(decoding, ev, slice(0, len(eps)), pool.state["device"])
    # Every camera's frames decoded into memory reused demo after demo: the consumers keep none of them.
    ds = ds.reusing()
    views = {c: _opened(v).reusing() for c, v in spec["views"].items()}
    for e in eps:
        feed(ds[e], got, views)
        pool.tick()
    parts = {k: c if isinstance(c, modelfree.PerDemo) else ("done", c.finish()) for k, c in got.items()}
    return [{"shard": index, "parts": parts}]
