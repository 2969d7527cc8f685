"""The ranking: how the registry's scores (``democheck.audit.scorers``) become one column, ``suspicion``.

Each score of the ranking in robust standard deviations within the group its demo is judged in
(``ranking_z``), a tail probability fitted on the audited demos' robust core (``ranking_tails``), and those
combined (``combine``: Fisher-Brown, the recording faults beside the rest, the scores of one look merged --
``scores`` holds the arithmetic and says how each part was chosen); ``combination`` adds the reason.  What each
scorer contributes -- its tail's family, whether it stands apart, its look, its floor -- is an attribute of its
``scorers.Scorer``, read here from the registry at call time (the registry's own ``suspicion`` scorer calls back
into this module).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from democheck.audit import scorers as registry
from democheck.audit.flagging import is_broken
from democheck.audit.scores import calibrated, combined_log10, merge_looks, robust_tails

if TYPE_CHECKING:
    from democheck.audit.scorers import Evidence, Scores


def ranking_z(ev: Evidence, names: list[str], core: np.ndarray | None = None) -> np.ndarray:
    """[N, K]: the ranking's scores ``names`` in robust standard deviations within the group each demo is judged in
    (its task, ``Evidence.groups``; a score on a log scale first where its scorer says so; one that is a robust z
    already as it is), each group's centre and the unit from the ``core`` demos (default: every demo;
    ``scores.calibrated``)."""
    cols, groups = [], ev.groups
    for n in names:
        s, x = registry.SCORERS[n], np.asarray(ev.scores[n], np.float64)
        x = np.log(np.maximum(x, 1e-12)) if s.log_in_ranking else x
        cols.append(x if s.in_robust_sd else calibrated(x, groups, min_scale=s.ranking_min_scale, core=core))
    return np.column_stack(cols) if cols else np.zeros((len(ev.episodes), 0))


def ranking_tails(ev: Evidence, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The tail probabilities (natural logs, [N, K]) of the ranking's scores ``names`` and the robust core they
    are fitted on (``scores.robust_tails`` of ``ranking_z``), each score's tail of its scorer's family."""
    return robust_tails(lambda core: ranking_z(ev, names, core), normal=normal_tails(names),
                        alone=alone_columns(names), outside=broken_rows(ev), looks=look_columns(names))


def broken_rows(ev: Evidence) -> np.ndarray:
    """Which demos are broken recordings (``flagging.is_broken``; ``flagging.broken_recordings`` on a table): bool
    [N], all False without that check."""
    return is_broken(ev.scores["broken"]) if "broken" in ev.scores else np.zeros(len(ev.episodes), bool)


def normal_tails(names: list[str]) -> np.ndarray:
    """Which of the ranking's scores ``names`` have a normal tail (``Scorer.tail``): bool [K]."""
    return np.array([registry.SCORERS[n].tail == "normal" for n in names], bool)


def alone_columns(names: list[str]) -> np.ndarray:
    """Which of the ranking's scores ``names`` stand apart in the combination (``Scorer.alone``): bool [K]."""
    return np.array([registry.SCORERS[n].alone for n in names], bool)


def look_columns(names: list[str]) -> np.ndarray:
    """Which look each of the ranking's scores ``names`` is (``Scorer.look``; a scorer without one, its own): [K]
    numbers, equal for the columns of one look."""
    looks = [registry.SCORERS[n].look or n for n in names]
    return np.array([looks.index(k) for k in looks])


def combine(names: list[str], log_p: np.ndarray) -> np.ndarray:
    """The ranking: -log10 of the combined tail probability of the scores ``names`` (``scores.combined_log10``,
    the recording faults beside the rest, the scores of one look merged)."""
    return -combined_log10(log_p, alone_columns(names), look_columns(names))


def ranked(available, tasks: np.ndarray, model_free: bool = False, untrusted=()) -> list[str]:
    """The scores the ranking combines, of those ``available`` (names, or columns by name): every
    ``in_suspicion`` scorer's, less the task embedding's on a dataset of one task (``in_single_task_ranking``),
    less the model's with ``model_free`` and those it did not earn (``untrusted``, ``trust.untrusted``), less a
    column with no score at all (the outcome of a dataset whose tasks are all too small to compare): a look that
    cannot see anything must not cost the others' correction."""
    one_task = len(np.unique(tasks)) == 1
    columns = isinstance(available, (dict, pd.DataFrame))

    def scored(n: str) -> bool:
        return not columns or bool(np.isfinite(np.asarray(available[n], np.float64)).any())

    return [n for n, s in registry.SCORERS.items() if s.in_suspicion and n in available and n not in untrusted
            and (s.model_free or not model_free) and (s.in_single_task_ranking or not one_task) and scored(n)]


REASON_P = 0.05  # a score this surprising (tail probability) is named in the ranking's reason beside the first


