"""The arithmetic of democheck's scores (the registry of scorers, ``democheck.audit.scorers``, calls it).

Every score is one number per demo, higher = more suspect:

- ``task_uncertainty`` (the paper's score): the mean over embedding dimensions
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
- ``action_error`` (on by default; ``audit --no-actions`` skips it): how badly the model's
  own controller, told the task by the other demos of the same task (their
  product-of-Gaussians mean; the demo's own mu for a task's only demo),
  explains what the demo did: the mean squared error, in normalised action
  units, between the demo's actions and the controller's at
  ``scorers.ACTION_STEPS`` evenly spaced timesteps (computed by
  ``scorers.ActionErrors`` in the audit's decoding pass).  The cue sees two frames; this sees the
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
  suspicion threshold flags those.  8 was chosen on two development sets
  (push-v1-dev + probes; Meta-World mw-dev with a your-data model) for at most
  about the OCSVM's 1% of clean demos once scores are calibrated within tasks:
  thresholds 6, 8, 10 flag 0.8%, 0.3%, 0.3% of push-v1-dev's clean demos and
  4.0%, 1.0%, 0.5% of mw-dev's, and 68%, 61%, 56% / 80%, 69%, 69% of their bad
  ones (``benchmarks/suspicion_choices.py``).  Before the calibration, the
  same 8 flagged 20% of mw-dev's clean demos.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from democheck.petnet.posterior import TaskPosterior


CONSISTENCY_K = 5
SUSPICION_FLAG = 8.0  # robust standard deviations; see ``is_anomaly`` above


def consistency_terms(post: TaskPosterior, tasks: np.ndarray, k: int | None = CONSISTENCY_K) -> np.ndarray:
    """Per demo and dimension, (mu - m)^2 / (v + var) against the product of its k nearest other demos of the
    task (see the module docstring): [N, z], NaN for a task's only demo."""
    m, v = post.others(tasks, k)
    return (post.mu - m) ** 2 / (v + post.var)


def consistency(post: TaskPosterior, tasks: np.ndarray, k: int | None = CONSISTENCY_K) -> np.ndarray:
    """Task consistency of each demo against its k nearest other demos of the task (see module docstring)."""
    return np.sqrt(consistency_terms(post, tasks, k).mean(1))


def robust_stats(x: np.ndarray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    if not len(x):
        return {"median": 0.0, "scale": 1.0}
    med = float(np.median(x))
    return {"median": med, "scale": float(max(1.4826 * np.median(np.abs(x - med)), 1e-9))}


def standardise(x: np.ndarray, stats: dict[str, float]) -> np.ndarray:
    return (x - stats["median"]) / stats["scale"]


# How a score is put in robust standard deviations before the ranking compares it with others: against all the
# demos scored ("all"), or within its task ("task": each demo's distance from its task's median, over the MAD of
# those distances across all demos), so that a task whose demos all score high -- a harder task, one the model
# knows less -- does not fill the top ranks, while a task of a dozen demos does not need a scale of its own.
# Chosen on two development sets (Meta-World mw-dev, 10 tasks x ~24 demos, a your-data model; push-v1-dev +
# probes, the shipped model; ``benchmarks/suspicion_choices.py``), mean AUROC of the ranking over their 13 kinds:
# all 0.917; each task's own median and MAD 0.947; "task" 0.958 (with the motion check and the action error on a
# log scale: mw-dev 0.949, push-v1-dev 0.961).  The model-free ``view`` check and a trimmed novelty density were
# measured in the ranking too and left out: on mw-dev they flagged 6-13% of clean demos at the threshold below.
CALIBRATION = "task"
CALIBRATIONS = ("all", "task")


def calibrated(x: np.ndarray, tasks: np.ndarray | None = None, how: str = CALIBRATION, min_scale: float = 0.0
               ) -> np.ndarray:
    """``x`` in robust standard deviations (median, 1.4826 x MAD): of all demos, or within each demo's task.

    ``min_scale``: the least spread a standard deviation stands for, in ``x``'s units -- for a measurement that
    scripted or very regular demos repeat almost exactly, where a MAD near zero would call any small difference
    many standard deviations."""
    if how == "all" or tasks is None or len(np.unique(tasks)) < 2:
        stats = robust_stats(x)
        return standardise(x, {**stats, "scale": max(stats["scale"], min_scale)})
    if how not in CALIBRATIONS:
        raise ValueError(f"calibration {how!r}; one of {', '.join(CALIBRATIONS)}")
    finite = np.where(np.isfinite(x), x, np.nan)
    resid = finite - pd.Series(finite).groupby(np.asarray(tasks)).transform("median").to_numpy()
    return standardise(resid, {"median": 0.0, "scale": max(robust_stats(resid)["scale"], min_scale)})




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


def reference(post: TaskPosterior, tasks: np.ndarray, nu: float = 0.01) -> dict[str, Any]:
    """What an audit of new data keeps from the training demos: the OCSVM, and their score scales (reported)."""
    return {"score": robust_stats(post.task_uncertainty()), "consistency": robust_stats(consistency(post, tasks)),
            "ocsvm": fit_ocsvm(post.sigma, nu)}


def flags(margin: np.ndarray, suspicion_z: np.ndarray) -> np.ndarray:
    """``is_anomaly``: on the anomalous side of the one-class SVM, or a suspicion above ``SUSPICION_FLAG``."""
    return (margin < 0) | (suspicion_z > SUSPICION_FLAG)


def rank_order(suspicion_z: np.ndarray, episode_index: np.ndarray) -> np.ndarray:
    """Row order of a ranking: most suspect first, ties by episode index (NaN last)."""
    return np.lexsort((episode_index, -np.nan_to_num(suspicion_z, nan=-np.inf)))
