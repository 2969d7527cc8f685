"""The path check's AUROC per planted kind under each way of scoring a path: at 16 or 32 points, by the RMS distance
over the whole path, at its furthest point, or the larger robust z of the two (``timeline.PATH_DISTANCES``, what
the audit does); and its state part in normalised time against dynamic time warping (``dtw_scores``), with how much
each reads the episode's length (the clean demos' Spearman correlation with it, within task).  Each dataset's
timelines are decoded once, at 64 points, and subsampled.

    python benchmarks/path_variants.py DATA LABELS.csv [DATA LABELS.csv ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from democheck.audit import neighbours, timeline
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


def dtw_scores(t: timeline.Timeline, groups: np.ndarray, points: int, band: float | None = None) -> np.ndarray:
    """The path's state part by dynamic time warping instead of normalised time: each state dimension in units of
    its task's robust SD over every point (at least ``timeline.STATE_FLOOR`` of its range), the mean cost of the best
    monotone alignment of two paths (steps of one point on either or both; within ``band`` x ``points`` of the
    diagonal where given), the median over the ``neighbours.NEAR`` nearest task-mates, and its robust z of log1p
    within the task, as the audit scores its distances."""
    from democheck.audit.scores import calibrated

    at = np.rint(np.linspace(0, DECODED - 1, points)).astype(int)
    x_all = timeline.stacked_states([p[at] if len(p) else p for p in t.state_path], slice(None))[:, :points]
    floor = timeline.state_floor(t.state_path)
    dist = np.full(len(x_all), np.nan)
    for rows in neighbours.grouped(groups):
        x = np.nan_to_num(x_all[rows])
        med = np.median(x.reshape(-1, x.shape[2]), axis=0)
        unit = np.fmax(1.4826 * np.median(np.abs(x.reshape(-1, x.shape[2]) - med), axis=0), floor)
        x = np.clip((x - med) / unit, -neighbours.CLIP, neighbours.CLIP)
        n = len(rows)
        i, j = np.triu_indices(n, 1)
        cost = ((x[i][:, :, None, :] - x[j][:, None, :, :]) ** 2).mean(axis=3)  # [pairs, T, T]
        if band is not None:
            off = np.abs(np.arange(points)[:, None] - np.arange(points)[None, :]) > max(1, int(band * points))
            cost = np.where(off[None], np.inf, cost)
        acc = np.full((len(i), points + 1, points + 1), np.inf)
        acc[:, 0, 0] = 0.0
        for a in range(1, points + 1):
            for b in range(1, points + 1):
                acc[:, a, b] = cost[:, a - 1, b - 1] + np.minimum(np.minimum(acc[:, a - 1, b], acc[:, a, b - 1]),
                                                                  acc[:, a - 1, b - 1])
        d = np.zeros((n, n))
        d[i, j] = d[j, i] = np.sqrt(acc[:, points, points] / (2 * points))
        np.fill_diagonal(d, np.inf)
        k = max(1, min(neighbours.NEAR, (n - 1) // 2))
        dist[rows] = np.median(np.sort(d, axis=1)[:, :k], axis=1)
    return calibrated(np.log1p(dist), groups, min_scale=timeline.STATE_MIN_SCALE)


def state_only_scores(t: timeline.Timeline, groups: np.ndarray, points: int) -> np.ndarray:
    """The path's state part alone in normalised time, as the audit scores it (both distances): the baseline
    ``dtw_scores`` is set against (the audit's path also reads the camera's)."""
    at = np.rint(np.linspace(0, DECODED - 1, points)).astype(int)
    x = timeline.stacked_states([p[at] if len(p) else p for p in t.state_path], slice(None))[:, :points]
    saved = timeline.PATH_POINTS
    timeline.PATH_POINTS = points
    try:
        return timeline._state_part(x, groups, np.tile(timeline.state_floor(t.state_path), points))[1]
    finally:
        timeline.PATH_POINTS = saved


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
        lengths = ds.episodes["length"].to_numpy(np.float64)
        state = {}
        for name, s in (("32 state, normalised time", state_only_scores(t, groups, 32)),
                        ("32 state, DTW", dtw_scores(t, groups, 32)),
                        ("32 state, DTW within 10%", dtw_scores(t, groups, 32, band=0.1))):
            s = np.nan_to_num(s, nan=-1e9)
            row = {k: round(detection(np.r_[np.ones((y == k).sum(), bool), np.zeros(clean.sum(), bool)],
                                      np.r_[s[y == k], s[clean]])["auroc"], 3) for k in sorted(set(y) - {"clean"})}
            # does the score read the length? Spearman of the clean demos' scores with their length, within task
            rho = pd.DataFrame({"s": s[clean], "n": lengths[clean], "g": groups[clean]}).groupby("g").apply(
                lambda d: d["s"].rank().corr(d["n"].rank()), include_groups=False)
            state[name] = {**row, "clean: rho with length": round(float(np.nanmean(rho)), 2) if np.isfinite(rho).any() else None}
        print(f"{data} ({time.perf_counter() - t0:.0f} s): AUROC of the path check against the clean demos")
        print(pd.DataFrame(table).to_string())
        print("the state part alone: normalised time against dynamic time warping")
        print(pd.DataFrame(state).to_string())


if __name__ == "__main__":
    main()
