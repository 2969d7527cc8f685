"""What the time-aligned checks (``start``, ``end``, ``path``) cost beside decoding: every demo of DATA decoded as
the audit decodes it, fed to their consumer, and the three scored, each timed on one thread.

    python benchmarks/time_checks_cost.py DATA [--camera KEY]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from democheck.audit import timeline
from democheck.audit.evidence import comparison_groups
from democheck.data import open_dataset


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--camera")
    args = ap.parse_args(argv)
    ds = open_dataset(args.data, camera=args.camera)
    consumer, decoding, feeding, frames = timeline.Timeline(), 0.0, 0.0, 0
    for e in ds.episode_indices:
        t0 = time.perf_counter()
        demo = ds[e]
        t1 = time.perf_counter()
        consumer.add(demo)
        decoding, feeding, frames = decoding + t1 - t0, feeding + time.perf_counter() - t1, frames + len(demo)
    groups = comparison_groups(ds.episodes["task"].to_numpy())
    t0 = time.perf_counter()
    for check in (timeline.start, timeline.end, timeline.path):
        check(consumer, groups)
    scoring = time.perf_counter() - t0
    out = {"demos": len(ds.episode_indices), "frames": frames, "decoding_s": round(decoding, 2),
           "consumer_s": round(feeding, 2), "scoring_s": round(scoring, 2),
           "share_of_decoding": round((feeding + scoring) / decoding, 4)}
    print(out)
    return out


if __name__ == "__main__":
    main()
