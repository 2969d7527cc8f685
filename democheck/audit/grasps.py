"""The ``grasps`` check (model-free): how often the gripper was opened or closed, against its task's demos.

A grasp that missed and was tried again, an object dropped on the way and picked up again: the gripper's command
changes between open and closed more often than in its task's other demos, while every other check sees the demo
only a little unlike them (a few more steps, a short detour).  A count says it plainly.  A command that flickers
(most of its changes a single step after the one before: a noisy or random command, which no gripper follows) is
told apart from a grasp tried again.

The gripper is the action dimensions the dataset names so ("gripper", "grip"); a dataset that names none has no
such check (NaN).  Each task has its own open and closed ends of each such dimension, the medians of its demos'
lowest and highest commands, since tasks hold the gripper differently (one never opens it, one grasps from a
command of 0 where another opens it at -1); a task that never moves it takes the ``SPAN`` percentiles over every
demo.  A command changes where it crosses from the lower third of that range to the upper third or back: a noisy
command near one end, or one that stops halfway, is no change.  The score is the number of changes; the ranking
judges it within its task (only more changes than the task's are suspect: fewer is a demo that never grasped,
which the outcome and motion checks see).  It reads the actions the other action checks keep
(``modelfree.ActionTraces``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import ActionTraces

GRIPPER_NAMES = ("grip",)  # an action dimension whose name holds one of these (any case) commands the gripper
SPAN = (0.01, 0.99)  # percentiles over every demo: the ends of a task that never moves the gripper
BAND = 1 / 3  # the command changes where it crosses from this share of the span at one end to as much at the other


def _frames(frames: list[int]) -> str:
    shown = [str(f) for f in frames[:6]]
    if len(frames) > 6:
        return ", ".join(shown) + ", ..."
    return ", ".join(shown[:-1]) + " and " + shown[-1] if len(shown) > 1 else shown[0]


def _times(count: float) -> str:
    return {1: "once", 2: "twice"}.get(int(count), f"{count:g} times") if count == int(count) else f"{count:g} times"


def _gripper(count: float) -> str:
    return "the gripper never opens or closes" if count == 0 else f"the gripper opens or closes {_times(count)}"


def _theirs(typical: float) -> str:
    return "its task's demos never do" if typical == 0 else f"its task's demos do so {_times(typical)}"


def _again(count: int, typical: float, frames: list[int]) -> str:
    return (f"{_gripper(count)} (at frames {_frames(frames)}) where {_theirs(typical)}: a grasp tried again, or an "
            "object dropped and picked up?")


def _otherwise(count: int, typical: float, frames: list[int]) -> str:
    return (f"{_gripper(count)} (at frames {_frames(frames)}) where {_theirs(typical)}, and ends the other way: an "
            "object let go where they hold it, or held where they let go?")


def _chatters(count: int, typical: float, frames: list[int], flickers: int) -> str:
    return (f"the gripper command flickers: {_gripper(count).removeprefix('the gripper ')} (at frames "
            f"{_frames(frames)}) where {_theirs(typical)}, {flickers} of them a step after the last: a noisy or "
            "random command?")


GRASPS = Vocabulary("grasps", {
    # More changes than its task's demos make, at least half of them a single step after the one before: the
    # command flickers between open and closed (no gripper closes, opens and closes again in a step).
    "chatters": _chatters,
    # More changes than its task's demos make: an even number more ends as theirs do (closed again), an odd number
    # ends the other way.
    "again": _again,
    "ends otherwise": _otherwise,
    "fewer": lambda count, typical: f"{_gripper(count)} where {_theirs(typical)}",
    "as its task's": lambda count: f"{_gripper(count)}, as its task's demos do",
    "no gripper": "",  # the dataset names no gripper among its actions
})


def gripper_dims(action_names: list[str] | None) -> list[int]:
    """The action dimensions whose names say they command the gripper (``GRIPPER_NAMES``); none without names."""
    return [k for k, name in enumerate(action_names or []) if any(g in str(name).lower() for g in GRIPPER_NAMES)]


def changes(command: np.ndarray, low: float, high: float) -> list[int]:
    """The steps at which a command crosses from the lower third of [``low``, ``high``] to the upper third or
    back (``BAND``): it stays open or closed until it reaches the other end."""
    lo, hi = low + BAND * (high - low), high - BAND * (high - low)
    state, out = None, []
    for t, v in enumerate(command):
        now = 1 if v >= hi else 0 if v <= lo else state
        if state is not None and now is not None and now != state:
            out.append(t)
        state = now if now is not None else state
    return out


def grasps(traces: ActionTraces, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """Per demo, how many times its gripper command changed between open and closed (``changes``, summed over the
    gripper's dimensions; NaN where the dataset names no gripper, or where its command never spans a range), with
    the frames and its task's median count."""
    commands = [np.asarray(a, np.float64).reshape(len(a), -1)[:, gripper_dims(names)]
                for a, names in zip(traces.actions, traces.names)]
    width = max((c.shape[1] for c in commands), default=0)
    n = len(commands)
    if not width or not all(c.shape[1] == width for c in commands):
        return np.full(n, np.nan), [GRASPS("no gripper")] * n
    every = np.concatenate([c for c in commands if len(c)]) if n else np.zeros((0, width))
    pooled = np.quantile(every, SPAN, axis=0) if len(every) else np.zeros((2, width))
    if not (pooled[1] > pooled[0]).any():
        return np.full(n, np.nan), [GRASPS("no gripper")] * n
    groups = np.asarray(groups)
    lows = np.array([c.min(0) if len(c) else np.full(width, np.nan) for c in commands])
    highs = np.array([c.max(0) if len(c) else np.full(width, np.nan) for c in commands])
    low = pd.DataFrame(lows).groupby(groups).transform("median").to_numpy()
    high = pd.DataFrame(highs).groupby(groups).transform("median").to_numpy()
    still = ~(high > low)  # a task whose demos keep the gripper as it is: the ends over every demo
    low, high = np.where(still, pooled[0], low), np.where(still, pooled[1], high)
    steps = [sorted(t for k in range(width) if high[i, k] > low[i, k] for t in changes(c[:, k], low[i, k], high[i, k]))
             for i, c in enumerate(commands)]
    count = np.array([len(s) for s in steps], np.float64)
    typical = pd.Series(count).groupby(groups).transform("median").to_numpy()
    found = []
    for c, m, s in zip(count, typical, steps):
        flickers = int(np.sum(np.diff(s) == 1)) if len(s) > 1 else 0
        kind = _kind(c, m, flickers)
        extra = {"flickers": flickers} if kind == "chatters" else {}
        found.append(GRASPS(kind, count=int(c), typical=float(m), frames=s, **extra))
    return count, found


def _kind(count: float, typical: float, flickers: int = 0) -> str:
    """More changes than its task's demos make: at least half of them a step after the one before (``chatters``),
    else an even number more ends as theirs do (``again``), an odd number ends the other way."""
    if count > typical:
        if flickers and 2 * flickers >= count - 1:
            return "chatters"
        return "again" if (count - round(typical)) % 2 == 0 else "ends otherwise"
    return "fewer" if count < typical else "as its task's"
