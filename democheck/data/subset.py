"""A LeRobot v3.0 dataset without some of its episodes (``democheck clean``).

The kept episodes are copied, not re-made: every data column they have is kept, episodes and frames are
re-indexed from 0 in their old order, and their videos are the source's files, copied whole -- an episode's
video is a time range of a file, so the kept ranges decode to exactly the frames they did (the dropped ranges
stay in the files, unreferenced).  ``meta/``: ``info.json`` totals and splits, the episodes table (renumbered,
with each episode's new data rows), ``stats.json`` pooled from the kept episodes' own statistics, the tasks as
they were, and democheck's sidecar where there is one.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from democheck.data.lerobot import DATA_PATH, EPISODES_PATH, SIDECAR_PATH, SUITE_PATH
from democheck.errors import DatasetError


def _episodes_table(root: Path) -> pd.DataFrame:
    files = sorted((root / "meta" / "episodes").rglob("*.parquet"))
    if not files:
        raise DatasetError(f"{root}: no meta/episodes/*.parquet; democheck clean writes LeRobot v3.0 datasets only")
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True).sort_values("episode_index")


def pooled_stats(per_episode: list[dict[str, np.ndarray]]) -> dict[str, Any]:
    """One feature's statistics over several episodes from each episode's own (mean, std, min, max, count and any
    quantiles q01..q99): exact for the moments and the extremes (pooled variance), count-weighted for quantiles."""
    counts = np.array([float(np.ravel(p["count"])[0]) for p in per_episode])
    w = counts / counts.sum()
    shape = np.asarray(per_episode[0]["mean"]).shape
    mean = sum(wi * np.asarray(p["mean"], np.float64) for wi, p in zip(w, per_episode))
    second = sum(wi * (np.asarray(p["std"], np.float64) ** 2 + np.asarray(p["mean"], np.float64) ** 2)
                 for wi, p in zip(w, per_episode))
    out: dict[str, Any] = {
        "mean": mean, "std": np.sqrt(np.maximum(second - mean ** 2, 0.0)),
        "min": np.min([np.asarray(p["min"], np.float64) for p in per_episode], axis=0),
        "max": np.max([np.asarray(p["max"], np.float64) for p in per_episode], axis=0),
        "count": np.array([int(counts.sum())]),
    }
    for key in per_episode[0]:
        if key.startswith("q") and key[1:].isdigit():
            out[key] = sum(wi * np.asarray(p[key], np.float64) for wi, p in zip(w, per_episode))
    return {k: np.asarray(v).reshape(shape if k != "count" else (1,)).tolist() for k, v in out.items()}


def _stats(episodes: pd.DataFrame, source_stats: dict[str, Any]) -> dict[str, Any]:
    """stats.json of the kept episodes: pooled from their ``stats/<feature>/<stat>`` columns; a feature the
    episodes table has no statistics for keeps the source's."""
    out = dict(source_stats)
    features = {c.split("/")[1] for c in episodes.columns if c.startswith("stats/")}
    for feature in features:
        cols = {c.split("/")[2]: c for c in episodes.columns if c.startswith(f"stats/{feature}/")}
        if not {"mean", "std", "min", "max", "count"} <= set(cols):
            continue
        per = [{stat: _array(row[col]) for stat, col in cols.items()} for _, row in episodes.iterrows()]
        out[feature] = pooled_stats(per)
    return out


def _array(value: Any) -> np.ndarray:
    """A statistic as parquet gives it back (nested object arrays for [3, 1, 1] image stats) as a float array."""
    if isinstance(value, np.ndarray) and value.dtype == object:
        return np.array([_array(v) for v in value], np.float64)
    return np.asarray(value, np.float64)


def _splits(splits: dict[str, str], renumber: dict[int, int]) -> dict[str, str]:
    """``start:stop`` episode ranges over the kept episodes, renumbered (order is kept, so a range stays one)."""
    out = {}
    for name, span in splits.items():
        try:
            start, stop = (int(x) for x in str(span).split(":"))
        except ValueError:
            continue
        kept = [renumber[e] for e in range(start, stop) if e in renumber]
        if kept:
            out[name] = f"{kept[0]}:{kept[-1] + 1}"
    return out


