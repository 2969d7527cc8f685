"""A copy of a LeRobot dataset without its environment-state columns, as real recordings come (they record the
robot's joints and cameras, not where the objects are).

    python benchmarks/without_env_state.py DATA OUT

Every file is linked (or copied where links cannot be made) but the data files, which are written again without
the ``observation.environment_state`` column (and any other ``observation.environment*`` feature), and
``meta/info.json`` and ``meta/stats.json``, which drop them too.  democheck's own sidecar (labels, sim records) is
kept, so an audit of the copy is scored against the same labels.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import pyarrow.parquet as pq


def environment_keys(info: dict) -> list[str]:
    return [k for k in info.get("features", {}) if k.startswith("observation.environment")]


def strip(src: Path, out: Path) -> list[str]:
    """Write ``out``: ``src`` without its environment-state features; returns the features dropped."""
    info = json.loads((src / "meta/info.json").read_text())
    drop = environment_keys(info)
    if out.exists():
        shutil.rmtree(out)
    for path in sorted(src.rglob("*")):
        target = out / path.relative_to(src)
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        rel = path.relative_to(src).as_posix()
        if rel.startswith("data/") and path.suffix == ".parquet":
            table = pq.read_table(path)
            pq.write_table(table.drop_columns([c for c in drop if c in table.column_names]), target)
        elif rel == "meta/info.json":
            info["features"] = {k: v for k, v in info["features"].items() if k not in drop}
            target.write_text(json.dumps(info, indent=4))
        elif rel == "meta/stats.json":
            stats = json.loads(path.read_text())
            target.write_text(json.dumps({k: v for k, v in stats.items() if k not in drop}, indent=4))
        else:
            try:
                os.link(path, target)
            except OSError:
                shutil.copy2(path, target)
    return drop


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    dropped = strip(args.data, args.out)
    print(f"{args.out}: {args.data} without {', '.join(dropped) or 'nothing (it records no environment state)'}")


if __name__ == "__main__":
    main()
