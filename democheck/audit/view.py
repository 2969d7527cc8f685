"""The view check (model-free): how much of a demo's average picture is unlike its task's other demos' there -- a
covered, moved or blinded camera, or another scene -- and the pieces other camera checks share with it: the
per-pixel robust z within a task (``task_z``) and where in the view a change lies (``place``).
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.audit.scores import calibrated
from democheck.data.demo import Demo


class ViewStats(PerDemo):
    """Consumer of decoded demos: what the camera saw on average -- every ``VIEW_EVERY``-th frame shrunk to
    ``VIEW_THUMB`` x ``VIEW_THUMB`` pixels (area interpolation) and averaged, kept as uint8 (768 bytes a demo)."""

    fields = ("thumbs",)
    thumbs: list[np.ndarray]

    def add(self, demo: Demo) -> None:
        size = (VIEW_THUMB, VIEW_THUMB)
        frames = demo.frames[::VIEW_EVERY]
        if not len(frames):
            self.thumbs.append(np.zeros((*size, 3), np.uint8))
            return
        small = [cv2.resize(np.ascontiguousarray(f), size, interpolation=cv2.INTER_AREA) for f in frames]
        self.thumbs.append(np.rint(np.mean(small, axis=0)).astype(np.uint8).reshape(*size, -1)[..., :3])

    def finish(self) -> np.ndarray:
        return np.stack(self.thumbs) if self.thumbs else np.zeros((0, VIEW_THUMB, VIEW_THUMB, 3), np.uint8)


VIEW_EVERY = 10
VIEW_THUMB = 16
# A thumbnail pixel is unlike its task's when it is VIEW_K robust standard deviations (over the task's demos,
# at least VIEW_FLOOR grey levels) from the task's median there (chosen on the development sets: docs/decisions.md,
# "View").
VIEW_K = 5.0
VIEW_FLOOR = 2.0
# A robust standard deviation of the share stands for at least 2% of the view: a fixed camera on a static scene
# sees nearly the same picture in every demo, and a MAD near zero would flag a passing shadow.
VIEW_MIN_SCALE = 0.02
VIEW_MIN_DEMOS = 5  # a task with fewer demos is compared with all the demos' picture
_PLACES = (("top", "middle", "bottom"), ("left", "centre", "right"))


def task_z(x: np.ndarray, tasks: np.ndarray, floor: np.ndarray | float, min_demos: int, small: str = "nan"
           ) -> tuple[np.ndarray, np.ndarray]:
    """Per entry of ``x`` [N, ...], |x - its task's median| over the task's robust SD there (1.4826 x MAD, at
    least ``floor``), NaN entries left out; and the median each was measured against.  A task of fewer than
    ``min_demos`` demos (with any value) is measured against all the demos (``small="all"``) or not at all
    (``small="nan"``: NaN)."""
    x, tasks = np.asarray(x), np.asarray(tasks)
    z, median = np.full(x.shape, np.nan), np.full(x.shape, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: NaN, as they should be
        for t in np.unique(tasks):
            rows = np.flatnonzero(tasks == t)
            ref = x[rows]
            if np.isfinite(ref.reshape(len(rows), -1)).any(1).sum() < min_demos:
                if small == "nan":
                    continue
                ref = x
            med = np.nanmedian(ref, axis=0)
            spread = np.fmax(1.4826 * np.nanmedian(np.abs(ref - med), axis=0), floor)
            z[rows] = np.abs(x[rows] - med) / spread
            median[rows] = med
    return z, median


def view_unlike(thumbs: np.ndarray, tasks: np.ndarray, k: float = VIEW_K, floor: float = VIEW_FLOOR) -> np.ndarray:
    """[N, h, w] True where a demo's average picture (``ViewStats``) is unlike its task's other demos' there:
    more than ``k`` robust standard deviations (at least ``floor`` grey levels) from the task's median, in some
    colour channel."""
    z, _ = task_z(np.asarray(thumbs, np.float32), tasks, floor, VIEW_MIN_DEMOS, small="all")
    return z.max(axis=-1) > k


VIEW = Vocabulary("view", {
    "changed": lambda share, place: f"the view is covered or changed: {100 * share:.0f}% of it unlike its task's "
                                    f"other demos' (mostly {place})",
    "like": "the view is like its task's other demos'",
})


def view(thumbs: np.ndarray, tasks: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """Robust z within its task of the share of a demo's average picture that is unlike its task's other demos'
    (``view_unlike``): a covered, moved or blinded camera, or another scene.  The reason says where in the view."""
    unlike = view_unlike(thumbs, tasks)
    share = unlike.mean(axis=(1, 2)) if len(unlike) else np.zeros(0)
    z = calibrated(share, tasks, min_scale=VIEW_MIN_SCALE)
    reasons = [VIEW("changed", share=float(f), place=place(u)) if u.any() else VIEW("like")
               for u, f in zip(unlike, share)]
    return z, reasons


def place(mask: np.ndarray) -> str:
    """Where in the view the True pixels of ``mask`` [h, w] lie, in words ("the top left", "the centre")."""
    rows, cols = np.nonzero(mask)
    if not len(rows):
        return "nowhere"
    where = [_PLACES[0][min(int(3 * rows.mean() / mask.shape[0]), 2)],
             _PLACES[1][min(int(3 * cols.mean() / mask.shape[1]), 2)]]
    return "the centre" if where == ["middle", "centre"] else f"the {' '.join(where)}"
