"""The ``frozen_state`` check (model-free): a state sensor that stopped updating while the arm was driven.

Per dimension of the state, the longest stretch of steps at which its value repeats exactly (bit for bit: a
live sensor's reading, or a simulator's, changes in its last digits whenever the arm moves) while the actions
change, as a share of the demo's steps.  Only the dimensions live in the demo's task count: those whose share's
``FROZEN_STATE_QUANTILE`` over the task's demos (over every demo where the task has fewer than
``FROZEN_STATE_MIN_DEMOS``) is at most ``FROZEN_STATE_LIVE`` -- still in hardly any of them.  A goal, an object at
rest until the arm reaches it, or one a simulator sometimes lets settle bit for bit, is left out; so is a stretch
held at a joint's stop, at the edge of its range in the demo while its own command stays there (``at_limit``).  The
score is the largest share over the live dimensions: one joint whose encoder died for the whole demo reads 1, the whole
state stream frozen from a step on reads the rest of the demo.  The reason names the dimension and the frames.
A recording fault: in the ranking beside the other scores (``alone`` in the ranking recipe).  A consumer of the
audit's decoding pass like the other model-free checks (``democheck.audit.modelfree``).

(Chosen on the development sets, with planted faults: docs/decisions.md, "Frozen state: added, and its 75th
percentile".)
"""

from __future__ import annotations

import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo, longest_run, steps_text
from democheck.data.demo import Demo

FROZEN_STATE_MIN_DEMOS = 4  # a task with fewer demos is compared with every demo
FROZEN_STATE_LIVE = 0.05  # a dimension is live in a task where its share's FROZEN_STATE_QUANTILE is at most this
FROZEN_STATE_QUANTILE = 0.75  # over the task's demos: live means still in hardly any of them
DRIVEN_SHARE = 0.01  # a step is driven when its action changes by this share of the demo's 90th-percentile change


def commands(state_names: list[str] | None, action_names: list[str] | None, s: int, a: int) -> np.ndarray:
    """[S] the action dimension that commands each state dimension, -1 for none: by name where the dataset names
    both (a joint's position and its commanded position, 'shoulder_pan.pos' in each), else by position where state
    and actions are as wide and neither is named otherwise; none where they differ (torques, velocities, a
    gripper's opening against an arm's pose)."""
    if state_names and action_names:
        where = {n: k for k, n in enumerate(action_names)}
        return np.array([where.get(n, -1) for n in state_names], int)
    return np.arange(s) if s == a and not (state_names or action_names) else np.full(s, -1)


class StateRepeats(PerDemo):
    """Consumer of decoded demos: per state dimension, the longest stretch of steps at which the value repeats
    while it is driven (its share of the demo's steps, where it starts, how many steps it lasts).  A dimension
    with a command of its own (``commands``) is driven where that command changes by more than ``DRIVEN_SHARE``
    of its large changes, and a stretch held at the edge of the demo's range while its command stays there or
    beyond is a joint at its limit, not a fault; another is driven where any action changes so."""

    fields = ("shares", "starts", "lengths", "steps", "names", "rests", "stirred")
    shares: list[np.ndarray]  # [S]
    starts: list[np.ndarray]  # [S]
    lengths: list[np.ndarray]  # [S]
    # [S] whether that stretch is a part at rest: other dimensions change during it, and the value changes again
    # after it or other dimensions hold with it (an object's position and orientation); an encoder that died holds
    # alone to the end, a stream that stopped holds every dimension
    rests: list[np.ndarray]
    stirred: list[np.ndarray]  # [S] whether other dimensions changed during that stretch (the arm moved)
    steps: list[int]  # the demo's steps (frames - 1)
    names: list[list[str] | None]  # the dataset's names of the state dimensions, where it names them

    def add(self, demo: Demo) -> None:
        x, a = np.asarray(demo.state), np.asarray(demo.actions)
        n = max(len(x) - 1, 0)
        steps = np.abs(np.diff(a, axis=0)) if n else np.zeros((0, a.shape[1]))
        # Driven: the command changes by more than float noise around a held pose -- a share of the demo's own
        # large changes (a controller holding still at its goal repeats its command to the sixth digit).
        change = steps.max(axis=1) if n else np.zeros(0)
        driven = np.repeat((change > DRIVEN_SHARE * np.quantile(change, 0.9) if n else np.zeros(0, bool))[:, None],
                           x.shape[1], axis=1)
        own = commands(demo.extra.get("state_names"), demo.extra.get("action_names"), x.shape[1], a.shape[1])
        for j, k in enumerate(own):
            if k >= 0 and n:
                driven[:, j] = steps[:, k] > DRIVEN_SHARE * np.quantile(steps[:, k], 0.9)
        changes = x[1:] != x[:-1] if n else np.zeros((0, x.shape[1]), bool)
        repeats = ~changes & driven
        runs = [longest_run(repeats[:, j]) for j in range(x.shape[1])]
        runs = [(0, 0) if own[j] >= 0 and at_limit(x[:, j], a[:, own[j]], s, k) else (s, k)
                for j, (s, k) in enumerate(runs)]
        starts = np.array([s for s, _ in runs], int)
        lengths = np.array([k for _, k in runs], int)
        self.shares.append(lengths / max(n, 1))
        self.starts.append(starts)
        self.lengths.append(lengths)
        self.steps.append(n)
        self.names.append(demo.extra.get("state_names"))
        moves = changes.any(axis=0)  # a goal or a constant holds through every stretch: no part of an object
        stirred = np.array([k > 0 and changes[s:s + k].any() for s, k in runs], bool)
        self.stirred.append(stirred)
        self.rests.append(np.array([stirred[j] and (
            changes[s + k:, j].any() or (repeats[s:s + k].all(axis=0) & moves).sum() > 1)
            for j, (s, k) in enumerate(runs)], bool))


