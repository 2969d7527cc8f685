"""The arithmetic of democheck's scores (the registry of scorers, ``democheck.audit.scorers``, calls it).

Every score is one number per demo, higher = more suspect.  The model's scores:

- ``task_uncertainty`` (the paper's score): the mean over embedding dimensions of the task standard deviation
  sqrt(var) of the demo's cue.  It catches cues that say nothing.
- ``novelty``: how unfamiliar the demo's end is to the model: the novelty part of its task variance over the
  prior's (a squared feature distance from the training demos' ends over the model's reference, mean over the
  embedding's dimensions).
- ``consistency``: the mean Euclidean distance from the demo's ``mu`` to those of its ``CONSISTENCY_K`` nearest
  *other* demos of the task (at most half of them, so that a small task's bad minority is not every clean demo's
  neighbours), each dimension in units of its median task standard deviation (``consistency_units``).  It
  catches cues that clearly say the wrong thing.  NaN for a task's only demo.
- ``action_error`` (``action_error.ActionErrors``; ``audit --no-actions`` skips it): the mean squared error, in
  normalised action units at ``action_error.ACTION_STEPS`` evenly spaced steps, between the demo's actions and the
  model's controller's, told the task by the task's other demos (``action_error.controller_z``).  It sees the
  behaviour: an arm that never moved, flailed or stopped half-way, whatever its first and last frames look like.

The ranking, ``suspicion`` (-log10 of ``p_value``: 2 = as unusual as one clean demo in a hundred):

- ``calibrated``: each score in robust standard deviations within its task (the task uncertainty and the action
  error on a log scale first: long right tails), so that a task whose demos all score high does not fill the top
  ranks; with ``core``, each task's centre and the unit come from the core's demos alone.
- ``tail_probabilities``: an exponential right tail through the core's ``TAIL_QUANTILES`` (a normal one for a
  score that is a mean over many steps, ``ScoreSpec.tail``).
- ``robust_tails``: the robust core -- every demo, then those whose combined probability is above ``core_p``,
  refitted until it stops changing -- so that bad demos widen neither the tails nor the units they are judged by.
- ``combined_log10``: Fisher's method with Brown's correction (``brown_scale``), so that several moderate
  surprises add up (a demo that gave up half-way is a little still, a little slow and ends a little short); the
  Sidak minimum (``sidak_log10``) under ``BROWN_MIN_DEMOS`` demos.  The scores of one look are merged first
  (``merge_looks``); the recording faults (``ScoreSpec.alone``) stand beside the sum by their own Sidak minimum.
- ``is_anomaly``: the flags, conformal on the same core (``democheck.audit.flagging``).

Each choice, the alternatives and the sets they were measured on: docs/decisions.md ("How scores become a ranking
and a flag"; "Consistency: the nearest task-mates").
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np
import pandas as pd

from democheck.petnet.posterior import TaskPosterior


CONSISTENCY_K = 5  # the nearest other demos of its task a demo's ``consistency`` is measured against
TAIL_QUANTILES = (0.25, 0.75)  # the core's percentiles an exponential tail passes through (probability 0.75, 0.25)
TAIL_MIN_SCALE = 0.5  # robust SD: no tail falls faster than by e per half a robust standard deviation
BROWN_CORE = 0.1  # Brown's dependence is measured on the demos whose Sidak-combined probability is above this
BROWN_MIN_DEMOS = 30  # with fewer such demos, the Sidak minimum instead of Fisher-Brown
MAD_RELATIVE_SE = 1.167  # the MAD's standard error over its value, times sqrt(demos), for normal data
CORE_ROUNDS = 10  # at most this many refits of the core


def task_neighbours(x: np.ndarray, tasks: np.ndarray, k: int, at_most_half: bool = False, chunk: int = 256
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Each row's ``k`` nearest other rows of its task by Euclidean distance (all of them when there are fewer;
    with ``at_most_half``, never more than half of them, at least one): their mean distance [N] and their mean
    [N, d]; NaN for a task's only row.  A task of thousands of rows is taken ``chunk`` rows at a time."""
    dist, centre = np.full(len(x), np.nan), np.full(x.shape, np.nan)
    for task in np.unique(tasks):
        idx = np.flatnonzero(tasks == task)
        if len(idx) < 2:
            continue
        kk = max(min(k, (len(idx) - 1) // 2 if at_most_half else len(idx) - 1), 1)
        e = x[idx].astype(np.float64)
        for s in range(0, len(idx), chunk):
            d = np.linalg.norm(e[s:s + chunk, None] - e[None], axis=-1)
            d[np.arange(len(d)), s + np.arange(len(d))] = np.inf  # not itself
            nn = np.argpartition(d, kk - 1, axis=1)[:, :kk]
            dist[idx[s:s + chunk]] = np.sort(np.take_along_axis(d, nn, 1), axis=1).mean(1)
            centre[idx[s:s + chunk]] = e[nn].mean(1)
    return dist, centre


def consistency_units(post: TaskPosterior) -> np.ndarray:
    """What one unit of each embedding dimension is for ``consistency``: the median over the demos of its task
    standard deviation."""
    return np.maximum(np.median(post.sigma, axis=0), 1e-12)


def consistency_parts(post: TaskPosterior, tasks: np.ndarray, k: int = CONSISTENCY_K) -> tuple[np.ndarray, np.ndarray]:
    """``consistency`` [N] and, per dimension, how far the demo's mean lies from its neighbours' mean [N, z], in
    ``consistency_units``."""
    x = post.mu / consistency_units(post)
    dist, centre = task_neighbours(x, tasks, k, at_most_half=True)
    return dist, np.abs(x - centre)


def consistency(post: TaskPosterior, tasks: np.ndarray, k: int = CONSISTENCY_K) -> np.ndarray:
    """Task consistency of each demo against its k nearest other demos of the task (see module docstring)."""
    return consistency_parts(post, tasks, k)[0]


def consistency_of(other: TaskPosterior, rows: np.ndarray, post: TaskPosterior, tasks: np.ndarray,
                   k: int = CONSISTENCY_K) -> np.ndarray:
    """``consistency`` of cues ``other`` that stand in for the demos at ``rows`` of ``post`` (the same demos'
    cues changed, e.g. played backwards): each one's mean distance to its k nearest demos of that demo's task,
    that demo left out, in the units and with the neighbour count the demos' own consistency uses."""
    units = consistency_units(post)
    x, y = post.mu / units, other.mu / units
    out = np.full(len(rows), np.nan)
    for i, row in enumerate(np.asarray(rows)):
        mates = np.flatnonzero((tasks == tasks[row]) & (np.arange(len(tasks)) != row))
        if not len(mates):
            continue
        kk = max(min(k, len(mates) // 2), 1)  # as ``consistency_parts``: at most half the task's others
        out[i] = np.sort(np.linalg.norm(x[mates] - y[i], axis=1))[:kk].mean()
    return out


def novelty(post: TaskPosterior, prior_var: np.ndarray) -> np.ndarray:
    """``novelty`` of each cue (see module docstring): above 1, less familiar than 9 in 10 of the real demos the
    model was referenced on."""
    return (post.var_novel / prior_var).mean(1)


def robust_stats(x: np.ndarray) -> dict[str, float]:
    x = x[np.isfinite(x)]
    if not len(x):
        return {"median": 0.0, "scale": 1.0}
    med = float(np.median(x))
    return {"median": med, "scale": float(max(1.4826 * np.median(np.abs(x - med)), 1e-9))}


def standardise(x: np.ndarray, stats: dict[str, float]) -> np.ndarray:
    return (x - stats["median"]) / stats["scale"]


# Scores are put in robust standard deviations within their task (a distance from the task's median over the MAD
# of those distances across all demos), so that a harder task's demos do not fill the top ranks and a task of a
# dozen demos needs no scale of its own -- unless its demos surely spread more (``task_units``); the alternatives
# measured: docs/decisions.md ("Calibration", "A task's own unit where its demos surely spread more").
def calibrated(x: np.ndarray, tasks: np.ndarray | None = None, min_scale: float = 0.0,
               core: np.ndarray | None = None, task_units: bool = False) -> np.ndarray:
    """``x`` in robust standard deviations (median, 1.4826 x MAD) within each demo's task (of all demos without
    ``tasks`` or with one task).

    ``min_scale``: the least spread a standard deviation stands for, in ``x``'s units -- for a measurement that
    scripted or very regular demos repeat almost exactly, where a MAD near zero would call any small difference
    many standard deviations.  ``core`` (bool [N]): the medians and the MAD of the demos believed clean alone
    (``robust_tails``; a task with none of them in the core keeps the median of all its demos), so that a
    task's bad demos move neither the centre its clean demos are judged from nor the unit.  ``task_units``: a
    task whose core demos surely spread more than the pooled unit says (the lower end of its robust SD's 95%
    interval is above it) is judged in that, so that a task whose clean demos vary more (contact, a tumbling
    object) is not read as many units off; a task of a few demos, whose spread chance moves, keeps the pooled."""
    x = np.asarray(x, np.float64)
    core = np.ones(len(x), bool) if core is None else np.asarray(core, bool)
    if tasks is None or len(np.unique(tasks)) < 2:
        stats = robust_stats(x[core] if core.any() else x)
        return standardise(x, {**stats, "scale": max(stats["scale"], min_scale)})
    finite = np.where(np.isfinite(x), x, np.nan)
    tasks = np.asarray(tasks)
    every = pd.Series(finite).groupby(tasks).transform("median").to_numpy()
    centre = pd.Series(np.where(core, finite, np.nan)).groupby(tasks).transform("median").to_numpy()
    resid = finite - np.where(np.isnan(centre), every, centre)
    scale = max(robust_stats(resid[core] if core.any() else resid)["scale"], min_scale)
    if task_units:  # the task's own robust SD where it is surely larger: the lower end of its 95% interval
        by_task = pd.Series(np.where(core, np.abs(resid), np.nan)).groupby(tasks)
        own = 1.4826 * by_task.transform("median").to_numpy()
        n = by_task.transform("count").to_numpy()
        with np.errstate(divide="ignore", invalid="ignore"):
            surely = own * (1.0 - 1.96 * MAD_RELATIVE_SE / np.sqrt(n))
        scale = np.fmax(np.nan_to_num(surely), scale)
    return resid / scale




def tail_probabilities(z: np.ndarray, core: np.ndarray | None = None, normal: np.ndarray | None = None
                       ) -> np.ndarray:
    """Natural log of the tail probability of each entry of [N, K] scores in robust standard deviations,
    column by column: an exponential tail through the ``TAIL_QUANTILES`` of the column's rows in ``core``
    (default: all; probability 0.75 at their 25th percentile, 0.25 at their 75th), at most 1, its scale at least
    ``TAIL_MIN_SCALE``; or, for the columns ``normal`` [K] marks, a normal tail through the core's median, its
    scale from the same two percentiles (the interquartile range / 1.349; at least ``TAIL_MIN_SCALE``) -- for a
    score that is a mean over many steps, whose clean spread the central limit theorem makes normal
    (``ScoreSpec.tail``).  NaN (no score)
    stays NaN, which the combinations leave out; +inf (an exact copy) gives log 0."""
    from scipy.stats import norm

    lo, hi = TAIL_QUANTILES
    core = np.ones(len(z), bool) if core is None else np.asarray(core, bool)
    normal = np.zeros(z.shape[1], bool) if normal is None else np.asarray(normal, bool)
    out = np.full(z.shape, np.nan)
    for k in range(z.shape[1]):
        x = z[:, k]
        ok = np.isfinite(x) | (x == np.inf)
        if not ok.any():
            continue
        fit = x[np.isfinite(x) & core]
        q_lo, q_mid, q_hi = np.quantile(fit, [lo, 0.5, hi]) if len(fit) else (0.0, 0.0, 0.0)
        if normal[k]:
            with np.errstate(invalid="ignore"):
                tail = norm.logsf((x - q_mid) / max((q_hi - q_lo) / (norm.ppf(hi) - norm.ppf(lo)), TAIL_MIN_SCALE))
        else:
            beta = max((q_hi - q_lo) / np.log((1 - lo) / (1 - hi)), TAIL_MIN_SCALE)
            tail = np.log(1 - lo) - (x - q_lo) / beta
        out[:, k] = np.where(ok, np.minimum(tail, 0.0), np.nan)
    return out


def robust_tails(z: np.ndarray | Callable[[np.ndarray], np.ndarray], core_p: float,
                 rounds: int = CORE_ROUNDS, normal: np.ndarray | None = None, alone: np.ndarray | None = None,
                 outside: np.ndarray | None = None, looks: np.ndarray | None = None,
                 beside: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``tail_probabilities`` fitted on the audited demos' robust core, and the core [N] (bool): starting from
    every demo (but those ``outside``), the tails are fitted, combined (``combined_log10``), and the demos whose
    combined probability is at most ``core_p`` left out of the next fit, until the core stops changing.  The core
    never shrinks below half the demos it started from (beyond that the bad demos would be the majority the
    calibration assumes they are not).

    ``z``: the [N, K] scores in robust SD, or a function of the core (None: every demo) that computes them (the
    ranking's: each task's centre and the unit from the core's demos, ``calibrated``), called again at every
    round.  ``normal``: the columns with a normal tail (``tail_probabilities``); ``alone``, ``beside`` and
    ``looks``: how the columns are combined (``combined_log10``); ``outside``: demos never in the core (broken
    recordings, suspect whatever their scores)."""
    z_of = z if callable(z) else (lambda core: z)
    zc = z_of(None)  # every demo
    start = np.ones(len(zc), bool) if outside is None else ~np.asarray(outside, bool)
    core = start
    if not core.all():
        zc = z_of(core)
    log_p = tail_probabilities(zc, core, normal)
    for _ in range(rounds):
        new = start & ~(10.0 ** combined_log10(log_p, alone, looks, beside) <= core_p)
        if (new == core).all() or new.sum() < start.sum() / 2:
            break
        core = new
        zc = z_of(core)
        log_p = tail_probabilities(zc, core, normal)
    return log_p, core


def sidak_log10(log_p: np.ndarray) -> np.ndarray:
    """log10 of the Sidak-corrected smallest of each row's K tail probabilities (given as natural logs; NaN: no
    score, left out): 1 - (1 - min p)^K, the chance that the most surprising of K independent clean scores is
    this surprising (valid, and conservative, whatever their dependence)."""
    seen = ~np.isnan(log_p)
    k = np.maximum(seen.sum(axis=1), 1)
    m = np.where(seen, log_p, 0.0).min(axis=1, initial=0.0)
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
    from scipy.stats import ConstantInputWarning, spearmanr

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", ConstantInputWarning)  # a constant column: handled just below
        rho = np.atleast_2d(spearmanr(-np.nan_to_num(log_p[core], nan=0.0)).correlation)
    rho = np.nan_to_num(rho, nan=0.0)  # a column constant over the core (no score there) depends on nothing
    # Never taken as less variable than independent scores: negative dependence is not counted on.
    var = 4.0 * k + 4.0 * max(float(rho.sum() - np.trace(rho)), 0.0)
    return var / (4.0 * k), 8.0 * k * k / var


def merge_looks(log_p: np.ndarray, looks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The columns of [N, K] tail probabilities (natural logs) that are one look at a demo (``looks`` [K]: the
    same number) merged into one column, their Sidak minimum -- two scores that ask one question, such as whether
    the actions are explained (by the model's controller, or by the state), are one piece of evidence, which
    Fisher's sum would count twice -- and, for each merged column, the first of its columns [L]."""
    looks = np.asarray(looks)
    _, first = np.unique(looks, return_index=True)
    first = np.sort(first)
    cols = []
    for j in first:
        group = looks == looks[j]
        if group.sum() == 1:
            cols.append(log_p[:, j])
            continue
        seen = ~np.isnan(log_p[:, group]).all(axis=1)
        cols.append(np.where(seen, sidak_log10(log_p[:, group]) * np.log(10), np.nan))
    return (np.column_stack(cols) if cols else np.zeros((len(log_p), 0))), first


def combined_log10(log_p: np.ndarray, alone: np.ndarray | None = None, looks: np.ndarray | None = None,
                   beside: np.ndarray | None = None) -> np.ndarray:
    """log10 of the combined tail probability of each row's K tail probabilities (given as natural logs):
    Fisher's -2 sum log p against Brown's scaled chi-square (``brown_scale``: the scores' dependence measured on
    the audited demos themselves), or, with too few demos to measure it, the Sidak minimum.  A row's missing
    scores (NaN) are left out, with their share of the degrees of freedom: a look that saw nothing is not
    evidence that the demo is typical (counted as p = 1, it would make a demo with a missing score look more
    ordinary than a clean demo with every score).

    ``alone`` (bool [K]) marks the columns that stand apart (the recording faults, ``ScoreSpec.alone``): the others
    are combined as above, the marked ones by their Sidak minimum (is the recording faulty?), and those two
    probabilities by theirs -- a camera that froze is a defect whatever the demo's behaviour says, and in Fisher's
    sum its one small probability would be diluted by every ordinary one beside it.  ``beside`` (bool [K]) marks
    columns that are in the sum and among the marked ones too: evidence that adds to the rest and is a defect by
    itself (``ScoreSpec.beside``).  ``looks`` ([K] numbers): the columns of one look are first merged into one
    (``merge_looks``)."""
    alone = np.zeros(log_p.shape[1], bool) if alone is None else np.asarray(alone, bool)
    beside = np.zeros(log_p.shape[1], bool) if beside is None else np.asarray(beside, bool)
    if looks is not None and len(np.unique(looks)) < log_p.shape[1]:
        log_p, first = merge_looks(log_p, looks)
        alone, beside = alone[first], beside[first]
    if alone.any() or beside.any():
        # A group that saw nothing in a row (NaN throughout) is no look there, as a missing score is none above.
        parts = []
        for group, combine in ((~alone, combined_log10), (alone | beside, sidak_log10)):
            if group.any():
                seen = ~np.isnan(log_p[:, group]).all(axis=1)
                parts.append(np.where(seen, combine(log_p[:, group]) * np.log(10), np.nan))
        return sidak_log10(np.column_stack(parts))
    if log_p.shape[1] == 0:
        return np.zeros(len(log_p))
    scale = brown_scale(log_p)
    if scale is None:
        return sidak_log10(log_p)
    from scipy.special import gammaln
    from scipy.stats import chi2

    c, f = scale
    seen = (~np.isnan(log_p)).sum(axis=1)
    f = f * np.maximum(seen, 1) / log_p.shape[1]
    stat = -2.0 * np.nan_to_num(log_p, nan=0.0, neginf=-np.inf).sum(axis=1)
    with np.errstate(all="ignore"):
        x = stat / c
        out = chi2.logsf(x, f)
        # Far out, where logsf underflows: the upper incomplete gamma's leading term, so that the most
        # surprising demos keep their order instead of all tying at -inf.
        far = (f / 2.0 - 1.0) * np.log(x / 2.0) - x / 2.0 - gammaln(f / 2.0)
        out = np.where(np.isfinite(out) | ~np.isfinite(x), out, far)
    return np.where(np.isinf(stat), -np.inf, np.where(seen > 0, out / np.log(10), 0.0))


def rank_order(suspicion: np.ndarray, episode_index: np.ndarray) -> np.ndarray:
    """Row order of a ranking: most suspect first, ties by episode index (NaN last)."""
    return np.lexsort((episode_index, -np.nan_to_num(suspicion, nan=-np.inf)))
