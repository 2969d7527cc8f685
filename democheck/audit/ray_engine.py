"""The audit's cue pass and decoding pass on Ray Data (``democheck audit --engine ray``), for datasets beyond
one machine.

The same shards as the local engine's workers (``run.cue_posteriors``: ``CUE_SHARD`` cues;
``run.parallel_decoding``: ``SHARD`` consecutive demos, the same consumers, merged the same way), so the scores
are the same bit for bit; only who runs them changes.  Each pass's shards become a Ray dataset of one row each,
``map_batches`` runs them in an actor pool (each actor loads the model once, one CPU each), and the results
stream back to this process, which merges them and scores as ever.  The per-task scores (consistency, the
calibration within each task) stay here: they read one small array per demo.  Every node must have democheck
installed and read the dataset at the same path (a shared filesystem).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from democheck.errors import DemocheckError

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
    """A Ray actor: the model loaded once, then shards of either pass run one at a time (``run._run_shard``)."""

    def __init__(self, model: str | None, device: str):
        from democheck.audit import run

        run._decode_init(model, device)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        from democheck.audit import run

        results = [run._run_shard(held.value)[0] for held in batch["job"]]
        return {"shard": np.array([r["shard"] for r in results]),
                "result": np.array([_Held(r) for r in results], dtype=object)}


class Session:
    """Ray, reached (or a local instance with ``workers`` CPUs started) for one audit's passes, and shut down
    after when it was started here.  ``run`` has the interface of the local engine's workers; each call runs
    its shards in an actor pool of its own (each actor loads the model once per pass).  Use as a context
    manager: entering it without Ray installed says how to get it."""

    def __init__(self, model: str | None, device: str, workers: int, address: str | None):
        self.model, self.device, self.workers, self.address = model, device, max(int(workers), 1), address
        self._started = False

    def __enter__(self) -> "Session":
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

        logging.getLogger("ray.data").setLevel(logging.WARNING)  # democheck's own bar reports the progress
        ray.data.DataContext.get_current().enable_progress_bars = False
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._started:
            _ray().shutdown()

    def run(self, jobs: list[tuple], total: int, on_progress: Callable[[int, int], None] | None = None
            ) -> list[dict[str, Any]]:
        """``run._run_shard(job)`` of every job, by an actor pool of ``workers`` actors: the shards' rows."""
        ray = _ray()
        sizes = {job[0]: len(job[2]) for job in jobs}
        done, out = 0, []
        items = [{"job": _Held(job)} for job in jobs]
        shards = ray.data.from_items(items, override_num_blocks=max(len(items), 1))
        ran = shards.map_batches(_Worker, fn_constructor_args=(self.model, self.device), batch_size=1,
                                 compute=ray.data.ActorPoolStrategy(size=self.workers), num_cpus=1)
        for batch in ran.iter_batches(batch_size=1, batch_format="numpy"):
            for shard, held in zip(batch["shard"], batch["result"]):
                out.append(held.value)
                done += sizes[int(shard)]
                if on_progress:
                    on_progress(done, total)
        return out
