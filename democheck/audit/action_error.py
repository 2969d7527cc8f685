"""The action error: how badly PETNet's controller, told the task, explains a demo's own actions.

``ActionErrors`` is a consumer of the audit's decoding pass (``add`` one decoded demo at a time, ``finish``
once): it batches ``ACTION_BATCH`` demos for the controller and compares its actions with the demo's at
``ACTION_STEPS`` evenly spaced timesteps, under the task variable of the demo's task's other demos
(``controller_z``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from democheck.audit.findings import Finding, Vocabulary
from democheck.data.demo import Demo, resize_frames
from democheck.petnet.checkpoint import Checkpoint
from democheck.petnet.posterior import TaskPosterior

ACTION_STEPS = 25  # timesteps per demo at which the controller's actions are compared with the demo's
ACTION_BATCH = 32  # demos per controller batch in the action error's pass


def controller_z(post: TaskPosterior, tasks: np.ndarray) -> np.ndarray:
    """The task variable each demo's actions are judged under: its task's other demos' posterior mean (own mu
    if alone)."""
    m, _ = post.others(tasks)
    return np.where(np.isfinite(m), m, post.mu).astype(np.float32)


class ActionErrors:
    """Consumer of decoded demos: the mean squared error between each demo's normalised actions and the
    controller's under its task variable ``z``, at ``steps`` evenly spaced timesteps (all of them when the demo
    is shorter), and the timestep where they differ most.  It reads the camera's frames and resizes the sampled
    ones to the model's size, so the other checks of the same pass read the camera's own."""

    def __init__(self, ckpt: Checkpoint, z: np.ndarray, device: Any, steps: int = ACTION_STEPS,
                 batch: int = ACTION_BATCH):
        self.ckpt, self.z, self.device, self.steps, self.batch = ckpt, z, device, steps, batch
        self.out = np.full(len(z), np.nan)
        self.worst: list[Finding] = [ACTION_ERROR("not read")] * len(z)
        self.pending: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.seen = 0

    def add(self, demo: Demo) -> None:
        t = np.unique(np.linspace(0, len(demo.actions) - 1, self.steps).round().astype(np.int64))
        if len(t) < self.steps:  # a short demo: repeat its timesteps so a batch stacks
            t = np.resize(t, self.steps)
        norm = self.ckpt.norm
        frames = resize_frames(demo.frames[t], self.ckpt.config.image_size)  # as the model's training read them
        self.pending.append((self.seen, frames, norm.state(demo.state[t]).astype(np.float32),
                             norm.action(demo.actions[t]).astype(np.float32), t))
        self.seen += 1
        if len(self.pending) == self.batch:
            self._flush()

    def _flush(self) -> None:
        p = self.pending
        frames = torch.from_numpy(np.stack([x[1] for x in p])).to(self.device)
        state = torch.from_numpy(np.stack([x[2] for x in p])).to(self.device)
        rows = np.array([x[0] for x in p])
        with torch.no_grad():
            pred = self.ckpt.model.controller.act(frames, state, torch.from_numpy(self.z[rows]).to(self.device))
        sq = (pred.cpu().numpy() - np.stack([x[3] for x in p])) ** 2
        self.out[rows] = sq.mean(axis=(1, 2))
        for row, per_t, (_, _, _, _, t) in zip(rows, sq.mean(axis=2), p):
            self.worst[row] = _peak(per_t, t)
        self.pending.clear()

    def finish(self) -> tuple[np.ndarray, list[Finding]]:
        if self.pending:
            self._flush()
        return self.out, self.worst


ACTION_ERROR = Vocabulary("action_error", {
    "otherwise": lambda first, last: "the controller, told the task, does otherwise, most at "
                                     + (f"timestep {first}" if first == last else f"timesteps {first}-{last}"),
    "not read": "",
})


def _peak(per_t: np.ndarray, t: np.ndarray) -> Finding:
    """Where a demo's action error peaks: the sampled timesteps around its largest error that stay above half of
    it, e.g. '... most at timesteps 55-70'."""
    i = int(np.argmax(per_t))
    high = per_t >= 0.5 * per_t[i]
    lo, hi = i, i
    while lo > 0 and high[lo - 1]:
        lo -= 1
    while hi < len(per_t) - 1 and high[hi + 1]:
        hi += 1
    return ACTION_ERROR("otherwise", first=int(t[lo]), last=int(t[hi]))


def action_errors(demos, ckpt: Checkpoint, z: np.ndarray, device: Any, steps: int = ACTION_STEPS,
                  batch: int = ACTION_BATCH) -> np.ndarray:
    """``ActionErrors`` over an iterable of demos, in ``z``'s order."""
    consumer = ActionErrors(ckpt, z, device, steps, batch)
    for demo in demos:
        consumer.add(demo)
    return consumer.finish()[0]
