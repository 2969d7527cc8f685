"""The ``backwards_state`` check (model-free): a reset recorded as a demo, read from the arm.  A task's demos go
from where they begin to where they end; a reset goes the other way.  Per task, the way from its demos' median first
state to their median last (``way_shares``); each demo's first state projected on it, and its last, and the lesser
of how far the first went toward the end and the last came back (``backwards_state``).  It reads the timeline's
states (``democheck.audit.timeline.Timeline``), and is one look with the camera's ``backwards`` in the ranking.
"""

from __future__ import annotations

import warnings

import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.neighbours import MIN_GROUP, ORDINARY, grouped
from democheck.audit.scores import calibrated
from democheck.audit.timeline import Timeline, stacked_states, state_floor
from democheck.data.reorder import velocities

WAY_MIN_SCALE = 0.05  # shares of a task's way from its start state to its end: the least robust SD of how far a
# demo's ends went along it toward the other end (clean demos' ends sit at their own end: a spread near zero)

BACKWARDS_STATE = Vocabulary("backwards_state", {
    # its first state past the middle of its task's way from start to end, and its last state short of the middle
    "done backwards": lambda began, ended, **_: (
        f"its arm begins where its task's demos end and ends where they begin (its first state {began:.0%} of their "
        f"way from start to end, its last {ended:.0%}): done backwards (a reset recorded as a demo?)"),
    "toward the other end": lambda began, ended, **_: (
        f"its arm begins further along its task's way, and ends less far, than its task's demos do (its first state "
        f"{began:.0%} of their way from start to end, its last {ended:.0%}): partly done backwards?"),
    "forwards": "its arm goes the way its task's demos go",
    "no way": "its task's demos share no way from where they begin to where they end: none to run backwards",
    "too few demos": "no task of enough demos to compare with",
    "no state": "no state recorded at its ends",
})


def way_shares(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per demo, where its first and its last state lie on its task's way (the line from the median first state of
    its task's demos to their median last, over the dimensions that move along it by ``ORDINARY`` robust SD or
    more, each in its robust SD over the task's ends, at least ``timeline.STATE_FLOOR`` of its range over every demo's
    ends): 0 at the task's start, 1 at its end, over the dimensions the demo recorded at both ends; and why not,
    where not (``""`` where measured): "no state" (none recorded, or only actions, which may be steps rather than
    places), "too few demos", "no way" (its task's demos share none: a push toward a goal each layout draws anew,
    an arm that goes out and comes home).  Velocities are left out: how fast the arm went at either end is not
    where it was."""
    n = len(t.state_path)
    began, ended = np.full(n, np.nan), np.full(n, np.nan)
    why = np.array(["too few demos"] * n, dtype=object)
    if not n:
        return began, ended, why
    first, last = stacked_states(t.state_path, 0), stacked_states(t.state_path, -1)
    keep = ~velocities(next((x for x, a in zip(t.names, t.from_actions) if x and not a), None), first.shape[1])
    first, last = first[:, keep], last[:, keep]
    stated = ~np.asarray(t.from_actions, bool) & np.isfinite(first).any(axis=1) & np.isfinite(last).any(axis=1)
    why[~stated] = "no state"
    if not stated.any():
        return began, ended, why
    floor = state_floor([first[stated], last[stated]])
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a dimension no demo of a task recorded: NaN throughout
        for rows in grouped(groups):
            rows = rows[stated[rows]]
            if len(rows) < MIN_GROUP:
                continue
            s, e = first[rows], last[rows]
            start_, end_ = np.nanmedian(s, axis=0), np.nanmedian(e, axis=0)
            spread = np.fmax(1.4826 * np.nanmedian(np.abs(np.concatenate([s - start_, e - end_])), axis=0), floor)
            way = np.nan_to_num((end_ - start_) / spread)
            way = np.where(np.abs(way) >= ORDINARY, way, 0.0)
            if not way.any():
                why[rows] = "no way"
                continue
            why[rows] = ""
            for x, out in ((s, began), (e, ended)):
                z = (x - start_) / spread
                seen = np.isfinite(z) & (way != 0)
                weight = (np.where(seen, way, 0.0) ** 2).sum(axis=1)
                out[rows] = np.where(weight > 0, np.where(seen, z * way, 0.0).sum(axis=1) / weight, np.nan)
    return began, ended, why


def backwards_state(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How far a demo's first state lies along its task's way toward their last state, and its last state back
    toward their first (``way_shares``; the lesser of the two, each within [0, 1]), robust z within its task (a
    robust SD at least ``WAY_MIN_SCALE`` of the way): a reset recorded as a demo, read from the arm where the
    camera's colours cannot tell a task's start from its end.  One look with ``backwards``: two readings of one
    question."""
    began, ended, why = way_shares(t, groups)
    began, ended = np.clip(began, 0, 1), np.clip(ended, 0, 1)
    crossed = np.minimum(began, 1 - ended)
    measured = np.isfinite(crossed)  # clipping and the lesser of two keep a NaN end NaN
    score = calibrated(crossed, groups, min_scale=WAY_MIN_SCALE)
    found = []
    for i in range(len(score)):
        if not measured[i]:
            found.append(BACKWARDS_STATE(why[i] or "no state"))
        elif not score[i] > ORDINARY:
            found.append(BACKWARDS_STATE("forwards"))
        else:
            kind = "done backwards" if began[i] > 0.5 and ended[i] < 0.5 else "toward the other end"
            found.append(BACKWARDS_STATE(kind, began=float(began[i]), ended=float(ended[i]), z=float(score[i])))
    return score, found
