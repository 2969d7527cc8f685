"""Can a path's own shape tell a detour, where its distance from its task-mates' paths cannot?  Per planted kind,
the AUROC against the clean demos (and the share beyond every clean demo) of features that need no task-mate --
the path's length, the largest excess of a way through one point over the straight way, the furthest the path went
and came back -- beside the path check's state distance as shipped, and of the path less its first point or less
the straight line from its first point to its last.

    python benchmarks/path_shapes.py DATA [DATA ...]

Each demo's state at ``timeline.PATH_POINTS`` points, each dimension in units of its robust SD over every point of
every demo (at least ``timeline.STATE_FLOOR`` of its range); a feature's robust z within its task.  Labels from
``DATA.labels.csv`` or the dataset's sidecar.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from democheck.audit import timeline
from democheck.audit.metrics import separation
from democheck.data import open_dataset


def paths(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, PATH_POINTS, d] state paths, [N] labels, [N] tasks."""
    ds = open_dataset(root).without_camera()
    eps = ds.episodes
    labels = eps["label"] if "label" in eps else pd.read_csv(f"{root}.labels.csv").set_index("episode_index")["label"]
    state = []
    for e in eps.index:
        s = np.asarray(ds[e].state, np.float64)
        state.append(s.reshape(len(s), -1)[timeline._points(len(s))])
    return np.stack(state), eps.index.map(labels).fillna("clean").astype(str).to_numpy(), eps["task"].to_numpy()


def shape_features(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per demo of ``x`` [N, P, d] (in units): its length, the largest |ab| + |bc| - |ac| over ordered points a, b,
    c (half of it), and the largest min(|ab|, |bc|) - |ac| (out and back)."""
    d = np.linalg.norm(x[:, :, None] - x[:, None, :], axis=-1)  # [N, P, P]
    excess, back = np.zeros(len(x)), np.full(len(x), -np.inf)
    for b in range(1, x.shape[1] - 1):
        ab, bc, ac = d[:, :b, b][:, :, None], d[:, b, b + 1:][:, None, :], d[:, :b, b + 1:]
        excess = np.maximum(excess, ((ab + bc - ac) / 2).max(axis=(1, 2)))
        back = np.maximum(back, (np.minimum(ab, bc) - ac).max(axis=(1, 2)))
    return {"length": np.linalg.norm(np.diff(x, axis=1), axis=-1).sum(1), "excess": excess, "out and back": back}


def within_task(v: np.ndarray, tasks: np.ndarray) -> np.ndarray:
    z = np.full(len(v), np.nan)
    for t in np.unique(tasks):
        r = tasks == t
        med = np.median(v[r])
        z[r] = (v[r] - med) / max(1.4826 * np.median(np.abs(v[r] - med)), 1e-9)
    return z


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="+", type=Path)
    for root in ap.parse_args(argv).data:
        state, labels, tasks = paths(root)
        floor = timeline.state_floor(list(state))
        every = state.reshape(-1, state.shape[2])
        unit = np.fmax(1.4826 * np.median(np.abs(every - np.median(every, 0)), 0), floor)
        steps = np.linspace(0, 1, state.shape[1])[None, :, None]
        scores = {name: within_task(v, tasks) for name, v in shape_features(state / unit).items()}
        line = state[:, :1] + steps * (state[:, -1:] - state[:, :1])
        for name, x in (("path as shipped", state), ("path less its first point", state - state[:, :1]),
                        ("path less the straight line", state - line)):
            scores[name] = timeline._state_part(x, tasks, np.tile(floor, state.shape[1]))[1]
        for name, s in scores.items():
            print(f"{root.name:20s} {name:28s} " + separation(labels, s), flush=True)


if __name__ == "__main__":
    main()
