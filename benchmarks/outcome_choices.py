"""The development-set sweep behind the ``outcome`` check's constants (``democheck.audit.modelfree``).

    python benchmarks/outcome_choices.py BENCH_DIR [BENCH_DIR ...]

BENCH_DIR is a ``democheck bench`` output (scores.parquet).  Every dataset the bench read is decoded once more
for each demo's first and last recorded environment state (or state: ``OutcomeStats``); then for each floor
(``OUTCOME_FLOOR``: the least robust SD of a dimension, as a share of its spread over all the demos) and scale
(raw or log) the outcome score replaces the bench's ``outcome`` column and the ranking is combined as ``democheck
audit`` combines it.  Printed per variant: the outcome score's own AUROC per kind, then the ranking's AUROC per
kind, the share of clean demos flagged at ``--fpr 0.01`` and each kind's share flagged; the first row is the
ranking without the outcome check.
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from democheck.audit import modelfree
from democheck.data import open_dataset
from view_choices import judged
from suspicion_choices import aurocs

FLOORS = (0.02, 0.05, 0.1, 0.2)
SCALES = {"raw": lambda s: s, "log": lambda s: np.log(np.maximum(s, 1e-6))}


def outcome_stats(table: pd.DataFrame) -> modelfree.OutcomeStats:
    """Every row's ``OutcomeStats``, in the table's order."""
    parts: dict[int, tuple[np.ndarray, str, list[str] | None]] = {}
    for path, rows in table.groupby("dataset").groups.items():
        ds, stats = open_dataset(path), modelfree.OutcomeStats()
        for i in rows:
            stats.add(ds[int(table.at[i, "source_index"])])
        for i, e, s, n in zip(rows, stats.ends, stats.sources, stats.names):
            parts[int(i)] = (e, s, n)
    out = modelfree.OutcomeStats()
    for i in range(len(table)):
        e, s, n = parts[i]
        out.ends.append(e), out.sources.append(s), out.names.append(n)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benches", nargs="+")
    args = ap.parse_args()
    for path in args.benches:
        table = pd.read_parquet(f"{path}/scores.parquet").reset_index(drop=True)
        labels = table["label"].fillna("clean").to_numpy()
        kinds = sorted(set(labels) - {"clean"})
        print(f"\n{path}: {len(table)} demos; AUROC {' '.join(kinds)} | clean flagged | kinds flagged")
        print(f"  {'without outcome':<22} {'':<48} {judged(table, None, 'outcome')}")
        stats, tasks = outcome_stats(table), table["task"].to_numpy()
        old = modelfree.OUTCOME_FLOOR
        try:
            for floor in FLOORS:
                modelfree.OUTCOME_FLOOR = floor
                score, _ = modelfree.outcome(stats, tasks)
                alone = " ".join(f"{a:.3f}" for a in aurocs(score, labels).values())
                for scale, f in SCALES.items():
                    print(f"  floor {floor:<5g} {scale:<4}  alone {alone} | ranking {judged(table, f(score), 'outcome')}",
                          flush=True)
        finally:
            modelfree.OUTCOME_FLOOR = old


if __name__ == "__main__":
    main()
