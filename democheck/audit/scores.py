"""Scores: one number per demo, higher = more suspect, plus a flag.

- ``score`` (task uncertainty, the paper): the mean over embedding dimensions
  of the task standard deviation sqrt(var) of the demo's cue.
- ``consistency``: how far the demo's ``mu`` lies from the product-of-Gaussians
  posterior of its ``CONSISTENCY_K`` nearest *other* demos of the same task
  (all of them when there are fewer), as the root-mean-square over
  dimensions of (mu - m) / sqrt(v + var), where (m, v) is that posterior and
  var the demo's own variance: the spread expected of a demo that says the
  same as its neighbours.  Nearest by that same distance, pairwise.  The
  posterior of *all* the others is blurred by the task's own bad demos and
  by tasks done in more than one way; the neighbours' is not (on a separate
  development set, ``push-v1-dev`` + probes, mean AUROC over the 8 kinds:
  all others 0.67; k = 1, 2, 3, 5, 8: 0.75, 0.76, 0.77, 0.80, 0.80; 5 is
  also the kNN baseline's k; ``benchmarks/score_choices.py``).  Variance catches cues that say nothing;
  consistency catches cues that clearly say the wrong thing.  NaN for a task
  with a single demo.
- ``action_error`` (optional, ``audit --actions``): how badly the model's
  own controller, told the task by the other demos of the same task (their
  product-of-Gaussians mean; the demo's own mu for a task's only demo),
  explains what the demo did: the mean squared error, in normalised action
  units, between the demo's actions and the controller's at ``ACTION_STEPS``
  evenly spaced timesteps.  The cue sees two frames; this sees the
  behaviour, so it catches an arm that never moved or flailed, or stopped
  half-way, whatever its first and last frames look like.
- ``suspicion``: the largest of those scores after robust standardisation
  against the audited demos themselves (median and 1.4826 x MAD, which a
  minority of bad demos does not move): a demo extreme on any count is
  suspect, and they are in the same units.  The action error has no
  training-time scale, and the consistency scale stored with older models
  (``reference``) belongs to the all-others definition; with the
  all-others consistency, standardising the cue scores by the training
  demos instead scored no-action 0.71 and gave-up 0.53 AUROC on the bench
  (push-v1-test + probes), this rule 0.88 and 0.76; with the current
  definition the two rules tie on the development set (all kinds 0.88).
- ``is_anomaly``: flagged by the linear one-class SVM of the paper (nu = 1%
  by default), fitted on the training demos' task uncertainty, *or* with a
  suspicion above ``SUSPICION_FLAG`` robust standard deviations.  A linear
  one-class SVM flags points on the origin's side of its hyperplane, so it
  is fitted on precisions 1/sigma^2 (the product of Gaussians' currency): a
  demo is flagged when its precision is low, i.e. its uncertainty high.  It
  sees sigma only, which barely moves for an idle or flailing arm; the
  suspicion threshold flags those.  8 was chosen on the development set
  (push-v1-dev + probes) for about the OCSVM's 1% of clean demos: 4, 6, 8, 10
  flag 12.5%, 4.4%, 0.5%, 0% of its clean demos (on push-v1-test 0.3% at 8;
  ``benchmarks/score_choices.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd


def task_score(sigma: np.ndarray) -> np.ndarray:
    """The paper's task uncertainty of each demo: mean task standard deviation, [N, z] -> [N]."""
    return sigma.mean(axis=1)


CONSISTENCY_K = 5
SUSPICION_FLAG = 8.0  # robust standard deviations; see ``is_anomaly`` above


