"""The ``dynamics`` check (model-free): how badly a demo's state follows its actions -- action-state
disagreement.

A ridge regression predicts each step's change of state from the state and the last two actions, fitted on the
steps of each block of ``DYNAMICS_BLOCK`` consecutive demos (so memory does not grow with the dataset, and the
blocks are the parallel decoding pass's shards: the same numbers with any number of workers); the score is the
log of the demo's mean squared prediction error over the median demo's, and the reason names the stretch of
``DYNAMICS_WINDOW`` steps it is worst over.  A robot held, blocked or pushed by something it met, an arm that
did not answer its commands, or actions recorded against another demo's state or shifted in time.  A consumer
of the audit's decoding pass like the other model-free checks (``democheck.audit.modelfree``).

The ``lag`` check reads the same fit: how much better the demo's states follow its actions shifted in time than
its task's demos' do -- the log of its mean squared prediction error with the actions moved by its task's usual
shift (the median of its task's demos' best shifts; none for most recordings) over the least error with them moved
up to ``LAG_MAX`` steps earlier or later (0 for a demo whose best shift lies within ``LAG_SCATTER`` robust SD of
its task's demos' best shifts or within ``LAG_RESOLUTION`` steps of their usual one, and for one whose error still
falls one step past ``LAG_MAX``: a drift between actions and state, no delay located), and the shift.  A recorder
that pairs each action with the next state shifts all of a task's demos alike, and a task whose demos something drags
behind their commands (a door on its hinge, with no door in the state) scatters them a few steps; a delay is one
demo's, and a step either way is a pairing's own resolution.
An action stream recorded late or early against the states and frames (a clock offset between two recorders) is
what a policy trained on it learns to be late by; the mean error above barely sees it where actions change slowly,
since a shifted action is still close to the right one.  Actions recorded at another scale also follow the states
better shifted (to where they are smaller or larger); where one factor on the actions explains the demo at least
as well as the best shift (and ``LAG_NAMED`` better than as recorded), and that factor is positive and
``SCALE_NAMED`` or more off its task's demos' (a unit or a gain, not the fit's spread; a negative one is no scale),
the reason names the scale, not a delay.

The ``state_jump`` check reads the same fit step by step: the largest ratio of one step's prediction error (the root
of its mean square over the state's dimensions, each weighted by the share of its change the fit explains: the
arm's, not an object's it pushes) to the median error of the steps around it (``modelfree.jump_ratios``), on a log
scale, over the steps with ``JUMP_NEIGHBOURS`` steps either side (an arm settling after its reset is a start's own
jolt).  A stretch of steps lost from the recording, and the steps re-indexed, leaves one step at which the state
moves as far as it did over the whole stretch while the actions there ask for one step's move; a fast move the
actions command is explained, and so is not a jump.  ``frames.frame_jump`` asks the same of the camera; the two are
one look in the ranking.

A demo's action gain, read off the same fit, was measured and not kept (docs/decisions.md, "A demo's action gain:
measured, not kept").
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import JUMP_NEIGHBOURS, PerDemo, jump_ratios, steps_text
from democheck.audit.neighbours import units
from democheck.audit.words import factor
from democheck.data.demo import Demo

DYNAMICS_RIDGE = 1e-3  # ridge penalty per step, on standardised features: a near-constant feature cannot blow up
DYNAMICS_BLOCK = 128  # demos per fit (= the audit's decoding shard of a large set, ``shards.SHARD``)
DYNAMICS_MIN_BLOCK = 32  # a last block of fewer demos is judged by the fit of the block before it
DYNAMICS_WINDOW = 10  # the reason names the stretch of this many steps the state follows the actions worst
LAG_MAX = 16  # steps either way the ``lag`` check moves a demo's actions (0.2 s at 80 fps, 0.5 s at 30 fps)
LAG_NAMED = 1.2  # the reason says the actions were recorded late or early where the shift cuts the error this much
# A delay lies further from its task's usual shift than this many robust SD of its task's demos' best shifts: a task
# whose demos something drags behind their commands scatters their best shifts.
LAG_SCATTER = 3.0
# ... and further than this many steps: a pairing's own resolution.  An action sampled just before or just after its
# state's tick, or a velocity that stands to the positions as a central difference does, reads a step either way.
LAG_RESOLUTION = 1
SCALE_NAMED = 2.0  # ... at another scale where a factor this far off its task's demos' explains the demo as well
# A unit or a gain holds throughout a recording: the factor is read in each of this many parts of the demo's steps
# too, and a scale is named only where every part that drives the arm (holds ``SCALE_BUSY`` of the actions' part of
# the prediction or more) is off the same way.  An arm held against something (a button pressed, a table met) follows
# its actions at a fraction of their size over that stretch alone.
SCALE_PARTS = 3
SCALE_BUSY = 0.1
STATE_JUMP_FLOOR = 0.1  # SDs of a state's change: the least usual error a step's error is measured against


def _dynamics_features(state: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Per step t < T-1: the state, the action and the action before it (zero at the first step)."""
    s, a = state.astype(np.float64), actions.astype(np.float64)
    before = np.vstack([np.zeros((1, a.shape[1])), a[:-1]])
    return np.column_stack([s[:-1], a[:-1], before[:-1]])


