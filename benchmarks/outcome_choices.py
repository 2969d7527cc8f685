"""The development-set sweep behind the ``outcome`` check's constants (``democheck.audit.outcome``).

    python benchmarks/outcome_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output (scores.parquet).  Every dataset the bench read is decoded once more
for each demo's first and last recorded environment state (or state: ``OutcomeStats``); then for each floor
(``OUTCOME_FLOOR``: the least robust SD of a dimension, as a share of its spread over all the demos) and each
way of putting a demo's dimensions together (``FORMS``: the RMS raw or on a log scale, the RMS of z capped at
5, 10 or 20, the share of dimensions over 3, 5 or 10 robust SD, the largest z, the RMS of the two or three
largest) the outcome score replaces the bench's ``outcome`` column and the ranking is combined as ``democheck
audit`` combines it.  Then, at the shipped floor and form, each other way of measuring a dimension against its
task (``REFERENCES``): one robust SD per dimension for every task (the MAD of all the demos' distances from their
task's median, as the ranking's ``calibrated`` puts scores in units), or each task's median and robust SD taken
again from its demos within 3 or 5 robust SD of the first (one reweighting step: a task's own bad demos -- three
or four of a dozen -- widen its MAD, and a gave-up demo that stopped near the goal then reads 2-3 robust SD).
Then what each end is compared with (``SIDES``): the whole task's median instead of the median of the demos that
started on the same side (``outcome.side_reference``), the side only in the dimensions the task's demos move,
the side's median over the *other* demos that started
there (at least 1, 2 or 3 of them), and each dimension's end and change predicted from the whole start by
gradient-boosted trees fitted on the set's other tasks (task-centred, cross-fitted in five folds by task).  Printed per variant: the
outcome score's own AUROC per kind, then the ranking's AUROC per kind, the share of clean demos flagged at
``--fpr 0.01`` and each kind's share flagged; the first row is the ranking without the outcome check.
``--only`` keeps the rows of one of the bench's datasets (the demos an audit of that dataset alone would see).
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from democheck.audit import modelfree, outcome, scores
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


def _largest(k: int):
    def rms_top(z: np.ndarray) -> np.ndarray:
        top = -np.sort(-np.where(np.isfinite(z), z, -np.inf), axis=1)[:, :k]
        return outcome.rms(np.where(np.isfinite(top), top, np.nan))
    return rms_top


FORMS |= {"max": (_largest(1), None), "rms top 2": (_largest(2), None), "rms top 3": (_largest(3), None)}


def pooled_unit(x: np.ndarray, tasks: np.ndarray, floor, min_demos: int, small: str = "nan"):
    """``modelfree.task_z`` with one unit per dimension for every task: the robust SD of all the demos' distances
    from their own task's median."""
    _, median = SHIPPED_Z(x, tasks, floor, min_demos, small)
    dev = np.abs(x - median)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        unit = np.fmax(1.4826 * np.nanmedian(dev[np.isfinite(median).any(1)], axis=0), floor)
    return dev / unit, median


def reweighted(cut: float):
    """``modelfree.task_z`` with each task's median and robust SD taken again, per dimension, from its demos within
    ``cut`` robust SD of the first (where at least ``min_demos`` are)."""

    def task_z(x: np.ndarray, tasks: np.ndarray, floor, min_demos: int, small: str = "nan"):
        z, median = SHIPPED_Z(x, tasks, floor, min_demos, small)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for t in np.unique(tasks):
                rows = np.flatnonzero(tasks == t)
                if not np.isfinite(median[rows]).any():
                    continue  # too few demos: as the shipped form leaves it
                ref = x[rows]
                spread = np.fmax(1.4826 * np.nanmedian(np.abs(ref - median[rows[0]]), axis=0), floor)
                inner = np.where(np.abs(ref - median[rows[0]]) / spread <= cut, ref, np.nan)
                enough = np.isfinite(inner).sum(0) >= min_demos
                med = np.where(enough, np.nanmedian(inner, axis=0), median[rows[0]])
                spread = np.where(enough, np.fmax(1.4826 * np.nanmedian(np.abs(inner - med), axis=0), floor), spread)
                z[rows], median[rows] = np.abs(ref - med) / spread, med
        return z, median
    return task_z


SHIPPED_Z = modelfree.task_z
REFERENCES = {"pooled unit": pooled_unit, "reweighted 3": reweighted(3.0), "reweighted 5": reweighted(5.0)}


