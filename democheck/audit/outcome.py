"""The ``outcome`` check (model-free): how differently from its task's other demos a demo left the world.

What is compared is the world record -- the environment state where the dataset has one (LeRobot's
``observation.environment_state``, robomimic's ``obs/object``), else the state -- at the demo's last step and its
change from the first, one feature at a time, and the features' robust z put together by their root mean square:
the wrong object pushed, both pushed, the job left half done.  The check is built to hold on any record's shape:

- **A task may end in several ways** (a button toggles a lock; a push stops short of its goal on the side it came
  from): a demo's value is measured against the median of its task's demos that started on the same side and
  reached the same outcome (``modes``: an outcome a share ``MODE_SHARE`` of the task reaches, well apart from the
  others; a side, that share of the task too), not against the whole task's median, so the minority's outcome is
  not an anomaly -- where the dataset holds several tasks, only an outcome that follows from where the demos began
  (``explained``: a toggle; a demo of another outcome is measured against the demos that began as it began) or a
  spread beside a pile: a fault a few of one task's demos share is no outcome.
  Values piled at one place (a kettle most demos leave where it stands, a slide against its stop) beside a
  spread of others are two outcomes too, each measured in its own spread, once the spread holds that share.
- **Rotations are compared as rotations** (``democheck.audit.world_record`` groups the record into features): a
  quaternion as its outer product ``q q^T``, the same for ``q`` and ``-q``; a body's roll, pitch and yaw as the
  same rotation's quaternion, so that the record's form does not change the score; another angle as its cosine
  and sine, so that +pi and -pi are one angle.
- **Units from how the feature moves**: a value's robust SD is at least ``END_FLOOR`` of its spread at the end
  over all the demos and ``MOVE_FLOOR`` of how far the task that works it most moves it within a typical episode
  (the median over its demos that move it), and never under ``RESOLUTION`` of its size; a rotation's at least
  ``ROTATION_FLOOR``.  For a demo that moved the feature at least ``TASK_FLOOR`` of how far its task's demos
  typically move it, at least that: a job done in part is measured in shares of the job, a part never moved (or
  only stirred) in its task's spread.  A feature no demo moves further than float noise (a fixed part) says nothing.
- **Where, not how fast**: a dimension the record names a velocity (``reorder.velocities``) is left out -- its value
  at the last step says how the demo stopped, not where it left anything.
- **The robot's own pose is the operator's**: where the record is the state (no environment state), one feature
  counts at most ``ROBOT_CLIP`` units in the score, so a joint the operator turned once, where the task's demos
  never turn it, is one far feature rather than the whole outcome.
- **A switch is a task's, not a stray demo's**: a value is discrete (each measured against the demos that reached
  its outcome) where the demos of two tasks or more each split between outcomes, each held by ``MODE_SHARE`` of
  the task -- one wrong-task demo in each of two tasks makes no switch.

``compare`` also says where each demo differs most and whether that part already differed at its first step
(another scene, not what the demo did: ``Differs``), and the reason says when the part never changed in the demo.
NaN for a task of fewer than ``OUTCOME_MIN_DEMOS`` demos.  A task's several outcomes (``modes``, ``piled``,
``explained``) are ``democheck.audit.outcome_modes``'.  A consumer of the audit's decoding pass like the other
model-free checks (``democheck.audit.modelfree``); ``benchmarks/shapes.py`` measures what the shapes cost.
"""

from __future__ import annotations

import warnings

import numpy as np

from democheck.audit import words
from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.audit.outcome_modes import MODE_GAP, MODE_SHARE, explained, modes, piled, sd, several
from democheck.audit.world_record import Feature, features_of, represent
from democheck.data.demo import Demo
from democheck.data.reorder import velocities

