"""The development-set sweep behind the ranking's design: which scores go in, and how they are combined.

    python benchmarks/suspicion_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output (its scores.parquet: each demo's task, label and every scorer's
score).  Every score of the ranking is first put in robust standard deviations within its task, exactly as
``democheck audit`` does (``ranking.ranking_z``); the variants then differ in how those are combined:

- ``max z``: the largest robust z (democheck's ranking before the tail probabilities);
- ``tail LO-HI``: each column's exponential tail through its LO and HI percentiles (``scores.tail_probabilities``
  with other ``TAIL_QUANTILES``), combined as the audit combines them (Fisher's sum with Brown's correction:
  ``scores.combined_log10``);
- ``Sidak 0.25-0.75``: the same tails, their smallest Sidak-corrected (the ranking before Fisher-Brown);
- ``rank min-p``, ``rank Fisher``: empirical p-values (each demo's rank among the audited demos), their
  minimum or Fisher's sum of -log p.

For each it prints the AUROC of every labelled kind against the clean demos and their mean; for the tail
probabilities also the share of clean demos flagged and the recall of the bad ones at several
false-positive rates (``audit --fpr``), next to the rate asked for.  ``--only`` keeps the rows of one of the
bench's datasets (the demos an audit of that dataset alone would see).
"""

from __future__ import annotations

import argparse
from typing import Iterator

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

from democheck.audit import flagging, ranking, scores
from democheck.audit.ranking import ranking_z
from democheck.audit.scorers import SCORERS, Evidence

FPRS = (0.001, 0.005, 0.01, 0.02, 0.05)


def aurocs(s: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    out = {}
    for k in sorted(set(labels) - {"clean"}):
        sel = (labels == k) | (labels == "clean")
        out[k] = roc_auc_score(labels[sel] == k, np.nan_to_num(s[sel], nan=-1e9, posinf=1e9))
    return out


def tail_p(z: np.ndarray, quantiles: tuple[float, float]) -> np.ndarray:
    """-log10 of the combined tail probability with ``quantiles`` in place of ``scores.TAIL_QUANTILES``."""
    saved = scores.TAIL_QUANTILES
    scores.TAIL_QUANTILES = quantiles
    try:
        return -scores.combined_log10(scores.tail_probabilities(z))
    finally:
        scores.TAIL_QUANTILES = saved


def rank_p(z: np.ndarray) -> np.ndarray:
    """Each entry's empirical p-value among its column: the share of demos at least as high."""
    z = np.where(np.isnan(z), -np.inf, z)
    out = np.empty(z.shape)
    for k in range(z.shape[1]):
        order = np.sort(z[:, k])
        out[:, k] = (len(z) - np.searchsorted(order, z[:, k], side="left")) / (len(z) + 1)
    return out


def variants(z: np.ndarray) -> dict[str, np.ndarray]:
    finite = np.where(np.isnan(z), -np.inf, z)
    p = rank_p(z)
    return {"max z": finite.max(axis=1),
            **{f"tail {lo:g}-{hi:g}": tail_p(z, (lo, hi)) for lo, hi in ((0.25, 0.75), (0.25, 0.5), (0.5, 0.75), (0.5, 0.9))},
            "Sidak 0.25-0.75": -scores.sidak_log10(scores.tail_probabilities(z)),
            "rank min-p": -np.log(p.min(axis=1)), "rank Fisher": -np.log(p).sum(axis=1)}


def bench_tables(doc: str) -> Iterator[tuple[str, str | None, pd.DataFrame]]:
    """The command line ``BENCH_DIR [BENCH_DIR ...] [--only DATASET]`` of a sweep whose help is ``doc``: each
    bench's path, the dataset kept, and its scores.parquet (only that dataset's rows with ``--only``)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benches", nargs="+")
    ap.add_argument("--only", help="keep the rows of this dataset of the bench (its path as the bench names it)")
    args = ap.parse_args()
    for path in args.benches:
        table = pd.read_parquet(f"{path}/scores.parquet")
        if args.only:
            table = table[table["dataset"] == args.only]
        yield path, args.only, table.reset_index(drop=True)


def main() -> None:
    for path, only, table in bench_tables(__doc__):
        labels = table["label"].fillna("clean").to_numpy()
        ev = Evidence(episodes=table[["episode_index", "task"]], scores={c: table[c].to_numpy() for c in table
                                                                         if c in SCORERS})
        ranked = ranking.ranked(table, table["task"].to_numpy())
        kinds = sorted(set(labels) - {"clean"})
        print(f"\n{path}{' (' + only + ')' if only else ''}: {len(table)} demos, "
              f"{table['task'].nunique()} tasks, {np.mean(labels != 'clean'):.0%} bad")
        print(f"  {'scores':<46} {'combination':<16} " + " ".join(f"{k[:8]:>8}" for k in kinds) + "     mean")
        sets = {"+".join(ranked): ranked}
        for drop in ranked:
            sets[f"without {drop}"] = [n for n in ranked if n != drop]
        extra = [n for n in ("jerk", "novelty", "frozen_video", "saturation", "dynamics", "timing") if n in table and n not in ranked]
        for name in extra:
            sets[f"with {name}"] = ranked + [name]
        for name, cols in sets.items():
            z = ranking_z(ev, cols)
            for how, s in variants(z).items():
                au = aurocs(s, labels)
                print(f"  {name[:46]:<46} {how:<16} " + " ".join(f"{au[k]:8.3f}" for k in kinds)
                      + f" {np.mean(list(au.values())):8.3f}")
        log_p, core = ranking.ranking_tails(ev, ranked)  # as the audit fits them
        clean = labels == "clean"
        for what, s in (("the shipped combination", ranking.combine(ranked, log_p)),
                        ("the Sidak minimum", -scores.sidak_log10(log_p))):
            print(f"  flags with {what} (conformal on the robust core, as the audit flags): fpr asked -> clean "
                  "share flagged (x asked), recall per kind")
            for fpr in FPRS:
                flagged = flagging.conformal_p(s, core) <= fpr
                recall = " ".join(f"{k[:8]} {flagged[labels == k].mean():.2f}" for k in kinds)
                print(f"    {fpr:<6g} -> {flagged[clean].mean():.4f} (x{flagged[clean].mean() / fpr:.2f})  {recall}")


if __name__ == "__main__":
    main()
