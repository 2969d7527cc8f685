"""The development-set sweep behind the ``view`` check's constants (``democheck.audit.modelfree``).

    python benchmarks/view_choices.py BENCH_DIR [BENCH_DIR ...]

BENCH_DIR is a ``democheck bench`` output (scores.parquet: each demo's dataset, source episode, task, label and
every scorer's score).  Every dataset the bench read is decoded once more to get each demo's average picture at
16 and 32 pixels (``ViewStats``); then for each thumbnail size, threshold K (robust SD), floor (grey levels) and
form of the share (raw, square root, logit) the view score replaces the bench's ``view`` column and the ranking
is combined as ``democheck audit`` combines it.  Printed per variant: the ranking's AUROC of every labelled
kind against the clean demos, the share of clean demos flagged at ``--fpr 0.01`` and each kind's share flagged;
the first row is the ranking without the view check.
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

from democheck.audit import flagging, modelfree, ranking, scores
from democheck.audit.scorers import SCORERS, Evidence
from democheck.data import open_dataset

SIZES = (16, 32)
THRESHOLDS = ((3.0, 2.0), (3.0, 4.0), (5.0, 2.0), (5.0, 4.0))  # (K, floor)
FORMS = {"raw": (lambda s: s, 0.02), "sqrt": (np.sqrt, 0.05),
         "logit": (lambda s: np.log(np.clip(s, 1e-3, 1 - 1e-3) / (1 - np.clip(s, 1e-3, 1 - 1e-3))), 0.25)}


def thumbnails(table: pd.DataFrame, size: int) -> np.ndarray:
    """[N, size, size, 3]: every row's average picture, as ``ViewStats`` makes it at ``size`` pixels."""
    old, modelfree.VIEW_THUMB = modelfree.VIEW_THUMB, size
    try:
        out = np.zeros((len(table), size, size, 3), np.uint8)
        for path, rows in table.groupby("dataset").groups.items():
            ds, stats = open_dataset(path), modelfree.ViewStats()
            for i in rows:
                stats.add(ds[int(table.at[i, "source_index"])])
            out[np.asarray(rows)] = stats.finish()
        return out
    finally:
        modelfree.VIEW_THUMB = old


def judged(table: pd.DataFrame, view: np.ndarray | None, name: str = "view", model_free: bool = False) -> str:
    """The ranking's AUROC per kind, the share of clean demos flagged at ``DEFAULT_FPR`` and each kind's, with the
    bench's ``name`` column replaced by ``view`` (None: left out of the ranking); the model-free scores alone with
    ``model_free``."""
    labels = table["label"].fillna("clean").to_numpy()
    cols = {c: table[c].to_numpy(float) for c in table if c in SCORERS}
    if view is None:
        cols.pop(name, None)
    else:
        cols[name] = view
    ev = Evidence(episodes=table[["episode_index", "task"]], scores=cols)
    names, log_p, core = ev.combination(model_free)  # as the audit ranks and flags
    s = ranking.combine(names, log_p)
    kinds = sorted(set(labels) - {"clean"})
    au = [roc_auc_score(labels[(labels == k) | (labels == "clean")] == k, s[(labels == k) | (labels == "clean")])
          for k in kinds]
    flagged = flagging.conformal_p(s, core) <= flagging.DEFAULT_FPR
    return (" ".join(f"{a:.3f}" for a in au) + f" | clean {flagged[labels == 'clean'].mean():.3f} | "
            + " ".join(f"{flagged[labels == k].mean():.2f}" for k in kinds))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benches", nargs="+")
    args = ap.parse_args()
    for path in args.benches:
        table = pd.read_parquet(f"{path}/scores.parquet")
        kinds = sorted(set(table["label"].fillna("clean")) - {"clean"})
        print(f"\n{path}: {len(table)} demos; AUROC {' '.join(kinds)} | clean flagged | kinds flagged")
        print(f"  {'without view':<26} {judged(table, None)}")
        tasks = table["task"].to_numpy()
        for size in SIZES:
            thumbs = thumbnails(table, size)
            for k, floor in THRESHOLDS:
                share = modelfree.view_unlike(thumbs, tasks, k, floor).mean(axis=(1, 2))
                for form, (f, min_scale) in FORMS.items():
                    z = scores.calibrated(f(share), tasks, min_scale=min_scale)
                    print(f"  {size:>2} px K {k:g} floor {floor:g} {form:<5}  {judged(table, z)}", flush=True)


if __name__ == "__main__":
    main()