def _dynamics_fit(states: list[np.ndarray], actions: list[np.ndarray]) -> dict[str, np.ndarray] | None:
    """One ridge regression of the change of state on ``_dynamics_features`` over these demos' steps, with its
    standardisation (state dimensions that never move and constant features left out) and the share of each
    state dimension's change it explains (``explained``: an arm's joints follow its actions, an object they push
    or a switch they flip far less); None when no demo has 3 steps or the state never changes."""
    usable = [i for i, a in enumerate(actions) if len(a) >= 3]
    if not usable:
        return None
    x = np.concatenate([_dynamics_features(states[i], actions[i]) for i in usable])
    y = np.concatenate([np.diff(states[i].astype(np.float64), axis=0) for i in usable])
    x_mean, x_sd, y_sd = x.mean(0), x.std(0), y.std(0)
    xs, ys = x_sd > 1e-6 * max(float(x_sd.max()), 1e-12), y_sd > 1e-6 * max(float(y_sd.max()), 1e-12)
    if not ys.any():  # the state never changes: there is nothing to follow
        return None
    xn = (x[:, xs] - x_mean[xs]) / x_sd[xs]
    yn = y[:, ys] / y_sd[ys]
    y_mean = yn.mean(0)
    w = np.linalg.solve(xn.T @ xn + DYNAMICS_RIDGE * len(xn) * np.eye(xn.shape[1]), xn.T @ (yn - y_mean))
    unexplained = ((yn - y_mean - xn @ w) ** 2).mean(0) / np.maximum(((yn - y_mean) ** 2).mean(0), 1e-12)
    return {"x_mean": x_mean[xs], "x_sd": x_sd[xs], "xs": xs, "y_sd": y_sd[ys], "ys": ys, "y_mean": y_mean, "w": w,
            "explained": np.clip(1.0 - unexplained, 0.0, 1.0)}


def _shifted(actions: np.ndarray, k: int) -> np.ndarray:
    """The actions moved ``k`` steps earlier (k > 0: step t gets the action recorded at t + k), the ends held."""
    if k == 0 or len(actions) < 2:
        return actions
    idx = np.clip(np.arange(len(actions)) + k, 0, len(actions) - 1)
    return actions[idx]


class Lag(NamedTuple):
    """What ``_lag`` reads of one demo."""

    gain: float  # log of the error as recorded over the least with the actions moved up to ``LAG_MAX`` steps
    best: int  # that shift (0 where the error still falls one step past the window: no delay located)
    factor: float  # the one factor on the actions' part of the prediction that fits the demo best
    scaled: float  # log of the error as recorded over the error with that factor
    curve: np.ndarray | None  # the error at each shift -LAG_MAX..LAG_MAX, NaN past reach; None: no delay located
    parts: np.ndarray  # the factor in each of ``SCALE_PARTS`` parts of the steps, NaN where the actions drive little


