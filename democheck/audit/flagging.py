"""The audit's flags (``is_anomaly``): which demos a user is told to drop, at a stated false-positive rate.

``is_anomaly`` is the demo's conformal p-value against the robust core of ``scores.robust_tails``
(``conformal_p``: the share of the core at least as suspect) at most the false-positive rate asked for
(``audit --fpr``, default ``DEFAULT_FPR``): if the core's demos are clean and a clean demo is like them, about
that share of clean demos is flagged, whatever the shape of the scores' tails.  The combined probability's own
level is a model, and clean demos' scores have heavier right tails than the exponential fit and move together
more in the far tail than Brown's two moments say: by it, about twice the share asked for was flagged.  Bad demos
left in the core (a kind only weakly seen) take its top ranks: the flags are then fewer than asked for, never
more.

Exact copies of another demo and broken recordings are flagged whatever their p-value (``flagged_regardless``).
The paper's linear one-class SVM stays a column (``democheck.audit.ocsvm``) and a bench scorer (``ocsvm_flag``):
fitted on the training demos' precisions 1/sigma^2, it sees sigma only, which barely moves for an idle or
flailing arm.

(Chosen on the development sets, with the alternatives measured there: docs/decisions.md, "The reference: a
robust core, and flags conformal on it".)
"""

from __future__ import annotations

import numpy as np
import pandas as pd

DEFAULT_FPR = 0.01  # the share of clean demos the audit flags unless ``--fpr`` says otherwise


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
    is under the ranking's ``core_p``)."""
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
