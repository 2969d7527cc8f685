"""Audit your own LeRobot dataset and drop the suspects.

    python examples/audit_lerobot_dataset.py path/to/dataset --model models/my-petnet

A model reads one camera at one image size: train one on your data first
(`democheck train path/to/dataset --out models/my-petnet`), or use the shipped
model on data that looks like the pushing suite (on other data, without a model, the audit runs its
model-free checks alone and says so). The report folder holds
scores.parquet (one row per demo), suspects.txt (flagged episode indices),
summary.json and report.rrd (open it with `democheck view report/`).
"""

import argparse
from pathlib import Path

import pandas as pd

from democheck.workflows import audit_dataset

ap = argparse.ArgumentParser()
ap.add_argument("dataset", type=Path)
ap.add_argument("--model", type=Path, default=None, help="default: the shipped petnet-push-v1")
ap.add_argument("--out", type=Path, default=Path("report"))
ap.add_argument("--camera", default=None)
args = ap.parse_args()

drop = args.out.with_name(args.out.name + ".drop.json")
summary = audit_dataset(args.dataset, args.out, model=args.model, camera=args.camera, force=True, drop_list=drop)
scores = pd.read_parquet(args.out / "scores.parquet")
flag = summary["flag"]
print(f"{summary['demos']} demos, {summary['flagged']} flagged at fpr {flag['fpr']:g} "
      f"(about {flag['expected_false_flags']:.1f} of them expected clean)")
for w in summary["warnings"]:
    print("warning:", w)
shown = [c for c in ("rank", "episode_index", "task", "task_uncertainty", "consistency", "action_error", "motion",
                     "idle", "suspicion", "is_anomaly", "reason") if c in scores]
print(scores.head(10)[shown])

# The episodes to drop, as a dataset-editing tool takes them, e.g.
#   lerobot-edit-dataset --operation.type delete_episodes --operation.episode_indices "$(cat report.drop.json)"
print(f"drop {drop.read_text().strip()} ({summary['flagged']} of {len(scores)} episodes)")
