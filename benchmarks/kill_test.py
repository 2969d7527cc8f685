"""SIGKILL democheck commands at random moments; nothing half-written may be accepted as finished.

    python benchmarks/kill_test.py --kills 5

For each of synth, probe, train and audit: start the command, kill -9 it
after a random delay (up to its measured uninterrupted run time), then check
that its output folder is either absent or complete (it opens and holds what
an uninterrupted run writes), and that running the command again succeeds.
For train it also checks that ``--resume`` after the kill ends with weights
identical to the uninterrupted run's.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CLI = [sys.executable, "-m", "democheck.cli"]


def _run(argv: list[str], kill_after: float | None = None) -> tuple[int, float]:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    t0 = time.perf_counter()
    proc = subprocess.Popen(CLI + argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            start_new_session=True)
    if kill_after is None:
        _, err = proc.communicate()
        if proc.returncode != 0:
            raise SystemExit(f"{argv}: exit {proc.returncode}: {err.decode()[-500:]}")
        return proc.returncode, time.perf_counter() - t0
    try:
        proc.wait(timeout=kill_after)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the command and its worker processes
        proc.wait()
    return proc.returncode, time.perf_counter() - t0


def _weights_digest(model: Path) -> str:
    return hashlib.sha256((model / "model.safetensors").read_bytes()).hexdigest()


def complete(kind: str, out: Path, reference: Path) -> bool:
    """Is ``out`` what an uninterrupted run writes (as far as a later command can tell)?"""
    if kind in ("synth", "probe"):
        from democheck.data import open_dataset

        a, b = open_dataset(out), open_dataset(reference)
        return len(a) == len(b) and all(np.array_equal(a.cue_frames(e), b.cue_frames(e)) for e in a.episode_indices)
    if kind == "train":
        from democheck.petnet.checkpoint import load_checkpoint

        load_checkpoint(out)
        return (out / "README.md").exists()
    if kind == "audit":
        import json

        names = {p.name for p in out.iterdir()}
        return {"scores.parquet", "scores.csv", "summary.json", "suspects.txt", "report.rrd"} <= names and \
            json.loads((out / "summary.json").read_text())["demos"] > 0
    raise ValueError(kind)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=5, help="random kills per command")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="democheck-kill-"))
    try:
        data = tmp / "data"
        commands = {
            "synth": lambda out: ["synth", "push-mini", "--out", str(out), "--tasks", "6", "--demos", "3",
                                  "--workers", "2"],
            "probe": lambda out: ["probe", str(data), "--out", str(out), "--per-kind", "3"],
            "train": lambda out: ["train", str(data), "--out", str(out), "--steps", "600", "--set", "batch_tasks=2",
                                  "--set", "timesteps=2", "--set", "ckpt_every=25", "--set", "val_every=300", "--device", "cpu",
                                  "--cache-dir", str(tmp / "cache")],
            "audit": lambda out: ["audit", str(data), "--out", str(out)],
        }
        _run(commands["synth"](data))
        rows = []
        for kind, make in commands.items():
            ref = tmp / f"{kind}-ref"
            _, full = _run(make(ref))
            accepted_partial = finished = absent = resumed = 0
            for k in range(args.kills):
                out = tmp / f"{kind}-{k}"
                code, _ = _run(make(out), kill_after=float(rng.uniform(0.2, 1.1) * full))
                if out.exists():
                    if complete(kind, out, ref):
                        finished += 1
                    else:
                        accepted_partial += 1
                else:
                    absent += 1
                partial = out.parent / f".{out.name}.partial"
                if kind == "train" and not out.exists() and any((partial / d / "state.json").exists()
                                                                for d in ("state", "state.old")):
                    _run(make(out) + ["--resume"])
                    assert _weights_digest(out) == _weights_digest(ref), "resume after SIGKILL changed the weights"
                    resumed += 1
                else:
                    _run(make(out) + ["--force"])  # the command runs again over whatever the kill left
                assert complete(kind, out, ref)
            rows.append((kind, args.kills, absent, finished, accepted_partial, resumed, full))
        print("| command | kills | output absent | output complete | half-written accepted | resumed to identical "
              "weights | uninterrupted run |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for kind, n, absent, finished, bad, resumed, full in rows:
            print(f"| {kind} | {n} | {absent} | {finished} | {bad} | {resumed if kind == 'train' else ''} | {full:.1f} s |")
        if any(r[4] for r in rows):
            raise SystemExit("a half-written output was accepted as finished")
        print("train: every kill that left a partial run was resumed with --resume to weights identical "
              "(sha256 of model.safetensors) to the uninterrupted run's")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
