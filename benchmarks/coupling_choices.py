"""Where the ``coupling`` check belongs in the ranking (``democheck.audit.coupling``).

    python benchmarks/coupling_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output (scores.parquet).  Every demo the bench read is decoded once more for its
state-action mutual information (``coupling.CouplingStats``), and the ranking combined as ``democheck audit``
combines it (``view_choices.judged``) four ways: with the model's scores, without and with the coupling (as the
ranking has it, the coupling only where the action error is not; forced in beside it; ``merged`` with it, the two
one piece of evidence -- the Sidak minimum of their tail probabilities, 1 - (1 - min p)^2, in the action error's
column -- since both ask whether the actions are explained), and with the model-free scores alone
(``model_free``), without and with it.  Printed per way: the ranking's AUROC per kind, the share of clean
demos flagged at --fpr 0.01 and each kind's; first, the coupling's own AUROC per kind.  ``--only`` keeps the
rows of one of the bench's datasets (the demos an audit of that dataset alone would see).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd

from democheck.audit import coupling, scores
from democheck.audit.scorers import SCORERS, ranked
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


def merged_tails(names: list[str]):
    """``scores.tail_probabilities`` with the coupling's column folded into the action error's: the Sidak minimum
    of the two (natural logs), the coupling's own column left out (NaN)."""
    shipped, a, c = scores.tail_probabilities, names.index("action_error"), names.index("coupling")

    def tails(z: np.ndarray, core: np.ndarray | None = None, normal: np.ndarray | None = None) -> np.ndarray:
        log_p = shipped(z, core, normal)
        low = np.fmin(log_p[:, a], log_p[:, c])
        with np.errstate(all="ignore"):  # log(1 - (1 - p)^2), which is log(2p) where p is tiny
            sidak = np.where(low < -30, low + np.log(2), np.log1p(-np.exp(2 * np.log1p(-np.exp(low)))))
        log_p[:, a], log_p[:, c] = np.where(np.isnan(low), np.nan, sidak), np.nan
        return log_p
    return tails


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
            if not model_free:
                SCORERS["coupling"] = replace(shipped, stands_in_for="")
                tails = scores.tail_probabilities
                try:
                    print(f"  {what + ', forced in':<24} {judged(table, value, 'coupling', model_free)}")
                    cols = {c: table[c].to_numpy(float) for c in table if c in SCORERS} | {"coupling": value}
                    scores.tail_probabilities = merged_tails(ranked(cols, table["task"].to_numpy()))
                    print(f"  {what + ', merged':<24} {judged(table, value, 'coupling', model_free)}")
                finally:
                    SCORERS["coupling"] = shipped
                    scores.tail_probabilities = tails


if __name__ == "__main__":
    main()