NO_LAG = Lag(float("nan"), 0, 1.0, 0.0, None, np.full(SCALE_PARTS, np.nan))


def _lag(state: np.ndarray, actions: np.ndarray, fit: dict[str, np.ndarray] | None) -> Lag:
    """How the demo's states follow its actions moved in time and scaled (``Lag``); ``NO_LAG`` without a fit or
    under 3 steps.  The fit is linear, so each part of the prediction is computed once and moving the actions is
    moving rows of theirs: what ``_dynamics_errors`` gives the actions ``_shifted`` by each k, at the cost of one
    prediction."""
    if fit is None or len(actions) < 3:
        return NO_LAG
    s, a = state.astype(np.float64), actions.astype(np.float64)
    n, ds, da = len(a), s.shape[1], a.shape[1]
    w = np.zeros((ds + 2 * da, fit["w"].shape[1]))
    w[fit["xs"]] = fit["w"] / fit["x_sd"][:, None]
    const = fit["y_mean"] - (fit["x_mean"] / fit["x_sd"]) @ fit["w"]
    from_state = s[:-1] @ w[:ds] + const
    from_action, from_before = a @ w[ds:ds + da], a @ w[ds + da:]
    target = np.diff(s, axis=0)[:, fit["ys"]] / fit["y_sd"]
    steps = np.arange(n - 1)
    reach = min(LAG_MAX, n - 2)
    errors = {}
    for k in range(-min(reach + 1, n - 2), min(reach + 1, n - 2) + 1):  # one step past the window: still falling?
        before = from_before[np.clip(steps - 1 + k, 0, n - 1)]
        before[0] = 0.0  # the first step has no action before it
        pred = from_state + from_action[np.clip(steps + k, 0, n - 1)] + before
        errors[k] = float(((pred - target) ** 2).mean())
        if k == 0:
            part = from_action[:-1] + before  # the actions' part of the prediction, as recorded
    best = min((k for k in errors if abs(k) <= reach), key=lambda k: (errors[k], abs(k)))
    past = int(np.sign(best)) * (reach + 1)
    located = not (best and abs(best) == reach and errors.get(past, np.inf) < errors[best])
    if not located:
        # The error still falls past the window's edge: no delay located -- a slow drift between the actions and
        # the state (an arm that settles at its goal), not a recording that is late by a number of steps.
        best = 0
    rest = target - from_state
    factor = float((part * rest).sum() / max(float((part ** 2).sum()), 1e-12))
    scaled = float(((rest - factor * part) ** 2).mean())
    curve = np.array([errors[k] if abs(k) <= reach else np.nan for k in range(-LAG_MAX, LAG_MAX + 1)]
                     ) if located else None
    energy = (part ** 2).sum(axis=1)
    parts = np.full(SCALE_PARTS, np.nan)
    for j, idx in enumerate(np.array_split(np.arange(len(part)), SCALE_PARTS)):
        if len(idx) and energy[idx].sum() >= SCALE_BUSY * max(float(energy.sum()), 1e-12):
            parts[j] = float((part[idx] * rest[idx]).sum() / float(energy[idx].sum()))
    return Lag(float(np.log(max(errors[0], 1e-12) / max(errors[best], 1e-12))), best, factor,
               float(np.log(max(errors[0], 1e-12) / max(scaled, 1e-12))), curve, parts)


def _dynamics_errors(states: list[np.ndarray], actions: list[np.ndarray], fit: dict[str, np.ndarray] | None
                     ) -> list[np.ndarray | None]:
    """Per demo, the squared error of each step's predicted change of state under ``fit`` in each state dimension
    that moves ([T - 1, d], each in its standard deviation); None for a demo under 3 steps, or without a fit."""
    out: list[np.ndarray | None] = [None] * len(actions)
    if fit is None:
        return out
    for i, (s, a) in enumerate(zip(states, actions)):
        if len(a) < 3:
            continue
        xn = (_dynamics_features(s, a)[:, fit["xs"]] - fit["x_mean"]) / fit["x_sd"]
        yn = np.diff(s.astype(np.float64), axis=0)[:, fit["ys"]] / fit["y_sd"]
        out[i] = (xn @ fit["w"] + fit["y_mean"] - yn) ** 2
    return out


