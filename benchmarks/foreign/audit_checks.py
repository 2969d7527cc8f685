"""The audit without a model against its own checks and a two-line linter, on a labelled dataset it did not make:

    python benchmarks/foreign/audit_checks.py DATASET [--labels DATASET.labels.csv] [--out OUT]

runs ``democheck audit DATASET --no-model`` (into OUT, default DATASET-audit beside it) and prints, per planted
kind against the clean demos: the AUROC of the ranking (``suspicion``), of its best single check (named), and of
the two-line linter (``run.linter``: mean |action| and mean |change of action|, robust z); then the clean demos
flagged at the audit's --fpr 0.01 with the binomial interval of that rate, and the share of each kind flagged.
``OUT/checks.json`` keeps the numbers.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import binom

from democheck.audit.metrics import detection

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run import linter  # noqa: E402

CHECKS = ("motion", "idle", "jerk", "saturation", "duplicate", "dynamics", "lag", "timing", "frozen_video",
          "frame_jump", "frozen_state", "view", "colours", "outcome", "coupling")


def auroc(bad: np.ndarray, clean: np.ndarray) -> float:
    return detection(np.r_[np.ones(len(bad), bool), np.zeros(len(clean), bool)], np.r_[bad, clean])["auroc"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--labels", type=Path)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    labels_csv = args.labels or args.dataset.with_name(args.dataset.name + ".labels.csv")
    out = args.out or args.dataset.with_name(args.dataset.name + "-audit")
    subprocess.run([sys.executable, "-m", "democheck", "audit", str(args.dataset), "--out", str(out), "--no-model",
                    "--force"], check=True, capture_output=True)
    table = pd.read_parquet(out / "scores.parquet").set_index("episode_index")
    labels = pd.read_csv(labels_csv).set_index("episode_index")["label"]
    table["label"] = labels[table.index].to_numpy()
    table["linter"] = linter(args.dataset)[table.index].to_numpy()
    clean = (table["label"] == "clean").to_numpy()
    results = {}
    for kind in sorted(set(table["label"]) - {"clean"}):
        bad = (table["label"] == kind).to_numpy()
        checks = {c: auroc(table[c].to_numpy(np.float64)[bad], table[c].to_numpy(np.float64)[clean])
                  for c in CHECKS if c in table and np.isfinite(table[c]).any()}
        best = max(checks, key=checks.get)
        results[kind] = {"ranking": round(auroc(table["suspicion"].to_numpy()[bad], table["suspicion"].to_numpy()[clean]), 4),
                         "best check": [best, round(checks[best], 4)],
                         "linter": round(auroc(table["linter"].to_numpy()[bad], table["linter"].to_numpy()[clean]), 4),
                         "flagged": round(float(table["is_anomaly"][bad].mean()), 3)}
    n = int(clean.sum())
    flagged = int(table["is_anomaly"][clean].sum())
    lo, hi = binom.interval(0.95, n, 0.01)
    results["clean flagged"] = {"count": flagged, "of": n, "binomial 95% interval at 0.01": [int(lo), int(hi)]}
    for kind, r in results.items():
        print(f"{kind:14s} {r}")
    (out / "checks.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
