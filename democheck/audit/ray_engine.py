"""The audit's decoding pass on Ray Data (``democheck audit --engine ray``), for datasets beyond one machine.

The same shards as the local engine (``run.parallel_decoding``: ``SHARD`` consecutive demos, the same consumers,
merged the same way), so the scores are the same bit for bit; only who runs them changes.  The shards become a
Ray dataset of one row each, ``map_batches`` runs them in an actor pool (each actor loads the model once, one
CPU each), and the results stream back to this process, which merges them and scores as ever.  The cue pass and
the per-task scores (consistency, the calibration within each task) stay here: they read one small array per
demo.  Every node must have democheck installed and read the dataset at the same path (a shared filesystem).
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


class _Decoder:
    """A Ray actor: the model loaded once, then shards decoded one at a time (``run._decode_shard``)."""

    def __init__(self, model: str | None, device: str):
        from democheck.audit import run

        run._decode_init(model, device)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        from democheck.audit import run

        results = [run._decode_shard(held.value)[0] for held in batch["job"]]
        return {"shard": np.array([r["shard"] for r in results]),
                "result": np.array([_Held(r) for r in results], dtype=object)}


def run_shards(jobs: list[tuple], model: str | None, device: str, workers: int, address: str | None,
               on_progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """What ``pool.run_shards(jobs, run._decode_shard, ...)`` returns, computed by ``workers`` Ray actors on the
    cluster at ``address`` (None: a local Ray instance with ``workers`` CPUs, started and stopped here)."""
    ray = _ray()
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                     log_to_driver=False, logging_level="ERROR")
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise DemocheckError(f"--engine ray: could not reach Ray at {address or 'a local instance'} ({exc})"
                                 ) from None
    try:
        import logging

        logging.getLogger("ray.data").setLevel(logging.WARNING)  # democheck's own bar reports the progress
        ray.data.DataContext.get_current().enable_progress_bars = False
        sizes = {job[0]: len(job[2]) for job in jobs}
        total, done, out = sum(sizes.values()), 0, []
        items = [{"job": _Held(job)} for job in jobs]
        shards = ray.data.from_items(items, override_num_blocks=max(len(items), 1))
        decoded = shards.map_batches(_Decoder, fn_constructor_args=(model, device), batch_size=1,
                                     compute=ray.data.ActorPoolStrategy(size=max(workers, 1)), num_cpus=1)
        for batch in decoded.iter_batches(batch_size=1, batch_format="numpy"):
            for shard, held in zip(batch["shard"], batch["result"]):
                out.append(held.value)
                done += sizes[int(shard)]
                if on_progress:
                    on_progress(done, total)
        return out
    finally:
        if started:
            ray.shutdown()
