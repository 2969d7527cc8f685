"""The path check's AUROC per planted kind under each way of scoring a path: at 16 or 32 points, by the RMS distance
over the whole path, at its furthest point, or the larger robust z of the two (``timeline.PATH_DISTANCES``, what
the audit does).  Each dataset's timelines are decoded once, at 64 points, and subsampled.

    python benchmarks/path_variants.py DATA LABELS.csv [DATA LABELS.csv ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from democheck.audit import timeline
from democheck.audit.evidence import comparison_groups
from democheck.audit.metrics import detection
from democheck.data import open_dataset

DECODED = 64  # points decoded per demo; each variant takes an even subset


def path_scores(t: timeline.Timeline, groups: np.ndarray, points: int, distances: tuple[str, ...]) -> np.ndarray:
    """The path check's scores at ``points`` of the ``DECODED``, reading ``distances`` (``timeline.PATH_DISTANCES``)."""
    at = np.rint(np.linspace(0, DECODED - 1, points)).astype(int)
    sub = timeline.Timeline()
    for f in t.fields:
        setattr(sub, f, list(getattr(t, f)))
    sub.state_path = [p[at] for p in t.state_path]
    sub.view_path = [None if v is None else v[at] for v in t.view_path]
    saved = timeline.PATH_POINTS, timeline.PATH_DISTANCES
    timeline.PATH_POINTS, timeline.PATH_DISTANCES = points, distances
    try:
        return timeline.path(sub, groups)[0]
    finally:
        timeline.PATH_POINTS, timeline.PATH_DISTANCES = saved


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", nargs="+", type=Path, metavar="DATA LABELS.csv",
                    help="a dataset and its labels (episode_index,label; unlisted: clean), one pair after another")
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        ap.error("give each dataset its labels: DATA LABELS.csv [DATA LABELS.csv ...]")
    for data, labels in zip(args.pairs[::2], args.pairs[1::2]):
        t0 = time.perf_counter()
        ds = open_dataset(data)
        saved = timeline.PATH_POINTS
        timeline.PATH_POINTS = DECODED
        t = timeline.Timeline()
        for demo in ds:
            t.add(demo)
        timeline.PATH_POINTS = saved
        y = pd.read_csv(labels).set_index("episode_index")["label"].reindex(ds.episode_indices).fillna("clean")
        y = y.astype(str).to_numpy()
        groups = comparison_groups(ds.episodes["task"].to_numpy())
        clean = y == "clean"
        table = {}
        for points in (16, 32):
            for distances in (("whole",), ("furthest",), ("whole", "furthest")):
                s = np.nan_to_num(path_scores(t, groups, points, distances), nan=-1e9)
                table[f"{points} {'+'.join(distances)}"] = {
                    k: round(detection(np.r_[np.ones((y == k).sum(), bool), np.zeros(clean.sum(), bool)],
                                       np.r_[s[y == k], s[clean]])["auroc"], 3) for k in sorted(set(y) - {"clean"})}
        print(f"{data} ({time.perf_counter() - t0:.0f} s): AUROC of the path check against the clean demos")
        print(pd.DataFrame(table).to_string())


if __name__ == "__main__":
    main()
