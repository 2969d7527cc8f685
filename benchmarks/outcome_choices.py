"""The development-set sweep behind the ``outcome`` check's constants (``democheck.audit.outcome``).

    python benchmarks/outcome_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output (scores.parquet).  Every dataset the bench read is decoded once more
for each demo's first and last recorded environment state (or state: ``OutcomeStats``); then for each floor
(``OUTCOME_FLOOR``: the least robust SD of a dimension, as a share of its spread over all the demos) and each
way of putting a demo's dimensions together (``FORMS``: the RMS raw or on a log scale, the RMS of z capped at
5, 10 or 20, the share of dimensions over 3, 5 or 10 robust SD) the outcome score replaces the bench's
``outcome`` column and the ranking is combined as ``democheck audit`` combines it.  Printed per variant: the
outcome score's own AUROC per kind, then the ranking's AUROC per kind, the share of clean demos flagged at
``--fpr 0.01`` and each kind's share flagged; the first row is the ranking without the outcome check.
``--only`` keeps the rows of one of the bench's datasets (the demos an audit of that dataset alone would see).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from democheck.audit import outcome, scores
from democheck.data import open_dataset
from suspicion_choices import aurocs, bench_tables
from view_choices import judged

FLOORS = (0.02, 0.05, 0.1, 0.2)


def _share_over(k: float):
    def share(z: np.ndarray) -> np.ndarray:
        seen = np.isfinite(z).sum(1)
        return np.where(seen > 0, (np.nan_to_num(z) > k).sum(1) / np.maximum(seen, 1), np.nan)
    return share


# name -> (how a demo's [F] robust z become one number, the least spread of its robust SD in the ranking, or
# None: a score the ranking puts in robust SD itself).  A share is put in robust SD within its task here, as the
# view check's share is.
FORMS = {"rms": (outcome.rms, None), "log rms": (lambda z: np.log(np.maximum(outcome.rms(z), 1e-6)), None),
         **{f"rms cap {c}": ((lambda z, c=c: outcome.rms(np.minimum(z, c))), None) for c in (5, 10, 20)},
         **{f"share > {k}": (_share_over(k), 0.02) for k in (3, 5, 10)}}


def outcome_stats(table: pd.DataFrame) -> outcome.OutcomeStats:
    """Every row's ``OutcomeStats``, in the table's order."""
    sets = {path: open_dataset(path) for path in table["dataset"].unique()}
    stats = outcome.OutcomeStats()
    for path, source in zip(table["dataset"], table["source_index"]):
        stats.add(sets[path][int(source)])
    return stats


def main() -> None:
    for path, _, table in bench_tables(__doc__):
        labels = table["label"].fillna("clean").to_numpy()
        kinds = sorted(set(labels) - {"clean"})
        print(f"\n{path}: {len(table)} demos; AUROC {' '.join(kinds)} | clean flagged | kinds flagged")
        print(f"  {'without outcome':<26} {judged(table, None, 'outcome')}")
        stats, tasks = outcome_stats(table), table["task"].to_numpy()
        old = outcome.OUTCOME_FLOOR
        try:
            for floor in FLOORS:
                outcome.OUTCOME_FLOOR = floor
                for form, (combine, min_scale) in FORMS.items():
                    score, _ = outcome.outcome(stats, tasks, combine)
                    ranked = score if min_scale is None else scores.calibrated(score, tasks, min_scale=min_scale)
                    alone = " ".join(f"{a:.3f}" for a in aurocs(score, labels).values())
                    print(f"  floor {floor:<5g} {form:<12} alone {alone} | ranking {judged(table, ranked, 'outcome')}",
                          flush=True)
        finally:
            outcome.OUTCOME_FLOOR = old


if __name__ == "__main__":
    main()
