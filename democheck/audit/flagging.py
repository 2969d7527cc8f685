"""The audit's flags (``is_anomaly``): which demos a user is told to drop, at a stated false-positive rate.

``is_anomaly`` is the demo's conformal p-value against the robust core of ``scores.robust_tails``
(``conformal_p``: the share of the core at least as suspect) at most the false-positive rate asked for
(``audit --fpr``, default ``DEFAULT_FPR``):
if the core's demos are clean and a clean demo is like them, about that share of clean demos is flagged,
whatever the shape of the scores' tails.  The combined probability's own level is a model: the clean demos'
scores have heavier right tails than the exponential fit and move together more in the far tail than Brown's
two moments say, so on push-v1-dev with the shipped model it flagged 2.1% of the clean demos at 0.01, the
conformal level 0.81% (0.65% before, when contamination widened every tail by chance), recall both-objects,
gave-up, occluded, wrong-object 1.00, 0.97, 1.00, 1.00; with the probes pooled in (37% bad) 0.16% and 1.00,
0.92, 1.00 (hidden), 1.00 (no-action), 0.26 (no-objects), 0.97, 1.00 (random), 0.95 where the flags before
caught 0.90, 0.66, 1.00, 1.00, 0.08, 0.92, 1.00, 0.95; Meta-World mw2-dev 2.5% of the clean demos (exact
copies and demos that end where their task's others do not), every bad demo.  Bad demos left in the core
(a kind only weakly seen) take its top ranks: the flags are then fewer than asked for, never more -- without
a model, push-v1-dev's gave-up demos are flagged 0.66 (0.92 by the combined probability's level, which
there flags 0.98% of the clean demos).  How much that varies from draw to draw (``benchmarks/flag_choices.py``
on benches of push-v1-dev's recipe at seeds 2, 3 and 4 with their probes pooled in, and on audits of each set
alone): gave-up flagged 1.00, 0.97, 1.00 pooled (the core holding 4, 8, 3 bad demos) and 1.00, 0.97, 1.00
alone; no-objects 1.00, 0.96, 1.00; 5, 5, 8 clean demos flagged pooled and 11, 7, 8 alone (6.1-6.2
expected); the fresh draw no choice was made on (seed 29, its core holding 15 bad demos) 0.84 and 2.  Measured
there and not kept: the flag level extrapolated from the core's bulk instead of read off its top (log10 of
its survival function fitted as a line between two of its quantiles -- bad demos left in the core sit at its
top, the bulk is clean): between the 90th and 98th percentiles every bad demo of every push draw flagged, but
7-10 clean demos pooled and 9 alone (up to 1.6%), and Meta-World mw2-dev's clean demos 3.5% against 2.5%
(the clean tail beyond the bulk is heavier than the line); lower quantile pairs flagged more.  And each
score's tail above its core's 80th, 90th or 95th percentile refitted by peaks over threshold (an exponential
whose scale is the core's mean excess, so that a score with a light clean tail -- the idle share of a
scripted expert, where a gave-up demo sits 4.6-6.6 robust SD out and the clean demos at most 3.8 -- is not
valued by the heavy tail its quartiles imply): the lighter tails put a third of the demos under ``scores.CORE_P``,
the core fell back to every demo, and the flags collapsed (90th: push-v1-dev pooled gave-up 0.24,
no-objects 0.00; 95th: 0.97 and 0.98 there, but 0.84 and 0.72 on seed 3).  Nor, the core found as now, each
score's tail probability taken again as its rank among the core's values (an exponential beyond the core's
largest): with a model the flags moved by one demo either way (seed 3 alone gave-up 0.97 -> 1.00; seed 2
pooled wrong-object 1.00 -> 0.95, 7 clean against 5), without one the ranking lost no-objects (0.96 ->
0.87 pooled): ranks among a core that holds the bad demos a kind is not seen by value them as the core does.
Exact copies of another demo are flagged too.  The paper's linear
one-class SVM stays a column (``democheck.audit.ocsvm``) and a bench scorer (``ocsvm_flag``): fitted on the training
demos' precisions 1/sigma^2, it sees sigma only, which barely moves for an idle or flailing arm.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

DEFAULT_FPR = 0.01  # see the module docstring


def conformal_p(suspicion: np.ndarray, core: np.ndarray) -> np.ndarray:
    """Each demo's conformal p-value against the core, given its ``suspicion`` (-log10 of its combined tail
    probability): the share of the *other* core demos at least as suspect, counting the demo itself once,
    (1 + #{j in core, j != i: s_j >= s_i}) / (1 + #{j in core, j != i}) -- if the core were clean demos and the demo
    another one like them, P(p <= a) <= a.  Beyond the most suspect core demo, where the core has nothing to
    count, the combined probability's own tail carries on from 1 / (1 + core size): a tenth of that per unit of
    suspicion beyond it.  With no core, the combined probability itself."""
    s = np.asarray(suspicion, np.float64)
    s = np.where(np.isnan(s), -np.inf, s)
    core = np.asarray(core, bool) & np.isfinite(s)  # a demo suspect whatever its scores (+inf) is no reference
    ref = np.sort(s[core])
    if not len(ref):
        return 10.0 ** -s
    at_least = len(ref) - np.searchsorted(ref, s, side="left")
    own = core.astype(int)  # a core demo is among its own reference: leave it out
    p = (1 + at_least - own) / (1 + len(ref) - own)
    with np.errstate(over="ignore"):
        beyond = 10.0 ** -(s - ref[-1]) / (1 + len(ref))
    return np.where(s > ref[-1], beyond, p)


def exact_copies(table: pd.DataFrame) -> np.ndarray | None:
    """Which rows of a score table are bit-exact copies of another demo (``duplicate`` is +inf); None when the
    table has no duplicate check."""
    return np.isinf(table["duplicate"].to_numpy(np.float64)) if "duplicate" in table else None


def flagged_regardless(table: pd.DataFrame) -> np.ndarray | None:
    """Which rows of a score table are flagged whatever their p-value: bit-exact copies of another demo
    (``exact_copies``) and broken recordings (``broken_recordings``); None when the table has neither check."""
    found = [m for m in (exact_copies(table), broken_recordings(table)) if m is not None]
    return np.logical_or.reduce(found) if found else None


def broken_recordings(table: pd.DataFrame) -> np.ndarray | None:
    """Which rows of a score table are broken recordings (``is_broken`` of its ``broken`` column); None when the
    table has no such check."""
    return is_broken(table["broken"]) if "broken" in table else None


def is_broken(values) -> np.ndarray:
    """Which of the ``broken`` check's values (``modelfree.broken``) mark a broken recording: above 0 (frames that
    could not be decoded, NaN or infinite states or actions)."""
    return np.nan_to_num(np.asarray(values, np.float64)) > 0


def expected_false_flags(core: np.ndarray, fpr: float) -> float:
    """The false flags to expect at ``fpr``: that share of the demos believed clean, the core
    (``scores.robust_tails``); the clean demos left out of it are too few to count (their combined tail probability
    is under ``scores.CORE_P``)."""
    return float(fpr * np.asarray(core, bool).sum())


def flag_level(table: pd.DataFrame, fpr: float) -> float | None:
    """What the flags at ``fpr`` amount to on a score table: the largest ``p_value`` of a demo its ``p_reference``
    flags (those flagged regardless aside); None when none is."""
    flagged = flags(table["p_reference"].to_numpy(), fpr) & np.isfinite(table["suspicion"].to_numpy(np.float64))
    return float(table["p_value"].to_numpy()[flagged].max()) if flagged.any() else None


def flags(p_value: np.ndarray, fpr: float = DEFAULT_FPR, regardless: np.ndarray | None = None) -> np.ndarray:
    """``is_anomaly``: a p-value (the audit's: ``conformal_p``) at most ``fpr``, or flagged ``regardless`` (an
    exact copy of another demo, a broken recording: ``flagged_regardless``)."""
    out = np.nan_to_num(p_value, nan=1.0) <= fpr
    return out | regardless if regardless is not None else out
