"""Does recording more of the world make the audit worse?  A LeRobot dataset copied with extra environment-state
dimensions shaped like those real scenes record -- a quaternion whose sign flips between demos, a switch that ends
in either of two states, a drawer that ends open or closed, a knob's angle that wraps at +-pi, a fixed part whose
position is constant to float noise -- every demo, clean or bad, drawn alike, so the extra dimensions say nothing
about which demos are bad.  The copy's audit should rank and flag as the original's does.

    python benchmarks/shapes.py DATASET OUT [--seed S] [--audit]

writes OUT (the copy; ``DATASET``'s labels stay in ``meta/democheck/episodes.parquet``) and, with ``--audit``,
audits both without a model and prints, for each, the ranking's AUROC per planted kind against the clean demos
and the share of clean demos flagged at --fpr 0.01 with its binomial interval.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

KEY = "observation.environment_state"
EXTRA = ["lid.qw", "lid.qx", "lid.qy", "lid.qz", "switch", "drawer", "knob.angle", "fixture.x"]


def _quat(yaw: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """[T, 4] (w, x, y, z): a yaw about z, then a tilt about x."""
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    ct, st = np.cos(tilt / 2), np.sin(tilt / 2)
    return np.stack([cy * ct, cy * st, sy * st, sy * ct], 1)


def extra_dims(n: int, task: int, rng: np.random.Generator, seed: int) -> np.ndarray:
    """[n, len(EXTRA)] the extra dimensions of one demo of length n, drawn the same for every demo of a task."""
    task_rng = np.random.default_rng([seed, task])
    p_switch, p_open = task_rng.uniform(0.3, 0.7, 2)
    t = np.linspace(0, 1, n)[:, None]
    yaw0 = rng.uniform(-np.pi, np.pi)
    yaw = yaw0 + t[:, 0] * rng.normal(0, 0.3)
    tilt = np.zeros(n) + (t[:, 0] > 0.5) * (np.radians(25) if rng.random() < 0.02 else 0.0)
    q = _quat(yaw, tilt) * (-1 if rng.random() < 0.5 else 1) + rng.normal(0, 1e-6, (n, 4))
    switch = (t[:, 0] > rng.uniform(0.3, 0.7)) * float(rng.random() < p_switch)
    drawer = np.where(rng.random() < p_open, 0.15, 0.0) * np.minimum(1, 2 * t[:, 0]) + rng.normal(0, 0.002, n)
    knob = np.angle(np.exp(1j * (np.pi + rng.normal(0, 0.05) + 0.01 * t[:, 0])))
    fixture = 0.000462 + rng.normal(0, 1e-7, n)
    return np.column_stack([q, switch, drawer, knob, fixture]).astype(np.float32)


def write_copy(src: Path, out: Path, seed: int) -> None:
    shutil.copytree(src, out)
    info = json.loads((out / "meta/info.json").read_text())
    feature = info["features"][KEY]
    rng = np.random.default_rng(seed)
    columns = []
    for path in sorted((out / "data").rglob("*.parquet")):
        table = pq.read_table(path)
        env = np.asarray(table[KEY].combine_chunks().flatten(), np.float32).reshape(table.num_rows, -1)
        ep = table["episode_index"].to_numpy()
        task = table["task_index"].to_numpy()
        extra = np.zeros((table.num_rows, len(EXTRA)), np.float32)
        for e in np.unique(ep):
            rows = np.flatnonzero(ep == e)
            extra[rows] = extra_dims(len(rows), int(task[rows[0]]), rng, seed)
        full = np.concatenate([env, extra], 1)
        columns.append(full)
        arr = pa.FixedSizeListArray.from_arrays(pa.array(full.ravel(), pa.float32()), full.shape[1])
        pq.write_table(table.set_column(table.column_names.index(KEY), KEY, arr), path)
    feature["shape"] = [len(feature["names"]) + len(EXTRA)]
    feature["names"] = list(feature["names"]) + EXTRA
    (out / "meta/info.json").write_text(json.dumps(info, indent=2))
    stats = json.loads((out / "meta/stats.json").read_text())
    x = np.concatenate(columns)
    stats[KEY] = {"mean": x.mean(0).tolist(), "std": x.std(0).tolist(), "min": x.min(0).tolist(),
                  "max": x.max(0).tolist(), "count": [len(x)]}
    (out / "meta/stats.json").write_text(json.dumps(stats))


def measure(dataset: Path, audit: Path) -> dict:
    import pandas as pd
    from scipy.stats import binom
    from sklearn.metrics import roc_auc_score

    subprocess.run([sys.executable, "-m", "democheck", "audit", str(dataset), "--out", str(audit), "--no-model", "--force"], check=True,
                   capture_output=True)
    t = pd.read_parquet(audit / "scores.parquet")
    clean = t.label == "clean"
    s = t.suspicion.to_numpy(np.float64)
    s = np.where(np.isnan(s), -np.inf, s)
    out = {k: round(roc_auc_score(np.r_[np.ones((t.label == k).sum()), np.zeros(clean.sum())],
                                  np.r_[s[t.label == k], s[clean]]), 4) for k in sorted(set(t.label) - {"clean"})}
    n, f = int(clean.sum()), int(t.is_anomaly[clean].sum())
    out["clean flagged"] = f"{f}/{n} ({f / n:.1%}; 95% binomial interval at 0.01: {binom.interval(0.95, n, 0.01)})"
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--audit", action="store_true")
    args = ap.parse_args()
    if not args.out.exists():
        write_copy(args.dataset, args.out, args.seed)
    if args.audit:
        for name, ds in (("original", args.dataset), ("with the extra dimensions", args.out)):
            print(name, json.dumps(measure(ds, args.out.parent / f"{args.out.name}-audit-{name.split()[0]}")))


if __name__ == "__main__":
    main()
