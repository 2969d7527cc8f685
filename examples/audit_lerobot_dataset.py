"""Audit your own LeRobot dataset and drop the suspects.

    python examples/audit_lerobot_dataset.py path/to/dataset --model models/my-petnet

A model reads one camera at one image size: train one on your data first
(`democheck train path/to/dataset --out models/my-petnet`), or use the shipped
model on data that looks like the pushing suite. The report folder holds
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

summary = audit_dataset(args.dataset, args.out, model=args.model, camera=args.camera, force=True)
scores = pd.read_parquet(args.out / "scores.parquet")
print(f"{summary['demos']} demos, {summary['flagged']} flagged")
print(scores.head(10)[["rank", "episode_index", "task", "task_uncertainty", "consistency", "action_error", "suspicion",
                        "is_anomaly", "reason"]])

# The episodes to keep: everything not flagged. Feed this list to your dataset-editing tool.
keep = sorted(scores.loc[~scores["is_anomaly"], "episode_index"])
print(f"keep {len(keep)} of {len(scores)} episodes; dropped: {(args.out / 'suspects.txt').read_text().split()}")