def combination(ev: Evidence, model_free: bool = False) -> Scores:
    """-log10 of the combined tail probability of the ranking's scores (``scores.combined_log10``), and the
    score that drove it."""
    names, log_p, core = ev.combination(model_free)
    if not names:
        return np.full(len(ev.episodes), np.nan), None
    value = combine(names, log_p)
    references = int(np.asarray(core, bool).sum())
    reasons = []
    for i, row in enumerate(np.nan_to_num(look_odds(names, log_p), nan=0.0)):  # no score: nothing to name
        order = clauses(names, row, references)
        parts = []
        for j in order:  # what the check saw in its own words first, then which check and how rare
            own = (ev.reasons.get(names[j]) or [""] * len(log_p))[i]
            odds = _odds(float(row[j]), references)
            parts.append(f"{own} ({names[j]}, {odds})" if own else f"{names[j]}: {odds}")
        reasons.append("; also ".join(parts))
    broken = broken_rows(ev)
    if broken.any():  # a broken recording is suspect whatever its other scores (``modelfree.broken``)
        value = np.where(broken, np.inf, value)
        reasons = [f"broken: {ev.reasons['broken'][i]}" if broken[i] else r for i, r in enumerate(reasons)]
    return value, reasons


# The checks whose words say what the demo did, in the order a reason prefers them: the arm, then the world it left,
# then what the camera saw.  The recording faults come after them, then the coupling (a frozen sensor and an
# operator who let go both loosen it), the model's readings last.
WHAT_HAPPENED = ("idle", "motion", "jerk", "outcome", "view", "colours")


def clauses(names: list[str], row: np.ndarray, references: int) -> list[int]:
    """The looks a demo's reason names (``row``: their log tail probabilities), in the order it names them: up to
    three, the smallest probability and those under ``REASON_P``.  First, of those beyond every clean demo (or the
    smallest alone), what the demo did (``WHAT_HAPPENED``) before how it was recorded before the model's reading of
    it -- a reviewer acts on the behaviour; then by probability."""
    order = [j for j in np.argsort(row, kind="stable") if j == np.argmin(row) or row[j] < np.log(REASON_P)]

    def kind(j: int) -> int:
        if names[j] in WHAT_HAPPENED:
            return WHAT_HAPPENED.index(names[j])
        s = registry.SCORERS[names[j]]
        return len(WHAT_HAPPENED) + (0 if s.alone else 1 if s.model_free else 2)

    beyond = [j for j in order if np.exp(row[j]) * (references + 1) < 1] or order[:1]
    lead = min(beyond, key=lambda j: (kind(j), row[j]))
    return [lead, *[j for j in order if j != lead]][:3]


def drivers(ev: Evidence, model_free: bool = False) -> list[str]:
    """The check each demo's reason names first (``clauses``; ``broken`` for a broken recording)."""
    names, log_p, core = ev.combination(model_free)
    if not names:
        return [""] * len(ev.episodes)
    rows = np.nan_to_num(look_odds(names, log_p), nan=0.0)
    references = int(np.asarray(core, bool).sum())
    broken = broken_rows(ev)
    return ["broken" if broken[i] else names[clauses(names, r, references)[0]] for i, r in enumerate(rows)]


REASON_CHARS = 160  # a reason keeps the driving check's clause and adds the others' while it stays this short


def brief(reason: str) -> str:
    """A reason as the table's ``reason`` holds it: the driving check's clause whole, then the others' while the
    whole stays within ``REASON_CHARS`` (all of them are in ``details``)."""
    parts = str(reason).split("; also ")
    out = parts[0]
    for part in parts[1:]:
        if len(out) + len("; also ") + len(part) > REASON_CHARS:
            break
        out += "; also " + part
    return out


def look_odds(names: list[str], log_p: np.ndarray) -> np.ndarray:
    """``log_p`` as a reason reads it: in each row, the score of a look of several (``Scorer.look``) that drove it
    carries the look's merged tail probability (``scores.merge_looks``: what the ranking counted), the look's
    other scores NaN, so that one look is named once, at its own odds."""
    looks = look_columns(names)
    out = np.array(log_p, np.float64, copy=True)
    for look in np.unique(looks):
        cols = np.flatnonzero(looks == look)
        if len(cols) < 2:
            continue
        merged, _ = merge_looks(log_p[:, cols], np.zeros(len(cols), int))
        first = cols[np.argmin(np.nan_to_num(log_p[:, cols], nan=np.inf), axis=1)]
        out[:, cols] = np.nan
        out[np.arange(len(out)), first] = merged[:, 0]
    return out


def _odds(log_p: float, references: int) -> str:
    """'as unusual as 1 clean demo in 3,400' for a tail probability (given as its natural log), to two
    significant figures; past what ``references`` demos believed clean can support, 'beyond every clean demo'."""
    p = float(np.exp(log_p))
    if p >= 0.5:
        return "typical"
    if p * (references + 1) < 1:
        return "beyond every clean demo"
    return f"as unusual as 1 clean demo in {float(f'{1 / p:.2g}'):,.0f}"
