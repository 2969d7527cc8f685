"""What the checks of how a demo goes in time (``start``, ``end``, ``path``), of what it moved (``moved``) and of its
gripper (``grasps``) cost beside decoding: every demo of DATA decoded as the audit decodes it, fed to their
consumers, and the checks scored, each timed on one thread.  The grasps read the action traces the audit keeps for its other action checks anyway,
so only their scoring is theirs.

    python benchmarks/time_checks_cost.py DATA [--camera KEY]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from democheck.audit import grasps, modelfree, moved, timeline
from democheck.audit.evidence import comparison_groups
from democheck.data import open_dataset


SHARED = {"grasps"}  # checks whose consumer the audit feeds for other checks too: their feeding is not theirs


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--camera")
    args = ap.parse_args(argv)
    ds = open_dataset(args.data, camera=args.camera)
    checks = {"time": (timeline.Timeline(), (timeline.start, timeline.end, timeline.path)),
              "moved": (moved.MovedStats(), (moved.moved,)),
              "grasps": (modelfree.ActionTraces(), (grasps.grasps,))}
    feeding = dict.fromkeys(checks, 0.0)
    decoding, frames = 0.0, 0
    for e in ds.episode_indices:
        t0 = time.perf_counter()
        demo = ds[e]
        decoding, frames = decoding + time.perf_counter() - t0, frames + len(demo)
        for name, (consumer, _) in checks.items():
            t1 = time.perf_counter()
            consumer.add(demo)
            feeding[name] += (time.perf_counter() - t1) * (name not in SHARED)
    groups = comparison_groups(ds.episodes["task"].to_numpy())
    out = {"demos": len(ds.episode_indices), "frames": frames, "decoding_s": round(decoding, 2)}
    for name, (consumer, scorers) in checks.items():
        t0 = time.perf_counter()
        for check in scorers:
            check(consumer, groups)
        cost = feeding[name] + time.perf_counter() - t0
        out[f"{name}_s"], out[f"{name}_share_of_decoding"] = round(cost, 2), round(cost / decoding, 4)
    print(out)
    return out


if __name__ == "__main__":
    main()
