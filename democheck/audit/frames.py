"""The frame checks (model-free): a camera that stopped delivering, or frames dropped or spliced.

``frozen_video``: the longest stretch of steps at which the camera frame repeats (mean absolute grey-level
change under ``FROZEN_LEVEL``) while the actions change, as a share of the demo's steps: a camera that stopped
delivering while the arm moved.

``frame_jump``: how much more the camera frame changes at one step than at the steps around it -- the largest
ratio of a step's mean absolute grey-level change to the median change of the ``modelfree.JUMP_NEIGHBOURS`` steps
either side (at least ``JUMP_FLOOR`` grey levels), on a log scale: a stretch of frames dropped from the recording
(and the steps re-indexed, so that no timestamp shows it), or two recordings spliced.  ``dynamics.state_jump``
asks the same of the state, one look with it in the ranking.

Both read one consumer of the audit's decoding pass (``FrameChanges``) and, with ``dynamics.lag`` and
``modelfree.timing``, are recording faults: in the ranking apart from the other scores (``alone`` in the ranking recipe).

A picture that stays the same is a camera that stopped or a view the arm left (under a card, say); the view and
colour checks then read a changed picture either way.  ``delivered_unlike`` tells them apart for the reasons: the
frames delivered, and the repeated one, each against its task's demos' frames at the same step, are like theirs
where the camera stopped and unlike where a card covers the view (from the start, or from where the picture
stopped).  Only a stretch of at least ``STOPPED_SHARE`` of the demo explains the view's and the colours' reading
(their average picture is then mostly the repeated frame); a shorter one leaves their reading its own.
"""

from __future__ import annotations

import cv2
import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import STILL, PerDemo, change_scale, jump_ratios, longest_run, steps_text
from democheck.audit.view import VIEW_EVERY, VIEW_FLOOR, VIEW_K, VIEW_MIN_SCALE, task_z
from democheck.audit.scores import calibrated
from democheck.data.demo import Demo

FROZEN_LEVEL = 0.1  # grey levels (0-255): a frame this close to the previous one repeats it
FRAME_CHECK_SIZE = 64  # pixels: the frame checks read frames shrunk to this (``FrameChanges``)
JUMP_FLOOR = 0.5  # grey levels: the least usual change a jump is measured against (a still scene's sensor noise)
STEP_THUMB = 8  # pixels: the grey thumbnails of every ``VIEW_EVERY``-th frame ``delivered_unlike`` compares
STOPPED_SHARE = 0.5  # a frozen stretch this share of the demo or more is most of the picture the view checks average
BLANK_RANGE = 2.0  # grey levels: a thumbnail whose lightest and darkest pixels are closer shows nothing (flat)


class FrameChanges(PerDemo):
    """Consumer of decoded demos: per step, the mean absolute grey-level change of the camera frame, and
    whether the actions changed (the ``frozen_video`` and ``frame_jump`` checks), and a ``STEP_THUMB`` grey
    thumbnail of every ``VIEW_EVERY``-th frame (``delivered_unlike``; 768 bytes a demo of 120 steps).  Frames
    larger than ``FRAME_CHECK_SIZE`` on their longer side are first shrunk to it (area averaging): the checks then
    read the same numbers whether or not a model had the frames decoded at its own size, and a video codec's
    per-pixel noise, which hides a jump among the steps around it, averages out."""

    fields = ("deltas", "changes", "thumbs")
    deltas: list[np.ndarray]
    changes: list[np.ndarray]
    thumbs: list[np.ndarray]

    def add(self, demo: Demo) -> None:
        grey = np.stack([_check_size(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY))
                         for f in demo.frames])
        self.deltas.append(np.abs(np.diff(grey.astype(np.int16), axis=0)).mean(axis=(1, 2)).astype(np.float32))
        self.changes.append(np.abs(np.diff(np.asarray(demo.actions, np.float64), axis=0)))
        size = (STEP_THUMB, STEP_THUMB)
        self.thumbs.append(np.stack([cv2.resize(g, size, interpolation=cv2.INTER_AREA)
                                     for g in grey[::VIEW_EVERY]]))


def _check_size(grey: np.ndarray) -> np.ndarray:
    """A grey frame shrunk (area averaging) so that its longer side is at most ``FRAME_CHECK_SIZE``."""
    h, w = grey.shape[:2]
    scale = FRAME_CHECK_SIZE / max(h, w)
    if scale >= 1.0:
        return grey
    return cv2.resize(grey, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)


def _frozen(frames: FrameChanges) -> list[np.ndarray]:
    """Per demo, bool per step: the frame repeats while the actions change."""
    scale = change_scale(frames.changes)
    out = []
    for d, c in zip(frames.deltas, frames.changes):
        n = min(len(d), len(c))
        out.append((d[:n] < FROZEN_LEVEL) & ((c[:n] / scale).mean(1) >= STILL))
    return out


def _stays(start: int, stop: int, length: int, scattered: int) -> str:
    # A still picture alone cannot tell a camera that stopped from an arm that left its view: both are named.
    return (f"the picture stays the same while the actions change over {steps_text(start, stop, length)} (the "
            "camera stopped, or the arm left its view)" + (f"; {scattered} more repeated frames elsewhere"
                                                          if scattered else ""))


def _blank(share: float, level: float) -> str:
    shade = "black" if level < 16 else "white" if level > 239 else f"grey ({level:.0f} of 255)"
    return f"the camera shows nothing: {100 * share:.0f}% of the demo's frames are one flat {shade} picture"


