"""The ``frozen_state`` check (model-free): a state sensor that stopped updating while the arm was driven.

Per dimension of the state, the longest stretch of steps at which its value repeats exactly (bit for bit: a
live sensor's reading, or a simulator's, changes in its last digits whenever the arm moves) while the actions
change, as a share of the demo's steps.  Only the dimensions live in the demo's task count: those whose share's
median over the task's demos (over every demo where the task has fewer than ``FROZEN_STATE_MIN_DEMOS``) is at
most ``FROZEN_STATE_LIVE`` -- a goal, or an object at rest until the arm reaches it, holds still in most of the
task's demos and is left out.  The score is the largest share over the live dimensions: one joint whose encoder
died for the whole demo reads 1, the whole state stream frozen from a step on reads the rest of the demo.  The
reason names the dimension and the frames.  A recording fault: in the ranking beside the other scores
(``scorers.Scorer.alone``), a robust standard deviation of it standing for at least ``FROZEN_STATE_MIN_SCALE``.
A consumer of the audit's decoding pass like the other model-free checks (``democheck.audit.modelfree``).

Chosen on the development sets, with a copy of mw3-dev whose parquet froze 6 clean demos' whole state from
30-60% of the demo on, held one moving state dimension of 6 others at its first value, and recorded 6 others'
actions x3 (``benchmarks/foreign/plant_faults.py``): with its your-data model, the frozen joint 0.86 -> 1.00
AUROC and 0.17 -> 1.00 flagged at --fpr 0.01, the frozen stream 0.895 -> 0.999 and 0.67 -> 1.00, the actions
x3 0.989 -> 0.981 and 0.17 -> 0.00, 1 of 132 clean demos flagged either way; without a model the joint 0.82 ->
1.00 (flagged 0.17 -> 1.00), the others within two pairs, 2 clean either way.  mw3-dev, mw2-dev, mw2-one-dev and
the push-v1 draws (alone and with their probes) ranked and flagged the same, with a model and without.  Every
dimension counted, as a robust z above its task's median, flagged 5-14% of the push draws' clean demos (their
objects rest bit-identical for stretches that vary from demo to demo); the ranking's usual floor of 0.02 for a
fault's robust SD flagged 5 of 132 clean demos, 0.1 lost the frozen stream's flags (0.67); the stretch from a
dimension's last change to the demo's end in place of the longest (a sensor that never came back) flagged 5 of
132, 6 of 150 and 12 of 200 clean Meta-World demos (their objects settle bit-identical once left); a dimension
live where the 75th percentile of its share over the task's demos is at most ``FROZEN_STATE_LIVE`` ranked and
flagged as the median does, the 90th lost a frozen joint's flag.  Held out (mw3-test planted the same way with
seed 43, its your-data model): the frozen joint 0.61 -> 0.99 AUROC and 0.17 -> 0.83 flagged, the frozen stream
0.74 -> 0.99 and 0.33 -> 1.00, 3 of 126 clean demos flagged either way; but on Meta-World mw2-test two clean demos
whose object rested bit-identical for 28% and 37% of the demo (live in their task: its other demos' objects
jitter) were flagged, 2 -> 4 of 200 (2.0%; the audit expected 2.0).
"""

from __future__ import annotations

import numpy as np

from democheck.audit.modelfree import PerDemo, longest_run, steps_text, task_z
from democheck.data.demo import Demo

FROZEN_STATE_MIN_DEMOS = 4  # a task with fewer demos is compared with every demo
FROZEN_STATE_LIVE = 0.05  # a dimension whose frozen share's task median is at most this is live in the task
FROZEN_STATE_MIN_SCALE = 0.05  # in the ranking, a robust SD of the score stands for at least 5% of the steps


class StateRepeats(PerDemo):
    """Consumer of decoded demos: per state dimension, the longest stretch of steps at which the value repeats
    while the actions change (its share of the demo's steps, where it starts, how many steps it lasts)."""

    fields = ("shares", "starts", "lengths", "steps")
    shares: list[np.ndarray]  # [S]
    starts: list[np.ndarray]  # [S]
    lengths: list[np.ndarray]  # [S]
    steps: list[int]  # the demo's steps (frames - 1)

    def add(self, demo: Demo) -> None:
        x, a = np.asarray(demo.state), np.asarray(demo.actions)
        n = max(len(x) - 1, 0)
        driven = np.any(a[1:] != a[:-1], axis=1) if n else np.zeros(0, bool)
        repeats = (x[1:] == x[:-1]) & driven[:, None] if n else np.zeros((0, x.shape[1]), bool)
        runs = [longest_run(repeats[:, j]) for j in range(x.shape[1])]
        starts = np.array([s for s, _ in runs], int)
        lengths = np.array([k for _, k in runs], int)
        self.shares.append(lengths / max(n, 1))
        self.starts.append(starts)
        self.lengths.append(lengths)
        self.steps.append(n)


def frozen_state(stats: StateRepeats, tasks: np.ndarray, live: float | None = None) -> tuple[np.ndarray, list[str]]:
    """The longest frozen stretch's share (see the module docstring) of the state dimensions live in the demo's
    task (those whose share's median over the task's demos is at most ``live``), the largest; and where."""
    if not stats.shares:
        return np.zeros(0), []
    live = FROZEN_STATE_LIVE if live is None else live
    shares = np.stack(stats.shares).astype(np.float64)
    _, usual = task_z(shares, tasks, 1.0, FROZEN_STATE_MIN_DEMOS, small="all")
    seen = np.where(usual <= live, shares, 0.0)
    out, reasons = np.zeros(len(shares)), []
    for i in range(len(shares)):
        if not seen.shape[1] or not stats.steps[i]:
            reasons.append("no state" if not seen.shape[1] else "a single frame")
            continue
        j = int(np.argmax(seen[i]))
        out[i] = float(seen[i, j])
        start, length = int(stats.starts[i][j]), int(stats.lengths[i][j])
        reasons.append(f"state[{j}] holds one value while the arm is driven over "
                       f"{steps_text(start, start + length, stats.steps[i] + 1)}, where its task's demos rarely "
                       "do" if out[i] > 0 else "every state dimension that moves in its task's demos moves")
    return out, reasons
