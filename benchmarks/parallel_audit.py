"""The audit with one worker process, with two, and on Ray Data: the same scores, and how much faster.

    python benchmarks/parallel_audit.py DATASET [MODEL] [--ray]

Audits DATASET (with MODEL, default the shipped one) with ``workers=1`` and ``workers=2`` (and with ``--ray``
on a local 2-CPU Ray instance, ``engine="ray"``, its start-up included), checks that every column of the score
tables is identical to the one-worker table, and prints the decoding pass's wall time for each and their
ratios (the cue pass stays in one process).
"""

import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from democheck.audit.run import audit  # noqa: E402
from democheck.data import open_dataset  # noqa: E402
from democheck.petnet.checkpoint import load_checkpoint  # noqa: E402

if __name__ == "__main__":  # spawned workers import this file again
    args = [a for a in sys.argv[1:] if a != "--ray"]
    ds = open_dataset(args[0])
    ckpt = load_checkpoint(args[1] if len(args) > 1 else None)
    setups = {"1 worker": (1, "local"), "2 workers": (2, "local")}
    if "--ray" in sys.argv:
        setups["Ray, 2 actors"] = (2, "ray")
    runs = {}
    for name, (workers, engine) in setups.items():
        t0 = time.perf_counter()
        table, summary = audit(ds, ckpt, workers=workers, engine=engine)
        runs[name] = (table, time.perf_counter() - t0, summary["timing"])
    base = runs["1 worker"]
    print(f"{ds.root}: {len(ds)} demos")
    for name, (table, wall, timing) in runs.items():
        differ = [c for c in base[0].columns if c not in ("sigma", "mu") and not base[0][c].equals(table[c])]
        print(f"  {name:<14} decoding {timing['actions_s']:6.1f} s (x{base[2]['actions_s'] / timing['actions_s']:.2f}),"
              f" whole audit {wall:6.1f} s; scores identical to 1 worker: {not differ}"
              + (f" (differ: {differ})" if differ else ""))
