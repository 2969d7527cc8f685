"""The ``backwards_state`` check (model-free): a reset recorded as a demo, read from the state.  A task's demos go
from where they begin to where they end; a reset goes the other way.  Per task and state dimension, the way from
its demos' median first value to their median last (``way_shares``); a demo done backwards begins near the end of
that way and ends near its start, in some dimension that moves along it -- the arm's joints where the reset is the
demo played backwards, the object's place where an operator carried it back with an arm that starts and ends at
home (``backwards_state``).  It reads the timeline's states (``democheck.audit.timeline.Timeline``), and is one look
with the camera's ``backwards`` in the ranking.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.neighbours import MIN_GROUP, ORDINARY, grouped
from democheck.audit.scores import calibrated
from democheck.audit.timeline import Timeline, dimension_names, stacked_states, state_floor
from democheck.data.reorder import velocities

WAY_MIN_SCALE = 0.05  # shares of a task's way from its start state to its end: the least robust SD of how far a
# demo's ends went along it toward the other end (clean demos' ends sit at their own end: a spread near zero)

BACKWARDS_STATE = Vocabulary("backwards_state", {
    # past the middle of its task's way from start to end at its first step, short of the middle at its last: the
    # whole state along the way (the arm), or one dimension of it (``name``: an object carried back)
    "done backwards": lambda began, ended, name=None, **_: (
        f"its {name or 'arm'} begins where its task's demos end and ends where they begin (its first "
        f"{'value' if name else 'state'} {began:.0%} of their way from start to end, its last {ended:.0%}): done "
        "backwards (a reset recorded as a demo?)"),
    "toward the other end": lambda began, ended, **_: (
        f"its arm begins further along its task's way, and ends less far, than its task's demos do (its first state "
        f"{began:.0%} of their way from start to end, its last {ended:.0%}): partly done backwards?"),
    "forwards": "its arm goes the way its task's demos go",
    "no way": "its task's demos share no way from where they begin to where they end: none to run backwards",
    "too few demos": "no task of enough demos to compare with",
    "no state": "no state recorded at its ends",
})


class Way(NamedTuple):
    """``way_shares``' result, per demo: where its first and last state lie on its task's way (``began``,
    ``ended``: 0 at the task's start, 1 at its end); the one state dimension done backwards most (``dim``, an index
    into the state, -1 where none; ``dim_began``, ``dim_ended`` its shares); why not measured (``""`` where it is)."""

    began: np.ndarray
    ended: np.ndarray
    dim: np.ndarray
    dim_began: np.ndarray
    dim_ended: np.ndarray
    why: np.ndarray


def way_shares(t: Timeline, groups: np.ndarray) -> Way:
    """Per demo, where its first and its last state lie on its task's way (the line from the median first state of
    its task's demos to their median last, over the dimensions that move along it by ``ORDINARY`` robust SD or
    more, each in its robust SD over the task's ends, at least ``timeline.STATE_FLOOR`` of its range over every
    demo's ends): 0 at the task's start, 1 at its end, over the dimensions the demo recorded at both ends; and the
    same in each of those dimensions alone, kept for the one done backwards most (``backwards_share``).  Why not,
    where not: "no state" (none recorded, or only actions, which may be steps rather than places), "too few
    demos", "no way" (its task's demos share none: a push toward a goal each layout draws anew, an arm that goes out
    and comes home).  Velocities are left out: how fast the arm went at either end is not where it was."""
    n = len(t.state_path)
    way = Way(began=np.full(n, np.nan), ended=np.full(n, np.nan), dim=np.full(n, -1), dim_began=np.full(n, np.nan),
              dim_ended=np.full(n, np.nan), why=np.array(["too few demos"] * n, dtype=object))
    if not n:
        return way
    first, last = stacked_states(t.state_path, 0), stacked_states(t.state_path, -1)
    keep = np.flatnonzero(~velocities(next((x for x, a in zip(t.names, t.from_actions) if x and not a), None),
                                      first.shape[1]))
    first, last = first[:, keep], last[:, keep]
    stated = ~np.asarray(t.from_actions, bool) & np.isfinite(first).any(axis=1) & np.isfinite(last).any(axis=1)
    way.why[~stated] = "no state"
    if not stated.any():
        return way
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
            along = np.nan_to_num((end_ - start_) / spread)
            along = np.where(np.abs(along) >= ORDINARY, along, 0.0)
            if not along.any():
                way.why[rows] = "no way"
                continue
            way.why[rows] = ""
            for x, out in ((s, way.began), (e, way.ended)):
                z = (x - start_) / spread
                seen = np.isfinite(z) & (along != 0)
                weight = (np.where(seen, along, 0.0) ** 2).sum(axis=1)
                out[rows] = np.where(weight > 0, np.where(seen, z * along, 0.0).sum(axis=1) / weight, np.nan)
            moving = np.flatnonzero(along)
            length = (end_ - start_)[moving]
            at_first, at_last = (s[:, moving] - start_[moving]) / length, (e[:, moving] - start_[moving]) / length
            crossed = np.nan_to_num(backwards_share(at_first, at_last), nan=-1.0)
            most, k = np.argmax(crossed, axis=1), np.arange(len(rows))
            found = crossed[k, most] > 0
            way.dim[rows] = np.where(found, keep[moving[most]], -1)
            way.dim_began[rows] = np.where(found, at_first[k, most], np.nan)
            way.dim_ended[rows] = np.where(found, at_last[k, most], np.nan)
    return way


def backwards_share(began: np.ndarray, ended: np.ndarray) -> np.ndarray:
    """How near its task's end one state dimension began and how near their start it ended, where it did both past
    the middle of the way (shares of the way, 0 at the start, 1 at the end): the lesser of the two nearnesses, in
    (0.5, 1] -- 1 for a value that began where its task's demos end and ended where they begin --, else 0.  One
    dimension is read only done backwards outright: a few of many that drift part of the way are noise, and a value
    that ends beyond the start, on the side no demo goes (an arm that swung the other way on its layout), came back
    to no start."""
    near = np.minimum(1 - np.abs(1 - began), 1 - np.abs(ended))
    return np.where(near > 0.5, near, 0.0)


def backwards_state(t: Timeline, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How far a demo's first state lies along its task's way toward their last state, and its last state back
    toward their first (``way_shares``; the lesser of the two, each within [0, 1]), or, where more, how near one
    state dimension done backwards outright began to their end and ended to their start (``backwards_share``: an
    object carried back by an arm that starts and ends at home), robust z within its task (a robust SD at least
    ``WAY_MIN_SCALE`` of the way): a reset recorded as a demo, read from the state where the camera's colours cannot
    tell a task's start from its end.  One look with ``backwards``: two readings of one question."""
    way = way_shares(t, groups)
    began, ended = np.clip(way.began, 0, 1), np.clip(way.ended, 0, 1)
    whole = np.minimum(began, 1 - ended)
    one = np.nan_to_num(backwards_share(way.dim_began, way.dim_ended))
    crossed = np.where(np.isfinite(whole), np.fmax(whole, one), np.nan)  # clipping keeps a NaN end NaN
    score = calibrated(crossed, groups, min_scale=WAY_MIN_SCALE)
    found = []
    for i in range(len(score)):
        if not np.isfinite(crossed[i]):
            found.append(BACKWARDS_STATE(way.why[i] or "no state"))
        elif not score[i] > ORDINARY:
            found.append(BACKWARDS_STATE("forwards"))
        elif one[i] > whole[i]:
            found.append(BACKWARDS_STATE("done backwards", began=float(np.clip(way.dim_began[i], 0, 1)),
                                         ended=float(np.clip(way.dim_ended[i], 0, 1)), z=float(score[i]),
                                         name=dimension_names(t.names[i], np.array([way.dim[i]]), "state")))
        else:
            kind = "done backwards" if began[i] > 0.5 and ended[i] < 0.5 else "toward the other end"
            found.append(BACKWARDS_STATE(kind, began=float(began[i]), ended=float(ended[i]), z=float(score[i])))
    return score, found
