"""The ``colours`` check (model-free): how differently from its task's other demos a demo's frames are coloured,
wherever the colours are in the picture -- an object missing (its colour gone), another object, a covered camera.
``view`` (``democheck.audit.modelfree``) compares the picture place by place, so it does not see a small object
that lies somewhere else in every demo.  A consumer of the audit's decoding pass like the other model-free checks.
"""

from __future__ import annotations

import colorsys
import warnings

import cv2
import numpy as np

from democheck.audit import words
from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.audit.view import VIEW_EVERY, VIEW_MIN_DEMOS, task_z
from democheck.audit.scores import calibrated
from democheck.data.demo import Demo


class ColourStats(PerDemo):
    """Consumer of decoded demos: the share of the pixels in each of ``COLOUR_LEVELS`` ** 3 colour bins (each
    channel cut into ``COLOUR_LEVELS`` equal ranges) over every ``VIEW_EVERY``-th frame, and one pixel's share
    of a frame (the unit below which a share is noise)."""

    fields = ("shares", "pixel")
    shares: list[np.ndarray]
    pixel: list[float]

    def add(self, demo: Demo) -> None:
        frames = np.asarray(demo.frames[::VIEW_EVERY])
        if frames.ndim == 3:  # grey frames [T, H, W]
            frames = frames[..., None]
        rgb = np.repeat(frames[..., :1], 3, axis=-1) if frames.shape[-1] < 3 else frames[..., :3]
        bins = COLOUR_LEVELS ** 3
        if not rgb.size:
            self.shares.append(np.full(bins, np.nan))
            self.pixel.append(np.nan)
            return
        # Each channel's value v falls in range (v * COLOUR_LEVELS) >> 8: OpenCV's histogram of equal ranges over
        # [0, 256), counted frame by frame (exact in its float32 counts) and summed.
        counts = np.zeros(bins, np.int64)
        levels = [COLOUR_LEVELS] * 3
        for frame in rgb:
            counts += cv2.calcHist([np.ascontiguousarray(frame)], [0, 1, 2], None, levels, [0, 256] * 3
                                   ).astype(np.int64).ravel()
        self.shares.append(counts / (len(rgb) * rgb.shape[1] * rgb.shape[2]))
        self.pixel.append(1.0 / (rgb.shape[1] * rgb.shape[2]))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """([N, bins] shares, [N] one pixel's share of a frame)."""
        bins = COLOUR_LEVELS ** 3
        return (np.stack(self.shares) if self.shares else np.zeros((0, bins)), np.asarray(self.pixel, np.float64))


# Colours in 4 ranges per channel (64 bins); per bin the log of the share of the pixels (plus one pixel's share,
# so that an absent colour is a finite number), its robust z within the task (a robust SD at least
# COLOUR_FLOOR log units: a factor of 1.28), root-mean-square over the bins the task or the demo shows (the task's
# median share or the demo's over one pixel a frame).  Each pixel counts in one bin (weights shared between
# neighbouring bins left specks of colour in bins the task never shows, which read as many robust SD); a whole
# camera's colour shift across a bin's edge still reads as a change (chosen on the development sets:
# docs/decisions.md, "Colours: in the ranking").
COLOUR_LEVELS = 4  # equal ranges per channel
COLOUR_FLOOR = 0.25  # log units: the least a robust SD of a bin's log share stands for
COLOUR_MIN_SCALE = 0.5  # a robust SD of the score within its task stands for at least half a robust SD of a bin


