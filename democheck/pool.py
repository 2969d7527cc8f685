"""Worker processes (a pool) for work that is parallel over episodes (generation, probes, rollouts).

``run_shards`` runs ``shard(job)`` for every job in ``spawn`` processes (never
``fork``: a process may already hold a GL context).  Each process first calls
``init(*args)``, which puts what its shards share -- a simulator, a model --
into ``state``; a shard reads it from there and calls ``tick()`` after each
episode so the parent's progress bar moves.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queue_mod
from typing import Any, Callable

# What this process's shards share, set by the ``init`` given to ``run_shards``.
state: dict[str, Any] = {}


def _start(progress: Any, init: Callable[..., None], args: tuple) -> None:
    state.clear()
    state["progress"] = progress
    init(*args)


def tick() -> None:
    """One episode done (reported to the parent's progress bar)."""
    if state.get("progress") is not None:
        state["progress"].put(1)


def run_shards(jobs: list, shard: Callable[[Any], list[dict[str, Any]]], init: Callable[..., None], args: tuple,
               workers: int, total: int, on_progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run ``shard(job)`` for every job in ``workers`` spawned processes (each first calls ``init(*args)``).

    A job is a tuple whose third item lists its episodes.  Each shard writes its own files and returns its
    metadata rows; the rows of all shards are returned, in job order.  One worker runs in this process.
    """
    rows: list[dict[str, Any]] = []
    done = 0
    if workers <= 1:
        _start(None, init, args)
        for job in jobs:
            rows += shard(job)
            done += len(job[2])
            if on_progress:
                on_progress(done, total)
        return rows
    ctx = mp.get_context("spawn")
    progress_q = ctx.Queue()
    with ctx.Pool(workers, initializer=_start, initargs=(progress_q, init, args)) as pool:
        pending = pool.map_async(shard, jobs, chunksize=1)
        while not pending.ready() or not progress_q.empty():
            try:
                done += progress_q.get(timeout=0.2)
                if on_progress:
                    on_progress(done, total)
            except queue_mod.Empty:
                pass
        for part in pending.get():
            rows += part
    return rows