def others_posterior(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray, k: int | None = None,
                     chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """For each demo, the product of Gaussians of the *other* demos of its task -- all of them, or its ``k``
    nearest by RMS (mu_i - mu_j) / sqrt(var_i + var_j): (m, v), NaN for a task's only demo."""
    m_out, v_out = np.full(mu.shape, np.nan), np.full(mu.shape, np.nan)
    prec = 1.0 / var
    for task in np.unique(tasks):
        idx = np.flatnonzero(tasks == task)
        if len(idx) < 2:
            continue
        if k is None or k >= len(idx) - 1:
            p_rest = prec[idx].sum(0)[None] - prec[idx]  # precision of the others, per demo
            m_out[idx] = ((prec[idx] * mu[idx]).sum(0)[None] - prec[idx] * mu[idx]) / p_rest
            v_out[idx] = 1.0 / p_rest
            continue
        for s in range(0, len(idx), chunk):  # [chunk, n, z] at a time: a task may hold thousands of demos
            rows = idx[s:s + chunk]
            d = ((mu[rows, None] - mu[None, idx]) ** 2 / (var[rows, None] + var[None, idx])).mean(-1)
            d[np.arange(len(rows)), s + np.arange(len(rows))] = np.inf  # not itself
            nn = idx[np.argpartition(d, k - 1, axis=1)[:, :k]]  # [rows, k]
            p = prec[nn].sum(1)
            m_out[rows] = (prec[nn] * mu[nn]).sum(1) / p
            v_out[rows] = 1.0 / p
    return m_out, v_out


def consistency(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray, k: int | None = CONSISTENCY_K) -> np.ndarray:
    """Task consistency of each demo against its k nearest other demos of the task (see module docstring)."""
    m, v = others_posterior(mu, var, tasks, k)
    return np.sqrt(((mu - m) ** 2 / (v + var)).mean(1))


def robust_stats(x: np.ndarray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    if not len(x):
        return {"median": 0.0, "scale": 1.0}
    med = float(np.median(x))
    return {"median": med, "scale": float(max(1.4826 * np.median(np.abs(x - med)), 1e-9))}


def standardise(x: np.ndarray, stats: dict[str, float]) -> np.ndarray:
    return (x - stats["median"]) / stats["scale"]


def suspicion(scores: dict[str, np.ndarray]) -> np.ndarray:
    """The largest robust z-score of each demo over the scores it has (NaN ones, e.g. a lone demo's, skipped)."""
    z = np.column_stack([standardise(x, robust_stats(x)) for x in scores.values()])
    return np.nanmax(np.where(np.isfinite(z), z, -np.inf), axis=1)


# ---------------------------------------------------------------------------
# one-class SVM (stored as plain numbers in the model's config.json)
# ---------------------------------------------------------------------------

def ocsvm_features(sigma: np.ndarray) -> np.ndarray:
    return 1.0 / np.maximum(sigma, 1e-6) ** 2


def fit_ocsvm(sigma: np.ndarray, nu: float = 0.01) -> dict[str, Any]:
    """Fit the linear one-class SVM on training demos' sigma vectors; returns JSON-able parameters."""
    from sklearn.svm import OneClassSVM

    x = ocsvm_features(sigma)
    scale = x.mean(0)  # features are precisions in the 1e2..1e8 range: put them near 1 for the solver
    svm = OneClassSVM(kernel="linear", nu=nu).fit(x / scale)
    return {"kernel": "linear", "feature": "precision", "nu": nu, "scale": scale.tolist(),
            "coef": svm.coef_.ravel().tolist(), "offset": float(svm.offset_[0]), "n_fit": int(len(x)),
            "flagged_fraction_on_fit": float((svm.decision_function(x / scale) < 0).mean())}


def ocsvm_margin(params: dict[str, Any], sigma: np.ndarray) -> np.ndarray:
    """Signed distance-like margin: negative = on the anomalous side of the hyperplane."""
    x = ocsvm_features(sigma) / np.asarray(params["scale"])
    return x @ np.asarray(params["coef"]) - params["offset"]


def reference(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray, nu: float = 0.01) -> dict[str, Any]:
    """What an audit of new data keeps from the training demos: the OCSVM, and their score scales (reported)."""
    sigma = np.sqrt(var)
    return {"score": robust_stats(task_score(sigma)), "consistency": robust_stats(consistency(mu, var, tasks)),
            "ocsvm": fit_ocsvm(sigma, nu)}


def score_table(episodes: pd.DataFrame, mu: np.ndarray, var: np.ndarray, ref: dict[str, Any] | None,
                action_error: np.ndarray | None = None) -> pd.DataFrame:
    """The ScoreTable: one row per demo, ranked by suspicion (rank 1 = most suspect)."""
    sigma = np.sqrt(var)
    tasks = episodes["task"].to_numpy()
    scores = {"score": task_score(sigma), "consistency": consistency(mu, var, tasks)}
    if action_error is not None:
        scores["action_error"] = action_error
    susp = suspicion(scores)
    table = pd.DataFrame({"episode_index": episodes["episode_index"].to_numpy(np.int64), "task": tasks, **scores,
                          "suspicion": susp})
    ref = ref or {}
    margin = ocsvm_margin(ref["ocsvm"], sigma) if ref.get("ocsvm") else np.full(len(table), np.nan)
    table["ocsvm_margin"] = margin
    table["is_anomaly"] = (margin < 0) | (susp > SUSPICION_FLAG)
    table["sigma"] = list(sigma.astype(np.float32))
    table["mu"] = list(mu.astype(np.float32))
    for col in ("label", "split"):
        if col in episodes:
            table[col] = episodes[col].to_numpy()
    order = np.lexsort((table["episode_index"].to_numpy(), -np.nan_to_num(susp, nan=-np.inf)))
    table = table.iloc[order].reset_index(drop=True)
    table.insert(2, "rank", np.arange(1, len(table) + 1))
    return table
