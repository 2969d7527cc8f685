"""LeRobot's own loader on a dataset ``democheck clean`` wrote: it opens, and every sampled frame of a kept
episode -- image, state, action, task -- is what LeRobot reads at the same place of the source dataset.

    HF_HUB_OFFLINE=1 /tmp/peers/venv-lerobot/bin/python benchmarks/lerobot_reads_clean.py SOURCE CLEAN --dropped "[3, 17]" \
        [--samples 3] [--backend pyav]

Runs in LeRobot's own virtual environment (LeRobot pins an older torch; ``../shared/peers/setup_peers.sh``
builds one), never in democheck's.  Kept episodes are matched by order: CLEAN's episode i is the i-th of
SOURCE's episodes that CLEAN's report did not drop, which is what ``democheck clean`` promises; the dropped
ones are read from CLEAN's ``meta/info.json`` totals alone.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", type=Path)
    ap.add_argument("clean", type=Path)
    ap.add_argument("--dropped", required=True, help="the dropped episode indices, as [3, 17]")
    ap.add_argument("--samples", type=int, default=3, help="frames compared per kept episode")
    ap.add_argument("--backend", default="pyav")
    args = ap.parse_args()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = LeRobotDataset("local/source", root=args.source, video_backend=args.backend)
    out = LeRobotDataset("local/clean", root=args.clean, video_backend=args.backend)
    dropped = set(json.loads(args.dropped))
    kept = [e for e in range(src.meta.total_episodes) if e not in dropped]
    assert out.meta.total_episodes == len(kept), (out.meta.total_episodes, len(kept))
    rng = np.random.default_rng(0)
    worst, compared = 0.0, 0
    for new, old in enumerate(kept):
        a0, a1 = int(src.meta.episodes["dataset_from_index"][old]), int(src.meta.episodes["dataset_to_index"][old])
        b0, b1 = int(out.meta.episodes["dataset_from_index"][new]), int(out.meta.episodes["dataset_to_index"][new])
        assert a1 - a0 == b1 - b0, (new, old)
        for f in sorted({0, a1 - a0 - 1, *rng.integers(0, a1 - a0, args.samples).tolist()}):
            x, y = src[a0 + f], out[b0 + f]
            assert int(y["episode_index"]) == new and int(y["frame_index"]) == int(x["frame_index"])
            assert x["task"] == y["task"]
            for key in x:
                if hasattr(x[key], "shape") and key not in ("episode_index", "index", "task_index"):
                    diff = float((x[key].float() - y[key].float()).abs().max()) if x[key].numel() else 0.0
                    worst = max(worst, diff)
            compared += 1
    print(f"LeRobot opens {args.clean}: {out.meta.total_episodes} episodes, {len(out)} frames "
          f"(source {src.meta.total_episodes}, {len(src)}); {compared} sampled frames of kept episodes compared "
          f"with the source: largest difference {worst:g}")
    sys.exit(0 if worst == 0 else 1)


if __name__ == "__main__":
    main()
