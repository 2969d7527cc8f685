"""The arithmetic of democheck's scores (the registry of scorers, ``democheck.audit.scorers``, calls it).

Every score is one number per demo, higher = more suspect:

- ``task_uncertainty`` (the paper's score): the mean over embedding dimensions
  of the task standard deviation sqrt(var) of the demo's cue.
- ``consistency``: how far the demo's ``mu`` lies from those of its ``CONSISTENCY_K`` nearest *other* demos of
  the same task -- never more than half of them, so that a bad minority of a small task is not among every
  clean demo's neighbours -- as the mean Euclidean distance to them, each dimension in units of its median
  task standard deviation over the audited demos (``consistency_units``): a cue's own variance does not shrink
  its distance, as the units sqrt(v + var) of the form before did (a wide cue then looked consistent).  The
  neighbours rather than all the others: the task's own bad demos and tasks done in more than one way blur the
  whole task (``benchmarks/score_choices.py``: all others 0.67, k = 5 0.80 mean AUROC over push-v1-dev +
  probes' 8 kinds, the form before).  Chosen with the robust core below (``benchmarks/calibration_choices.py``
  on push-v1-dev + probes with the shipped model): ranking AUROC no-objects 0.952 -> 0.982 (the form before,
  with the tails fitted on every demo -> this form on the core), every other kind 0.999-1.000 either way;
  without the core, this form was diluted in the ranking (0.949).  Variance catches cues that say nothing;
  consistency catches cues that clearly say the wrong thing.  NaN for a task with a single demo.
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
  all score high does not fill the top ranks; the task uncertainty and the action error on a log scale: their
  clean demos' right tails are long), then turned into a tail probability by ``tail_probabilities``: an
  exponential right tail through the 25th and 75th percentiles of the audited demos' *robust core*
  (``robust_tails``; a normal tail for a score its scorer says is a mean over many steps, ``Scorer.tail``: the
  coupling, whose choice ``democheck.audit.coupling`` gives): fitted on every demo, then again on those whose
  combined probability is above ``CORE_P``, until the core stops changing; at every round each task's centre and the robust unit are taken
  again from the core's demos alone (``calibrated`` with ``core``; motion, view and colours, robust z within
  their task already, keep the centre of all the task's demos), so that a task's bad demos shift neither
  the centre its clean demos are judged from nor the unit: with the probes pooled in, a task of 15 demos holds
  5 bad ones, and the MAD over all the demos had the clean demos' largest action error at 1.4 robust SD and a
  no-objects probe's at 1.9.  Chosen with the ``colours`` check (``benchmarks/colour_choices.py``): on
  push-v1-dev + probes at --fpr 0.01 no-objects flagged 0.74 -> 0.88, gave-up 0.82 -> 0.95, 1 -> 4 of 614
  clean demos (6.2 expected); Meta-World mw2-dev and mw2-one-dev unchanged.  push-v1-dev audited alone
  (``democheck audit data/push-v1-dev``; the sweep's ``--only`` rows keep the scores the pooled bench computed
  with the probes among each task's demos, which an audit of the set alone does not see): 10 of 614 clean
  demos flagged before, 11 with both (the audit expected 6.1), every bad demo either way -- mostly clean demos
  whose object ended 10-18 robust SD past their task's other demos.  Fitted on every demo, as before, a share of bad demos widened
  every tail they sat in: with 37% of the demos bad (push-v1-dev + its probes) no clean demo and few bad ones
  were flagged (gave-up 0.66, no-objects 0.08), and a score that alone saw a kind was diluted by the others
  in the ranking.  The tail probabilities are combined by Fisher's method with Brown's correction
  (``combined_log10``; the scores of one look, the action error and the coupling, first merged into their Sidak
  minimum, ``merge_looks``): -2 sum log p against a scaled chi-square whose variance counts the scores'
  dependence, measured on the audited demos (``brown_scale``).  Several moderate surprises add up -- a demo
  that gave up half-way is a little still, a little slow, and ends a little short -- where the smallest alone
  (the Sidak minimum; still used below ``BROWN_MIN_DEMOS`` demos) waits for one of them to be extreme
  (``benchmarks/suspicion_choices.py``; Fisher's sum without Brown's correction flags several times the rate
  asked for on scores that move together, ``tests/test_modelfree.py``).  Earlier choices: the tails against the
  largest robust z, other percentile pairs, ranks among the audited demos (they cannot tell how far beyond
  every clean demo a bad one lies), a reference of held-out training demos, a Weibull tail and refits on a
  looser core were measured and not kept (the model card and README say how); so were, with the core, tails through
  the core's upper percentiles (50-90, 75-95, 50-95: gave-up unchanged, no-objects 0.989 -> 0.968-0.984 on
  push-v1-dev + probes, occluded 0.999 -> 0.982-0.990 on mw2-dev; ``benchmarks/calibration_choices.py``).
  Also measured with the core and not kept (the same script; push-v1-dev + probes, push-v1-dev alone, mw2-dev):
  the Cauchy combination test instead of Fisher-Brown (gave-up AUROC 0.999 -> 0.996, flagged 0.92 -> 0.42: a
  demo that gave up half-way is moderately unusual on several scores, which a test ruled by its smallest p does
  not add up); a normal tail for the idle share (gave-up 1.000, flagged 0.97, and 0.97 against 0.68 without a
  model, but mw2-dev's clean demos flagged 3.5% against 2.5%, 4.0% without a model: Meta-World's resting demos
  give the idle share a long tail); each score's tail family, normal or exponential, chosen by likelihood on the
  core (7 clean demos of push-v1-dev flagged against 5, no-objects 0.988 -> 0.979); each score's rank among the
  core, the exponential beyond its largest (no-objects 0.988 -> 0.967, flagged 0.34 -> 0.18); each task's centre
  from its core demos alone, without the ``colours`` check (push-v1-dev alone: 9 clean flagged, 1.47%, against
  5, by the combined probability's own level; kept since, with the conformal flags of
  ``democheck.audit.flagging``).  The recording faults (``Scorer.alone``: timing, frozen video, frame jump, lag;
  since, the jerk and the frozen state) are not added into Fisher's sum: their own Sidak minimum (is the
  recording faulty?) stands beside the sum's combined probability (is the behaviour unusual?), the ranking the
  Sidak minimum of the two (``combined_log10``'s ``alone``).  Chosen with ``benchmarks/fault_choices.py`` on a
  Meta-World set with the faults planted (mw3-dev: 150 clean, 6 each of jittery, frozen-camera, lagged, dropped; trained on itself), the push-v1 development draws and Meta-World
  mw2-dev and mw2-one-dev.  On mw3-dev, AUROC/flagged at --fpr 0.01, dropped, frozen-camera, jittery, lagged:
  the faults out of the ranking 0.756/0.00, 0.903/0.00, 0.997/1.00, 0.840/0.00; in Fisher's sum 0.988/0.33,
  1.000/1.00, 0.996/0.83, 0.992/0.67; beside it 0.999/1.00, 1.000/1.00, 0.997/1.00, 0.999/1.00 (1 of 150 clean
  flagged either way, 1.5 expected); without a model, out 0.910/0.00, 0.879/0.17, 1.000/1.00, 0.924/0.00,
  beside 0.979/0.50, 1.000/1.00, 1.000/1.00, 0.997/1.00, and 0.994/1.00 for dropped (2 clean flagged) once the
  frame checks read every camera at 64 px (``frames.FRAME_CHECK_SIZE``; a model's decoding already did).  The push-v1 draws audited alone: clean flagged
  8 / 10 / 9 -> 8 / 9 / 7 of 614, every bad demo either way (in Fisher's sum 7 / 7 / 6); seed 2 with its probes
  pooled 7 -> 7, every bad demo (in Fisher's sum 4, gave-up and wrong-object 0.97); mw2-dev and mw2-one-dev
  unchanged, with a model and without.  Each fault a look of its own in one Sidak minimum with the others'
  probability (four looks) cost the rest more: without a model occluded push demos flagged 0.55 / 0.58 / 0.39
  before, 0.47 / 0.47 / 0.29 with two looks, 0.34 / 0.42 / 0.21 with four, and the pooled no-objects probes
  ranked 0.942, 0.943, 0.914; with a model mw3-dev's jittery demos flagged 0.83.  Each fault's robust SD stands
  for at least ``scorers.FAULT_MIN_SCALE``: without that floor mw3-dev's clean flags were 9 of 150 and mw2-dev's
  11 of 200 against 7 (clean Meta-World demos never freeze two frames in a row: a MAD of zero); with 0.05,
  lagged 0.989/0.50.  Normal tails for the faults flagged 7 of 150 and 14 of 200.  Timing (every development
  set's timestamps are regular: a constant 0 there, which changed none of the numbers above) measured on a copy
  of mw3-dev whose parquet puts 6 clean demos' frames from a step on 1-5 frame periods later, without a model:
  AUROC 0.42 -> 1.00, flagged 0.00 -> 1.00, 1 clean demo flagged either way.  The jerk and the frozen state joined
  the faults since (``modelfree.JERK_MIN_SCALE`` and ``democheck.audit.sensors`` say what each did on the
  development sets).
- ``is_anomaly``: the flags, conformal on the robust core the ranking's tails were fitted on
  (``democheck.audit.flagging``, which says how they were chosen).
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np
import pandas as pd

from democheck.petnet.posterior import TaskPosterior


CONSISTENCY_K = 5
TAIL_QUANTILES = (0.25, 0.75)  # see ``suspicion`` above
TAIL_MIN_SCALE = 0.5  # robust SD: no tail falls faster than by e per half a robust standard deviation
BROWN_CORE = 0.1  # see ``brown_scale``
BROWN_MIN_DEMOS = 30
# The robust core the tails are fitted on and the flags calibrated on (``robust_tails``): the demos whose combined
# tail probability is above this.  On the development sets (``benchmarks/calibration_choices.py``) 1e-3 left
# clean demos out of the core, where they are all flagged (push-v1-dev: 1.6% of the clean demos at --fpr 0.01),
# 1e-5 kept weakly seen bad demos in, where they take the flags' budget (gave-up 0.68 with the probes pooled).
CORE_P = 1e-4
CORE_ROUNDS = 10


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
# dozen demos needs no scale of its own; the alternatives measured: docs/decisions.md ("Calibration").
def calibrated(x: np.ndarray, tasks: np.ndarray | None = None, min_scale: float = 0.0,
               core: np.ndarray | None = None) -> np.ndarray:
    """``x`` in robust standard deviations (median, 1.4826 x MAD) within each demo's task (of all demos without
    ``tasks`` or with one task).

    ``min_scale``: the least spread a standard deviation stands for, in ``x``'s units -- for a measurement that
    scripted or very regular demos repeat almost exactly, where a MAD near zero would call any small difference
    many standard deviations.  ``core`` (bool [N]): the medians and the MAD of the demos believed clean alone
    (``robust_tails``; a task with none of them in the core keeps the median of all its demos), so that a
    task's bad demos move neither the centre its clean demos are judged from nor the unit."""
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
    scale = robust_stats(resid[core] if core.any() else resid)["scale"]
    return standardise(resid, {"median": 0.0, "scale": max(scale, min_scale)})




