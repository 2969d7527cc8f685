"""democheck on data it did not make, the whole way a user goes: train on the dataset, audit it, measure.

    python benchmarks/foreign/run.py data/foreign/mw-test [--labels data/foreign/mw-test.labels.csv] \
        [--recipe your-data] [--model M] [--out runs/foreign/mw-test]

The dataset is any LeRobot folder with a labels CSV beside it (``DATASET.labels.csv``: episode_index,label;
``metaworld_lerobot.py`` writes both).  Runs, as a user would and timed:

    democheck train DATASET --out OUT/model --recipe your-data        (skipped with --model)
    democheck audit DATASET --out OUT/audit --model OUT/model
    democheck audit DATASET --out OUT/audit-no-model --no-model
    democheck bench DATASET --labels LABELS --model OUT/model --out OUT/bench

and prints, per planted kind against the clean demos, the AUROC of democheck's ranking and of each of its
scores, of a two-line linter (mean |action| and mean |change of action|, the larger robust |z| over the
demos), of the audit without a model (its ranking: ``no-model``), and the audit's flags: the share of each kind
flagged and of the clean demos, against the false flags the audit expected.  ``OUT/results.json``
keeps the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

SCORES = ("suspicion", "task_uncertainty", "consistency", "action_error", "novelty", "motion", "idle")


def democheck(*args: str) -> float:
    """Run a democheck command as a user would; its wall time in seconds."""
    exe = Path(sys.executable).with_name("democheck")
    t0 = time.perf_counter()
    res = subprocess.run([str(exe), *args], capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "egl"})
    if res.returncode != 0:
        raise SystemExit(f"democheck {' '.join(args)} failed:\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}")
    return time.perf_counter() - t0


def linter(dataset: Path) -> pd.Series:
    """The two-line linter: mean |action| and mean |change of action|, robust z over all demos, the larger |z|."""
    from democheck.data import open_dataset

    ds = open_dataset(dataset)
    rows = []
    for demo in ds:
        a = np.asarray(demo.actions, np.float64)
        rows.append((np.abs(a).mean(), np.abs(np.diff(a, axis=0)).mean()))
    f = np.asarray(rows)
    med = np.median(f, 0)
    z = np.abs(f - med) / np.maximum(1.4826 * np.median(np.abs(f - med), 0), 1e-9)
    return pd.Series(z.max(1), index=ds.episode_indices)


def auroc(labels: np.ndarray, score: np.ndarray, kind: str) -> float:
    sel = (labels == kind) | (labels == "clean")
    return float(roc_auc_score(labels[sel] == kind, np.nan_to_num(score[sel], nan=np.nanmin(score))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--labels", type=Path, default=None, help="default: DATASET.labels.csv")
    ap.add_argument("--recipe", default="your-data")
    ap.add_argument("--model", type=Path, default=None, help="an already trained model (skips training)")
    ap.add_argument("--out", type=Path, default=None, help="default: runs/foreign/<dataset name>")
    args = ap.parse_args()
    labels_csv = args.labels or args.dataset.with_name(args.dataset.name + ".labels.csv")
    out = args.out or Path("runs/foreign") / args.dataset.name
    out.mkdir(parents=True, exist_ok=True)
    times = {}
    model = args.model or out / "model"
    if args.model is None:
        times["train_s"] = democheck("train", str(args.dataset), "--out", str(model), "--recipe", args.recipe, "--force")
    times["audit_s"] = democheck("audit", str(args.dataset), "--out", str(out / "audit"), "--model", str(model),
                                 "--force")
    times["audit_no_model_s"] = democheck("audit", str(args.dataset), "--out", str(out / "audit-no-model"),
                                          "--no-model", "--force")
    times["bench_s"] = democheck("bench", str(args.dataset), "--labels", str(labels_csv), "--model", str(model),
                                 "--out", str(out / "bench"), "--force")
    audit = pd.read_parquet(out / "audit" / "scores.parquet").set_index("episode_index")
    truth = pd.read_csv(labels_csv).set_index("episode_index")["label"].reindex(audit.index).fillna("clean")
    audit["label"] = truth
    audit["linter"] = linter(args.dataset).reindex(audit.index)
    audit["no-model"] = pd.read_parquet(out / "audit-no-model" / "scores.parquet").set_index("episode_index")[
        "suspicion"].reindex(audit.index)
    labels = audit["label"].to_numpy()
    kinds = sorted(set(labels) - {"clean"})
    cols = [c for c in (*SCORES, "no-model", "linter") if c in audit]
    table = {c: {k: auroc(labels, audit[c].to_numpy(float), k) for k in kinds} for c in cols}
    for c in cols:
        table[c]["any"] = float(roc_auc_score(labels != "clean", np.nan_to_num(audit[c].to_numpy(float), nan=-1e9)))
    flagged = audit["is_anomaly"].to_numpy(bool)
    flags = {k: float(flagged[labels == k].mean()) for k in kinds} | {"clean": float(flagged[labels == "clean"].mean())}
    summary = json.loads((out / "audit" / "summary.json").read_text())
    results = {"dataset": str(args.dataset), "demos": len(audit), "tasks": int(audit["task"].nunique()),
               "labels": {k: int((labels == k).sum()) for k in ["clean", *kinds]}, "auroc": table,
               "flagged_share": flags, "flag_recall": float(flagged[labels != "clean"].mean()),
               "flag": summary["flag"],
               "warnings": summary.get("warnings", []), "times_s": {k: round(v, 1) for k, v in times.items()},
               "model": str(model)}
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"{args.dataset}: {len(audit)} demos, {results['tasks']} tasks, {results['labels']}")
    print("| AUROC (kind vs clean) | " + " | ".join(kinds) + " | any |")
    print("|---|" + "---:|" * (len(kinds) + 1))
    for c in cols:
        print(f"| {c} | " + " | ".join(f"{table[c][k]:.2f}" for k in [*kinds, "any"]) + " |")
    print("| flagged (share) | " + " | ".join(f"{flags[k]:.2f}" for k in kinds)
          + f" | clean {flags['clean']:.3f}, recall {results['flag_recall']:.2f} |")
    flag = summary["flag"]
    print(f"flags at fpr {flag['fpr']:g}: {int(flagged.sum())} flagged, {int(flagged[labels == 'clean'].sum())} of them "
          f"clean; the audit expected about {flag['expected_false_flags']:.1f} false flags")
    for w in results["warnings"]:
        print(f"warning: {w}")
    print("times: " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items()))


if __name__ == "__main__":
    main()
