"""A copy of a LeRobot dataset without its environment-state columns, as real recordings come (they record the
robot's joints and cameras, not where the objects are).

    python benchmarks/without_env_state.py DATA OUT [--state DIMS]

Every file is linked (or copied where links cannot be made) but the data files, which are written again without
the ``observation.environment_state`` column (and any other ``observation.environment*`` feature), and
``meta/info.json`` and ``meta/stats.json``, which drop them too.  democheck's own sidecar (labels, sim records) is
kept, so an audit of the copy is scored against the same labels.

A simulator may put the objects in ``observation.state`` too (Fetch's block and goal, Meta-World's puck).
``--state`` keeps only the state dimensions it lists -- names the dataset gives them (``grip.x,finger.left``) or
indices and ranges (``0-3``) -- in the data, ``info.json``, ``stats.json`` and the per-episode statistics (v3.0's
and v2.1's): the robot's own state alone, as a teleoperated recording has it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

STATE = "observation.state"


def environment_keys(info: dict) -> list[str]:
    return [k for k in info.get("features", {}) if k.startswith("observation.environment")]


def state_dims(info: dict, spec: str) -> list[int]:
    """The state dimensions ``spec`` lists (names, indices, ``a-b`` ranges; comma-separated), in the state's order."""
    names = info["features"][STATE].get("names")
    width = info["features"][STATE]["shape"][0]
    keep: set[int] = set()
    for part in (p.strip() for p in spec.split(",") if p.strip()):
        if isinstance(names, list) and part in names:
            keep.add(names.index(part))
        elif part.replace("-", "").isdigit():
            a, _, b = part.partition("-")
            keep.update(range(int(a), int(b or a) + 1))
        else:
            raise SystemExit(f"--state: {part!r} is neither a state name ({names}) nor an index")
    if not keep or max(keep) >= width:
        raise SystemExit(f"--state: the state has {width} dimensions")
    return sorted(keep)


def _cut(column: pa.ChunkedArray, keep: list[int]) -> pa.Array:
    """A list column (one vector a row) with only the elements ``keep``, its list type kept (fixed size or not)."""
    rows = np.stack(column.to_numpy(zero_copy_only=False))[:, keep]
    value = column.type.value_type
    kind = pa.list_(value, len(keep)) if pa.types.is_fixed_size_list(column.type) else pa.list_(value)
    return pa.array(list(rows), type=kind)


def _cut_table(table: pa.Table, keep: list[int]) -> pa.Table:
    """The state column, and the per-episode statistics' state columns, cut to ``keep``."""
    for i, name in enumerate(table.column_names):
        if name == STATE or (name.startswith(f"stats/{STATE}/") and not name.endswith("/count")):
            table = table.set_column(i, name, _cut(table[name], keep))
    return table


def _cut_stats(stats: dict, keep: list[int]) -> dict:
    """A feature's statistics (min, max, mean, ... one value a dimension; count one for all) cut to ``keep``."""
    return {k: (v if k == "count" else [v[j] for j in keep]) for k, v in stats.items()}


def strip(src: Path, out: Path, state: list[int] | None = None) -> list[str]:
    """Write ``out``: ``src`` without its environment-state features (and with only the ``state`` dimensions of
    its state, where given); returns the features dropped."""
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
            table = table.drop_columns([c for c in drop if c in table.column_names])
            pq.write_table(_cut_table(table, state) if state else table, target)
        elif rel.startswith("meta/episodes/") and path.suffix == ".parquet" and state:
            pq.write_table(_cut_table(pq.read_table(path), state), target)
        elif rel == "meta/episodes_stats.jsonl" and state:  # LeRobot v2.1's per-episode statistics
            rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
            for row in rows:
                if STATE in row.get("stats", {}):
                    row["stats"][STATE] = _cut_stats(row["stats"][STATE], state)
            target.write_text("".join(json.dumps(row) + "\n" for row in rows))
        elif rel == "meta/info.json":
            info["features"] = {k: v for k, v in info["features"].items() if k not in drop}
            if state:
                feature = info["features"][STATE]
                feature["shape"] = [len(state)]
                names = feature.get("names")  # a flat list is cut; another form cannot be, and goes
                feature["names"] = [names[j] for j in state] if isinstance(names, list) else None
            target.write_text(json.dumps(info, indent=4))
        elif rel == "meta/stats.json":
            stats = {k: v for k, v in json.loads(path.read_text()).items() if k not in drop}
            if state and STATE in stats:
                stats[STATE] = _cut_stats(stats[STATE], state)
            target.write_text(json.dumps(stats, indent=4))
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
    ap.add_argument("--state", default="", help="keep only these state dimensions: names or indices and ranges "
                                                "(grip.x,grip.y or 0-3), comma-separated")
    args = ap.parse_args(argv)
    info = json.loads((args.data / "meta/info.json").read_text())
    state = state_dims(info, args.state) if args.state else None
    dropped = strip(args.data, args.out, state)
    print(f"{args.out}: {args.data} without {', '.join(dropped) or 'nothing (it records no environment state)'}"
          + (f"; the state cut to dimensions {state}" if state else ""))


if __name__ == "__main__":
    main()
