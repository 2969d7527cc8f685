"""Is a score seeing the fault, or the episode's length?  Per planted kind, the AUROC of the suspicion within
length-matched pairs -- each bad demo against the clean demos of its task nearest it in length -- beside the AUROC
of the length alone:

    python benchmarks/length_matched.py AUDIT DATA [--labels LABELS.csv] [--score suspicion]

AUDIT is a ``democheck audit`` folder of DATA; labels come from the table's ``label`` column or a csv of
``episode_index,label``.  A pair counts 1 where the bad demo scores higher, 0.5 on a tie (against several clean
demos as near in length, the mean over them).  Length's AUROC is taken both ways (the larger of longer-is-bad and
shorter-is-bad): near 0.5, length says nothing of the kind.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from democheck.audit.metrics import detection
from democheck.data import open_dataset


def matched_pairs(table: pd.DataFrame, kind: str) -> list[tuple[int, list[int]]]:
    """(bad row, clean rows) per demo of ``kind``: the clean demos of its task nearest it in length -- all of them
    where several are as near (a generator that gives every episode its task's length ties them all)."""
    pairs = []
    clean = table[table["label"] == "clean"]
    for i, row in table[table["label"] == kind].iterrows():
        mates = clean[clean["task"] == row["task"]]
        if len(mates):
            gap = (mates["length"] - row["length"]).abs()
            pairs.append((i, [int(c) for c in gap.index[gap == gap.min()]]))
    return pairs


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("audit", type=Path)
    ap.add_argument("data", type=Path)
    ap.add_argument("--labels", type=Path)
    ap.add_argument("--score", default="suspicion")
    args = ap.parse_args(argv)
    table = pd.read_parquet(args.audit / "scores.parquet")
    if args.labels is not None:
        table = table.drop(columns="label", errors="ignore").merge(pd.read_csv(args.labels), on="episode_index")
    table["label"] = table["label"].fillna("clean").astype(str)
    lengths = open_dataset(args.data).episodes["length"]
    table["length"] = table["episode_index"].map(lengths).to_numpy()
    out = {}
    for kind in sorted(set(table["label"]) - {"clean"}):
        pairs = matched_pairs(table, kind)
        s = table[args.score].to_numpy(np.float64)
        wins = [np.mean([1.0 if s[b] > s[c] else 0.5 if s[b] == s[c] else 0.0 for c in cs]) for b, cs in pairs]
        bad, clean = table["label"] == kind, table["label"] == "clean"
        y = np.r_[np.ones(bad.sum(), bool), np.zeros(clean.sum(), bool)]
        length = np.r_[table.loc[bad, "length"], table.loc[clean, "length"]].astype(float)
        by_length = detection(y, length)["auroc"]
        gap = float(np.median([abs(table.loc[b, "length"] - table.loc[cs[0], "length"]) for b, cs in pairs])) if pairs \
            else float("nan")
        out[kind] = {"pairs": len(pairs), "AUROC within pairs": round(float(np.mean(wins)), 3) if wins else None,
                     "AUROC of length alone": round(max(by_length, 1 - by_length), 3),
                     "median length gap": gap}
        print(f"{kind:14s} {out[kind]}", flush=True)
    return out


if __name__ == "__main__":
    main()
