"""Plant sensor and recording faults in a copy of a LeRobot v3.0 dataset, by editing its data parquet only (the
videos and the metadata stay as they are), and write the labels beside the copy:

    python benchmarks/foreign/plant_faults.py data/foreign/mw3-dev data/foreign/mw3-dev.labels.csv OUT \
        --seed 41 --per-kind 6 [--kinds dead-dim,frozen-state,scaled,sensor-nan]

Each kind replaces ``--per-kind`` of the demos the labels call clean (drawn by the seed):

- ``dead-dim``: one state dimension that moves in the demo reads its first value the whole demo (an encoder that
  died);
- ``frozen-state``: the whole state holds its value from 30-60% of the demo on while the actions go on (the
  state stream stopped updating);
- ``scaled``: the actions recorded x3 (another unit, or another gain);
- ``sensor-nan``: 3-10 consecutive steps of one state dimension read NaN (a sensor that dropped out).

OUT.labels.csv holds every demo's label (the source's, with the planted kinds in place of ``clean``).  The same
seed and kinds give the same copy.  What democheck made of these: ``democheck.audit.sensors`` and the README.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

KINDS = ("dead-dim", "frozen-state", "scaled", "sensor-nan")
STATE, ACTION = "observation.state", "action"


def plan(labels: pd.Series, kinds: list[str], per_kind: int, rng: np.random.Generator) -> dict[int, str]:
    """Which clean demo gets which kind."""
    clean = labels[labels == "clean"].index.to_numpy()
    if len(clean) < per_kind * len(kinds):
        raise SystemExit(f"{len(clean)} clean demos: too few for {per_kind} of each of {len(kinds)} kinds")
    chosen = rng.choice(clean, size=per_kind * len(kinds), replace=False)
    return {int(e): kinds[i // per_kind] for i, e in enumerate(chosen)}


def plant(state: np.ndarray, actions: np.ndarray, kind: str, rng: np.random.Generator) -> None:
    """One demo's rows of state [T, S] and actions [T, A], changed in place."""
    n = len(state)
    if kind == "dead-dim":
        j = rng.choice(np.flatnonzero(state.std(0) > 1e-3))
        state[:, j] = state[0, j]
    elif kind == "frozen-state":
        at = int(n * rng.uniform(0.3, 0.6))
        state[at:] = state[at]
    elif kind == "scaled":
        actions *= 3.0
    elif kind == "sensor-nan":
        length = int(rng.integers(3, 11))
        at = int(rng.integers(1, max(n - length, 2)))
        state[at:at + length, int(rng.integers(state.shape[1]))] = np.nan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", type=Path, help="a LeRobot v3.0 dataset")
    ap.add_argument("labels", type=Path, help="its labels (episode_index,label)")
    ap.add_argument("out", type=Path, help="where the copy goes (replaced)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--per-kind", type=int, default=6)
    ap.add_argument("--kinds", default="dead-dim,frozen-state,scaled", help=f"comma-separated, of {', '.join(KINDS)}")
    args = ap.parse_args()
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        raise SystemExit(f"unknown kind {', '.join(unknown)}; kinds: {', '.join(KINDS)}")
    rng = np.random.default_rng(args.seed)
    labels = pd.read_csv(args.labels).set_index("episode_index")["label"]
    todo = plan(labels, kinds, args.per_kind, rng)
    shutil.rmtree(args.out, ignore_errors=True)
    shutil.copytree(args.source, args.out)
    for path in sorted(args.out.glob("data/*/*.parquet")):
        table = pq.read_table(path)
        frame = table.to_pandas()
        state = np.stack(frame[STATE].to_numpy()).astype(np.float32)
        actions = np.stack(frame[ACTION].to_numpy()).astype(np.float32)
        episode = frame["episode_index"].to_numpy()
        for e, kind in todo.items():
            rows = np.flatnonzero(episode == e)
            if len(rows):
                s, a = state[rows], actions[rows]
                plant(s, a, kind, rng)
                state[rows], actions[rows] = s, a
        frame[STATE], frame[ACTION] = list(state), list(actions)
        pq.write_table(pa.Table.from_pandas(frame, preserve_index=False).cast(table.schema), path)
    out = labels.copy()
    for e, kind in todo.items():
        out[e] = kind
    out.reset_index().to_csv(args.out.with_name(args.out.name + ".labels.csv"), index=False)
    print(f"{args.out}: " + ", ".join(f"{k} {sum(v == k for v in todo.values())}" for k in kinds))


if __name__ == "__main__":
    main()
