"""Audit speed and peak memory at two dataset sizes (the audit must stream, not load everything).

Makes an N-times replica of a LeRobot v3 dataset (videos hard-linked, so --workdir must be on the same filesystem; episode
tables and data files rewritten with new episode and frame indices: a valid
dataset N times larger), then audits the original and the replica, each in
its own process, and prints demos/s (model load and t-SNE reported apart)
and peak resident memory.

    python benchmarks/audit_scale.py data/push-v1 --times 10
    python benchmarks/audit_scale.py data/fetch-hub1-s80 --times 209 --first 24 --no-model --workdir runs
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq


def trimmed(eps: pd.DataFrame, cameras: list[str], fps: float, first: int) -> pd.DataFrame:
    """The episode table of the same episodes cut to their first ``first`` frames: lengths, frame ranges and each
    camera's end timestamp."""
    e = eps.copy()
    e["length"] = np.minimum(e["length"], first)
    e["dataset_to_index"] = np.cumsum(e["length"])
    e["dataset_from_index"] = e["dataset_to_index"] - e["length"]
    for key in cameras:
        e[f"videos/{key}/to_timestamp"] = e[f"videos/{key}/from_timestamp"] + e["length"] / fps
    return e


def trimmed_data(table: pa.Table, eps: pd.DataFrame) -> pa.Table:
    """A data file's rows of the frames ``eps`` (``trimmed``) keeps, their global ``index`` renumbered."""
    start = dict(zip(eps["episode_index"], eps["dataset_from_index"]))
    length = dict(zip(eps["episode_index"], eps["length"]))
    ep, frame = table.column("episode_index").to_numpy(), table.column("frame_index").to_numpy()
    keep = frame < np.array([length[int(e)] for e in ep])
    table = table.filter(pa.array(keep))
    index = np.array([start[int(e)] for e in ep[keep]], np.int64) + frame[keep]
    return table.set_column(table.column_names.index("index"), "index", pa.array(index))


def replicate(src: Path, dst: Path, times: int, first: int | None = None) -> None:
    """``src`` (LeRobot v3.0) ``times`` over at ``dst``: every camera's video files hard-linked, the data files and
    the episode tables (and democheck's sidecar, where there is one) rewritten with new episode and frame indices.
    ``first``: each episode cut to its first frames (the videos stay whole; the episodes end earlier in them)."""
    info = json.loads((src / "meta/info.json").read_text())
    eps = pd.concat([pd.read_parquet(p) for p in sorted((src / "meta/episodes").glob("chunk-*/file-*.parquet"))],
                    ignore_index=True)
    sidecar = src / "meta/democheck/episodes.parquet"
    side = pd.read_parquet(sidecar) if sidecar.exists() else None
    cameras = [k for k, f in info["features"].items() if isinstance(f, dict) and f.get("dtype") == "video"]
    if first:
        eps = trimmed(eps, cameras, float(info["fps"]), first)
        info["total_frames"] = int(eps["length"].sum())
    n_eps, n_frames = int(info["total_episodes"]), int(info["total_frames"])
    files = {kind: int(eps[f"{kind}/file_index"].max()) + 1 for kind in ["data", *(f"videos/{k}" for k in cameras)]}
    (dst / "meta/episodes/chunk-000").mkdir(parents=True)
    for name in ("tasks.parquet", "stats.json"):
        if (src / "meta" / name).exists():
            shutil.copy(src / "meta" / name, dst / "meta" / name)
    all_eps, all_side = [], []
    for c in range(times):
        e = eps.copy()
        e["episode_index"] += c * n_eps
        e["dataset_from_index"] += c * n_frames
        e["dataset_to_index"] += c * n_frames
        for kind, n in files.items():
            e[f"{kind}/file_index"] += c * n
            e[f"{kind}/chunk_index"] = e[f"{kind}/file_index"] // 1000
        e["meta/episodes/chunk_index"], e["meta/episodes/file_index"] = 0, 0
        all_eps.append(e)
        if side is not None:
            s = side.copy()
            s["episode_index"] += c * n_eps
            all_side.append(s)
        for key in cameras:
            for f in range(files[f"videos/{key}"]):
                new = f + c * files[f"videos/{key}"]
                vdst = dst / f"videos/{key}/chunk-{new // 1000:03d}/file-{new:03d}.mp4"
                vdst.parent.mkdir(parents=True, exist_ok=True)
                # a hard link: a symlink out of the dataset is (rightly) refused by the reader
                os.link(src / f"videos/{key}/chunk-{f // 1000:03d}/file-{f:03d}.mp4", vdst)
        for f in range(files["data"]):
            new = f + c * files["data"]
            t = pq.read_table(src / f"data/chunk-{f // 1000:03d}/file-{f:03d}.parquet")
            t = trimmed_data(t, eps) if first else t
            t = t.set_column(t.column_names.index("episode_index"), "episode_index",
                             pc.add(t.column("episode_index"), pa.scalar(c * n_eps, pa.int64())))
            t = t.set_column(t.column_names.index("index"), "index",
                             pc.add(t.column("index"), pa.scalar(c * n_frames, pa.int64())))
            ddst = dst / f"data/chunk-{new // 1000:03d}/file-{new:03d}.parquet"
            ddst.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(t, ddst)
    pd.concat(all_eps).to_parquet(dst / "meta/episodes/chunk-000/file-000.parquet", index=False)
    if all_side:
        (dst / "meta/democheck").mkdir(parents=True)
        pd.concat(all_side).to_parquet(dst / "meta/democheck/episodes.parquet", index=False)
    info["total_episodes"] = n_eps * times
    info["total_frames"] = n_frames * times
    info["splits"] = {"train": f"0:{n_eps * times}"}
    (dst / "meta/info.json").write_text(json.dumps(info, indent=2))


