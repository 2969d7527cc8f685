"""The development-set sweep behind the recording faults in the ranking (timing, frozen video, frame jump, lag).

    python benchmarks/fault_choices.py TABLE[@LABELS.csv] [TABLE[@LABELS.csv] ...] [--no-model] [--fpr 0.01]

TABLE is a ``democheck audit`` or ``democheck bench`` output folder (its scores.parquet; it must hold the
``frame_jump`` and ``lag`` columns, which audits since they were added do); LABELS a CSV of episode_index,label
for an audit whose table has no labels (``metaworld_lerobot.py`` writes one beside the dataset).  Each variant
recombines the table's scores exactly as the audit does (``ranking.ranking_tails``, ``ranking.combine``, the
conformal flags on the robust core) with the faults' scorers changed:

- ``without``: the faults out of the ranking (columns only; the ranking before);
- ``in Fisher's sum``: in the ranking like any other score;
- ``alone``: each on its own beside the combination of the others (``Scorer.alone``: the Sidak minimum), their
  robust SD at least ``FAULT_MIN_SCALE`` (the shipped form), or at least 0.05, 0.1, or no floor;
- ``alone, normal tails``: the same with a normal tail in place of the exponential through the quartiles;
- ``alone, each its own look``: each fault's tail probability beside the others' combined one in one Sidak
  minimum over the four, instead of the faults' own Sidak minimum beside it (two looks; shipped).

For each it prints the clean demos flagged at ``--fpr`` against the number the audit expects, and per labelled
kind the ranking's AUROC against the clean demos and the share flagged.  ``--no-model`` recombines the model-free
scores alone, as ``democheck audit --no-model`` does.
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

from democheck.audit import flagging, ranking, scores
from democheck.audit.scorers import FAULT_MIN_SCALE, SCORERS, Evidence

FAULTS = ("timing", "frozen_video", "frame_jump", "lag")
VARIANTS = {
    "without": {"in_suspicion": False},
    "in Fisher's sum": {"alone": False},
    f"alone, floor {FAULT_MIN_SCALE:g} (shipped)": {},
    "alone, floor 0.05": {"ranking_min_scale": 0.05},
    "alone, floor 0.1": {"ranking_min_scale": 0.1},
    "alone, no floor": {"ranking_min_scale": 0.0},
    "alone, normal tails": {"tail": "normal"},
    "alone, each its own look": {},
}
SHIPPED_COMBINED = scores.combined_log10


def each_its_own_look(log_p: np.ndarray, alone: np.ndarray | None = None, looks: np.ndarray | None = None
                      ) -> np.ndarray:
    """``scores.combined_log10`` with every fault a look of its own in the last Sidak minimum."""
    alone = np.zeros(log_p.shape[1], bool) if alone is None else np.asarray(alone, bool)
    if looks is not None:  # the scores of one look merged first, as the audit does
        log_p, first = scores.merge_looks(log_p, looks)
        alone = alone[first]
    if not alone.any():
        return SHIPPED_COMBINED(log_p)
    rest = SHIPPED_COMBINED(log_p[:, ~alone]) * np.log(10)
    return scores.sidak_log10(np.column_stack([rest, log_p[:, alone]]))


@contextmanager
def faults_as(**changes) -> Iterator[None]:
    """The registry with the faults' scorers changed for the duration."""
    saved = {n: SCORERS[n] for n in FAULTS}
    try:
        for n in FAULTS:
            SCORERS[n] = dataclasses.replace(saved[n], **changes)
        yield
    finally:
        SCORERS.update(saved)


def recombined(table: pd.DataFrame, model_free: bool, fpr: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(suspicion, flags, expected false flags) of a score table as the audit computes them."""
    values = {c: table[c].to_numpy(float) for c in table if c in SCORERS and SCORERS[c].in_audit}
    values = {c: v for c, v in values.items() if c not in ("suspicion",)}
    names = ranking.ranked(values, table["task"].to_numpy(), model_free)
    ev = Evidence(episodes=table[["episode_index", "task"]], scores=values)
    log_p, core = ranking.ranking_tails(ev, names)
    suspicion = ranking.combine(names, log_p)
    flagged = flagging.flags(flagging.conformal_p(suspicion, core), fpr, flagging.flagged_regardless(table))
    return suspicion, flagged, flagging.expected_false_flags(core, fpr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tables", nargs="+")
    ap.add_argument("--no-model", action="store_true")
    ap.add_argument("--fpr", type=float, default=flagging.DEFAULT_FPR)
    args = ap.parse_args()
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    for spec in args.tables:
        path, _, labels_csv = spec.partition("@")
        table = pd.read_parquet(f"{path}/scores.parquet").reset_index(drop=True)
        missing = [c for c in FAULTS if c not in table]
        if missing:
            raise SystemExit(f"{path}: no {', '.join(missing)} column: audit the dataset again")
        if labels_csv:
            table["label"] = table["episode_index"].map(pd.read_csv(labels_csv).set_index("episode_index")["label"])
        labels = table["label"].fillna("clean").to_numpy() if "label" in table else np.full(len(table), "clean")
        kinds = sorted(set(labels) - {"clean"})
        clean = labels == "clean"
        print(f"\n{path}: {len(table)} demos, {clean.sum()} clean; per kind AUROC/flagged: {' '.join(kinds)}")
        for name, changes in VARIANTS.items():
            # The core's rounds (scores) and the ranking (scorers) both combine.
            scores.combined_log10 = ranking.combined_log10 = (
                each_its_own_look if name == "alone, each its own look" else SHIPPED_COMBINED)
            try:
                with faults_as(**changes):
                    s, flagged, expected = recombined(table, args.no_model, args.fpr)
            finally:
                scores.combined_log10 = ranking.combined_log10 = SHIPPED_COMBINED
            cells = []
            for k in kinds:
                sel = clean | (labels == k)
                auroc = roc_auc_score(labels[sel] == k, np.nan_to_num(s[sel], nan=-1e9, posinf=1e9))
                cells.append(f"{auroc:.4f}/{flagged[labels == k].mean():.2f}")
            print(f"  {name:<28} clean {int(flagged[clean].sum()):3d} (expected {expected:4.1f}) | " + " ".join(cells))


if __name__ == "__main__":
    main()
