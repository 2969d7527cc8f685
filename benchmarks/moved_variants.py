"""The ``moved`` check alone under each way of reading what changed between a demo's first and last picture: the
pictures' side, the change threshold, the hue bins, the first and last pictures' colours counted together or apart,
and how a demo's colours are put together (RMS over the colours shown or over all, the largest, the RMS of the four
largest).  AUROC per planted kind against the clean demos, and the share of each kind beyond every clean demo.

    python benchmarks/moved_variants.py DATA [DATA ...]

Each dataset's first and last pictures are decoded once (``DemoSet.cue_frames``) at 64 px and made smaller for the
32 px variant; labels come from the dataset's sidecar or ``DATA.labels.csv``.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from democheck.audit import colours, moved
from democheck.audit.metrics import separation
from democheck.audit.scores import calibrated
from democheck.data import open_dataset

DEFAULT = dict(side=64, change=moved.MOVED_CHANGE, hues=colours.HUE_BINS, apart=False, combine="rms shown")
VARIANTS = {
    "shipped": {},
    "32 px": dict(side=32),
    "change 20": dict(change=20), "change 45": dict(change=45),
    "12 hues": dict(hues=12), "24 hues": dict(hues=24),
    "first and last apart": dict(apart=True),
    "rms of all": dict(combine="rms all"), "largest": dict(combine="largest"), "four largest": dict(combine="top 4"),
}


def labelled_pictures(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, 2, 64, 64, 3] first and last pictures, [N] labels, [N] tasks."""
    ds = open_dataset(root)
    eps = ds.episodes
    labels = eps["label"] if "label" in eps else pd.read_csv(f"{root}.labels.csv").set_index("episode_index")["label"]
    pictures = np.stack([[cv2.resize(np.ascontiguousarray(f[..., :3]), (64, 64), interpolation=cv2.INTER_AREA)
                          for f in ds.cue_frames(e)] for e in eps.index])
    return pictures, eps.index.map(labels).fillna("clean").astype(str).to_numpy(), eps["task"].to_numpy()


def counts(first: np.ndarray, last: np.ndarray, change: int, hues: int, apart: bool) -> np.ndarray:
    pictures = moved.changed_pixels(first, last, change)
    per = [np.bincount(colours.colour_bins(p, hues), minlength=hues * 4).astype(float) for p in pictures]
    return np.concatenate(per) if apart else per[0] + per[1]


def scores(pictures: np.ndarray, tasks: np.ndarray, side: int, change: int, hues: int, apart: bool, combine: str
           ) -> np.ndarray:
    small = [[cv2.resize(p, (side, side), interpolation=cv2.INTER_AREA) for p in pair] for pair in pictures]
    root = np.sqrt(np.stack([counts(f, last, change, hues, apart) for f, last in small]))
    shown, _ = moved.colour_z(root, tasks, moved.MOVED_FLOOR * side / moved.MOVED_SIZE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        top = -np.sort(-np.nan_to_num(shown), axis=1)
        value = {"rms shown": np.sqrt(np.nanmean(shown ** 2, axis=1)),
                 "rms all": np.sqrt(np.mean(np.nan_to_num(shown) ** 2, axis=1)),
                 "largest": top[:, 0], "top 4": np.sqrt(np.mean(top[:, :4] ** 2, axis=1))}[combine]
    return calibrated(np.nan_to_num(value), tasks, min_scale=moved.MOVED_MIN_SCALE)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", type=Path)
    args = ap.parse_args(argv)
    for root in args.data:
        pictures, labels, tasks = labelled_pictures(root)
        for name, change in VARIANTS.items():
            print(f"{root.name:28s} {name:22s} " + separation(labels, scores(pictures, tasks, **{**DEFAULT, **change})),
                  flush=True)


if __name__ == "__main__":
    main()
