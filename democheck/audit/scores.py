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
  suspicion threshold flags those.  8 was chosen on the development set
  (push-v1-dev + probes) for about the OCSVM's 1% of clean demos: 4, 6, 8, 10
  flag 12.5%, 4.4%, 0.5%, 0% of its clean demos (on push-v1-test 0.3% at 8;
  ``benchmarks/score_choices.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

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


def standardised(scores: dict[str, np.ndarray]) -> np.ndarray:
    """Each score robustly standardised against the demos given: [N, len(scores)], -inf where a score is NaN."""
    z = np.column_stack([standardise(x, robust_stats(x)) for x in scores.values()])
    return np.where(np.isfinite(z), z, -np.inf)



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
