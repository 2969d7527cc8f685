"""What the generators of simulators democheck did not make share: the options, the plan of clean and planted
episodes, the grey card of an occluded demo, and LeRobot's own writer fed in order, one episode at a time, by
worker processes (a set of 480x640 frames does not fit in memory).  Runs in LeRobot's virtual environment.

An episode, as a generator's worker returns it: ``index``, ``task`` (the dataset's words), ``label`` (``clean`` or
a planted kind), ``frames`` (T x H x W x 3 uint8, the first camera's), ``state``, ``env_state`` and ``actions``
(T x d float32), and ``views`` (each further camera's name and frames) where the generator records several cameras.
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing as mp
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

KINDS = ("idle", "random", "wrong-task", "gave-up", "occluded", "jerky")
# On request (--kinds): a clean demo recorded backwards (a reset recorded as a demo) or with a pause put in, as
# ``democheck.data.reorder`` makes them (velocities negated by their names).
TIME_KINDS = ("reversed", "hesitates")
# On request, where a generator can plant them (its ``plants``: the tasks each fits): what operators do on the way --
# a detour to an empty spot and back, an object dropped during the carry and grasped again (both still succeed), an
# object put down off its goal (it fails).
WAY_KINDS = ("detour", "drop-regrasp", "failed-place")
# On request: a clean demo one of whose cameras stops delivering at 20-50% of the episode, its last picture repeated
# (``--freeze-camera`` names the camera; default the second where there are several).
CAMERA_KINDS = ("frozen-camera",)
# A generator may also plant a ``reset`` (its ``plants``): the task undone, as an operator puts the scene back between
# demos -- done forwards, and done (a reset that fails is drawn again).


def parser(doc: str, demos: int, size: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--demos", type=int, default=demos, help="clean demos per task")
    ap.add_argument("--plant", type=int, default=6, help="bad demos of each kind, in all")
    ap.add_argument("--kinds", default=",".join(KINDS),
                    help=f"comma-separated, of {', '.join(KINDS + TIME_KINDS + WAY_KINDS + CAMERA_KINDS)}, reset "
                         f"(default: {', '.join(KINDS)}; of {', '.join(WAY_KINDS)} and reset, those the simulator can "
                         "plant)")
    ap.add_argument("--tasks", help="comma-separated: only these of the simulator's tasks (default: all)")
    ap.add_argument("--size", default=size, help="camera image size in pixels: N (square) or HxW, e.g. 480x640")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--force", action="store_true")
    return ap


def listed(flag: str, text: str, known) -> tuple[str, ...]:
    """The names the comma-separated ``text`` of option ``flag`` gives, in its order; refused unless each is one of
    ``known`` and there is one at least."""
    names = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = sorted(set(names) - set(known))
    if unknown or not names:
        raise SystemExit(f"{flag}: unknown {', '.join(unknown) or 'none given'}; "
                         f"{flag.lstrip('-')}: {', '.join(known)}")
    return names


def options(args: argparse.Namespace, plants: dict[str, tuple[str, ...]] | None = None
            ) -> tuple[tuple[str, ...], tuple[int, int]]:
    """The kinds asked for and the image size (height, width); OUT cleared when --force allows it.  ``plants``:
    the ``WAY_KINDS`` the simulator can plant."""
    kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
    known = KINDS + TIME_KINDS + tuple(plants or ()) + CAMERA_KINDS
    unknown = sorted(set(kinds) - set(known))
    if unknown:
        raise SystemExit(f"unknown kind {', '.join(unknown)}; kinds here: {', '.join(known)}")
    if args.out.exists():
        if not args.force:
            raise SystemExit(f"{args.out}: exists (--force replaces it)")
        shutil.rmtree(args.out)
    h, _, w = args.size.partition("x")
    return kinds, (int(h), int(w or h))


def plan(names: list[str], demos: int, plant: int, seed: int, kinds: tuple[str, ...],
         plants: dict[str, tuple[str, ...]] | None = None) -> list[tuple]:
    """(episode index, task, kind, other task, seed) of every episode: ``demos`` clean per task, ``plant`` of
    each kind in all on tasks drawn by the seed (of a kind in ``plants``, among the tasks it fits), in a shuffled
    order."""
    rng = np.random.default_rng([seed, 1])
    rows = [(n, "clean") for n in names for _ in range(demos)]
    fits = {k: [n for n in (plants or {}).get(k, names) if n in names] for k in kinds}
    bare = sorted(k for k, among in fits.items() if plant and not among)
    if bare:
        raise SystemExit(f"--kinds {', '.join(bare)}: none of the tasks asked for fits it")
    rows += [(str(rng.choice(fits[k])), k) for k in kinds for _ in range(plant)]
    order = rng.permutation(len(rows))
    jobs = []
    for i, j in enumerate(order):
        task, kind = rows[j]
        other = str(rng.choice([n for n in names if n != task] or [task]))
        jobs.append((i, task, kind, other, seed))
    return jobs


def planted_action(kind: str, t: int, stop: int | None, rng: np.random.Generator, noise: float, dims: int,
                   oracle: Callable[[], np.ndarray]) -> np.ndarray:
    """The action at step ``t`` of a demo of ``kind``: none (idle, or stopped from ``stop`` on), uniform in [-1, 1]
    (random), else the oracle's, with Gaussian noise of SD ``noise`` where that is not 0 (jerky)."""
    if kind == "idle" or (stop is not None and t >= stop):
        return np.zeros(dims)
    if kind == "random":
        return rng.uniform(-1, 1, dims)
    a = oracle()
    return np.clip(a + rng.normal(0, noise, dims), -1, 1) if noise else a


