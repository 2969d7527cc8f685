"""Workers for work that is parallel over episodes (generation, probes, rollouts, the audit's passes).

``run_shards`` runs ``shard(job)`` for every job in ``spawn`` processes (never
``fork``: a process may already hold a GL context).  Each process first calls
``init(*args)``, which puts what its shards share -- a simulator, a model --
into ``state``; a shard reads it from there and calls ``tick()`` after each
episode so the parent's progress bar moves.  ``Workers`` keeps the processes
for several runs.

``RayWorkers`` runs the same jobs on Ray Data instead, for datasets beyond one
machine (``democheck audit --engine ray``, ``democheck synth --engine ray``):
the jobs become a Ray dataset of one row each, ``map_batches`` runs them in an
actor pool (each actor calls ``init`` once, one CPU each), and the rows come
back in job order -- the same rows as the local workers', so the same scores
and files.  Every node must have democheck installed and read the dataset (and,
for generation, the output's staging folder) at the same path: a shared
filesystem.  ``pip install 'democheck[ray]'``.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import threading
from functools import partial
from typing import Any, Callable, Iterator

import numpy as np

from democheck.errors import DemocheckError

def usable_cores(cpu_max: str = "/sys/fs/cgroup/cpu.max") -> int:
    """The cores this process may use: the machine's, less those its CPU affinity leaves out, less what a
    container's CPU quota (cgroup v2 ``cpu.max``) allows.  torch's default thread count is the machine's cores,
    which on a container given two of many runs each step many times slower than one thread per usable core."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        quota, period = open(cpu_max).read().split()[:2]
        if quota != "max":
            cores = min(cores, max(1, int(float(quota) / float(period))))
    except (OSError, ValueError):
        pass
    return max(1, cores)


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


class _Ticks:
    """``tick``'s queue in this process (one worker): the progress moves with each episode."""

    def __init__(self, on_progress: Callable[[int, int], None] | None, total: int):
        self.on_progress, self.total, self.done = on_progress, total, 0

    def put(self, n: int) -> None:
        self.reach(self.done + n)

    def reach(self, done: int) -> None:
        done = min(done, self.total)
        if done > self.done:
            self.done = done
            if self.on_progress:
                self.on_progress(done, self.total)


@contextlib.contextmanager
def _workers_ignore_ctrl_c() -> Iterator[None]:
    """Processes started inside never see Ctrl-C: SIGINT is blocked while they start, and a blocked signal stays
    blocked in a child across exec.  The terminal sends SIGINT to the whole process group; only this process should
    answer it -- with one line -- while the pool stops the workers.  Here a Ctrl-C during the start is held, not
    lost, and answered as soon as the workers have started.  The mask holds only this thread: another thread of
    this process (a progress bar's, a queue's) may take the signal, and Python would then raise it here, half-way
    through starting the pool, whose started workers nobody would stop.  So this process's handler only notes the
    press until the workers have started."""
    held: list[int] = []
    main = threading.current_thread() is threading.main_thread()
    handler = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum)) if main else None
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)
        if main:
            signal.signal(signal.SIGINT, handler)
            if held:
                signal.raise_signal(signal.SIGINT)


class Workers:
    """``workers`` spawned processes (each first calls ``init(*args)``), kept for several ``run`` calls -- an
    audit's cue pass and decoding pass share them, and so the model each one loads.  One worker: this process.
    Use as a context manager."""

    def __init__(self, workers: int, init: Callable[..., None], args: tuple):
        self.workers, self._init, self._args = max(int(workers), 1), init, args
        self._pool: Any = None
        self._progress: Any = None
        self._state: dict[str, Any] = {}

    def __enter__(self) -> "Workers":
        if self.workers <= 1:
            _start(None, self._init, self._args)
            self._state = dict(state)  # put back at each run: another pool in this process may have used ``state``
        else:
            ctx = mp.get_context("spawn")
            self._progress = ctx.Queue()
            with _workers_ignore_ctrl_c():
                self._pool = ctx.Pool(self.workers, initializer=_start,
                                      initargs=(self._progress, self._init, self._args))
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None

    def run(self, jobs: list, shard: Callable[[Any], list[dict[str, Any]]], total: int,
            on_progress: Callable[[int, int], None] | None = None,
            on_result: Callable[[int, list[dict[str, Any]]], None] | None = None) -> list[dict[str, Any]]:
        """``shard(job)`` for every job: the rows of all shards, in job order (see ``run_shards``); ``on_result(i,
        rows)`` as each job ``i`` finishes."""
        results: list[Any] = [None] * len(jobs)
        done = 0
        if self._pool is None:  # each episode's tick moves the progress at once; a job's end, to its episodes
            ticks = _Ticks(on_progress, total)
            state.clear()
            state.update(self._state, progress=ticks)
            for i, job in enumerate(jobs):
                results[i] = _guarded(shard, job)
                if on_result:
                    on_result(i, results[i])
                done += len(job[2])
                ticks.reach(done)
            return [row for rows in results for row in rows]
        while True:  # ticks of an earlier run that arrived after its results
            try:
                self._progress.get_nowait()
            except queue_mod.Empty:
                break
        pending = self._pool.imap_unordered(partial(_numbered, shard), list(enumerate(jobs)), chunksize=1)
        for _ in jobs:
            while True:
                try:
                    i, rows = pending.next(timeout=0.2)
                    break
                except mp.TimeoutError:
                    ticked = done
                    while True:
                        try:
                            done = min(done + self._progress.get_nowait(), total)
                        except queue_mod.Empty:
                            break
                    if on_progress and done > ticked:
                        on_progress(done, total)
            results[i] = rows
            if on_result:
                on_result(i, rows)
        if on_progress and done < total:
            on_progress(total, total)
        return [row for rows in results for row in rows]


