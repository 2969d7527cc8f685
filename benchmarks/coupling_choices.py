"""Where the ``coupling`` check belongs in the ranking (``democheck.audit.coupling``).

    python benchmarks/coupling_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output (scores.parquet).  Every demo the bench read is decoded once more for its
state-action mutual information (``coupling.CouplingStats``), and the ranking combined as ``democheck audit``
combines it (``view_choices.judged``) five ways: with the model's scores, without the coupling (as the ranking had
it before, the coupling only where the action error was not), with it as the ranking has it (one look with the
action error, ``Scorer.look``: the Sidak minimum of their two tail probabilities, since both ask whether the
actions are explained) and ``beside`` it (a look of its own in Fisher's sum); and with the model-free scores
alone (``model_free``), without and with it.  Printed per way: the ranking's AUROC per kind, the share of clean
demos flagged at --fpr 0.01 and each kind's; first, the coupling's own AUROC per kind.  ``--only`` keeps the
rows of one of the bench's datasets (the demos an audit of that dataset alone would see).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd

from democheck.audit import coupling
from democheck.audit.scorers import SCORERS
from democheck.data import open_dataset
from suspicion_choices import aurocs, bench_tables
from view_choices import judged


def coupling_scores(table: pd.DataFrame) -> np.ndarray:
    """Every row's coupling score, in the table's order."""
    sets = {path: open_dataset(path) for path in table["dataset"].unique()}
    stats = coupling.CouplingStats()
    for path, source in zip(table["dataset"], table["source_index"]):
        stats.add(sets[path][int(source)])
    return coupling.coupling(stats, table["task"].to_numpy())[0]


def main() -> None:
    shipped = SCORERS["coupling"]
    for path, only, table in bench_tables(__doc__):
        labels = table["label"].fillna("clean").to_numpy()
        kinds = sorted(set(labels) - {"clean"})
        value = coupling_scores(table)
        print(f"\n{path}{' (' + only + ')' if only else ''}: {len(table)} demos; AUROC {' '.join(kinds)} | "
              "clean flagged | kinds flagged")
        print(f"  {'coupling alone':<24} " + " ".join(f"{a:.3f}" for a in aurocs(value, labels).values()))
        for model_free in (False, True):
            what = "no model" if model_free else "with the model"
            print(f"  {what + ', without':<24} {judged(table, None, 'coupling', model_free)}")
            print(f"  {what + ', with':<24} {judged(table, value, 'coupling', model_free)}", flush=True)
            if not model_free:  # "with" is the shipped look, merged with the action error; "beside": a look of its own
                SCORERS["coupling"] = replace(shipped, look="")
                try:
                    print(f"  {what + ', beside':<24} {judged(table, value, 'coupling', model_free)}")
                finally:
                    SCORERS["coupling"] = shipped


if __name__ == "__main__":
    main()
