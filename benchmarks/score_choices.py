"""The measurement behind ``CONSISTENCY_K`` in ``democheck.audit.scores``, on a bench's scores.parquet (the
ranking's combination and its flag levels: ``benchmarks/suspicion_choices.py``).

    democheck synth push-v1-test --seed 2 --out data/push-v1-dev       # a development set, not the test bench
    democheck probe data/push-v1-dev --out data/push-v1-dev-probes --seed 2
    democheck bench data/push-v1-dev data/push-v1-dev-probes --out runs/bench-dev
    python benchmarks/score_choices.py runs/bench-dev/scores.parquet

It prints the AUROC of consistency against the k nearest other demos of the task, per kind, for several k
(and all others), and two forms measured and not shipped, each dimension in units of its median task SD
instead of sqrt(v + var), so that a cue's own variance does not shrink its distance: from the same product
("scaled product") and the kNN baseline's mean distance to the k nearest ("scaled kNN").  The bench must
have been written with a model (its table holds ``mu`` and ``sigma``).
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

from democheck.audit.baselines import knn_same_task
from democheck.petnet.posterior import product_of_others


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scores", help="scores.parquet written by democheck bench")
    args = ap.parse_args()
    t = pd.read_parquet(args.scores)
    mu = np.stack(t["mu"].to_numpy()).astype(np.float64)
    var = np.stack(t["sigma"].to_numpy()).astype(np.float64) ** 2
    labels, tasks = t["label"].to_numpy(), t["task"].to_numpy()
    kinds = sorted(set(labels) - {"clean"})

    def show(name: str, score: np.ndarray) -> None:
        au = []
        for kind in kinds:
            sel = (labels == kind) | (labels == "clean")
            au.append(roc_auc_score(labels[sel] == kind, np.nan_to_num(score[sel])))
        print(f"  {name}: " + " ".join(f"{a:.2f}" for a in au) + f" | {np.mean(au):.3f}")

    print("consistency AUROC by k:", " ".join(kinds), "| mean")
    for k in (1, 2, 3, 5, 8, None):
        m, v = product_of_others(mu, var, tasks, k)
        show(f"k={k or 'all':>3}", np.sqrt(((mu - m) ** 2 / (v + var)).mean(1)))
    scale = np.median(np.sqrt(var), axis=0)
    for k in (5, 8):
        show(f"scaled product, k={k}", np.sqrt((((mu - product_of_others(mu, var, tasks, k)[0]) / scale) ** 2).mean(1)))
    show("scaled kNN, k=5", knn_same_task(mu / scale, tasks, 5))

if __name__ == "__main__":
    main()