def others_on_side(min_others: int):
    """``outcome.side_reference`` over the *other* demos that started on the demo's side (at least
    ``min_others``)."""

    def side_reference(first, last, tasks, median, min_side=None):
        ref = median.copy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for t in np.unique(tasks):
                rows = np.flatnonzero(tasks == t)
                side = np.sign(first[rows] - median[rows[0]])
                for k, i in enumerate(rows):
                    same = (side == side[k]) & (np.arange(len(rows)) != k)[:, None] & (side[k] != 0)
                    enough = same.sum(0) >= min_others
                    ref[i] = np.where(enough, np.nanmedian(np.where(same, last[rows], np.nan), axis=0), ref[i])
        return ref
    return side_reference


def tree_z(x: np.ndarray, tasks: np.ndarray, floor, min_demos: int, small: str = "nan"):
    """``modelfree.task_z`` of each dimension's end and change against its prediction from the demo's whole start
    (its end less its change) by gradient-boosted trees (absolute error) fitted on the other folds' tasks, start and
    target centred on their task's median and in robust units."""
    from sklearn.ensemble import HistGradientBoostingRegressor
    from sklearn.model_selection import GroupKFold, KFold

    d = x.shape[1] // 2
    first = x[:, :d] - x[:, d:]
    _, med = SHIPPED_Z(x, tasks, floor, min_demos, small)
    _, start_med = SHIPPED_Z(first, tasks, 0.0, min_demos, small)
    ok = np.flatnonzero(np.isfinite(med).any(1) & np.isfinite(x).all(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        xs = first - start_med
        xs = xs / np.fmax(1.4826 * np.nanmedian(np.abs(xs[ok]), 0), 1e-9)
        unit = np.fmax(1.4826 * np.nanmedian(np.abs((x - med)[ok]), 0), floor)
    y = np.nan_to_num((x - med) / unit)
    pred = med.copy()
    folds = GroupKFold(5) if len(np.unique(tasks[ok])) >= 5 else KFold(5, shuffle=True, random_state=0)
    for fit, held in folds.split(ok, groups=tasks[ok]):
        for j in range(x.shape[1]):
            if not np.isfinite(unit[j]):
                continue
            trees = HistGradientBoostingRegressor(loss="absolute_error", max_iter=60, min_samples_leaf=10)
            trees.fit(xs[ok[fit]], y[ok[fit], j])
            pred[ok[held], j] = med[ok[held], j] + trees.predict(xs[ok[held]]) * unit[j]
    z, _ = SHIPPED_Z(x - pred, tasks, floor, min_demos, small)
    return z, pred


def moved_only(first, last, tasks, median, min_side=outcome.OUTCOME_MIN_SIDE):
    """``outcome.side_reference`` only in the dimensions the task's demos move (their median change beyond
    ``outcome.dimension_floor``): the other object keeps the task's median."""
    ref = SHIPPED_SIDE(first, last, tasks, median, min_side)
    _, change = SHIPPED_Z(last - first, tasks, 0.0, outcome.OUTCOME_MIN_DEMOS)
    return np.where(np.abs(change) > outcome.dimension_floor(last), ref, median)


SHIPPED_SIDE = outcome.side_reference
SIDES = {"whole task": {"by_side": False}, "side where moved": {"side": moved_only}, **{f"others on side >= {k}": {"side": others_on_side(k)} for k in (1, 2, 3)},
         "trees on the start": {"by_side": False, "task_z": tree_z}}


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
        for name, task_z in REFERENCES.items():
            outcome.task_z = task_z
            try:
                score, _ = outcome.outcome(stats, tasks)
            finally:
                outcome.task_z = SHIPPED_Z
            alone = " ".join(f"{a:.3f}" for a in aurocs(score, labels).values())
            print(f"  {name:<26} alone {alone} | ranking {judged(table, score, 'outcome')}", flush=True)
        for name, how in SIDES.items():
            outcome.task_z, outcome.side_reference = how.get("task_z", SHIPPED_Z), how.get("side", SHIPPED_SIDE)
            try:
                score, _ = outcome.outcome(stats, tasks, by_side=how.get("by_side", True))
            finally:
                outcome.task_z, outcome.side_reference = SHIPPED_Z, SHIPPED_SIDE
            alone = " ".join(f"{a:.3f}" for a in aurocs(score, labels).values())
            print(f"  {name:<26} alone {alone} | ranking {judged(table, score, 'outcome')}", flush=True)


if __name__ == "__main__":
    main()