def _numbered(shard: Callable[[Any], list[dict[str, Any]]], item: tuple[int, Any]) -> tuple[int, list]:
    return item[0], _guarded(shard, item[1])


def run_shards(jobs: list, shard: Callable[[Any], list[dict[str, Any]]], init: Callable[..., None], args: tuple,
               workers: int, total: int, on_progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run ``shard(job)`` for every job in ``workers`` spawned processes (each first calls ``init(*args)``).

    A job is a tuple whose third item lists its episodes.  Each shard writes its own files and returns its
    metadata rows; the rows of all shards are returned, in job order.  One worker runs in this process.
    """
    with Workers(workers, init, args) as pool:
        return pool.run(jobs, shard, total, on_progress)


ENGINES = ("local", "ray")


def check_engine(engine: str) -> None:
    """One clear line for an ``--engine`` that is not one of ``ENGINES``."""
    if engine not in ENGINES:
        raise DemocheckError(f"--engine {engine!r}: one of {', '.join(ENGINES)}")


def workers_for(engine: str, workers: int, init: Callable[..., None], args: tuple, address: str | None = None
                ) -> "Workers | RayWorkers":
    """The (unentered) workers of ``engine``: this machine's processes ("local") or Ray actors ("ray", the
    cluster at ``address``; default: a local instance).  Both run the same jobs to the same rows."""
    check_engine(engine)
    return RayWorkers(workers, init, args, address) if engine == "ray" else Workers(workers, init, args)


def run_on(engine: str, jobs: list, shard: Callable[[Any], list[dict[str, Any]]], init: Callable[..., None],
           args: tuple, workers: int, total: int, on_progress: Callable[[int, int], None] | None = None,
           address: str | None = None) -> list[dict[str, Any]]:
    """``run_shards`` on the workers of ``engine`` (``workers_for``): the same rows."""
    with workers_for(engine, workers, init, args, address) as runner:
        return runner.run(jobs, shard, total, on_progress)


INSTALL = "pip install 'democheck[ray]'"


def _ray():
    try:
        import ray
        import ray.data  # noqa: F401  (Ray without its data library cannot run the pass)
    except ImportError:
        raise DemocheckError(f"--engine ray needs Ray Data, which is not installed: {INSTALL}") from None
    return ray


class _Held:
    """One shard's job or result in a Ray dataset's row: an opaque object, which Ray serialises as it serialises
    any task argument (so nothing is converted to Arrow on the way)."""

    def __init__(self, value: Any):
        self.value = value


class _Worker:
    """A Ray actor: ``init(*args)`` once (a model, a simulator), then jobs run one at a time by ``shard``, as a
    spawned worker runs them."""

    def __init__(self, init: Callable[..., None], args: tuple, shard: Callable[[Any], list[dict[str, Any]]]):
        _start(None, init, args)
        self.shard = shard

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        done = [(held.value[0], _guarded(self.shard, held.value[1])) for held in batch["job"]]
        return {"position": np.array([p for p, _ in done]),
                "result": np.array([_Held(rows) for _, rows in done], dtype=object)}


class RayWorkers:
    """Ray, reached (or a local instance with ``workers`` CPUs started) for one command, and shut down after when
    it was started here.  The interface of ``pool.Workers``: ``run(jobs, shard, total)`` gives the rows of every
    job in job order; each call runs its jobs in an actor pool of its own, ``workers`` actors of one CPU, each
    first calling ``init(*args)`` (so the model or simulator is set up once per actor and call).  Use as a context
    manager: entering it without Ray installed says how to get it."""

    def __init__(self, workers: int, init: Callable[..., None], args: tuple, address: str | None = None):
        self.workers, self.init, self.args, self.address = max(int(workers), 1), init, args, address
        self._started = False

    def __enter__(self) -> "RayWorkers":
        ray = _ray()
        if not ray.is_initialized():
            try:
                ray.init(address=self.address, num_cpus=None if self.address else self.workers,
                         include_dashboard=False, log_to_driver=False, logging_level="ERROR")
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise DemocheckError(f"--engine ray: could not reach Ray at {self.address or 'a local instance'} "
                                     f"({exc})") from None
            self._started = True
        import logging

        logging.getLogger("ray.data").setLevel(logging.ERROR)  # democheck's own bar reports the progress
        ray.data.DataContext.get_current().enable_progress_bars = False
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._started:
            _ray().shutdown()

    def run(self, jobs: list[tuple], shard: Callable[[Any], list[dict[str, Any]]], total: int,
            on_progress: Callable[[int, int], None] | None = None,
            on_result: Callable[[int, list[dict[str, Any]]], None] | None = None) -> list[dict[str, Any]]:
        """``shard(job)`` of every job (a tuple whose third item lists its episodes) by the actor pool: the rows
        of all jobs, in job order; ``on_result(i, rows)`` as each job ``i`` comes back."""
        ray = _ray()
        done, results = 0, [None] * len(jobs)
        items = [{"job": _Held((i, job))} for i, job in enumerate(jobs)]
        shards = ray.data.from_items(items, override_num_blocks=max(len(items), 1))
        ran = shards.map_batches(_Worker, fn_constructor_args=(self.init, self.args, shard), batch_size=1,
                                 compute=ray.data.ActorPoolStrategy(size=self.workers), num_cpus=1)
        for batch in ran.iter_batches(batch_size=1, batch_format="numpy"):
            for position, held in zip(batch["position"], batch["result"]):
                results[int(position)] = held.value
                if on_result:
                    on_result(int(position), held.value)
                done += len(jobs[int(position)][2])
                if on_progress:
                    on_progress(min(done, total), total)
        return [row for rows in results for row in rows]