def tail_probabilities(z: np.ndarray, core: np.ndarray | None = None, normal: np.ndarray | None = None
                       ) -> np.ndarray:
    """Natural log of the tail probability of each entry of [N, K] scores in robust standard deviations,
    column by column: an exponential tail through the ``TAIL_QUANTILES`` of the column's rows in ``core``
    (default: all; probability 0.75 at their 25th percentile, 0.25 at their 75th), at most 1, its scale at least
    ``TAIL_MIN_SCALE``; or, for the columns ``normal`` [K] marks, a normal tail through the core's median, its
    scale from the same two percentiles (the interquartile range / 1.349; at least ``TAIL_MIN_SCALE``) -- for a
    score that is a mean over many steps, whose clean spread the central limit theorem makes normal
    (``Scorer.tail``).  NaN (no score)
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


def robust_tails(z: np.ndarray | Callable[[np.ndarray], np.ndarray], core_p: float = CORE_P,
                 rounds: int = CORE_ROUNDS, normal: np.ndarray | None = None, alone: np.ndarray | None = None,
                 outside: np.ndarray | None = None, looks: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``tail_probabilities`` fitted on the audited demos' robust core, and the core [N] (bool): starting from
    every demo (but those ``outside``), the tails are fitted, combined (``combined_log10``), and the demos whose
    combined probability is at most ``core_p`` left out of the next fit, until the core stops changing.  The core
    never shrinks below half the demos it started from (beyond that the bad demos would be the majority the
    calibration assumes they are not).

    ``z``: the [N, K] scores in robust SD, or a function of the core (None: every demo) that computes them (the
    ranking's: each task's centre and the unit from the core's demos, ``calibrated``), called again at every
    round.  ``normal``: the columns with a normal tail (``tail_probabilities``); ``alone`` and ``looks``: how the
    columns are combined (``combined_log10``); ``outside``: demos never in the core (broken recordings, suspect
    whatever their scores)."""
    z_of = z if callable(z) else (lambda core: z)
    zc = z_of(None)  # every demo
    start = np.ones(len(zc), bool) if outside is None else ~np.asarray(outside, bool)
    core = start
    if not core.all():
        zc = z_of(core)
    log_p = tail_probabilities(zc, core, normal)
    for _ in range(rounds):
        new = start & ~(10.0 ** combined_log10(log_p, alone, looks) <= core_p)
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