def _state_jump(errors: np.ndarray) -> tuple[float, int]:
    """The largest ``jump_ratios`` of a demo's per-step errors (their roots: the error in the state's change's SDs,
    each dimension weighted by the share of its change the actions explain) and the step it is at, of the steps
    with ``JUMP_NEIGHBOURS`` steps on either side: the first step's prediction has no action before it, and an arm
    settling after its reset is a start's own jolt.  NaN: too short."""
    k = JUMP_NEIGHBOURS
    if len(errors) < 2 * k + 2:
        return float("nan"), 0
    ratio, _ = jump_ratios(np.sqrt(errors[1:]), STATE_JUMP_FLOOR)
    at = k + int(np.argmax(ratio[k:len(ratio) - k]))
    return float(ratio[at]), at + 1


class DynamicsFit(PerDemo):
    """Consumer of decoded demos for ``dynamics``: each block of ``DYNAMICS_BLOCK`` demos is fitted and scored as
    soon as it is complete, per demo only its mean error and its worst stretch kept; a last block of fewer than
    ``DYNAMICS_MIN_BLOCK`` demos is scored by the fit of the block before it (on its own steps alone a few
    demos would explain themselves)."""

    fields = ("errors", "worst", "lags", "jumps", "states", "actions")
    errors: list[float]  # per scored demo: mean squared error (NaN: not scored)
    worst: list[tuple[int, int, int]]  # per scored demo: start, width of its worst stretch, its steps
    lags: list[Lag]  # per scored demo: ``_lag``
    jumps: list[tuple[float, int]]  # per scored demo: its largest ``jump_ratios`` of a step's error, and that step
    states: list[np.ndarray]  # the block not scored yet
    actions: list[np.ndarray]

    def __init__(self) -> None:
        super().__init__()
        self.last_fit: dict[str, np.ndarray] | None = None  # the latest full block's

    def add(self, demo: Demo) -> None:
        self.states.append(np.asarray(demo.state, np.float32))
        self.actions.append(np.asarray(demo.actions, np.float32))
        self._score_blocks()

    def _score_blocks(self, last: bool = False) -> None:
        while len(self.actions) >= DYNAMICS_BLOCK or last and self.actions:
            block = slice(0, DYNAMICS_BLOCK)
            states, actions = self.states[block], self.actions[block]
            if len(actions) >= DYNAMICS_MIN_BLOCK or self.last_fit is None:
                fit = _dynamics_fit(states, actions)
                if len(actions) == DYNAMICS_BLOCK and fit is not None:
                    self.last_fit = fit
            else:
                fit = self.last_fit
            for squared, state, a in zip(_dynamics_errors(states, actions, fit), states, actions):
                if squared is None:
                    self.errors.append(np.nan)
                    self.worst.append((0, 0, 0))
                    self.lags.append(NO_LAG)
                    self.jumps.append((np.nan, 0))
                    continue
                self.lags.append(_lag(state, a, fit))
                weight = fit["explained"]  # the dimensions its actions drive
                self.jumps.append(_state_jump(squared @ weight / weight.sum()) if weight.sum() > 0 else (np.nan, 0))
                e = squared.mean(1)
                width = min(DYNAMICS_WINDOW, len(e))
                start = int(np.argmax(np.convolve(e, np.ones(width) / width, mode="valid")))
                self.errors.append(float(e.mean()))
                self.worst.append((start, width, len(e)))
            del self.states[block], self.actions[block]

    @classmethod
    def merged(cls, parts: list["PerDemo"]) -> "DynamicsFit":
        """The shards' scores in order, and their waiting demos scored in blocks as they fill up -- what one
        consumer fed every demo would hold, as long as each shard's blocks line up with the whole's
        (``shards.decode_shard`` is a multiple of ``DYNAMICS_BLOCK``, or smaller)."""
        out = cls()
        for part in parts:
            if part.errors and out.actions:
                raise ValueError("the dynamics check's blocks do not line up with the decoding shards: a shard "
                                 f"must hold a multiple of {DYNAMICS_BLOCK} demos, or fewer")
            out.errors += part.errors
            out.worst += part.worst
            out.lags += part.lags
            out.jumps += part.jumps
            out.states += part.states
            out.actions += part.actions
            if part.last_fit is not None:
                out.last_fit = part.last_fit
            out._score_blocks()
        return out

    def finish(self) -> "DynamicsFit":
        self._score_blocks(last=True)
        return self


