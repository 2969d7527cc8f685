"""The ``moved`` check (model-free): what a demo changed in the scene, read from its camera as the colours of the
pixels that differ between its first and its last picture.  In a task every demo moves the same object, wherever
it lies, so a demo that moved another object (the wrong one, or both) changes other colours -- the outcome seen
where no object state is recorded.  The place of the change is left out on purpose: it follows the layout, which
every demo draws anew.

Each picture is the median of the demo's ``END_FRAMES`` first (last) frames at ``MOVED_SIZE`` px; a pixel changed
where some channel differs by more than ``MOVED_CHANGE`` levels; its colour in the first picture and in the last
both count (what left a place and what arrived there), in ``HUE_BINS`` hues x saturated or not x bright or not.
Per colour the square root of its count (a count's noise grows with its root), robust z within the task, RMS over
the colours the task or the demo changed.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd

from democheck.audit.colours import HUE_BINS, bin_colour, colour_bins, saturated
from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.audit.scores import calibrated
from democheck.audit.timeline import END_FRAMES, picture
from democheck.audit.view import VIEW_MIN_DEMOS, task_z
from democheck.data.demo import Demo

MOVED_SIZE = 64  # px: the side both pictures are compared at (an object a few pixels wide still counts)
MOVED_CHANGE = 30  # levels of 255: a pixel whose first and last value differ this much in some channel changed
BINS = HUE_BINS * 4
MOVED_FLOOR = 1.0  # root-count units: a robust SD stands for at least one pixel's change of a colour
MOVED_MIN_SCALE = 0.1  # the score's least robust SD within its task, in robust SD of a colour
SAID = 1.0  # robust SD: of the colours at least this far off their task's, the three furthest are named
# A share of the picture: a demo that changed this much more of it than its task's median demo had its view covered
# or moved, since an object a task moves is a few percent of the picture.
VIEW_CHANGE = 0.05


class MovedStats(PerDemo):
    """Consumer of decoded demos: per demo, how many pixels of each colour bin changed between its first and last
    picture (NaN: no frames)."""

    fields = ("counts",)
    counts: list[np.ndarray]

    def add(self, demo: Demo) -> None:
        frames = np.asarray(demo.frames)
        if frames.ndim != 4 or not len(frames) or not frames.shape[1]:
            self.counts.append(np.full(BINS, np.nan))
            return
        if frames.shape[-1] < 3:
            frames = np.repeat(frames[..., :1], 3, axis=-1)
        first = picture(frames[:END_FRAMES], MOVED_SIZE)
        last = picture(frames[-END_FRAMES:], MOVED_SIZE)
        self.counts.append(changed_colours(first, last))

    def array(self) -> np.ndarray:
        return np.stack(self.counts) if self.counts else np.zeros((0, BINS))


def changed_pixels(first: np.ndarray, last: np.ndarray, change: int = MOVED_CHANGE
                   ) -> tuple[np.ndarray, np.ndarray]:
    """[n, 3] each of the pixels of ``first`` and of ``last`` (uint8 RGB [h, w, 3] each) that differ between them
    by more than ``change`` levels in some channel."""
    changed = (np.abs(first.astype(np.int16) - last.astype(np.int16)) > change).any(axis=-1)
    return first[changed], last[changed]


def changed_colours(first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """[BINS] counts of the changed pixels' colours, in ``first`` and in ``last`` (uint8 RGB [h, w, 3] each)."""
    return np.bincount(colour_bins(np.concatenate(changed_pixels(first, last))), minlength=BINS).astype(float)


def colour_z(root: np.ndarray, tasks: np.ndarray, floor: float = MOVED_FLOOR) -> tuple[np.ndarray, np.ndarray]:
    """Per demo and colour ([N, bins] each): the robust z within its task of its root count (a robust SD at least
    ``floor``), NaN where neither the task nor the demo changed that colour; and the task's median root count."""
    z, median = task_z(root, tasks, floor, VIEW_MIN_DEMOS, small="all")
    return np.where((median > 0) | (root > 0), z, np.nan), median


def _listed(names: list[str]) -> str:
    return " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)


def _another_words(gained: list[str], lost: list[str], **_) -> str:
    said = [f"more {_listed(gained)}", f"less {_listed(lost)}" if lost else ""]
    return ("what changed between its first and last picture is unlike its task's demos: "
            + ", ".join(s for s in said if s) + " than theirs (another object moved?)")


MOVED = Vocabulary("moved", {
    # colours changed that its task's demos do not change (and maybe less of theirs)
    "another object": _another_words,
    # only less of the colours its task's demos change
    "not moved": lambda lost, **_: (f"less {_listed(lost)} changed between its first and last picture than in its "
                                    "task's demos (what they move left where it was, or not there?)"),
    "view": lambda share, median, **_: (
        f"more of its picture changed between its first and last frames than in its task's demos: {share:.0%} "
        f"against their {median:.0%} (the camera covered or moved?)"),
    "like": "changed the scene as its task's demos do",
    "no frames": "no camera to compare",
})


def moved(stats: MovedStats, tasks: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """Robust z within its task of how unlike its task's demos the colours a demo changed are (see the module
    docstring); the words name the (up to three) colours furthest off, of those beyond ``SAID`` robust SD."""
    counts, tasks = stats.array(), np.asarray(tasks)
    if not len(counts):
        return np.zeros(0), []
    root = np.sqrt(counts)
    z, median = colour_z(root, tasks)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # no colour shown: the mean of nothing
        rms = np.sqrt(np.nanmean(z ** 2, axis=1))
    # Nothing changed where its task's demos change nothing either: as they are.  No frames: no score.
    rms = np.where(np.isfinite(root).all(axis=1), np.nan_to_num(rms), np.nan)
    share = counts.sum(axis=1) / (2 * MOVED_SIZE ** 2)
    usual = pd.Series(share).groupby(tasks).transform("median").to_numpy()
    found = []
    for i in range(len(z)):
        if not np.isfinite(rms[i]):
            found.append(MOVED("no frames"))
            continue
        off = np.flatnonzero(z[i] > SAID)
        off = off[np.argsort(-z[i, off])][:3]
        if not len(off):
            found.append(MOVED("like"))
            continue
        if share[i] > usual[i] + VIEW_CHANGE:
            found.append(MOVED("view", share=float(share[i]), median=float(usual[i]), z=float(z[i, off[0]])))
            continue
        more = [int(b) for b in off if root[i, b] > median[i, b]]
        gained = list(dict.fromkeys(bin_colour(b) for b in more))
        lost = list(dict.fromkeys(bin_colour(int(b)) for b in off if root[i, b] <= median[i, b]))
        # A grey that changed more is the arm's, the table's or a shadow's as often as an object's: where only greys
        # were gained and some of the task's colours lost, what the task moves did not move.
        hue_gained = any(saturated(b) for b in more)
        kind = "another object" if hue_gained or not lost else "not moved"
        found.append(MOVED(kind, gained=gained, lost=lost, z=float(z[i, off[0]])))
    return calibrated(rms, tasks, min_scale=MOVED_MIN_SCALE), found