OUTCOME_MIN_DEMOS = 4
# Demos (itself among them) that started on its side for the side to be its reference: this many and
# ``MODE_SHARE`` of its task's -- two demos of another scene whose parts start elsewhere are no side of the task.
OUTCOME_MIN_SIDE = 2
POOLED_SCALE = 0.5  # a task's robust SD of a feature is at least this share of the median task's
END_FLOOR = 0.05  # a value's least robust SD: this share of its spread at the end over all the demos,
MOVE_FLOOR = 0.005  # and this share of how far the demos that move it move it (a near-constant end has no spread)
# Within a task that works a feature: at least this share of how far its demos typically move it.  A demo that left
# a part a few tenths short of where its task's others pile (a slide short of its stop) did the task's job in part;
# one that never moved it, or moved what its task leaves alone, stays many units out.
TASK_FLOOR = 0.1
# Robust SD: where the record is the robot's own state, a feature further off counts this far in the score (its
# words keep the distance).  A joint the task's demos leave where it began (a wrist never turned) piles at one value,
# and an operator who turned it once is then hundreds of the pile's units off: the robot's pose is the operator's
# choice, not a changed world.
ROBOT_CLIP = 20.0
ROTATION_FLOOR = 0.05  # a rotation's least robust SD, in units of q q^T or of cosine and sine (about 3 degrees)
# A demo moves a dimension when its range over the demo exceeds this many of its jitters (the median size of its
# second differences: about 0 for smooth motion, and white noise's range is 3-6 of them).
STILL = 10.0
ORDINARY = 3.0  # robust SD: a start this near its task's demos' ends began where they end (a job undone)
ALREADY = 0.5  # a difference this share of which the feature showed at the first step was there before the demo
RESOLUTION = 1e-5  # ... and more than this share of its size (at least 1): what float noise cannot reach



class OutcomeStats(PerDemo):
    """Consumer of decoded demos: the first and last step of what the dataset records of the world -- the
    environment state where the demo has one, else its state -- how far each dimension moved over the demo and its
    jitter, and the record's dimension names."""

    fields = ("ends", "sources", "names", "moves")
    ends: list[np.ndarray]
    sources: list[str]
    names: list[list[str] | None]
    moves: list[np.ndarray]

    def add(self, demo: Demo) -> None:
        env = demo.env_state is not None and np.size(demo.env_state) > 0
        x = np.asarray(demo.env_state if env else demo.state, np.float64)
        x = x.reshape(len(x), -1)
        self.ends.append(np.stack([x[0], x[-1]]) if len(x) else np.full((2, x.shape[1]), np.nan))
        self.sources.append("environment state" if env else "state")
        self.names.append(demo.extra.get("env_state_names" if env else "state_names"))
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            jitter = np.nanmedian(np.abs(np.diff(x, 2, axis=0)), 0) if len(x) > 2 else np.zeros(x.shape[1])
            self.moves.append(np.stack([np.ptp(x, 0) if len(x) else np.zeros(x.shape[1]), jitter]))


def unit(feature: Feature, value: np.ndarray, moves: np.ndarray, tasks: np.ndarray) -> float | None:
    """The least robust SD of a feature (see the module docstring), None when no demo moves it (it says
    nothing).  ``value`` [N, m] its represented values at the end, ``moves`` [N, 2, d] each demo's range and
    jitter per record dimension, ``tasks`` [N] what each demo is compared with."""
    rng = moves[:, 0, feature.columns]
    size, moving = _moving(feature, value, moves)
    if not moving.any():
        return None
    if feature.kind in ("rotation", "angle"):
        return ROTATION_FLOOR
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        # How far the task that works this part moves it in a typical demo: not the median over every demo that
        # stirs it, which a door every task jostles by a milliradian would make a milliradian.
        moved = max(float(np.nanmedian(np.where(moving, rng, np.nan)[tasks == t])) for t in np.unique(tasks)
                    if moving[tasks == t].any())
        spread = float(1.4826 * np.nanmedian(np.abs(value - np.nanmedian(value, 0))))
    return max(MOVE_FLOOR * moved, END_FLOOR * spread, RESOLUTION * max(1.0, float(np.nan_to_num(size))))


def _moving(feature: Feature, value: np.ndarray, moves: np.ndarray) -> tuple[float, np.ndarray]:
    """The feature's typical size (at least 1), and [N, c] whether each demo moved each of its columns beyond its
    jitter and float noise."""
    rng, jitter = moves[:, 0, feature.columns], moves[:, 1, feature.columns]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        size = np.nanmedian(np.abs(value)) if feature.kind in ("value", "relative") else 1.0
    size = max(1.0, float(np.nan_to_num(size)))
    return size, (rng > STILL * jitter) & (rng > RESOLUTION * size)


