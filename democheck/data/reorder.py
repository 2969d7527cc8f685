"""A recording in another order: played backwards (what a reset recorded as a demo looks like), or with a pause put
in (an operator who hesitates).  Numpy alone, so that generators running in other environments plant the same.

Time run backwards flips a velocity's sign and keeps a position, a torque or an acceleration: the dimensions a
dataset names as velocities (``VELOCITY``) are negated, the others only reordered.  A recording's action at a step
is the one that took it from that step's state to the next; played backwards, the transition from step t to t + 1
is the one the action of the step before undid, so the reversed actions are one step on (``reverse_actions``): a
reset recorded as a demo has no lag its recording did not.
"""

from __future__ import annotations

import re

import numpy as np

# A name, or a part of one between separators, that says velocity: vel, speed, qvel, dq, a linear or angular
# velocity's axis (vx, wz) or a step's displacement (dx, delta).
VELOCITY = re.compile(r"(^|[._/\- ])(vel|velocity|velocities|speed|qvel|dq|[vw][xyz]|d[xyz]|delta)([._/\- \[]|$)",
                      re.I)
PAUSE_AT = (0.3, 0.7)  # where in the demo a pause begins, as a share of its motion (of its steps where it has none)
PAUSE_LENGTH = (0.3, 0.5)  # how long it lasts, as a share of the demo's steps


def velocities(names: list[str] | None, width: int) -> np.ndarray:
    """[width] bool: the dimensions ``names`` calls velocities (none where the dataset names none)."""
    if not names or len(names) != width:
        return np.zeros(width, bool)
    return np.array([bool(VELOCITY.search(str(n))) for n in names])


def reverse(x: np.ndarray, names: list[str] | None = None) -> np.ndarray:
    """A recorded stream [T, ...] played backwards: its steps in the other order, velocities negated."""
    x = np.asarray(x)[::-1].copy()
    if x.ndim == 2:
        x[:, velocities(names, x.shape[1])] *= -1
    return x


def reverse_actions(actions: np.ndarray, names: list[str] | None = None) -> np.ndarray:
    """A recording's actions [T, ...] as the same recording played backwards would have them: reversed, velocities
    negated, one step on (the last step holds the one before it, its velocities still)."""
    a = reverse(actions, names)
    if len(a) < 2:
        return a
    last = a[-1:].copy()
    if last.ndim == 2:
        last[:, velocities(names, last.shape[1])] = 0
    return np.concatenate([a[1:], last])


def pause(steps: int, seed: int, done: np.ndarray | None = None) -> tuple[int, int]:
    """Where a pause drawn by ``seed`` begins in a demo of ``steps`` steps, and how many steps it lasts
    (``PAUSE_LENGTH``).  It begins where the share ``PAUSE_AT`` of the demo's motion is done (``done``, from
    ``motion_done``), or of its steps where no motion is given: a demo that does its task in its first steps and
    then rests is paused on its way, not in its rest."""
    rng = np.random.default_rng([seed, 0x9A05E])
    share, length = rng.uniform(*PAUSE_AT), max(1, int(rng.uniform(*PAUSE_LENGTH) * steps))
    if done is None or not len(done):
        return int(share * steps), length
    return min(int(np.searchsorted(done, share)), steps - 1), length


def motion_done(x: np.ndarray, names: list[str] | None = None) -> np.ndarray | None:
    """[T] the share of a recorded stream's motion (its state's, velocities left out, each dimension in its range
    over the demo) done by each step, 0 at the first and 1 at the last; None where it never moves."""
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    x = x[:, ~velocities(names, x.shape[1])]
    if len(x) < 2 or not x.size:
        return None
    span = np.ptp(x, axis=0)
    step = np.linalg.norm(np.nan_to_num(np.diff(x, axis=0) / np.where(span > 0, span, 1.0)), axis=1)
    total = step.sum()
    return np.r_[0.0, np.cumsum(step)] / total if total > 0 else None


def hold(x: np.ndarray, at: int, steps: int, names: list[str] | None = None) -> np.ndarray:
    """A recorded stream [T, ...] with step ``at`` held for ``steps`` more steps (velocities zero there), then the
    rest: the stream of a demo paused at ``at``."""
    x = np.asarray(x)
    still = np.repeat(x[at:at + 1], steps, 0)
    if still.ndim == 2:
        still[:, velocities(names, x.shape[1])] = 0
    return np.concatenate([x[:at], still, x[at:]])


def replant(kind: str, streams: dict, names: dict, seed: int) -> tuple[dict, dict[str, int]]:
    """``streams`` (name -> [T, ...] array, or None) of a demo as ``kind`` plants it: "reversed" played backwards,
    "hesitates" paused where ``pause`` draws by ``seed``, on its way (by the state's motion, else the actions');
    ``names`` gives each stream's dimension names (velocities).  Returns the streams and where a pause is ({} for a
    reversal)."""
    if kind == "reversed":
        return {k: None if v is None else (reverse_actions if k == "actions" else reverse)(v, names.get(k))
                for k, v in streams.items()}, {}
    by = next((k for k in ("state", "actions") if streams.get(k) is not None and np.size(streams[k])), None)
    at, n = pause(len(streams["actions"]), seed, None if by is None else motion_done(streams[by], names.get(by)))
    return ({k: None if v is None else hold(v, at, n, names.get(k)) for k, v in streams.items()},
            {"at": at, "steps": n})