DYNAMICS = Vocabulary("dynamics", {
    "worse": lambda ratio, start, stop, length: f"the state follows the actions {factor(ratio)} x worse than usual; "
                                                f"worst over {steps_text(start, stop, length)}",
    "too short": "too short, or a state that never changes",
    "no state change": "the state never changes, or too short",
})


def dynamics(fit: DynamicsFit) -> tuple[np.ndarray, list[Finding]]:
    """log(each demo's mean squared error of its block's linear prediction of the change of state / the
    demos' median of that), and the stretch of ``DYNAMICS_WINDOW`` steps it is worst over."""
    errors = np.asarray(fit.errors, np.float64)
    ok = np.isfinite(errors)
    if not ok.any():
        return np.full(len(errors), np.nan), [DYNAMICS("no state change")] * len(errors)
    typical = max(float(np.median(errors[ok])), 1e-12)
    out = np.where(ok, np.log(np.maximum(errors, 1e-12) / typical), np.nan)
    reasons = [DYNAMICS("worse", ratio=float(e / typical), start=start, stop=start + width, length=n + 1) if good
               else DYNAMICS("too short") for e, good, (start, width, n) in zip(errors, ok, fit.worst)]
    return out, reasons


STATE_JUMP = Vocabulary("state_jump", {
    "jump": lambda frame, next, ratio: (f"between frames {frame} and {next} its state changes as its actions do not "
                                        f"explain: {factor(ratio)} x the usual error at the steps around it (steps "
                                        "lost from the recording?)"),
    "too short": "too short, or a state that never changes",
})


def state_jump(fit: DynamicsFit) -> tuple[np.ndarray, list[Finding]]:
    """log of the largest ratio of one step's error of the dynamics fit to the usual error around it (see the
    module docstring), and the step where it is."""
    out = np.array([np.log(max(ratio, 1.0)) if np.isfinite(ratio) else np.nan for ratio, _ in fit.jumps])
    reasons = [STATE_JUMP("jump", frame=at, next=at + 1, ratio=float(ratio)) if np.isfinite(ratio)
               else STATE_JUMP("too short") for ratio, at in fit.jumps]
    return out, reasons


def _steps(k: int) -> str:
    return f"{abs(k)} step{'s' if abs(k) > 1 else ''}"


def _moved(k: int) -> str:
    """The actions moved ``k`` steps, in words: '3 steps earlier' (k > 0), '1 step later'."""
    return f"{_steps(k)} {'earlier' if k > 0 else 'later'}"


def _shift(steps: int, gain: float, named: bool, task_shift: int = 0) -> str:
    than = "" if not task_shift else " than its task's demos' do"
    return (f"its states follow its actions best with the actions {_moved(steps)}{than} ({factor(gain)} x less error)"
            + (f": the actions were recorded {_steps(steps)} {'late' if steps > 0 else 'early'}" if named else ""))


def _as_recorded(task_shift: int = 0) -> str:
    if not task_shift:
        return "its actions go with its states as recorded"
    return f"its actions go with its states as its task's demos' do (best with the actions {_moved(task_shift)})"


LAG = Vocabulary("lag", {
    # the states follow the actions moved in time: named a recording fault (``named``) only where the shift
    # explains ``LAG_NAMED`` times more
    "delay": _shift,
    # one factor on the actions explains them as well, ``SCALE_NAMED`` or more off its group's
    "scale": lambda size, gain: (f"the actions are {factor(size)} x the size its states follow, against its task's "
                                 f"demos ({factor(gain)} x less error taken so): recorded at another scale"),
    "as recorded": _as_recorded,
    "too short": "too short, or a state that never changes",
})