def cover(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The frames with a grey card over 35-55% of the view, the same card in every frame."""
    h, w = frames.shape[1:3]
    share = rng.uniform(0.35, 0.55)
    ch, cw = int(h * np.sqrt(share)), int(w * np.sqrt(share))
    r, c = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    out = frames.copy()
    out[:, r:r + ch, c:c + cw] = np.uint8(rng.integers(90, 160))
    return out


def episode(job: tuple, rollout: Callable[..., dict], words: dict[str, str], min_first: int = 0) -> dict:
    """One planned episode (a ``plan`` job): ``rollout(task, scene, kind, rng, layout, stop=None)`` on layouts the
    job's seed draws until one fits its kind -- a clean, occluded or reset demo succeeds (its goal met no sooner
    than ``min_first`` steps in), a kind on the way did what it says (the rollout's ``planted``, where it says),
    another task's oracle does not do this one by chance, a demo that gave up stops at 30-60% of the steps the
    oracle needs and fails.  ``words``: each task as the dataset names it."""
    index, task, kind, other, seed = job
    rng = np.random.default_rng([seed, index])
    for _ in range(30):
        layout = int(rng.integers(1 << 30))
        if kind == "gave-up":
            full = rollout(task, task, "clean", rng, layout)
            if not full["success"] or full["first_success"] is None:
                continue
            rec = rollout(task, task, kind, rng, layout, stop=int(full["first_success"] * rng.uniform(0.3, 0.6)))
            if rec["success"]:
                continue
        else:
            # recorded as a clean demo, then reordered or its camera stopped when written
            led = "clean" if kind in TIME_KINDS + CAMERA_KINDS else kind
            rec = rollout(other if kind == "wrong-task" else task, task, led, rng, layout)
            fails = led in ("wrong-task", "failed-place")  # a detour and a regrasp still do the task
            if led in ("clean", "occluded", "reset", *WAY_KINDS, "wrong-task") and rec["success"] == fails:
                continue
            if not rec.get("planted", True):  # the kind's deed never came (the carry ended before the drop)
                continue
            if led in ("clean", "occluded", "reset") and (rec["first_success"] or 0) < min_first:
                continue
        break
    else:
        raise RuntimeError(f"episode {index} ({task}, {kind}): no usable rollout in 30 layouts")
    if kind == "occluded":
        rec["frames"] = cover(rec["frames"], rng)
    return {"index": index, "task": words[task], "label": kind, "views": rec.get("views", {}),
            **{k: rec[k] for k in ("frames", "state", "env_state", "actions")}}


def frozen(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The frames of a camera that stops delivering at 20-50% of the episode: its last picture repeats."""
    at = max(1, int(len(frames) * rng.uniform(0.2, 0.5)))
    return np.concatenate([frames[:at], np.repeat(frames[at - 1:at], len(frames) - at, axis=0)])


def reordered(ep: dict, names: dict[str, list[str] | None], seed: int) -> dict:
    """A ``reversed`` or ``hesitates`` episode's streams in their planted order (the others as they are).  The
    time kinds need democheck importable (``PYTHONPATH`` naming its checkout); the others do not."""
    if ep["label"] not in TIME_KINDS:
        return ep
    from democheck.data import reorder

    keys = ("frames", "state", "env_state", "actions")
    views = ep.get("views", {})
    given = {**{k: ep[k] for k in keys}, **{("view", k): v for k, v in views.items()}}
    streams, _ = reorder.replant(ep["label"], given, names, seed)
    return {**ep, **{k: streams[k] for k in keys}, "views": {k: streams[("view", k)] for k in views}}


def features(cameras: list[str], size: tuple[int, int], state: list[str], env: list[str], action: list[str]
             ) -> dict:
    """LeRobot's feature table of a generator's dataset: the cameras, and the state, environment state and actions
    with the dataset's names of their dimensions."""
    return {
        **{f"observation.images.{camera}": {"dtype": "video", "shape": (size[0], size[1], 3),
                                            "names": ["height", "width", "channels"]} for camera in cameras},
        "observation.state": {"dtype": "float32", "shape": (len(state),), "names": state},
        "observation.environment_state": {"dtype": "float32", "shape": (len(env),), "names": env},
        "action": {"dtype": "float32", "shape": (len(action),), "names": action},
    }


def main(ap: argparse.ArgumentParser, tasks: list[str], episode: Callable[[tuple], dict], init: Callable,
         features_of: Callable[..., dict], fps: int, robot_type: str,
         init_args: Callable[[argparse.Namespace], tuple] = lambda args: (),
         plants: dict[str, tuple[str, ...]] | None = None) -> None:
    """A generator's command line: parse ``ap``, plan, simulate in workers (``init(size, *init_args(args))`` in
    each) and write (``features_of(size, *init_args(args))``).  ``plants``: the ``WAY_KINDS`` the simulator can
    plant, and on which of its tasks."""
    args = ap.parse_args()
    if args.tasks:
        asked = listed("--tasks", args.tasks, tasks)
        tasks = [t for t in tasks if t in asked]
    if len(tasks) < 2 and "wrong-task" in (k.strip() for k in args.kinds.split(",")):
        raise SystemExit("--kinds wrong-task needs two tasks at least (--tasks)")
    kinds, size = options(args, plants)
    feats = features_of(size, *init_args(args))
    cameras = [k for k, f in feats.items() if f["dtype"] == "video"]
    freeze = getattr(args, "freeze_camera", None) or cameras[min(1, len(cameras) - 1)].rpartition(".")[2]
    if f"observation.images.{freeze}" not in cameras:
        raise SystemExit(f"--freeze-camera {freeze}: no such camera; cameras: {', '.join(cameras)}")
    record(args.out, plan(tasks, args.demos, args.plant, args.seed, kinds, plants), episode, args.workers, init,
           (size, *init_args(args)), feats, fps, robot_type, freeze)


def record(out: Path, jobs: list[tuple], episode: Callable[[tuple], dict], workers: int,
           init: Callable, initargs: tuple, features: dict, fps: int, robot_type: str, freeze: str = "") -> None:
    """Simulate ``jobs`` with ``episode`` in ``workers`` spawned processes (``init(*initargs)`` in each) and write
    them with LeRobot's writer to OUT; OUT.labels.csv beside it holds each episode's label.  ``freeze``: the camera
    a ``frozen-camera`` demo's stops on."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    cameras = [k for k, f in features.items() if f["dtype"] == "video"]
    streams = {"frames": cameras[0], "state": "observation.state", "env_state": "observation.environment_state",
               "actions": "action"}
    ds = LeRobotDataset.create(repo_id=f"local/{out.name}", fps=fps, features=features, root=out,
                               robot_type=robot_type, use_videos=True)
    t0, labels = time.perf_counter(), []
    with mp.get_context("spawn").Pool(workers, initializer=init, initargs=initargs) as pool:
        for job, ep in zip(jobs, pool.imap(episode, jobs)):
            ep = reordered(ep, {k: features[key].get("names") for k, key in streams.items()}, job[-1] + job[0])
            views = {cameras[0]: ep["frames"], **{f"observation.images.{k}": v for k, v in ep["views"].items()}}
            if ep["label"] in CAMERA_KINDS:
                key = f"observation.images.{freeze}"
                views[key] = frozen(views[key], np.random.default_rng([job[-1], job[0], 2]))
            for t in range(len(ep["actions"])):
                ds.add_frame({**{key: views[key][t] for key in cameras}, "observation.state": ep["state"][t],
                              "observation.environment_state": ep["env_state"][t], "action": ep["actions"][t],
                              "task": ep["task"]})
            ds.save_episode()
            labels.append(ep["label"])
            if len(labels) % 25 == 0 or len(labels) == len(jobs):
                print(f"simulated and written {len(labels)}/{len(jobs)} episodes ({time.perf_counter() - t0:.0f} s)",
                      flush=True)
    ds.finalize()
    path = out.with_name(out.name + ".labels.csv")
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode_index", "label"])
        w.writerows(enumerate(labels))
    counts = {k: labels.count(k) for k in dict.fromkeys(["clean", *sorted(set(labels) - {"clean"})])}
    print(f"{out}: {len(labels)} episodes {counts} in {time.perf_counter() - t0:.0f} s; labels: {path}")