def write_subset(src: Path, keep: list[int], out: Path) -> dict[str, Any]:
    """Write the episodes ``keep`` of the v3.0 dataset ``src`` as a dataset in the (empty, temporary) folder
    ``out``; returns {"kept", "dropped", "frames"}."""
    info = json.loads((src / "meta" / "info.json").read_text())
    if info.get("codebase_version") != "v3.0":
        raise DatasetError(f"{src}: codebase_version {info.get('codebase_version')!r}; democheck clean writes "
                           "LeRobot v3.0 datasets only")
    episodes = _episodes_table(src)
    unknown = sorted(set(keep) - set(episodes["episode_index"]))
    if unknown:
        raise DatasetError(f"{src}: episode {unknown[0]} is not in the dataset")
    kept = episodes[episodes["episode_index"].isin(keep)].reset_index(drop=True)
    renumber = {int(e): i for i, e in enumerate(kept["episode_index"])}
    data_template = info.get("data_path", DATA_PATH)

    # Data: each file's kept rows, renumbered, frames re-indexed in order; a file left empty is not written.
    start, first_row = 0, {}
    files = kept[["data/chunk_index", "data/file_index"]].drop_duplicates().sort_values(
        ["data/chunk_index", "data/file_index"])
    for chunk, file in files.itertuples(index=False):
        rel = data_template.format(chunk_index=int(chunk), file_index=int(file))
        table = pq.read_table(src / rel)
        old = table.column("episode_index").to_numpy()
        mask = np.isin(old, list(renumber))
        table = table.filter(pa.array(mask))
        new_ep = np.array([renumber[int(e)] for e in old[mask]], np.int64)
        order = np.lexsort((table.column("frame_index").to_numpy(), new_ep)) if "frame_index" in table.column_names \
            else np.argsort(new_ep, kind="stable")
        table = table.take(pa.array(order))
        new_ep = new_ep[order]
        table = table.set_column(table.column_names.index("episode_index"), "episode_index", pa.array(new_ep))
        if "index" in table.column_names:
            table = table.set_column(table.column_names.index("index"), "index",
                                     pa.array(np.arange(start, start + len(table), dtype=np.int64)))
        for e in np.unique(new_ep):
            first_row[int(e)] = start + int(np.argmax(new_ep == e))
        start += len(table)
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, out / rel)

    # Videos: the files the kept episodes point into, whole (of the video features info.json names).
    for key in [k for k, f in info.get("features", {}).items()
                if isinstance(f, dict) and f.get("dtype") == "video" and f"videos/{k}/chunk_index" in kept]:
        template = info.get("video_path", "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4")
        for chunk, file in kept[[f"videos/{key}/chunk_index", f"videos/{key}/file_index"]].drop_duplicates() \
                .itertuples(index=False):
            rel = template.format(video_key=key, chunk_index=int(chunk), file_index=int(file))
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, out / rel)

    lengths = kept["length"].to_numpy(np.int64)
    kept["episode_index"] = np.arange(len(kept), dtype=np.int64)
    kept["dataset_from_index"] = [first_row[i] for i in range(len(kept))]
    kept["dataset_to_index"] = kept["dataset_from_index"] + lengths
    for col in ("meta/episodes/chunk_index", "meta/episodes/file_index"):
        if col in kept:
            kept[col] = 0
    (out / EPISODES_PATH).parent.mkdir(parents=True, exist_ok=True)
    kept.to_parquet(out / EPISODES_PATH, index=False)
    shutil.copy2(src / "meta" / "tasks.parquet", out / "meta" / "tasks.parquet")
    source_stats = json.loads((src / "meta" / "stats.json").read_text()) if (src / "meta" / "stats.json").exists() \
        else {}
    (out / "meta" / "stats.json").write_text(json.dumps(_stats(kept, source_stats), indent=2))
    info = {**info, "total_episodes": len(kept), "total_frames": int(lengths.sum()),
            "splits": _splits(info.get("splits") or {}, renumber) or {"train": f"0:{len(kept)}"}}
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    if (src / SIDECAR_PATH).exists():
        side = pd.read_parquet(src / SIDECAR_PATH)
        side = side[side["episode_index"].isin(list(renumber))].copy()
        side["episode_index"] = [renumber[int(e)] for e in side["episode_index"]]
        (out / SIDECAR_PATH).parent.mkdir(parents=True, exist_ok=True)
        side.sort_values("episode_index").to_parquet(out / SIDECAR_PATH, index=False)
        if (src / SUITE_PATH).exists():
            shutil.copy2(src / SUITE_PATH, out / SUITE_PATH)
    return {"kept": len(kept), "dropped": int(len(episodes) - len(kept)), "frames": int(lengths.sum())}