FROZEN_VIDEO = Vocabulary("frozen_video", {
    # most of the frames (``STOPPED_SHARE``) flat (``BLANK_RANGE``): a camera that delivered no picture
    "blank": _blank,
    # for STOPPED_SHARE of the demo or more, and the frames delivered are like its group's at the same steps
    # (``delivered_unlike``): the camera stopped, and the view's and colours' reading of a changed picture is that
    "stopped camera": _stays,
    "still picture": _stays,  # shorter, or the frames delivered differ too (a card over the view)
    "changes": "frames change while the arm moves",
    "single frame": "a single frame",
})


def frozen_video(frames: FrameChanges, groups: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """The longest stretch of steps at which the frame repeats while the actions change, as a share of the demo's
    steps, and where it is: a camera that stopped delivering repeats one frame for a stretch, where a video
    codec's or a still scene's repeated frames are scattered (Meta-World's clean demos, AV1: 14% of their steps,
    but never two in a row).  ``stopped camera`` where the stretch is ``STOPPED_SHARE`` of the demo or more and
    the frames delivered are like its group's (``delivered_unlike`` under ``VIEW_K``); ``blank`` where that share
    of its thumbnails or more are flat (``BLANK_RANGE``): a camera that delivered no picture at all."""
    out, found = np.zeros(len(frames.deltas)), []
    delivered = None
    thumbs = getattr(frames, "thumbs", None) or [np.zeros((0, STEP_THUMB, STEP_THUMB))] * len(frames.deltas)
    for i, frozen in enumerate(_frozen(frames)):
        n = len(frozen)
        if not n:
            found.append(FROZEN_VIDEO("single frame"))
            continue
        start, length = longest_run(frozen)
        out[i] = length / n
        t = np.asarray(thumbs[i], np.float32).reshape(len(thumbs[i]), -1)
        flat = (t.max(axis=1) - t.min(axis=1)) < BLANK_RANGE if len(t) else np.zeros(0, bool)
        if len(flat) and flat.mean() >= STOPPED_SHARE:
            found.append(FROZEN_VIDEO("blank", share=float(flat.mean()), level=float(t[flat].mean())))
            continue
        if not length:
            found.append(FROZEN_VIDEO("changes"))
            continue
        if out[i] >= STOPPED_SHARE and delivered is None:
            delivered = delivered_unlike(frames, groups)
        stopped = out[i] >= STOPPED_SHARE and bool(delivered[i] < VIEW_K)
        found.append(FROZEN_VIDEO("stopped camera" if stopped else "still picture", start=start,
                                  stop=start + length, length=n + 1, scattered=int(frozen.sum()) - length))
    return out, found


def delivered_unlike(frames: FrameChanges, groups: np.ndarray) -> np.ndarray:
    """[N] robust z within its group (``Evidence.groups``) of the share of a demo's thumbnails unlike its group's
    demos' at the same step (over ``VIEW_K`` robust SD, at least ``VIEW_FLOOR`` grey levels, from their median
    there -- the view check's measure, step by step): the larger of the share over the frames before and after
    its longest frozen stretch and that of the repeated frame itself, so that a card put down where the picture
    stopped counts.  One group in memory at a time; NaN without thumbnails."""
    thumbs = getattr(frames, "thumbs", None)
    if not thumbs:
        return np.full(len(frames.deltas), np.nan)
    groups = np.asarray(groups)
    steps = max(len(t) for t in thumbs)
    share = np.zeros(len(thumbs))
    frozen = _frozen(frames)
    for group in np.unique(groups):
        rows = np.flatnonzero(groups == group)
        x = np.full((len(rows), steps, STEP_THUMB, STEP_THUMB), np.nan, np.float32)
        for k, i in enumerate(rows):
            x[k, :len(thumbs[i])] = thumbs[i]
        z, _ = task_z(x, np.zeros(len(rows), int), VIEW_FLOOR, 1)
        for k, i in enumerate(rows):
            start, length = longest_run(frozen[i])
            shown = np.arange(len(thumbs[i])) * VIEW_EVERY
            repeats = (shown > start) & (shown <= start + length)  # frames start + 1 .. start + length: frame start
            parts = [z[k, :len(shown)][~repeats], z[k, np.flatnonzero(repeats)[:1]]]  # and the repeated frame, once
            share[i] = max((float((p > VIEW_K).mean()) for p in parts if p.size), default=0.0)
    return calibrated(share, groups, min_scale=VIEW_MIN_SCALE)


FRAME_JUMP = Vocabulary("frame_jump", {
    "jump": "the frame jumps between frames {frame} and {next}: {ratio:.1f} x the change around it ({change:.1f} "
            "grey levels against {usual:.1f})",
    "too short": "too short",
})


def frame_jump(frames: FrameChanges) -> tuple[np.ndarray, list[Finding]]:
    """log of the largest ratio of a step's frame change to the median change around it (see the module
    docstring), and the step where it is."""
    out, reasons = np.full(len(frames.deltas), np.nan), []
    for i, d in enumerate(frames.deltas):
        if len(d) < 2:
            reasons.append(FRAME_JUMP("too short"))
            continue
        ratio, usual = jump_ratios(d, JUMP_FLOOR)
        at = int(np.argmax(ratio))
        out[i] = float(np.log(max(ratio[at], 1.0)))  # no step changes more than around it: 0 (a still camera)
        reasons.append(FRAME_JUMP("jump", frame=at, next=at + 1, ratio=float(ratio[at]), change=float(d[at]),
                                  usual=float(usual[at])))
    return out, reasons
