"""Detection metrics for scorers with the uniform contract: higher score = more suspect."""

from __future__ import annotations

import numpy as np


def precision_at_k(is_bad: np.ndarray, scores: np.ndarray, k: int | None = None) -> float:
    """Share of true bad demos among the k highest scores (k defaults to the number of bad demos)."""
    is_bad = np.asarray(is_bad, bool)
    k = int(is_bad.sum()) if k is None else k
    if k == 0:
        return float("nan")
    order = np.argsort(-np.nan_to_num(np.asarray(scores, float), nan=-np.inf), kind="stable")
    return float(is_bad[order[:k]].mean())


def detection(is_bad: np.ndarray, scores: np.ndarray) -> dict[str, float]:
    """AUROC, AUPRC and precision at k (k = number of bad demos) of one scorer for one kind versus clean."""
    from scipy.stats import rankdata
    from sklearn.metrics import average_precision_score, roc_auc_score

    is_bad = np.asarray(is_bad, bool)
    scores = np.asarray(scores, float)
    # Only the order matters: ranks keep +inf (a broken demo) on top and put NaN (nothing to say) at the bottom.
    s = rankdata(np.nan_to_num(scores, nan=-np.inf))
    # A scorer that says nothing of any of these demos (a gripper's count where none is named) has no figure.
    both = 0 < is_bad.sum() < len(is_bad) and not np.isnan(scores).all()
    return {"auroc": float(roc_auc_score(is_bad, s)) if both else float("nan"),
            "auprc": float(average_precision_score(is_bad, s)) if both else float("nan"),
            "p_at_k": precision_at_k(is_bad, s), "n": int(is_bad.sum())}


def by_label(table, column: str = "suspicion") -> dict[str, dict[str, float]]:
    """Detection of every non-clean label versus the clean demos, by one score column of a ScoreTable."""
    out = {}
    labels = table["label"].to_numpy()
    for kind in sorted(set(labels) - {"clean"}):
        keep = (labels == kind) | (labels == "clean")
        out[kind] = detection(labels[keep] == kind, table[column].to_numpy()[keep])
    bad = labels != "clean"
    if bad.any() and len(set(labels) - {"clean"}) > 1:
        out["all"] = detection(bad, table[column].to_numpy())
    return out


def separation(labels: np.ndarray, scores: np.ndarray) -> str:
    """Per non-clean label, its AUROC against the clean demos and the share of its demos above every clean one
    (which a flag needs): 'detour 0.959 (0.38 beyond), ...'."""
    labels, scores = np.asarray(labels), np.asarray(scores, float)
    clean = labels == "clean"
    top = np.nanmax(scores[clean])
    return ", ".join(f"{k} {detection(labels[clean | (labels == k)] == k, scores[clean | (labels == k)])['auroc']:.3f} "
                     f"({np.mean(scores[labels == k] > top):.2f} beyond)" for k in sorted(set(labels) - {"clean"}))
