"""Out-of-distribution probes of a dataset, written as a labelled LeRobot dataset (``democheck probe``).

Each probe is made from one *source* demo and keeps its task, split and a link
to it (``source_episode``); its ``label`` is the probe kind:

- ``no-action``: the source's scene, the arm never moves (re-simulated from the
  source's sim record; without one, the first frame and state held);
- ``random``: the source's scene, smoothed random torques (needs the sim record);
- ``no-objects``: the source's actions replayed in the scene without objects
  (needs the sim record);
- ``hidden``: the source's frames with opaque squares over a large share of the
  view, the same squares all episode (works on any dataset);
- on request (``TIME_PROBES``, any dataset): ``reversed``, the source's recording played backwards (what a reset
  recorded as a demo looks like), and ``hesitates``, the source with a pause put in
  (``democheck.data.reorder``).

A re-simulated probe's frames are rendered now, and the source's were stored by a lossy video encoder, so
they go through the same encoder (the source's pixel format and quality: ``source_codec``) before they are
written: otherwise every re-simulated probe would differ from every clean demo by the encoder's traces alone,
which any pixel statistic sees.  (Measured on push-v1-dev's probes: the size of the cue's two frames as PNG,
smaller = more suspect, ranked no-action, random and no-objects probes above every clean demo, AUROC 1.00;
through the encoder 0.73, 0.98, 0.88.  The task uncertainty did not lean on it: 0.985, 0.457, 0.411 without,
0.982, 0.445, 0.413 with.)
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from democheck import pool
from democheck.data import open_dataset, reorder
from democheck.data.demo import Demo
from democheck.data.lerobot_write import VideoOptions, write_meta, write_shard
from democheck.data.lerobot import SUITE_PATH, read_json
from democheck.data.video import DEFAULT_CRF, DEFAULT_PIX_FMT, through_codec
from democheck.errors import DatasetError, DemocheckError
from democheck.fsutil import atomic_output_dir
from democheck.sim.env import ACTION_NAMES, ENV_STATE_NAMES, STATE_NAMES
from democheck.sim.variants import IMAGE_PROBES, PROBES, TIME_PROBES, EnvCache, resimulate

EPISODES_PER_FILE = 50
HIDDEN_COVER = (0.5, 0.7)  # share of the image the squares cover, drawn per probe
HIDDEN_SIDE = (0.25, 0.5)  # side of each square, as a share of the image side


def hide(frames: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, list[list[int]]]:
    """Cover ``frames`` [T,H,W,3] with random solid squares until a drawn share of the view is hidden.

    Returns the covered frames and the squares as [row, col, side, r, g, b].
    """
    T, H, W, _ = frames.shape
    goal = rng.uniform(*HIDDEN_COVER)
    mask = np.zeros((H, W), bool)
    out = frames.copy()
    squares = []
    while mask.mean() < goal:
        side = max(1, int(round(rng.uniform(*HIDDEN_SIDE) * min(H, W))))
        r, c = int(rng.integers(0, H - side + 1)), int(rng.integers(0, W - side + 1))
        colour = rng.integers(0, 256, size=3)
        out[:, r:r + side, c:c + side] = colour.astype(np.uint8)
        mask[r:r + side, c:c + side] = True
        squares.append([r, c, side, *(int(v) for v in colour)])
    return out, squares


def pick_sources(episodes: Any, kinds: list[str], per_kind: int, seed: int) -> list[tuple[str, int]]:
    """(kind, source episode) for every probe: ``per_kind`` clean demos per kind, drawn by ``seed``."""
    pool = episodes.index
    if "label" in episodes:
        pool = episodes.index[episodes["label"].fillna("clean") == "clean"]
    pool = np.asarray(sorted(int(e) for e in pool))
    if not len(pool):
        raise DatasetError("no clean demos to make probes from")
    rng = np.random.default_rng([seed, 0x960BE])
    picks = []
    for kind in kinds:
        chosen = rng.choice(pool, size=min(per_kind, len(pool)), replace=False)
        picks += [(kind, int(e)) for e in sorted(chosen)]
    return picks


def source_codec(ds: Any) -> tuple[str, int] | None:
    """(pixel format, CRF) of the H.264 a LeRobot dataset's camera was recorded with (democheck's own writer, the
    one whose datasets carry the sim records re-simulated probes need), for the frames a probe renders anew: the
    CRF from a democheck suite's recipe, else democheck's default.  None for lossless, image or other video."""
    root = Path(ds.root)
    if not ds.format.startswith("lerobot") or not (root / "meta/info.json").is_file():
        return None
    info_json = read_json(root / "meta/info.json")
    feature = ((info_json.get("features") if isinstance(info_json, dict) else None) or {}).get(ds.camera) or {}
    info = feature.get("info") or {}
    pix_fmt = info.get("video.pix_fmt")
    if feature.get("dtype") != "video" or info.get("video.codec") != "h264" or pix_fmt not in ("yuv444p", "yuv420p"):
        return None
    suite = read_json(root / SUITE_PATH) if (root / SUITE_PATH).is_file() else {}
    recipe = (suite.get("recipe") if isinstance(suite, dict) else None) or {}
    return pix_fmt, int(recipe.get("crf", DEFAULT_CRF))


def _probe_init(source: str, camera: str | None, root: str, context: dict[str, Any]) -> None:
    ds = open_dataset(source, camera=camera)
    pool.state.update(ds=ds, root=Path(root), envs=EnvCache(ds.image_shape[0]), **context)


def _probe_shard(job: tuple[int, int, list[tuple[int, str, int, int]]]) -> list[dict[str, Any]]:
    file_index, first_index, episodes = job
    w = pool.state
    ds = w["ds"]
    demos = []
    for episode_index, kind, src, probe_seed in episodes:
        source = ds[src]
        T = len(source)
        rng = np.random.default_rng(probe_seed)
        probe = {"kind": kind, "source_episode": src, "seed": probe_seed}
        sim = None
        if kind == "hidden":
            frames, probe["squares"] = hide(source.frames, rng)
            state, actions, env_state = source.state, source.actions, source.env_state
            sim = source.sim
        elif kind in TIME_PROBES:
            x = source.extra
            streams, pause = reorder.replant(
                kind, {"frames": source.frames, "state": source.state, "actions": source.actions,
                       "env_state": source.env_state},
                {"state": x.get("state_names"), "actions": x.get("action_names"),
                 "env_state": x.get("env_state_names")}, probe_seed)
            frames, state, actions, env_state = (streams[k] for k in ("frames", "state", "actions", "env_state"))
            if pause:
                probe["pause"] = pause
        elif source.sim is None:  # image-level no-action: the first frame and state held
            frames = np.repeat(source.frames[:1], T, 0)
            state, actions, env_state = np.repeat(source.state[:1], T, 0), np.zeros_like(source.actions), None
        else:
            rec = resimulate(w["envs"], source.sim, kind, seed=probe_seed,
                             actions=source.actions if kind == "no-objects" else None)
            frames, state, actions, env_state = rec["frames"], rec["state"], rec["actions"], rec["env_state"]
            if w["source_codec"] is not None:
                frames = through_codec(frames, w["fps"], *w["source_codec"])
            sim = {**source.sim, "policy": kind, "seed": probe_seed}
        if not w["env_state_dim"]:  # the source records no environment state: nor does its probe
            env_state = None
        elif env_state is None:  # a probe of a dataset that records the environment, where it is unknown
            env_state = np.full((len(actions), w["env_state_dim"]), np.nan, np.float32)
        sim = {**(sim or {}), "probe": probe}
        demos.append(Demo(episode_index=episode_index, task=source.task, frames=frames, state=state, actions=actions,
                          success=None, label=kind, split=source.split, sim=sim, env_state=env_state,
                          source_episode=src))
        pool.tick()
    return write_shard(w["root"], file_index, demos, w["task_index"], first_index, w["fps"], w["video"])


def make_probes(source: str | Path, out: str | Path, kinds: list[str] | None = None, per_kind: int = 50,
                seed: int = 0, workers: int = 2, camera: str | None = None, force: bool = False,
                on_progress: Callable[[int, int], None] | None = None, engine: str = "local",
                ray_address: str | None = None) -> dict[str, Any]:
    """Write a probe dataset made from ``source`` under ``out`` (atomically); returns its summary.  ``engine``
    "ray" renders the same shards in Ray actors (``pool.run_on``): the same files.

    ``kinds``: default, every kind the data allows (all four with sim records, ``IMAGE_PROBES`` without).
    The probes keep the source's camera name, and their video is lossless, so a probe's frames equal its
    source's bit for bit wherever the probe does not change them; the frames a probe renders anew have been
    through the source's encoder first (``source_codec``)."""
    ds = open_dataset(source, camera=camera).require_camera("a probe")
    has_sim = "sim" in ds.episodes and bool(ds.episodes["sim"].fillna("").astype(str).str.len().gt(0).all())
    kinds = list(kinds or (PROBES if has_sim else IMAGE_PROBES))
    unknown = [k for k in kinds if k not in (*PROBES, *TIME_PROBES)]
    if unknown:
        raise DemocheckError(f"unknown probe kind {', '.join(unknown)}; kinds: {', '.join((*PROBES, *TIME_PROBES))}")
    if per_kind < 1:
        raise DemocheckError("--per-kind must be at least 1")
    h, w, _ = ds.image_shape
    picks = pick_sources(ds.episodes, kinds, per_kind, seed)
    need_sim = sorted({k for k, _ in picks if k not in (*IMAGE_PROBES, *TIME_PROBES)})
    if need_sim and not has_sim:
        raise DatasetError(f"{ds.root}: {', '.join(need_sim)} probes re-simulate each demo and this dataset has no "
                           f"sim records (it was not made by democheck synth); use --kinds {','.join(IMAGE_PROBES)}")
    lengths = ds.episodes["length"]
    episodes = [(i, kind, src, int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
                for i, (kind, src) in enumerate(picks)]
    jobs, frame = [], 0
    for f, s in enumerate(range(0, len(episodes), EPISODES_PER_FILE)):
        chunk = episodes[s:s + EPISODES_PER_FILE]
        jobs.append((f, frame, chunk))
        frame += int(sum(lengths[src] + (reorder.pause(lengths[src], s)[1] if kind == "hesitates" else 0)
                         for _, kind, src, s in chunk))
    tasks = sorted({str(ds.episodes.loc[src, "task"]) for _, src in picks})
    # The probes keep the source's names (democheck's own where its sim records say how to re-simulate).
    names = ((STATE_NAMES, ACTION_NAMES, ENV_STATE_NAMES) if has_sim else
             (ds.names("state"), ds.names("action"), ds.names("env_state")))
    context = {"task_index": {t: i for i, t in enumerate(tasks)}, "fps": int(round(ds.fps)),
               "env_state_dim": len(names[2]),
               "source_codec": source_codec(ds),
               "video": VideoOptions(DEFAULT_PIX_FMT, DEFAULT_CRF, camera=ds.camera, lossless=True)}
    t0 = time.perf_counter()
    with atomic_output_dir(out, force=force) as tmp:
        rows = pool.run_on(engine, jobs, _probe_shard, _probe_init, (str(ds.root), camera, str(tmp), context),
                           workers, len(episodes), on_progress, ray_address)
        summary = {"source": str(ds.root), "kinds": {k: sum(kk == k for kk, _ in picks) for k in kinds},
                   "per_kind": per_kind, "seed": seed, "episodes": len(episodes),
                   "rendered_frames_through": (None if context["source_codec"] is None else
                                               dict(zip(("pix_fmt", "crf"), context["source_codec"]))),
                   "wall_s": round(time.perf_counter() - t0, 3)}
        write_meta(tmp, rows, tasks, context["fps"], (h, w), *names, context["video"], suite={"probes": summary})
    return summary