CHILD = """
import json, resource, sys, time
from democheck.workflows import audit_dataset
s = audit_dataset(sys.argv[1], sys.argv[2], model=sys.argv[3] if sys.argv[3] != '-' else None, device=sys.argv[4],
                  force=True, actions=sys.argv[5] != "cues", no_model=sys.argv[5] == "no-model")
# VmHWM, not ru_maxrss: Linux carries ru_maxrss across execve, so a child of a parent that once held a large
# memmap (benchmarks/run.py after the training benchmark) would report the parent's peak.
try:
    peak = int(open("/proc/self/status").read().split("VmHWM:")[1].split()[0]) / 1024
except (OSError, IndexError):
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"demos": s["demos"], "timing": s["timing"], "peak_rss_mb": peak}))
"""


def run_audit(dataset: Path, out: Path, model: str, device: str = "cpu", actions: bool = False,
              no_model: bool = False) -> dict:
    """One audit in a fresh process; the cue pass (``--no-actions``) unless ``actions``; the decoding pass alone
    with ``no_model``."""
    how = "no-model" if no_model else "actions" if actions else "cues"
    res = subprocess.run([sys.executable, "-c", CHILD, str(dataset), str(out), model, device, how],
                         capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(res.stderr)
    return json.loads(res.stdout.strip().splitlines()[-1])


def measure(dataset: Path, times: int = 10, model: str = "-", repeats: int = 1, workdir: Path | None = None,
            device: str = "cpu", verbose: bool = False, no_model: bool = False, first: int | None = None) -> dict:
    """Audit ``dataset`` and its ``times``-fold replica, each ``repeats`` times in a fresh process; medians.
    ``first``: both with every episode cut to its first frames (many episodes in little time).

    The cue pass (``audit --no-actions``): the action error decodes every frame and is timed on its own
    (``audit_actions``)."""
    import statistics

    out = {}
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        big = Path(tmp) / f"x{times}"
        replicate(dataset, big, times, first)
        if first:
            replicate(dataset, Path(tmp) / "x1", 1, first)
            dataset = Path(tmp) / "x1"
        for name, ds in (("1x", dataset), (f"{times}x", big)):
            runs = [run_audit(ds, Path(tmp) / f"report-{name}-{i}", model, device, no_model=no_model)
                    for i in range(repeats)]
            med = lambda f: statistics.median(f(r) for r in runs)  # noqa: E731
            out[name] = {"demos": runs[0]["demos"], "demos_per_s": med(lambda r: r["timing"]["demos_per_s"]),
                         "model_load_s": med(lambda r: r["timing"]["model_load_s"]),
                         "tsne_s": med(lambda r: r["timing"]["tsne_s"]), "peak_rss_mb": med(lambda r: r["peak_rss_mb"])}
            if verbose:
                o = out[name]
                print(f"{name:>4}: {o['demos']:6d} demos, {o['demos_per_s']:7.0f} demos/s (model load "
                      f"{o['model_load_s']:.2f} s, t-SNE {o['tsne_s']:.1f} s), peak memory {o['peak_rss_mb']:.0f} MB",
                      flush=True)
    out["memory_ratio"] = out[f"{times}x"]["peak_rss_mb"] / out["1x"]["peak_rss_mb"]
    out["device"], out["repeats"] = device, repeats
    return out


def audit_actions(dataset: Path, model: str = "-", device: str = "cpu") -> dict:
    """The default audit (with the action error) of ``dataset`` once: demos/s of each pass and peak memory."""
    with tempfile.TemporaryDirectory() as tmp:
        r = run_audit(dataset, Path(tmp) / "report", model, device, actions=True)
    t = r["timing"]
    return {"demos": r["demos"], "cue_demos_per_s": t["demos_per_s"],
            "action_demos_per_s": r["demos"] / t["actions_s"], "peak_rss_mb": r["peak_rss_mb"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--times", type=int, default=10)
    ap.add_argument("--model", default="-")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--workdir", type=Path, default=None, help="where to put the replica (default: a temp folder)")
    ap.add_argument("--actions", action="store_true", help="time the default audit, with the action error, instead")
    ap.add_argument("--no-model", action="store_true",
                    help="the audit without a model (every demo decoded), at both sizes: what grows with the data")
    ap.add_argument("--first", type=int, default=None,
                    help="cut every episode to its first FIRST frames, at both sizes: many episodes in little time")
    args = ap.parse_args()
    if args.actions:
        r = audit_actions(args.dataset, args.model)
        print(f"{r['demos']} demos: cue pass {r['cue_demos_per_s']:.0f} demos/s, action pass "
              f"{r['action_demos_per_s']:.0f} demos/s, peak memory {r['peak_rss_mb']:.0f} MB")
        return
    res = measure(args.dataset, args.times, args.model, args.repeats, args.workdir, verbose=True,
                  no_model=args.no_model, first=args.first)
    print(f"peak memory ratio {args.times}x / 1x: {res['memory_ratio']:.2f}")


if __name__ == "__main__":
    main()
