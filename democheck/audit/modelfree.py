"""Model-free checks: what a demo's actions, state and frames say without any model.

Each check consumes the audit's decoding pass (``add`` one decoded demo at a time, ``finish`` once) and returns one
number per demo -- higher is more suspect -- and a reason located in time.  They need no training, so ``democheck
audit --no-model`` runs them on any robot.  Every scale is the audited demos' own: a step's change of action is
measured per action dimension in units of that dimension's median change over all the demos (at least 1% of the
busiest dimension's, so that a gripper held shut cannot make a tiny twitch look huge).

- ``motion``: how unusually much or little the actions move for the task (mean |action| and mean |change of
  action| against the demos' median, on a log scale; the larger robust |z|).
- ``idle``: the share of steps at which the actions hardly change (under ``STILL`` of the median change), against
  its task's share, since demos often rest once the task is done: an arm that never moves, or stops half-way.
- ``pause``: the longest still stretch between the demo's first and last move, as a share of its steps: an
  operator who hesitated mid-task (a still start or end is no pause).
- ``jerk``: the log mean absolute third difference of the actions: shaking, chattering or random commands.
- ``view`` (``democheck.audit.view``): how much of the demo's average picture is unlike its task's other demos'
  there (a covered, moved or blinded camera, another scene); ``colours`` (``democheck.audit.colours``): its
  colours, wherever they are.
- ``frozen_video``, ``frame_jump`` (``democheck.audit.frames``), ``state_jump`` (``democheck.audit.dynamics``) and
  ``timing``: recording faults -- a camera that stopped, steps dropped or recordings spliced, and the worst time
  step of the ``timestamp`` column against the frame period, log(1 + |step - period| / period) over the steps off
  by more than ``TIMING_TOLERANCE`` of it (NaN without timestamps).
- ``saturation``: the share of steps at which some action sits at its smallest or largest value (clipped).
- ``dynamics`` (``democheck.audit.dynamics``): how badly the state follows the actions; ``outcome``
  (``democheck.audit.outcome``): how differently from its task's other demos the demo left the world.
- ``broken``: the share of frames that could not be decoded, or of state and actions that were NaN or infinite
  (repaired so that the other checks can read the demo); any makes the demo suspect.
- ``duplicate``: how close the demo's actions come to another demo's (the log median nearest-neighbour distance,
  resampled to ``DUPLICATE_STEPS`` steps); an exact copy is named as such.
"""

from __future__ import annotations

import hashlib
import zlib

import numpy as np
import pandas as pd

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.scores import calibrated
from democheck.audit.words import factor
from democheck.data.demo import Demo

STILL = 0.05  # a step is still when its change of action is under 5% of the median change
DUPLICATE_STEPS = 32
TIMING_TOLERANCE = 0.5  # a time step off the usual one by more than half of it is irregular
JUMP_NEIGHBOURS = 5  # steps either side of a step that say how much a step usually changes there


def steps_text(start: int, stop: int, length: int) -> str:
    return f"frames {start}-{stop} ({100 * (stop - start + 1) / max(length, 1):.0f}% of the demo)"


def longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(start, length) of the longest run of True in a 1-d mask; (0, 0) when there is none."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    if not len(edges):
        return 0, 0
    starts, stops = edges[::2], edges[1::2]
    i = int(np.argmax(stops - starts))
    return int(starts[i]), int(stops[i] - starts[i])


