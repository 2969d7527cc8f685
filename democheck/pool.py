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
from functools import partial
from typing import Any, Callable

# What this process's shards share, set by the ``init`` given to ``run_shards``.
state: dict[str, Any] = {}


def _start(progress: Any, init: Callable[..., None], args: tuple) -> None:
    state.clear()
    state["progress"] = progress
    try:
        init(*args)
    except Exception as exc:  # raised by the first shard instead: a pool would restart a failing worker forever
        state["init_error"] = exc


def _guarded(shard: Callable[[Any], list[dict[str, Any]]], job: Any) -> list[dict[str, Any]]:
    if "init_error" in state:
        raise state["init_error"]
    return shard(job)


def tick(n: int = 1) -> None:
    """``n`` episodes done (reported to the parent's progress bar)."""
    if state.get("progress") is not None:
        state["progress"].put(n)


class Workers:
    """``workers`` spawned processes (each first calls ``init(*args)``), kept for several ``run`` calls -- an
    audit's cue pass and decoding pass share them, and so the model each one loads.  One worker: this process.
    Use as a context manager."""

    def __init__(self, workers: int, init: Callable[..., None], args: tuple):
        self.workers, self._init, self._args = max(int(workers), 1), init, args
        self._pool: Any = None
        self._progress: Any = None

    def __enter__(self) -> "Workers":
        if self.workers <= 1:
            _start(None, self._init, self._args)
        else:
            ctx = mp.get_context("spawn")
            self._progress = ctx.Queue()
            self._pool = ctx.Pool(self.workers, initializer=_start, initargs=(self._progress, self._init, self._args))
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None

    def run(self, jobs: list, shard: Callable[[Any], list[dict[str, Any]]], total: int,
            on_progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
        """``shard(job)`` for every job: the rows of all shards, in job order (see ``run_shards``)."""
        rows: list[dict[str, Any]] = []
        done = 0
        if self._pool is None:
            for job in jobs:
                rows += _guarded(shard, job)
                done += len(job[2])
                if on_progress:
                    on_progress(done, total)
            return rows
        while True:  # ticks of an earlier run that arrived after its results
            try:
                self._progress.get_nowait()
            except queue_mod.Empty:
                break
        pending = self._pool.map_async(partial(_guarded, shard), jobs, chunksize=1)
        while not pending.ready():
            try:
                done = min(done + self._progress.get(timeout=0.2), total)
                if on_progress:
                    on_progress(done, total)
            except queue_mod.Empty:
                pass
        for part in pending.get():
            rows += part
        if on_progress and done < total:
            on_progress(total, total)
        return rows


def run_shards(jobs: list, shard: Callable[[Any], list[dict[str, Any]]], init: Callable[..., None], args: tuple,
               workers: int, total: int, on_progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run ``shard(job)`` for every job in ``workers`` spawned processes (each first calls ``init(*args)``).

    A job is a tuple whose third item lists its episodes.  Each shard writes its own files and returns its
    metadata rows; the rows of all shards are returned, in job order.  One worker runs in this process.
    """
    with Workers(workers, init, args) as pool:
        return pool.run(jobs, shard, total, on_progress)