def combined_log10(log_p: np.ndarray, alone: np.ndarray | None = None, looks: np.ndarray | None = None
                   ) -> np.ndarray:
    """log10 of the combined tail probability of each row's K tail probabilities (given as natural logs):
    Fisher's -2 sum log p against Brown's scaled chi-square (``brown_scale``: the scores' dependence measured on
    the audited demos themselves), or, with too few demos to measure it, the Sidak minimum.  A row's missing
    scores (NaN) are left out, with their share of the degrees of freedom: a look that saw nothing is not
    evidence that the demo is typical (counted as p = 1, it would make a demo with a missing score look more
    ordinary than a clean demo with every score).

    ``alone`` (bool [K]) marks the columns that stand apart (the recording faults, ``Scorer.alone``): the others
    are combined as above, the marked ones by their Sidak minimum (is the recording faulty?), and those two
    probabilities by theirs -- a camera that froze is a defect whatever the demo's behaviour says, and in Fisher's
    sum its one small probability would be diluted by every ordinary one beside it.  ``looks`` ([K] numbers): the
    columns of one look are first merged into one (``merge_looks``)."""
    alone = np.zeros(log_p.shape[1], bool) if alone is None else np.asarray(alone, bool)
    if looks is not None and len(np.unique(looks)) < log_p.shape[1]:
        log_p, first = merge_looks(log_p, looks)
        alone = alone[first]
    if alone.any():
        # A group that saw nothing in a row (NaN throughout) is no look there, as a missing score is none above.
        parts = []
        for group, combine in ((~alone, combined_log10), (alone, sidak_log10)):
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