def colour_z(shares: np.ndarray, pixel: np.ndarray, tasks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per demo and colour bin ([N, bins] each): the robust z of the log share within the task, NaN where neither
    the task nor the demo shows the colour, and the task's median share there."""
    x = np.log(shares + pixel[:, None])
    z, median = task_z(x, tasks, COLOUR_FLOOR, VIEW_MIN_DEMOS, small="all")
    shown = (median > np.log(2.0 * pixel[:, None])) | (shares > pixel[:, None])
    typical = np.exp(median) - pixel[:, None]
    return np.where(shown, z, np.nan), np.where(typical < 0.5 * pixel[:, None], 0.0, typical)


def colour_rgb(bin_index: int) -> tuple[int, int, int]:
    """The middle of a colour bin of ``ColourStats``, 0-255 each."""
    step = 256 // COLOUR_LEVELS
    r, g, b = (bin_index // COLOUR_LEVELS ** 2, (bin_index // COLOUR_LEVELS) % COLOUR_LEVELS,
               bin_index % COLOUR_LEVELS)
    return tuple(c * step + step // 2 for c in (r, g, b))


HUES = ((15, "red"), (45, "orange"), (70, "yellow"), (160, "green"), (200, "cyan"), (260, "blue"),
        (320, "purple"), (345, "pink"), (360, "red"))  # the hue (degrees) each name reaches up to


def colour_name(bin_index: int) -> str:
    """A colour bin as a person names it, with its code: 'grey (#a0a0a0)', 'dark purple (#602060)'."""
    return named_colour(colour_rgb(bin_index))


def named_colour(rgb: tuple[int, int, int], code: bool = True) -> str:
    """An RGB colour (0-255 each) as a person names it, with its code where ``code``."""
    hue, saturation, value = colorsys.rgb_to_hsv(*(c / 255 for c in rgb))
    if value < 0.2:
        name = "black"
    elif saturation < 0.2:
        name = "white" if value > 0.85 else "light grey" if value > 0.6 else "grey" if value > 0.35 else "dark grey"
    else:
        name = next(n for top, n in HUES if hue * 360 < top)
        name = ("dark " if value < 0.5 else "pale " if saturation < 0.45 else "") + name
    return f"{name} (#{''.join(f'{c:02x}' for c in rgb)})" if code else name


HUE_BINS = 18  # hues of 20 degrees
SATURATED = 80  # of 255: a more saturated pixel has a hue worth naming; a less saturated one is a grey
BRIGHT = 128  # of 255: a brighter pixel is light, a darker one dark


def colour_bins(pixels: np.ndarray, hues: int = HUE_BINS) -> np.ndarray:
    """[n] the colour bin of each of ``pixels`` (uint8 RGB [n, 3]): ``hue * 4 + saturated * 2 + bright``."""
    if not len(pixels):
        return np.zeros(0, np.int64)
    hsv = cv2.cvtColor(np.ascontiguousarray(pixels[None], np.uint8), cv2.COLOR_RGB2HSV_FULL)[0].astype(np.int64)
    return hsv[:, 0] * hues // 256 * 4 + (hsv[:, 1] > SATURATED) * 2 + (hsv[:, 2] > BRIGHT)


def saturated(b: int) -> bool:
    """Whether a colour bin (``colour_bins``) holds saturated colours, a hue worth naming, not greys."""
    return bool((b // 2) % 2)


def bin_colour(b: int) -> str:
    """A colour bin (``colour_bins``) as a person names it: 'red', 'dark blue', 'light grey'."""
    rgb = colorsys.hsv_to_rgb((b // 4 + 0.5) / HUE_BINS, 0.8 if saturated(b) else 0.1, 0.85 if b % 2 else 0.35)
    return named_colour(tuple(int(255 * c) for c in rgb), code=False)


COLOURS = Vocabulary("colours", {
    "changed": lambda more, colour, share, median, z: (
        f"the view's colours changed: {'more' if more else 'less'} {colour} than its task's other demos: "
        f"{words.percent(share)} of the view against their median {words.percent(median)} ({z:.0f} robust SD)"),
    "like": "coloured like its task's other demos",
    "no frames": "no frames to compare",
})


def colours(stats: ColourStats, tasks: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """Robust z within its task of how differently the demo's frames are coloured from its task's other demos'
    (RMS over the colours shown of each colour's robust z, ``colour_z``); the reason names the colour that
    differs most and by how much."""
    shares, pixel = stats.arrays()
    tasks = np.asarray(tasks)
    if not len(shares):
        return np.zeros(0), []
    z, median = colour_z(shares, pixel, tasks)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a demo with no frames: NaN
        rms = np.sqrt(np.nanmean(z ** 2, axis=1))
    reasons = []
    for i in range(len(z)):
        if not np.isfinite(z[i]).any():
            reasons.append(COLOURS("no frames"))
            continue
        j = int(np.nanargmax(z[i]))
        if z[i, j] < 1:
            reasons.append(COLOURS("like"))
            continue
        more = shares[i, j] > median[i, j]
        reasons.append(COLOURS("changed", more=bool(more), colour=colour_name(j), share=float(shares[i, j]),
                               median=float(median[i, j]), z=float(z[i, j])))
    return calibrated(rms, tasks, min_scale=COLOUR_MIN_SCALE), reasons
