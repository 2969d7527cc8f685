"""The audit with one worker process and with two: the same scores, and how much faster.

    python benchmarks/parallel_audit.py DATASET [MODEL]

Audits DATASET (with MODEL, default the shipped one) twice, ``workers=1`` and ``workers=2``, checks that every
column of the two score tables is identical, and prints the decoding pass's wall time for each and their
ratio (the cue pass stays in one process).
"""

import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from democheck.audit.run import audit  # noqa: E402
from democheck.data import open_dataset  # noqa: E402
from democheck.petnet.checkpoint import load_checkpoint  # noqa: E402

if __name__ == "__main__":  # spawned workers import this file again
    ds = open_dataset(sys.argv[1])
    ckpt = load_checkpoint(sys.argv[2] if len(sys.argv) > 2 else None)
    runs = {}
    for workers in (1, 2):
        t0 = time.perf_counter()
        table, summary = audit(ds, ckpt, workers=workers)
        runs[workers] = (table, time.perf_counter() - t0, summary["timing"])
    a, b = runs[1][0], runs[2][0]
    differ = [c for c in a.columns if c not in ("sigma", "mu") and not a[c].equals(b[c])]
    print(f"{ds.root}: {len(ds)} demos; identical scores: {not differ}" + (f" (differ: {differ})" if differ else ""))
    one, two = runs[1][2]["actions_s"], runs[2][2]["actions_s"]
    print(f"decoding pass: 1 worker {one:.1f} s, 2 workers {two:.1f} s, ratio {one / two:.2f}; "
          f"whole audit {runs[1][1]:.1f} s vs {runs[2][1]:.1f} s")
