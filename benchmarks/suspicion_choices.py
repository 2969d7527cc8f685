"""The development-set sweep behind the ranking's design: how to calibrate scores, and which go into it.

    python benchmarks/suspicion_choices.py BENCH_DIR [BENCH_DIR ...]

BENCH_DIR is a ``democheck bench`` output (its scores.parquet: each demo's task, label and every scorer's
score).  For every variant it prints the AUROC of each labelled kind against the clean demos, the mean over
kinds, and the share of clean and of bad demos above a range of flag thresholds.

Variants: how each score is standardised before the ranking takes the largest -- against all demos
(``all``), within its task by the task's median and MAD (``task``), or the task's median and the pooled MAD
of every demo's distance from its task's median (``task-median``) -- and which scores go in.
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

SCALE = 1.4826


def _mad(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return max(SCALE * float(np.median(np.abs(x - np.median(x)))), 1e-9) if len(x) else 1.0


def standardise(x: np.ndarray, tasks: np.ndarray, how: str, two_sided: bool = False) -> np.ndarray:
    z = np.full(len(x), np.nan)
    if how == "all":
        ok = np.isfinite(x)
        z = (x - np.median(x[ok])) / _mad(x)
    else:
        resid = np.full(len(x), np.nan)
        for t in np.unique(tasks):
            i = tasks == t
            resid[i] = x[i] - np.nanmedian(x[i])
        if how == "task-median":
            z = resid / _mad(resid)
        else:
            for t in np.unique(tasks):
                i = tasks == t
                z[i] = resid[i] / _mad(x[i])
    return np.abs(z) if two_sided else z


LOGGED = {False: (), True: ("task_uncertainty", "consistency", "action_error", "novelty"), "act": ("action_error",),
          "act+unc": ("action_error", "task_uncertainty")}


def ranking(table: pd.DataFrame, cols: list[str], how: str, log=False) -> np.ndarray:
    tasks = table["task"].to_numpy()
    # ``log``: positive scores on a log scale first, where their clean demos' right tails are nearer Gaussian.
    vals = {c: np.log(np.maximum(table[c].to_numpy(float), 1e-6)) if c in LOGGED[log]
            else table[c].to_numpy(float) for c in cols}
    z = np.column_stack([standardise(vals[c], tasks, how, two_sided=c.startswith("motion")) for c in cols])
    return np.nanmax(np.where(np.isfinite(z), z, -np.inf), axis=1)


def report(table: pd.DataFrame, name: str, cols: list[str], how: str, log=False) -> None:
    s = table[cols[0]].to_numpy(float) if how == "as is" else ranking(table, cols, how, log)
    labels = table["label"].to_numpy()
    kinds = sorted(set(labels) - {"clean"})
    au = []
    for k in kinds:
        sel = (labels == k) | (labels == "clean")
        au.append(roc_auc_score(labels[sel] == k, np.nan_to_num(s[sel], nan=-1e9)))
    clean, bad = s[labels == "clean"], s[labels != "clean"]
    flags = " ".join(f"{th}:{np.mean(clean > th):.3f}/{np.mean(bad > th):.2f}" for th in (4, 6, 8, 10, 12))
    print(f"  {name:<34} {how + (f' log {log}' if log else ''):<22} " + " ".join(f"{a:.2f}" for a in au) + f" | {np.mean(au):.3f} | {flags}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benches", nargs="+")
    args = ap.parse_args()
    for path in args.benches:
        table = pd.read_parquet(f"{path}/scores.parquet")
        kinds = sorted(set(table["label"]) - {"clean"})
        have = set(table.columns)
        print(f"{path}: {len(table)} demos, {table['task'].nunique()} tasks; AUROC " + " ".join(kinds)
              + " | mean | flag threshold: clean/bad share above")
        base = ["task_uncertainty", "consistency", "action_error"]
        sets = {"ranking (unc., cons., act.)": base}
        if "motion" in have:
            sets["+ motion"] = base + ["motion"]
            sets["cons. + act. + motion"] = ["consistency", "action_error", "motion"]
        if "novelty" in have:
            sets["+ novelty"] = base + ["novelty"]
            if "motion" in have:
                sets["+ motion + novelty"] = base + ["motion", "novelty"]
        table["as computed"] = table["suspicion"]
        report(table, "democheck's suspicion, as computed", ["as computed"], "as is")
        for name, cols in sets.items():
            for how in ("all", "task", "task-median"):
                for log in LOGGED:
                    report(table, name, cols, how, log)


if __name__ == "__main__":
    main()