def lag(fit: DynamicsFit, groups: np.ndarray | None = None) -> tuple[np.ndarray, list[Finding]]:
    """How much better each demo's states follow its actions moved in time than at its group's usual shift (the
    median of its group's demos' best shifts; ``Evidence.groups``, default one group): the log of ``_lag``'s error
    there over the least, 0 where its best lies within ``LAG_SCATTER`` of its group's scatter of best shifts or within
    ``LAG_RESOLUTION`` of the usual -- and by how many steps from it; or, where one factor on the actions explains the
    demo as well as its best shift and lies ``SCALE_NAMED`` or more off the median of its group's demos', in every
    part of the demo that drives the arm (``SCALE_PARTS``), the log of its error as recorded over the error with that
    factor, and at what size."""
    gains = np.array([lag.gain for lag in fit.lags], np.float64)
    best = np.array([lag.best for lag in fit.lags], int)
    factors = np.array([lag.factor for lag in fit.lags], np.float64)
    groups = np.zeros(len(gains), int) if groups is None else np.asarray(groups)
    typical, usual, scatter = np.ones(len(gains)), np.zeros(len(gains), int), np.zeros(len(gains))
    for group in np.unique(groups):
        mine = (groups == group) & np.isfinite(gains)
        if mine.any():
            typical[groups == group] = float(np.median(factors[mine]))
            centre, spread = units(best[mine].astype(np.float64), 0.0)
            usual[groups == group], scatter[groups == group] = int(np.round(centre)), float(spread)
    apart = np.abs(best - usual) > np.maximum(LAG_SCATTER * scatter, LAG_RESOLUTION)
    out, reasons = np.full(len(gains), np.nan), []
    for i, (read, base, u) in enumerate(zip(fit.lags, typical, usual)):
        if not np.isfinite(read.gain):
            reasons.append(LAG("too short"))
            continue
        off = _off_usual(read, u) if apart[i] else 0.0
        if read.scaled >= max(read.gain, np.log(LAG_NAMED)) and _scale_throughout(read, base):
            out[i] = read.scaled
            reasons.append(LAG("scale", size=float(base / read.factor), gain=float(np.exp(read.scaled))))
        elif off > 0:
            out[i] = off
            reasons.append(LAG("delay", steps=int(read.best - u), gain=float(np.exp(off)),
                               named=bool(off >= np.log(LAG_NAMED)), task_shift=int(u)))
        else:
            out[i] = 0.0
            reasons.append(LAG("as recorded", task_shift=int(u)))
    return out, reasons


def _scale_throughout(read: Lag, typical: float) -> bool:
    """Whether the demo's actions are at another scale than its group's (whose median factor is ``typical``): its
    factor, and its factor in every part that drives the arm, ``SCALE_NAMED`` or more off the same way (a group whose
    actions fit backwards, or a negative factor, has no size)."""
    if not typical > 0:
        return False
    sizes = np.append(read.parts[np.isfinite(read.parts)], read.factor) / typical
    return bool((sizes >= SCALE_NAMED).all() or ((sizes > 0) & (sizes <= 1 / SCALE_NAMED)).all())


def _off_usual(lag: Lag, usual: int) -> float:
    """The log of a demo's error at its group's usual shift over its error at its own best (``_lag``), at least 0;
    the usual shift taken within the demo's reach.  0 where no delay is located, NaN where the demo has no lag."""
    if lag.curve is None or not np.isfinite(lag.gain):
        return float(lag.gain)
    reach = int(np.isfinite(lag.curve).sum() // 2)
    at_usual = lag.curve[LAG_MAX + int(np.clip(usual, -reach, reach))]
    return max(float(np.log(max(at_usual, 1e-12) / max(lag.curve[LAG_MAX + lag.best], 1e-12))), 0.0)
