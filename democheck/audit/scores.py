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
  also the kNN baseline's k; ``benchmarks/score_choices.py``).  Measured and not shipped: each dimension in
  units of its median task SD instead of sqrt(v + var) -- alone far better (dev mean AUROC 0.96, no-objects
  0.99, hidden 1.00) but the ranking *worse* on no-objects (dev 0.952 -> 0.924-0.949): the combination
  dilutes it (see ``suspicion``).  Variance catches cues that say nothing;
  consistency catches cues that clearly say the wrong thing.  NaN for a task
  with a single demo.
- ``action_error`` (on by default; ``audit --no-actions`` skips it): how badly the model's
  own controller, told the task by the other demos of the same task (their
  product-of-Gaussians mean; the demo's own mu for a task's only demo),
  explains what the demo did: the mean squared error, in normalised action
  units, between the demo's actions and the controller's at
  ``action_error.ACTION_STEPS`` evenly spaced timesteps (computed by
  ``action_error.ActionErrors`` in the audit's decoding pass).  The cue sees two frames; this sees the
  behaviour, so it catches an arm that never moved or flailed, or stopped
  half-way, whatever its first and last frames look like.
- ``suspicion`` (the ranking): how surprising the demo is, all evidence together, as -log10 of a
  probability (``p_value``): 2 means "as unusual as one clean demo in a hundred".  Each score of the
  ranking is first put in robust standard deviations within its task (``calibrated``: a task whose demos
  all score high does not fill the top ranks), then turned into a tail probability by
  ``tail_probabilities``.  The reference is the audited demos themselves -- their middle half, which a
  minority of bad demos does not move: each score's right tail is taken as exponential from its 25th to its
  75th percentile onwards, so a score whose clean demos spread widely (the task uncertainty of a model on new
  tasks) needs a larger value to count as much as one whose clean demos agree (how still the arm is).
  The tail probabilities are combined by Fisher's method with Brown's correction (``combined_log10``):
  -2 sum log p against a scaled chi-square whose variance counts the scores' dependence, measured on the
  audited demos' core (``brown_scale``).  Several moderate surprises add up -- a demo that gave up half-way
  is a little still, a little slow, and ends a little short, each as unusual as one clean demo in ten to a
  hundred -- where the smallest alone (the Sidak minimum, the ranking before; still used below
  ``BROWN_MIN_DEMOS`` demos) waits for one of them to be extreme.  Chosen on the development sets
  (``benchmarks/suspicion_choices.py``): on push-v1-dev audited alone (614 clean, the shipped model, the
  outcome check in), at ``--fpr 0.01`` the Sidak minimum flagged 0.81% of the clean demos and 0.61 of the
  gave-up demos, Fisher-Brown 0.65% and 0.97 (both-objects and occluded 1.00, wrong-object 0.95 either way;
  ranking AUROC 0.993 and 0.999 for gave-up, the other kinds equal); on Meta-World
  mw2-dev (200 clean, its your-data model) 4.0% and 3.0% of the clean demos (2 of them exact copies of
  another demo), every bad demo either way.  Fisher's sum without Brown's correction takes the scores as
  independent: on scores that move together it flags several times the rate asked for
  (``tests/test_modelfree.py``).  Earlier choices, with the Sidak minimum: the tails against the largest
  robust z, mean AUROC over the kinds of push-v1-dev + probes and Meta-World mw-dev 0.962 and 0.957 with the
  largest z, 0.971 and 0.965 with these tail probabilities; the 25th-50th, 50th-75th and 50th-90th
  percentiles gave 0.975/0.961, 0.970/0.966 and 0.963/0.975 (no better on both); ranks among the audited
  demos instead (empirical p-values: their minimum, or Fisher's sum) 0.966/0.953 and 0.956/0.948: ranks
  cannot tell how far beyond every clean demo a bad one lies.
- ``is_anomaly``: ``p_value`` at most the false-positive rate asked for (``audit --fpr``, default
  ``DEFAULT_FPR``): if the audited demos were all clean, about that share of them would be flagged.  The
  exponential tails and Brown's two-moment match are models, not laws -- with labels, the audit's summary
  reports the observed rate.  Exact copies of another demo are flagged too.  The paper's linear one-class SVM
  stays a column (``ocsvm_margin``) and a bench scorer (``ocsvm_flag``): fitted on the training demos'
  precisions 1/sigma^2, it sees sigma only, which barely moves for an idle or flailing arm.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from democheck.petnet.posterior import TaskPosterior


CONSISTENCY_K = 5
DEFAULT_FPR = 0.01  # see ``is_anomaly`` above
TAIL_QUANTILES = (0.25, 0.75)  # see ``suspicion`` above
TAIL_MIN_SCALE = 0.5  # robust SD: no tail falls faster than by e per half a robust standard deviation
BROWN_CORE = 0.1  # see ``brown_scale``
BROWN_MIN_DEMOS = 30


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
# log scale: mw-dev 0.949, push-v1-dev 0.961).  A trimmed novelty density was measured in the ranking too and left
# out: on mw-dev it flagged 6-13% of clean demos at the threshold below.  (mw-dev was made by a Meta-World
# generator that rendered about a third of its clean demos from a broken GL state; ``modelfree.view`` was chosen
# on its regenerated successor, mw2-dev.)
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


def tail_probabilities(z: np.ndarray) -> np.ndarray:
    """Natural log of the tail probability of each entry of [N, K] scores in robust standard deviations,
    column by column: an exponential tail through the column's ``TAIL_QUANTILES`` (probability 0.75 at its
    25th percentile, 0.25 at its 75th), at most 1, its scale at least ``TAIL_MIN_SCALE``.  NaN (no score)
    gives log 1; +inf (an exact copy) log 0."""
    lo, hi = TAIL_QUANTILES
    out = np.zeros(z.shape)
    for k in range(z.shape[1]):
        x = z[:, k]
        ok = np.isfinite(x) | (x == np.inf)
        if not ok.any():
            continue
        q_lo, q_hi = np.quantile(x[np.isfinite(x)], [lo, hi]) if np.isfinite(x).any() else (0.0, 0.0)
        beta = max((q_hi - q_lo) / np.log((1 - lo) / (1 - hi)), TAIL_MIN_SCALE)
        tail = np.log(1 - lo) - (x - q_lo) / beta
        out[:, k] = np.where(ok, np.minimum(tail, 0.0), 0.0)
    return out


def sidak_log10(log_p: np.ndarray) -> np.ndarray:
    """log10 of the Sidak-corrected smallest of each row's K tail probabilities (given as natural logs):
    1 - (1 - min p)^K, the chance that the most surprising of K independent clean scores is this surprising
    (valid, and conservative, whatever their dependence)."""
    k = log_p.shape[1]
    m = np.nan_to_num(log_p.min(axis=1), nan=0.0, neginf=-np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        exact = np.log(-np.expm1(k * np.log1p(-np.exp(np.minimum(m, -1e-16)))))
    return np.where(m < -30, np.log(k) + m, exact) / np.log(10)


def brown_scale(log_p: np.ndarray) -> tuple[float, float] | None:
    """(c, f) of Brown's method for the rows' K tail probabilities: Fisher's statistic -2 sum log p is taken as
    c x chi-square with f degrees of freedom, matching its mean 2K and its variance 4K + 4 sum_{i != j} rho_ij,
    the rho_ij the Spearman correlations of the columns' -log p over the core (their sum taken as at least 0):
    the rows whose Sidak-combined probability is above ``BROWN_CORE`` (a bad demo, surprising on several scores
    at once, would otherwise pass for dependence).  None when the core has fewer than ``BROWN_MIN_DEMOS`` rows or a single column."""
    k = log_p.shape[1]
    core = 10.0 ** sidak_log10(log_p) > BROWN_CORE
    if k < 2 or core.sum() < BROWN_MIN_DEMOS:
        return None
    from scipy.stats import spearmanr

    with np.errstate(all="ignore"):
        rho = np.atleast_2d(spearmanr(-log_p[core]).correlation)
    rho = np.nan_to_num(rho, nan=0.0)  # a column constant over the core (no score there) depends on nothing
    # Never taken as less variable than independent scores: negative dependence is not counted on.
    var = 4.0 * k + 4.0 * max(float(rho.sum() - np.trace(rho)), 0.0)
    return var / (4.0 * k), 8.0 * k * k / var


def combined_log10(log_p: np.ndarray) -> np.ndarray:
    """log10 of the combined tail probability of each row's K tail probabilities (given as natural logs):
    Fisher's -2 sum log p against Brown's scaled chi-square (``brown_scale``: the scores' dependence measured on
    the audited demos themselves), or, with too few demos to measure it, the Sidak minimum."""
    if log_p.shape[1] == 0:
        return np.zeros(len(log_p))
    scale = brown_scale(log_p)
    if scale is None:
        return sidak_log10(log_p)
    from scipy.special import gammaln
    from scipy.stats import chi2

    c, f = scale
    stat = -2.0 * np.nan_to_num(log_p, nan=0.0, neginf=-np.inf).sum(axis=1)
    with np.errstate(all="ignore"):
        x = stat / c
        out = chi2.logsf(x, f)
        # Far out, where logsf underflows: the upper incomplete gamma's leading term, so that the most
        # surprising demos keep their order instead of all tying at -inf.
        far = (f / 2.0 - 1.0) * np.log(x / 2.0) - x / 2.0 - gammaln(f / 2.0)
        out = np.where(np.isfinite(out) | ~np.isfinite(x), out, far)
    return np.where(np.isinf(stat), -np.inf, out / np.log(10))


def exact_copies(table: pd.DataFrame) -> np.ndarray | None:
    """Which rows of a score table are bit-exact copies of another demo (``duplicate`` is +inf); None when the
    table has no duplicate check."""
    return np.isinf(table["duplicate"].to_numpy(np.float64)) if "duplicate" in table else None


def flags(p_value: np.ndarray, fpr: float = DEFAULT_FPR, exact_copy: np.ndarray | None = None) -> np.ndarray:
    """``is_anomaly``: a combined tail probability at most ``fpr``, or an exact copy of another demo."""
    out = np.nan_to_num(p_value, nan=1.0) <= fpr
    return out | exact_copy if exact_copy is not None else out


def rank_order(suspicion: np.ndarray, episode_index: np.ndarray) -> np.ndarray:
    """Row order of a ranking: most suspect first, ties by episode index (NaN last)."""
    return np.lexsort((episode_index, -np.nan_to_num(suspicion, nan=-np.inf)))
