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

from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numpy as np
import pandas as pd

from democheck import pool
from democheck.audit import dynamics, modelfree, scorers as registry
from democheck.audit.action_error import ACTION_BATCH
from democheck.audit.evidence import Evidence, Scorer
from democheck.data.demo import DemoSet
from democheck.petnet.encode import encode_demos
from democheck.petnet.posterior import TaskPosterior

CUE_BATCH = 256  # cues encoded at a time, in one process and in a worker alike
# Cues per shard of a parallel cue pass: whole batches of ``CUE_BATCH``, as one process encodes them.
CUE_SHARD = 4 * CUE_BATCH
# Demos per shard of a parallel decoding pass: a multiple of the action error's batch, so that every batch the
# controller sees holds the same demos as in one process (and the numbers are the same), and of the dynamics
# check's block (``dynamics.DYNAMICS_BLOCK``), for the same reason.
SHARD = 4 * ACTION_BATCH
assert SHARD % dynamics.DYNAMICS_BLOCK == 0 or SHARD < dynamics.DYNAMICS_BLOCK, "see dynamics.DynamicsFit.merged"
# Below this many shards per worker, starting the workers (each imports torch and loads the model, ~2 s) costs
# more than it saves: on push-v1, 168 demos took 2.1 s in one process and 3.4 s in two, 768 demos 10.1 s and
# 7.5 s, 6,048 demos 78.6 s and 47.8 s (identical scores each time; benchmarks/parallel_audit.py).
PARALLEL_MIN_SHARDS = 2


def pays(n_demos: int, shard: int, engine: str, workers: int) -> bool:
    """Whether a pass over ``n_demos`` in shards of ``shard`` is worth spreading (always on Ray: asked for)."""
    return engine == "ray" or workers > 1 and n_demos >= PARALLEL_MIN_SHARDS * shard * workers


@contextmanager
def runner(parallel: bool, engine: str, workers: int, model: str | None, device: str, address: str | None
           ) -> Iterator[Any]:
    """What runs an audit's shards (``run(jobs, _run_shard, total)``), started once for its cue pass and its
    decoding pass: ``pool.workers_for(engine)`` -- spawned processes, each loading the model once, or Ray actors,
    an actor pool per pass -- or None (this process, shard-free)."""
    if not parallel:
        yield None
        return
    with pool.workers_for(engine, workers, _decode_init, (model, device), address) as workers_:
        yield workers_


def where(ds: DemoSet) -> dict[str, Any]:
    """How a worker opens ``ds`` as this process reads it."""
    return {"root": str(ds.root), "camera": ds.camera, "image_size": ds.image_size}


def parallel_cues(ds: DemoSet, runner_: Any, batch: int, on_progress: Callable[[int, int], None] | None = None
                  ) -> TaskPosterior:
    """The cue pass of ``ds`` by ``runner_``'s workers, in shards of ``CUE_SHARD`` cues encoded in batches of
    ``batch`` (the jobs carry it): what one process encoding in batches of ``batch`` gives."""
    eps = ds.episode_indices
    jobs = [(i, {"pass": "cues", "batch": batch, **where(ds)}, eps[s:s + CUE_SHARD])
            for i, s in enumerate(range(0, len(eps), CUE_SHARD))]
    got = sorted(runner_.run(jobs, _run_shard, len(eps), on_progress), key=lambda r: r["shard"])
    return TaskPosterior.concat([r["post"] for r in got])


def parallel_decoding(ds: DemoSet, ev: Evidence, rows: slice, decoding: dict[str, Scorer], runner_: Any,
                      on_progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """The decoding pass of ``ds`` (its rows ``rows`` of the evidence) by ``runner_``'s workers: each decodes
    shards of ``SHARD`` consecutive demos with its own copy of the model; what a consumer keeps per demo
    (``modelfree.PerDemo``) is merged before it finishes, what it finishes per demo is pooled after."""
    eps = ds.episode_indices
    z = ev.task_variables()[rows] if ev.posterior is not None else None
    jobs = [(i, {"pass": "decode", **where(ds), "tasks": ds.episodes.loc[eps[s:s + SHARD], "task"].tolist(),
                 "names": [x.name for x in decoding.values()], "z": None if z is None else z[s:s + SHARD]},
             eps[s:s + SHARD])
            for i, s in enumerate(range(0, len(eps), SHARD))]
    got = sorted(runner_.run(jobs, _run_shard, len(eps), on_progress), key=lambda r: r["shard"])
    out = {}
    for key in decoding:
        parts = [r["parts"][key] for r in got]
        out[key] = (type(parts[0]).merged(parts).finish() if isinstance(parts[0], modelfree.PerDemo)
                    else concat([p[1] for p in parts]))
    return out


def consumers(scorers, ev: Evidence, rows: slice, device: Any) -> dict[str, Any]:
    """One consumer per behaviour key of ``scorers`` (scorers that share a key share it), for ``rows``."""
    out: dict[str, Any] = {}
    for s in scorers:
        if s.source not in out:
            out[s.source] = s.decode(ev, rows, device)
    return out


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

    key = (spec["root"], spec["camera"], spec["image_size"])
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
    got = consumers([registry.SCORERS[n] for n in spec["names"]], ev, slice(0, len(eps)), pool.state["device"])
    for e in eps:
        demo = ds[e]
        for c in got.values():
            c.add(demo)
        pool.tick()
    parts = {k: c if isinstance(c, modelfree.PerDemo) else ("done", c.finish()) for k, c in got.items()}
    return [{"shard": index, "parts": parts}]