def at_limit(state: np.ndarray, command: np.ndarray, start: int, length: int) -> bool:
    """Whether a joint held over steps ``start`` .. ``start + length`` sits at the edge of its range in the demo
    while its own command stays there or beyond (fingers open as far as they go, told to open): held by its stop,
    not by a dead sensor.  Within 1% of the joint's range of the edge."""
    if not length:
        return False
    held = float(state[start + 1])
    lo, hi = float(np.min(state)), float(np.max(state))
    tol = 0.01 * max(hi - lo, 1e-9)
    asked = command[start + 1:start + length + 1]
    return bool((held >= hi - tol and (asked >= held - tol).all()) or (held <= lo + tol and (asked <= held + tol).all()))


def _holds(what: str, start: int, stop: int, length: int) -> str:
    return f"{what} holds one value while the arm is driven over {steps_text(start, stop, length)}, where its " \
           "task's demos rarely do"


FROZEN_STATE = Vocabulary("frozen_state", {
    # held while the arm was driven for longer than the arm ever stood still: a sensor that stopped updating
    "stopped": _holds,
    "held": _holds,  # held no longer than the arm stood still at some point: it may have rested with the arm
    # it moves again after the hold, or holds with other moving dimensions (or with others its task's demos move)
    # while the rest of the state changes: a part at rest (an object left alone), which says how the demo differs,
    # not that a sensor failed
    "at rest": _holds,
    "moves": "every state dimension that moves in its task's demos moves",
    "no state": "no state",
    "single frame": "a single frame",
})


def frozen_state(stats: StateRepeats, tasks: np.ndarray, live: float | None = None,
                 still: np.ndarray | None = None) -> tuple[np.ndarray, list[Finding]]:
    """The longest frozen stretch's share (see the module docstring) of the state dimensions live in the demo's
    task (those whose share's ``FROZEN_STATE_QUANTILE`` over the task's demos is at most ``live``), the largest;
    and which dimension held where (``at rest``: a part at rest, ``StateRepeats.rests`` or ``_left_alone``;
    ``stopped``: held longer than the arm's longest still stretch, ``still`` [N] as a share of the steps, where
    given; else ``held``)."""
    if not stats.shares:
        return np.zeros(0), []
    seen = _live_shares(stats, tasks, live)
    out, found = np.zeros(len(seen)), []
    for i in range(len(seen)):
        if not seen.shape[1] or not stats.steps[i]:
            found.append(FROZEN_STATE("no state" if not seen.shape[1] else "single frame"))
            continue
        j = int(np.argmax(seen[i]))
        out[i] = float(seen[i, j])
        if out[i] <= 0:
            found.append(FROZEN_STATE("moves"))
            continue
        start, length = int(stats.starts[i][j]), int(stats.lengths[i][j])
        names = stats.names[i] if i < len(stats.names) else None
        kind = ("at rest" if stats.rests[i][j] or _left_alone(stats, seen, i, j) else
                "stopped" if still is not None and out[i] > still[i] else "held")
        found.append(FROZEN_STATE(kind, what=names[j] if names and j < len(names) else f"state[{j}]", dim=j,
                                  start=start, stop=start + length, length=stats.steps[i] + 1))
    return out, found


def _left_alone(stats: StateRepeats, seen: np.ndarray, i: int, j: int) -> bool:
    """Whether demo ``i``'s dimension ``j`` held over the same stretch as another dimension live in its task
    (``seen`` [N, S], ``_live_shares``; ``j`` holds the longest, so the other's stretch covers its own only where
    the two are one) while the arm moved: an object's coordinates the demo never touched, which its task's demos
    move -- an encoder dies alone."""
    start, stop = stats.starts[i][j], stats.starts[i][j] + stats.lengths[i][j]
    starts, stops = np.asarray(stats.starts[i]), np.asarray(stats.starts[i]) + np.asarray(stats.lengths[i])
    together = (seen[i] > 0) & (starts <= start) & (stops >= stop)
    together[j] = False
    return bool(stats.stirred[i][j] and together.any())


def _live_shares(stats: StateRepeats, tasks: np.ndarray, live: float | None = None) -> np.ndarray:
    """[N, S] each demo's frozen share per state dimension, 0 where the dimension is not live in its task (those
    whose share's ``FROZEN_STATE_QUANTILE`` over the task's demos is more than ``live``)."""
    live = FROZEN_STATE_LIVE if live is None else live
    shares = np.stack(stats.shares).astype(np.float64)
    tasks = np.asarray(tasks)
    usual = np.zeros_like(shares)  # per demo and dimension: its task's FROZEN_STATE_QUANTILE of the share
    for t in np.unique(tasks):
        rows = tasks == t
        usual[rows] = np.quantile(shares[rows] if rows.sum() >= FROZEN_STATE_MIN_DEMOS else shares,
                                  FROZEN_STATE_QUANTILE, axis=0)
    return np.where(usual <= live, shares, 0.0)
