"""Are two runs' numbers the same?  Compares what two output folders of one democheck command hold.

    python benchmarks/same_numbers.py OLD NEW [OLD2 NEW2 ...]

For each pair of folders (a bench, an audit report, an eval, a model), every
file both have among bench.json, eval.json, summary.json, scores.parquet,
trials.parquet, suspects.txt and model.safetensors is compared exactly:
JSON value by value, tables column by column (dtype included), tensors bit
for bit.  Names democheck renamed (``RENAMED``) are matched across, and
what a run records about itself (wall time, speed, paths) is left out.
Exit status 1 when anything differs.  This is how a refactor shows that the
shipped model's numbers did not move.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

# Old name -> new name, for outputs made before the scorer registry.
RENAMED = {"score": "task_uncertainty", "sigma": "task_uncertainty", "sigma_head": "task_uncertainty_head",
           "sigma_vec": "sigma", "embed": "task_matching", "broken": "broken_cue"}
# What a run records about itself, and prose: the scores' definitions in summary.json, the scorers' notes.
SELF = {"wall_s", "rollouts_per_s", "model", "datasets", "dataset", "tecnet", "timing", "notes", "command",
        "commit", "path", "scores"}


def _json(a, b, where: str) -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k, v in a.items():
            if k in SELF:
                continue
            k2 = k if k in b else RENAMED.get(k, k)
            out += _json(v, b[k2], f"{where}/{k}") if k2 in b else [f"{where}/{k}: not in the new run"]
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items, now {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _json(x, y, f"{where}[{i}]")]
    if isinstance(a, str) and RENAMED.get(a) == b:
        return []
    return [] if a == b else [f"{where}: {a!r}, now {b!r}"]


def _column(x: pd.Series, y: pd.Series) -> bool:
    if x.dtype == object and len(x) and isinstance(x.iloc[0], np.ndarray):
        return np.array_equal(np.stack(x.to_numpy()), np.stack(y.to_numpy()))
    if x.dtype.kind in "fc":
        return x.dtype == y.dtype and np.array_equal(x.to_numpy(), y.to_numpy(), equal_nan=True)
    return x.astype(str).equals(y.astype(str))


def _table(a: pd.DataFrame, b: pd.DataFrame, where: str) -> list[str]:
    if len(a) != len(b):
        return [f"{where}: {len(a)} rows, now {len(b)}"]
    out = []
    # Old benches and evals held "sigma" (the scalar) beside "sigma_vec"; now "sigma" is the vector everywhere.
    moved = "sigma_vec" in a and "sigma_vec" not in b
    for col in (c for c in a.columns if c not in SELF):
        new = RENAMED.get(col, col) if col not in b or (moved and col == "sigma") else col
        if new not in b:
            out.append(f"{where}:{col}: not in the new run")
        elif not _column(a[col], b[new]):
            out.append(f"{where}:{col}: differs")
    return out


def compare(old: Path, new: Path) -> tuple[list[str], list[str]]:
    """(files compared, differences) of two output folders."""
    seen, diffs = [], []
    for name in ("bench.json", "eval.json", "summary.json"):
        if (old / name).exists() and (new / name).exists():
            seen.append(name)
            diffs += _json(json.loads((old / name).read_text()), json.loads((new / name).read_text()), name)
    for name in ("scores.parquet", "trials.parquet"):
        if (old / name).exists() and (new / name).exists():
            seen.append(name)
            diffs += _table(pd.read_parquet(old / name), pd.read_parquet(new / name), name)
    if (old / "suspects.txt").exists() and (new / "suspects.txt").exists():
        seen.append("suspects.txt")
        if (old / "suspects.txt").read_text() != (new / "suspects.txt").read_text():
            diffs.append("suspects.txt differs")
    if (old / "model.safetensors").exists() and (new / "model.safetensors").exists():
        from safetensors.numpy import load_file

        seen.append("model.safetensors")
        x, y = load_file(str(old / "model.safetensors")), load_file(str(new / "model.safetensors"))
        diffs += [f"model.safetensors:{k}" for k in sorted(set(x) | set(y))
                  if k not in x or k not in y or not np.array_equal(x[k], y[k])]
    return seen, diffs


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", help="OLD NEW [OLD2 NEW2 ...]")
    args = ap.parse_args().folders
    if len(args) % 2:
        sys.exit(__doc__)
    bad = 0
    for old, new in zip(args[::2], args[1::2]):
        seen, diffs = compare(Path(old), Path(new))
        print(f"{old} -> {new}: {', '.join(seen) or 'nothing to compare'}: "
              + ("identical" if not diffs else f"{len(diffs)} differences"))
        for d in diffs[:40]:
            print(f"    {d}")
        bad += bool(diffs) or not seen
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