def task_floors(feature: Feature, moves: np.ndarray, tasks: np.ndarray) -> np.ndarray:
    """[N] each demo's least unit from its own task's job: ``TASK_FLOOR`` of how far its task's demos typically
    move the feature (the median of their ranges: about 0 where most leave it alone), where the demo itself moved
    it at least that far -- did a tenth of the job or more; one that never moved it, or only stirred it (a block
    slid along the table where its task lifts it), is measured in its task's spread -- for a plain value or a
    relative position; 0 for a rotation or an angle."""
    floors = np.zeros(len(tasks))
    if feature.kind not in ("value", "relative"):
        return floors
    rng = moves[:, 0, feature.columns[0]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for t in np.unique(tasks):
            floors[tasks == t] = TASK_FLOOR * float(np.nan_to_num(np.nanmedian(rng[tasks == t])))
    return np.where(rng >= floors, floors, 0.0)


def _left(source: str) -> str:
    """What a demo did, by the record read: the world where one is recorded; the state alone may be the robot's
    own joints, never called the world."""
    return ("left the world unlike its task's other demos" if source == "environment state"
            else "ended unlike its task's other demos")


def _world_words(name: str, form: str, part: str, value: float, ref: float, z: float, source: str, **_) -> str:
    """The words for the feature that differs most (``form``: value, rotation or angle): what it read at the end
    or how it changed, against its task's demos."""
    if form == "rotation":
        what = f"{name} at the end" if part == "at the end" else f"how {name} changed"
        return f"{_left(source)}: {what} differs from theirs ({_robust_sd_text(z)})"
    what = f"{name} at the end" if part == "at the end" else f"the change of {name}"
    if form == "angle":
        what += " (cosine and sine)"
    value_text, ref_text = words.pair(value, ref, 3)
    return f"{_left(source)}: {what} {value_text} where its task's demos reach {ref_text} ({_robust_sd_text(z)})"


def _held_words(name: str, part: str, value: float, ref: float, z: float, source: str, **_) -> str:
    """The demo's record of the feature never changed (a part it never moved, or a sensor that read one value)."""
    value_text, ref_text = words.pair(value, ref, 3)
    theirs = f"reach {ref_text}" if part == "at the end" else f"change it by {ref_text}"
    return (f"{_left(source)}: {name} holds one value through the demo ({value_text}) where its task's demos "
            f"{theirs} ({_robust_sd_text(z)})")


def _undone_words(name: str, part: str, value: float, ref: float, **_) -> str:
    value_text, ref_text = words.pair(value, ref, 3)
    what = f"{name} at the end" if part == "at the end" else f"the change of {name}"
    return (f"undid its task's job: began where its task's demos leave {name}, and {what} is {value_text} where "
            f"theirs is {ref_text} (done backwards: a reset recorded as a demo?)")


OUTCOME = Vocabulary("outcome", {
    "another job": _world_words,  # the world the demo left differs from its task's: the wrong object, a job half done
    "held": _held_words,  # the part that differs most never changed in the demo
    # the part that differs most began where its task's demos leave it, and the demo moved it: done backwards
    "undone": _undone_words,
    # the part that differs most already differed, by ``ALREADY`` of the difference or more, at the first step:
    # another scene, not what the demo did to it
    "another scene": lambda held, **p: (_held_words if held else _world_words)(**p),
    "too few demos": "no task of enough demos to compare with",
    "nothing moves": "no part of the {source} moves in any demo",
    "not recorded": "no {source} recorded",
})


def outcome(stats: OutcomeStats, tasks: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """How differently from its task's other demos each demo left the world (see the module docstring), and the
    feature that differs most (its record, ``source``; its ``columns``): ``another scene`` where that feature
    already differed at the demo's first step, ``held`` where the demo never changed it, else ``another job``."""
    n = len(stats.ends)
    out, found = np.full(n, np.nan), [OUTCOME("too few demos")] * n
    tasks = np.asarray(tasks)
    for source in sorted(set(stats.sources)):
        rows = np.flatnonzero(np.asarray(stats.sources) == source)
        first = _padded([stats.ends[i][0] for i in rows])
        last = _padded([stats.ends[i][1] for i in rows])
        moves = np.stack([_padded_pair(stats.moves[i], last.shape[1]) for i in rows])
        names = next((stats.names[i] for i in rows if stats.names[i]), None)
        z_cols, what, values, refs, before, held, began_at_end = [], [], [], [], [], [], []
        rates = velocities(names, last.shape[1])
        for f in features_of(names, first, last, source):
            if rates[f.columns].all():  # how fast a part moved at the last step is how the demo stopped
                continue
            end, start = represent(f, last), represent(f, first)
            u = unit(f, end, moves, tasks[rows])
            if u is None:
                continue
            own = task_floors(f, moves, tasks[rows])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                at_start = np.nanmax(_task_gaps(start, None, tasks[rows], u, began=start)[0], axis=1,
                                     initial=-np.inf)
            ended = _began_where_they_end(start, end, moves[:, 0, f.columns].max(axis=1), tasks[rows], u)
            for part, x, sided in (("at the end", end, True), ("change", end - start, False)):
                z, ref = _task_gaps(x, start if sided else None, tasks[rows], u, own, began=start)
                best = np.nanargmax(np.where(np.isnan(z), -np.inf, z), axis=1)
                with warnings.catch_warnings():  # a demo of a task too small to compare has only NaN
                    warnings.simplefilter("ignore", RuntimeWarning)
                    z_cols.append(np.sqrt(np.nanmean(z ** 2, axis=1)) if z.shape[1] > 1 else z[:, 0])
                what.append((f, part))
                values.append(x[np.arange(len(x)), best])
                refs.append(ref[np.arange(len(x)), best])
                before.append(at_start)
                began_at_end.append(ended)
                held.append((moves[:, 0, f.columns] == 0).all(axis=1) & (f.kind == "value"))
        if not z_cols:
            for i in rows:
                found[i] = OUTCOME("nothing moves", source=source)
            continue
        z = np.column_stack(z_cols)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            # the robot's own pose: one wild feature is one feature, not the distance (``ROBOT_CLIP``)
            counted = np.minimum(z, ROBOT_CLIP) if source == "state" else z
            out[rows] = np.sqrt(np.nanmean(counted ** 2, axis=1))
        for k, i in enumerate(rows):
            if not np.isfinite(z[k]).any():
                if not np.isfinite(last[k]).any():
                    found[i] = OUTCOME("not recorded", source=source)
                continue
            j = int(np.nanargmax(z[k]))
            feature, part = what[j]
            still = bool(held[j][k])
            params = dict(name=feature.name, form=feature.kind, part=part, value=float(values[j][k]),
                          ref=float(refs[j][k]), z=float(z[k, j]), source=source, columns=list(feature.columns))
            if (source == "environment state" and feature.kind in ("value", "relative") and not still
                    and z[k, j] >= MODE_GAP and began_at_end[j][k]):
                # begun where its task's demos leave the part, and left it elsewhere: the task done backwards
                found[i] = OUTCOME("undone", **params)
            elif before[j][k] >= ALREADY * z[k, j]:
                found[i] = OUTCOME("another scene", held=still, **params)
            else:
                found[i] = OUTCOME("held" if still else "another job", **params)
    return out, found


def _began_where_they_end(start: np.ndarray, end: np.ndarray, travel: np.ndarray, tasks: np.ndarray, floor: float
                          ) -> np.ndarray:
    """[N] bool: the demo began where its task's demos leave the feature (``start``, ``end`` [N, m] its values),
    within ``ORDINARY`` of their ends' robust SD (at least ``floor``) of their median end, in every column, and
    moved it (its range over the demo, ``travel`` [N], at least half its task's typical), where the task's demos
    move it (they typically begin ``MODE_GAP`` of those SD or more from their median end)."""
    out = np.zeros(len(start), bool)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for t in np.unique(tasks):
            rows = np.flatnonzero(tasks == t)
            if len(rows) < OUTCOME_MIN_DEMOS:
                continue
            ends, starts = end[rows], start[rows]
            centre = np.nanmedian(ends, axis=0)
            scale = np.maximum(1.4826 * np.nanmedian(np.abs(ends - centre), axis=0), floor)
            moved = np.nanmedian(np.abs(starts - centre), axis=0) >= MODE_GAP * scale
            near = (np.abs(starts - centre) <= ORDINARY * scale).all(axis=1)
            out[rows] = moved.all() & near & (travel[rows] >= 0.5 * np.nanmedian(travel[rows]))
    return out


def _robust_sd_text(z: float) -> str:
    """A distance in robust SD as a reader takes it: past 100 the number says no more than 'far'."""
    return f"{z:.2g} robust SD" if z < 100 else "over 100 robust SD"


def _task_gaps(x: np.ndarray, start: np.ndarray | None, tasks: np.ndarray, floor: float,
               own: np.ndarray | None = None, began: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """[N, m] robust z of each value against its task's demos and the value it was measured against.

    A column whose values over the whole dataset fall into several outcomes (``modes``: a switch on or off, a drawer
    open or closed) between which the demos of two tasks or more each split (``_several``) is discrete: each value
    is measured against the median of its task's demos that reached the same outcome (the dataset's where it is the
    only one of its task).  Otherwise against the median of its task's demos -- with ``start``, of those that
    started on the same side of the task's median value, where at least ``OUTCOME_MIN_SIDE`` and ``MODE_SHARE`` of
    the task's did -- and, where the task's own values fall into several outcomes, of those that reached the same
    one: a spread beside a pile (``piled``), or, in a dataset of several tasks, outcomes that follow from where
    the demos began (``explained``, by ``began``: the feature at the first step); in a dataset of one task, any.
    The unit: the task's robust SD about those medians, at least ``floor``, each demo's own floor in ``own``
    and ``POOLED_SCALE`` of the typical task's (a task of a few demos that happen to agree is not that precise)."""
    own = np.zeros(len(x)) if own is None else own
    z, ref = np.full(x.shape, np.nan), np.full(x.shape, np.nan)
    several_tasks = len(np.unique(tasks)) > 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for c in range(x.shape[1]):
            every = np.flatnonzero(np.isfinite(x[:, c]))
            outcomes = np.full(len(x), -1)
            outcomes[every] = modes(x[every, c], floor, piles=False)
            # Several outcomes that recur within more than one task: a switch, not where one task's demos went --
            # each an outcome of the task (``MODE_SHARE`` of its demos, at least 2), not a stray demo or two.
            spans = [several(outcomes[every][tasks[every] == t]) for t in np.unique(tasks[every])]
            discrete = outcomes.max() > 0 and sum(spans) >= 2
            fitted = []
            for t in np.unique(tasks):
                rows = np.flatnonzero(tasks == t)
                ok = np.flatnonzero(np.isfinite(x[rows, c]))
                if len(ok) < OUTCOME_MIN_DEMOS:
                    continue
                v = x[rows[ok], c]
                centre = np.full(len(v), np.median(v))
                if discrete:
                    label = outcomes[rows[ok]]
                    for k in np.unique(label):
                        mine = label == k
                        pool = v[mine] if mine.sum() >= 2 else x[outcomes == k, c]
                        centre[mine] = np.median(pool)
                else:
                    if start is not None:
                        side = np.sign(start[rows[ok], c] - centre)
                        for s in (-1.0, 1.0):
                            on = side == s
                            if on.sum() >= max(OUTCOME_MIN_SIDE, MODE_SHARE * len(v)):
                                centre[on] = np.median(v[on])
                    label = modes(v - centre, floor)
                    if several_tasks and label.any() and not piled(v - centre, floor).any():
                        # a few of one task's demos that agree and began as the others did: a fault they share
                        label = (np.zeros_like(label) if began is None else
                                 explained(label, began[rows[ok], c], floor))
                    for k in np.unique(label):
                        mine = label == k
                        centre[mine] += np.median((v - centre)[mine])
                pooled = max(sd(v - centre), floor)
                # Each outcome in its own spread where that is wider than the task's (a spread beside a pile).
                scale = np.full(len(v), pooled)
                for k in np.unique(label):
                    scale[label == k] = max(pooled, sd((v - centre)[label == k]))
                scale = np.maximum(scale, own[rows[ok]])
                fitted.append((rows[ok], v, centre, scale, pooled))
            typical = POOLED_SCALE * np.median([f[4] for f in fitted]) if fitted else 0.0
            for at, v, centre, scale, _ in fitted:
                z[at, c] = np.abs(v - centre) / np.maximum(scale, typical)
                ref[at, c] = centre
    return z, ref


def _padded(rows: list[np.ndarray]) -> np.ndarray:
    """Rows of different lengths (datasets a bench pools) as one NaN-padded matrix."""
    out = np.full((len(rows), max((len(r) for r in rows), default=0)), np.nan)
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out


def _padded_pair(moves: np.ndarray, d: int) -> np.ndarray:
    out = np.zeros((2, d))
    out[:, :moves.shape[1]] = moves
    return out