def jump_ratios(change: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Per step, its ``change`` [T] over the median change of the ``JUMP_NEIGHBOURS`` steps either side (the step
    itself left out; at least ``floor``) -- how much more happened at that step than around it -- and that usual
    change.  A stretch cut out of a recording is one step that changes as much as the whole stretch did."""
    k = JUMP_NEIGHBOURS
    change = np.asarray(change, np.float64)
    padded = np.concatenate([np.full(k, np.nan), change, np.full(k, np.nan)])
    window = np.lib.stride_tricks.sliding_window_view(padded, 2 * k + 1)
    usual = np.maximum(np.nanmedian(np.delete(window, k, axis=1), axis=1), floor)
    return change / usual, usual


def change_scale(changes: list[np.ndarray]) -> np.ndarray:
    """Per action dimension, the unit a step's |change of action| is measured in (see the module docstring)."""
    if not changes or not sum(len(c) for c in changes):
        return np.ones(changes[0].shape[1] if changes else 1)
    median = np.median(np.concatenate(changes), axis=0)
    return np.maximum(median, max(0.01 * float(median.max()), 1e-9))


class PerDemo:
    """A consumer that keeps lists with one entry per demo (``fields``); ``merged`` puts several consumers'
    lists one after another -- the shards of one dataset decoded in parallel, or the datasets a bench pools --
    and ``finish`` (here: the consumer itself) then sees them as if one consumer had been fed them all."""

    fields: tuple[str, ...] = ()

    def __init__(self) -> None:
        for name in self.fields:
            setattr(self, name, [])

    def finish(self) -> "PerDemo":
        return self

    @classmethod
    def merged(cls, parts: list["PerDemo"]) -> "PerDemo":
        out = cls()
        for part in parts:
            for name in cls.fields:
                getattr(out, name).extend(getattr(part, name))
        return out


class ActionTraces(PerDemo):
    """Consumer of decoded demos: each demo's actions and their names, a fingerprint of its actions, state and
    frames, and its ``timing``, kept for the action checks (``idle``, ``jerk``, ``saturation``, ``duplicate``,
    ``timing``, ``grasps``), which need the scales of all the demos."""

    fields = ("actions", "names", "digests", "timing", "damaged")
    actions: list[np.ndarray]
    names: list[list[str] | None]  # the dataset's names of the action dimensions, where it names them
    digests: list[str]
    timing: list[tuple[float, Finding]]
    damaged: list[tuple[float, str, list[tuple[str, str]]]]  # share, in words, (file, why) of unreadable frames

    def add(self, demo: Demo) -> None:
        a = np.asarray(demo.actions, np.float32)
        self.actions.append(a)
        self.names.append(demo.extra.get("action_names"))
        frames = max((d.frames for d in demo.damaged), default=0)
        self.damaged.append((frames / max(len(a), 1), "; ".join(d.what for d in demo.damaged),
                             [(d.file, d.why) for d in demo.damaged if d.file]))
        self.timing.append(_timing_of(demo.extra.get("timestamp"), demo.extra.get("fps")))
        # Equal actions and states bit for bit (a cryptographic hash), and equal frames (a CRC-32 of them: a hub
        # camera's frames, 0.2 GB a demo, in a tenth of a hash's time, and two demos alike in every action and
        # state that differ in their frames alone collide once in 4e9).
        h = hashlib.blake2b(digest_size=16)
        for x in (a, np.asarray(demo.state, np.float32)):
            h.update(np.ascontiguousarray(x).tobytes())
        pictures = np.ascontiguousarray(demo.frames)
        crc = zlib.crc32(memoryview(pictures).cast("B")) if pictures.size else 0
        self.digests.append(f"{h.hexdigest()}-{crc:08x}")


def still_steps(traces: ActionTraces) -> list[np.ndarray]:
    """Per demo, bool per step: whether the actions hardly change there (``STILL`` of the typical change)."""
    changes = [np.abs(np.diff(a.astype(np.float64), axis=0)) for a in traces.actions]
    scale = change_scale(changes)
    return [(c / scale).mean(1) < STILL if len(c) else np.zeros(0, bool) for c in changes]


def _still_words(share: float, start: int, stop: int, length: int) -> str:
    return f"the arm stands still at {100 * share:.0f}% of steps, longest {steps_text(start, stop, length)}"


IDLE = Vocabulary("idle", {
    "still": _still_words,  # it stops and stands to the end, or never moves
    "paused": _still_words,  # it began late or paused, then moved on: how the demo differs, not what went wrong
    "never still": "never still",
    "single frame": "a single frame",
})


def idle(traces: ActionTraces) -> tuple[np.ndarray, list[Finding]]:
    """Share of each demo's steps at which the actions hardly change, and its longest still stretch (``longest``,
    a share of the steps): ``paused`` where the arm stands still for less than half the demo and moves again after
    that stretch (it began late or paused), else ``still``."""
    out, found = np.zeros(len(traces.actions)), []
    for i, still in enumerate(still_steps(traces)):
        if not len(still):
            found.append(IDLE("single frame"))
            continue
        out[i] = float(still.mean())
        start, n = longest_run(still)
        if not n:
            found.append(IDLE("never still"))
            continue
        kind = "paused" if start + n < len(still) and out[i] < 0.5 else "still"
        found.append(IDLE(kind, share=out[i], start=start, stop=start + n, length=len(still) + 1,
                          longest=n / len(still)))
    return out, found


PAUSE = Vocabulary("pause", {
    "paused": lambda start, stop, length, share, **_: f"the arm stops mid-task and then goes on: still over "
                                                      f"{steps_text(start, stop, length)}",
    "no pause": "no pause between its first and last move",
    "single frame": "a single frame",
})


def pause(traces: ActionTraces) -> tuple[np.ndarray, list[Finding]]:
    """The longest stretch at which the actions hardly change between the demo's first and last change, as a share
    of its steps: an operator who hesitated mid-task.  A still start (the recording began before the operator
    did) and a still end (the task done, the recording not yet stopped) are no pause."""
    out, found = np.zeros(len(traces.actions)), []
    for i, still in enumerate(still_steps(traces)):
        if not len(still):
            found.append(PAUSE("single frame"))
            continue
        moving = np.flatnonzero(~still)
        inner = np.zeros(len(still), bool)
        if len(moving):
            inner[moving[0]:moving[-1] + 1] = still[moving[0]:moving[-1] + 1]
        start, n = longest_run(inner)
        out[i] = n / len(still)
        found.append(PAUSE("paused", start=start, stop=start + n, length=len(still) + 1, share=float(out[i])) if n
                     else PAUSE("no pause"))
    return out, found


BROKEN = Vocabulary("broken", {"damaged": "{what}", "intact": ""})


def broken(traces: ActionTraces) -> tuple[np.ndarray, list[Finding]]:
    """The share of the demo's frames that could not be decoded (the reader gave black frames instead) or whose
    state or actions held NaN or infinite values (repaired by ``data.demo.repair_non_finite``), the most damaged
    of these, and where: the readers make every demo readable so that every check can run.  A recording that is
    broken so ranks first whatever its other scores, is flagged, and is no reference for the others
    (``scorers.broken_rows``, ``flagging.flagged_regardless``).  A damaged demo's finding names the files whose
    frames could not be read (``files``)."""
    found = [BROKEN("damaged", what=what, files=files) if share > 0 else BROKEN("intact")
             for share, what, files in traces.damaged]
    return np.array([share for share, _, _ in traces.damaged], np.float64), found


JUMP_STEPS = 3  # a demo's jerk is one jump when its largest this many steps hold
JUMP_SHARE = 0.5  # ... this share of it: an arm stopped (or started) at once, not a shaking command


JERK = Vocabulary("jerk", {
    "shakes": "the actions shake, most at frame {frame}",
    "jumps": "the actions jump at frame {frame}",  # one jump: an arm stopped or started at once
    "too short": "too short",
})


def jerk(traces: ActionTraces) -> tuple[np.ndarray, list[Finding]]:
    """log mean |third difference of actions| in median-change units, and where it is largest: the actions shake,
    or jump once (``JUMP_SHARE`` of it in ``JUMP_STEPS`` steps)."""
    out, peak, jumps = _jerk_parts(traces)
    found = [JERK("too short") if k < 0 else JERK("jumps" if j else "shakes", frame=int(k))
             for k, j in zip(peak, jumps)]
    return out, found


def _jerk_parts(traces: ActionTraces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    changes = [np.diff(a.astype(np.float64), axis=0) for a in traces.actions]
    scale = change_scale([np.abs(c) for c in changes])
    out, peak, jumps = np.full(len(changes), np.nan), np.full(len(changes), -1), np.zeros(len(changes), bool)
    for i, c in enumerate(changes):
        third = np.abs(np.diff(c, n=2, axis=0)) / scale
        if not len(third):
            continue
        per_step = third.mean(1)
        out[i] = float(np.log(per_step.mean() + 1e-9))
        peak[i] = int(np.argmax(per_step)) + 2
        jumps[i] = np.sort(per_step)[-JUMP_STEPS:].sum() > JUMP_SHARE * per_step.sum()
    return out, peak, jumps


SATURATION = Vocabulary("saturation", {
    "at a limit": lambda share, dims: f"{100 * share:.0f}% of steps at a limit"
    + (f" (dimension {', '.join(map(str, dims[:3]))})" if len(dims) else ""),
})


def saturation(traces: ActionTraces) -> tuple[np.ndarray, list[Finding]]:
    """Share of steps at which some action dimension sits at its limit over all the demos."""
    if not traces.actions:
        return np.zeros(0), []
    every = np.concatenate(traces.actions)
    lo, hi = every.min(0), every.max(0)
    moving = hi > lo  # a dimension that never changes is at both limits all the time: it does not count
    out, reasons = np.zeros(len(traces.actions)), []
    for i, a in enumerate(traces.actions):
        at = ((a == lo) | (a == hi))[:, moving]
        hit = at.any(1) if at.size else np.zeros(len(a), bool)
        out[i] = float(hit.mean()) if len(a) else 0.0
        dims = np.flatnonzero(moving)[at.any(0)] if at.size else []
        reasons.append(SATURATION("at a limit", share=out[i], dims=[int(d) for d in dims]))
    return out, reasons


DUPLICATE = Vocabulary("duplicate", {
    "exact copy": "an exact copy of episode {episode} (actions, state and frames)",
    "nearest": lambda episode, ratio: f"nearest episode {episode}, {factor(ratio)} x the usual distance",
    "alone": "",
})


def duplicate(traces: ActionTraces, episode_index: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How much nearer than usual the demo's nearest other demo is (log ratio), and which demo that is; an exact
    copy of another demo scores ``inf``."""
    n = len(traces.actions)
    out, reasons = np.full(n, np.nan), [DUPLICATE("alone")] * n
    if n < 2:
        return out, reasons
    dims = traces.actions[0].shape[1]
    grid = np.linspace(0.0, 1.0, DUPLICATE_STEPS)
    rows = []
    for a in traces.actions:
        t = np.linspace(0.0, 1.0, len(a)) if len(a) > 1 else np.zeros(1)
        rows.append(np.column_stack([np.interp(grid, t, a[:, d]) if len(a) > 1 else np.full(DUPLICATE_STEPS, a[0, d])
                                     for d in range(dims)]))
    x = np.stack(rows)
    x = (x / np.maximum(x.reshape(-1, dims).std(0), 1e-9)).reshape(n, -1)
    from sklearn.neighbors import NearestNeighbors

    dist, idx = NearestNeighbors(n_neighbors=2).fit(x).kneighbors(x)
    # The first neighbour is the demo itself, unless an identical demo came first: take the nearest other.
    other = np.where(idx[:, 0] == np.arange(n), idx[:, 1], idx[:, 0])
    near = np.where(idx[:, 0] == np.arange(n), dist[:, 1], dist[:, 0]) / np.sqrt(x.shape[1])
    typical = float(np.median(near))
    out = np.log(max(typical, 1e-12) / np.maximum(near, 1e-12))
    first: dict[str, int] = {}
    for i, digest in enumerate(traces.digests):
        j = first.setdefault(digest, i)
        if j != i:
            out[i] = np.inf
            reasons[i] = DUPLICATE("exact copy", episode=int(episode_index[j]))
        else:
            reasons[i] = DUPLICATE("nearest", episode=int(episode_index[other[i]]),
                                   ratio=float(near[i] / max(typical, 1e-12)))
    return out, reasons


def _off_period(share: float, period: float, first: int, first_dt: float, worst: int, worst_dt: float,
                back: int | None) -> str:
    return (f"{100 * share:.0f}% of time steps off the frame period ({period:.3g} s), first at frame {first}: "
            f"{first_dt:.3g} s; the worst at frame {worst}: {worst_dt:.3g} s"
            + (f"; time stands still or goes back at frame {back}" if back is not None else ""))


TIMING = Vocabulary("timing", {
    "off the period": _off_period,
    "regular": "regular time steps",
    "no timestamps": "no timestamps",
    "timestamps missing": "timestamps missing at some frames",
    "single frame": "a single frame",
})


def _timing_of(t: np.ndarray | None, fps: float | None) -> tuple[float, Finding]:
    """``timing`` of one demo: how far its worst time step is off the frame period (see the module docstring)."""
    if t is None or not fps:
        return np.nan, TIMING("no timestamps")
    if not np.isfinite(t).all():
        return np.nan, TIMING("timestamps missing")
    if len(t) < 2:
        return 0.0, TIMING("single frame")
    period = 1.0 / float(fps)
    dt = np.diff(np.asarray(t, np.float64))
    # A step that stands still or goes back is at least a period off, however small |dt - period| is.
    error = np.where(dt > 0, np.abs(dt - period), period + np.abs(dt)) / period
    off = error > TIMING_TOLERANCE
    if not off.any():
        return 0.0, TIMING("regular")
    first, worst = int(np.argmax(off)), int(np.argmax(error))
    back = np.flatnonzero(dt <= 0)
    return float(np.log1p(error[worst])), TIMING(
        "off the period", share=float(off.mean()), period=period, first=first + 1, first_dt=float(dt[first]),
        worst=worst + 1, worst_dt=float(dt[worst]), back=int(back[0]) + 1 if len(back) else None)


def timing(traces: ActionTraces) -> tuple[np.ndarray, list[Finding]]:
    """How far each demo's worst time step is off the frame period (see the module docstring), and where."""
    return np.array([v for v, _ in traces.timing], np.float64), [r for _, r in traces.timing]


MOTION_TASK_MIN = 5  # demos a task needs for its median to set a dimension's unit of motion


class MotionStats(PerDemo):
    """Consumer of decoded demos: how much each demo's actions move, model-free -- per action dimension the mean
    |action| and the mean |change of action| between steps."""

    fields = ("level", "change", "tasks")
    level: list[np.ndarray]
    change: list[np.ndarray]
    tasks: list[str]

    def add(self, demo: Demo) -> None:
        a = np.asarray(demo.actions, np.float64)
        self.level.append(np.abs(a).mean(0))
        self.change.append(np.abs(np.diff(a, axis=0)).mean(0) if len(a) > 1 else np.zeros(a.shape[1]))
        self.tasks.append(str(demo.task))

    def finish(self) -> np.ndarray:
        """[N, 2]: mean |action| and mean |change| over the action dimensions, each dimension in units of its
        typical motion in the task that works it most (the largest of the medians of tasks of at least
        ``MOTION_TASK_MIN`` demos), at least 1% of the busiest dimension's: a gripper that one task closes and the
        others never touch weighs as much as any other dimension, and a dimension no task moves cannot make a
        small motion look a thousand times too large."""
        tasks = np.asarray(self.tasks)
        out = []
        for rows in (np.stack(self.level), np.stack(self.change)):
            medians = [np.median(rows[tasks == t], axis=0) for t in np.unique(tasks)
                       if (tasks == t).sum() >= MOTION_TASK_MIN]
            typical = np.max(medians, axis=0) if medians else np.median(rows, axis=0)
            scale = np.maximum(typical, max(0.01 * float(typical.max()), 1e-9))
            out.append((rows / scale).mean(1))
        return np.column_stack(out)


# On a log scale: an arm that never moves is as many times too still as a flailing one is too busy, and a
# long, busy expert demo is not mistaken for either (at 0.001 of the median, "still" stops counting).  A robust
# standard deviation stands for at least 10% more or less motion: scripted demos repeat their motion almost
# exactly, and their MAD alone would make 7% less motion a flag.
MOTION_FLOOR = 1e-3
MOTION_MIN_SCALE = 0.1  # in log units


MOTION_FEATURES = ("mean |action|", "mean |change of action|")
HARDLY_MOVES = 0.2  # under this share of its task's median motion, a reason says the arm hardly moves


MOTION = Vocabulary("motion", {
    "hardly": lambda feature, ratio: f"the arm hardly moves: {feature} {factor(ratio)} x its task's median",
    # within a factor 1 / HARDLY_MOVES of its task's median: another task, or a careful or hurried operator
    "less": lambda feature, ratio: f"the arm moves less than its task's demos: {feature} {factor(ratio)} x its task's "
                                   "median",
    "more": lambda feature, ratio: (f"the actions move more than its task's demos: {feature} {factor(ratio)} x its "
                                    "task's median"),
    "flails": lambda feature, ratio: (f"the actions move more than its task's demos: {feature} {factor(ratio)} x its "
                                      "task's median"),
})


def _motion_kind(ratio: float) -> str:
    """What a demo's motion, as a multiple of its task's median, says of the arm."""
    if ratio < HARDLY_MOVES:
        return "hardly"
    return "less" if ratio < 1 else "more" if ratio <= 1 / HARDLY_MOVES else "flails"


def motion(features: np.ndarray, tasks: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """The larger robust |z| within its task of a demo's two ``MotionStats`` features on a log scale, and which."""
    z, pick, ratio = _motion_parts(features, tasks)
    found = [MOTION(_motion_kind(r), feature=MOTION_FEATURES[j], ratio=float(r)) for j, r in zip(pick, ratio)]
    return z, found


def _motion_parts(features: np.ndarray, tasks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    logs = np.log(np.maximum(features, MOTION_FLOOR))
    z = np.column_stack([np.abs(calibrated(logs[:, i], tasks, min_scale=MOTION_MIN_SCALE))
                         for i in range(logs.shape[1])])
    pick = np.argmax(z, axis=1)
    # In words, against its own task's median (what the robust z compares it with).
    ratio = features / np.maximum(pd.DataFrame(features).groupby(np.asarray(tasks)).transform("median").to_numpy(),
                                  MOTION_FLOOR)
    return z.max(axis=1), pick, ratio[np.arange(len(pick)), pick]
