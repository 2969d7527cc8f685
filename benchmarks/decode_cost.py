"""Where the audit's time goes beside decoding, on any LeRobot set: every video file of every camera decoded by PyAV
alone (to RGB, as the audit asks for frames), then the audit's decoding pass in one process with each part timed
-- reading a demo (decoding, conversion, its state and actions), and each check's consumer -- and the whole audit
without a model.  The ratio the issue of hub-sized data asks for is the audit's time over PyAV's, in the same run.

    python benchmarks/decode_cost.py DATA [--camera KEY] [--repeats 1] [--workers 1] [--model M] [--parts]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import av
import numpy as np


def pyav_decode(files: list[Path], rgb: bool = True) -> tuple[float, int]:
    """Seconds and frames to decode every frame of ``files`` with PyAV (one thread each, as the audit reads them),
    converted to RGB where ``rgb``."""
    t0, frames = time.perf_counter(), 0
    for path in files:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "NONE"
            stream.codec_context.thread_count = 1
            for frame in container.decode(stream):
                if rgb:
                    frame.to_ndarray(format="rgb24")
                frames += 1
    return time.perf_counter() - t0, frames


def video_files(root: Path, cameras: list[str]) -> list[Path]:
    return sorted(p for c in cameras for p in (root / "videos" / c).rglob("*.mp4"))


def decoding_parts(root: Path, camera: str | None) -> dict[str, float]:
    """The audit's decoding pass without a model, in this process, each part's seconds: ``read`` (a demo of the
    first camera: video, state, actions), ``read@<camera>`` (another camera's pictures), and each consumer."""
    from democheck.audit import scorers as registry, shards
    from democheck.audit.evidence import Evidence
    from democheck.audit.findings import CAMERA_MARK, camera_column
    from democheck.data import open_dataset
    from dataclasses import replace

    ds = open_dataset(root, camera=camera)
    ev = Evidence(episodes=ds.episodes.reset_index())
    decoding = {}
    for s in registry.select():
        if s.can_decode(ev):
            decoding.setdefault(s.source, s)
    views = ds.other_cameras()
    for s in list(decoding.values()):
        for c in views if s.per_camera else ():
            decoding[camera_column(s.source, c)] = s
    got = shards.consumers(decoding, ev, slice(0, len(ds)), "cpu")
    spent: dict[str, float] = defaultdict(float)
    for e in ds.episode_indices:
        t0 = time.perf_counter()
        demo = ds[e]
        spent["read"] += time.perf_counter() - t0
        seen = {"": demo}
        for c, other in views.items():
            t0 = time.perf_counter()
            seen[c] = replace(demo, frames=other[e].frames)
            spent[f"read{CAMERA_MARK}{c}"] += time.perf_counter() - t0
        for key, consumer in got.items():
            t0 = time.perf_counter()
            consumer.add(seen[key.partition(CAMERA_MARK)[2]])
            spent[key] += time.perf_counter() - t0
    for key, consumer in got.items():
        t0 = time.perf_counter()
        consumer.finish()
        spent[key] += time.perf_counter() - t0
    return dict(spent)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--camera")
    ap.add_argument("--repeats", type=int, default=1, help="interleaved repeats of PyAV and the audit; medians")
    ap.add_argument("--parts", action="store_true", help="also time each part of the decoding pass")
    ap.add_argument("--workers", type=int, default=1, help="the audit's workers (PyAV decodes on one thread)")
    ap.add_argument("--model", help="audit with this model (default: the model-free checks alone)")
    args = ap.parse_args(argv)
    from democheck.audit.run import audit
    from democheck.data import open_dataset
    from democheck.petnet.checkpoint import load_checkpoint

    ds = open_dataset(args.data, camera=args.camera)
    cameras = getattr(ds, "cameras", [ds.camera])  # a democheck that reads one camera: its own
    files = video_files(args.data, cameras)
    runs = defaultdict(list)
    ckpt = load_checkpoint(args.model) if args.model else None
    for _ in range(args.repeats):
        runs["pyav_rgb_s"].append(pyav_decode(files)[0])
        runs["pyav_s"].append(pyav_decode(files, rgb=False)[0])
        t0 = time.perf_counter()
        audit(open_dataset(args.data, camera=args.camera), ckpt, workers=args.workers)
        runs["audit_s"].append(time.perf_counter() - t0)
    out = {k: round(float(np.median(v)), 2) for k, v in runs.items()}
    frames = int(ds.episodes["length"].sum())
    out.update(demos=len(ds), frames=frames, cameras=len(cameras), video_files=len(files), workers=args.workers,
               audit_frames_per_s=round(frames * len(cameras) / out["audit_s"], 1),
               pyav_rgb_frames_per_s=round(frames * len(cameras) / out["pyav_rgb_s"], 1),
               audit_over_pyav_rgb=round(out["audit_s"] / out["pyav_rgb_s"], 2),
               audit_over_pyav=round(out["audit_s"] / out["pyav_s"], 2))
    if args.parts:
        out["parts_s"] = {k: round(v, 2) for k, v in decoding_parts(args.data, args.camera).items()}
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
