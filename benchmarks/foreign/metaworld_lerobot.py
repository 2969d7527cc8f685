"""A dataset democheck did not make: Meta-World tasks done by Meta-World's own scripted policies, written by
LeRobot's own writer, with planted bad demos.  Runs in LeRobot's virtual environment (LeRobot pins an older
torch), never in democheck's:

    PEERS_WITH_FFMPEG=0 ../shared/peers/setup_peers.sh /tmp/peers     # LeRobot 0.4.4 in /tmp/peers/venv-lerobot
    /tmp/peers/venv-lerobot/bin/pip install metaworld==3.1.1
    MUJOCO_GL=egl /tmp/peers/venv-lerobot/bin/python benchmarks/foreign/metaworld_lerobot.py OUT \
        --tasks mt10 --demos 20 --plant 7 --seed 0

OUT is a LeRobot v3.0 dataset (camera ``observation.images.corner``, AV1 video as LeRobot writes it by
default, 39-d state, 4-d actions, 80 fps); ``OUT.labels.csv`` beside it (episode_index,label) holds the ground
truth and is not part of the dataset.  Every planted kind replaces a demo of a task it is labelled with:

- ``idle``: the arm never moves (zero actions);
- ``random``: uniformly random actions;
- ``wrong-task``: a clean demo of another task, in that task's scene, labelled with this one;
- ``gave-up``: the task's policy until 30-60% of the time it takes to succeed on that layout, then the arm
  stops (so the task is never done; a clean demo may rest after succeeding);
- ``occluded``: a clean demo whose camera is covered by a grey card over 40-60% of the view, all episode.

Four more kinds, recording faults no choice of democheck's was made on, planted only when ``--kinds`` names them
(the default is the five above, so that a seed gives the datasets it gave before):

- ``jittery``: a shaky operator -- the policy's actions plus Gaussian noise of SD 0.2-0.4 (actions span -1..1),
  executed and recorded;
- ``frozen-camera``: a clean demo whose camera stops delivering at 20-50% of the episode (its last frame repeats
  to the end; state and actions go on);
- ``lagged``: a clean demo whose recorded actions run 8-16 steps (0.1-0.2 s) late against its states and frames
  (its first action held until then);
- ``dropped``: a clean demo that lost a stretch of 20-30% of its steps in the middle (frames, states and actions
  alike), re-indexed as if nothing were missing.

Three more, what operators do on the way, planted only when ``--kinds`` names them; each episode as long as
every other (``--steps``):

- ``detour``: 25-45% of the time the policy takes to succeed on the layout, the hand leaves for an empty spot
  8-15 cm aside and 5-10 cm up for 15-25 steps, the gripper as it was, then the policy resumes and succeeds (any
  task);
- ``drop-regrasp``: 30-60% of the way from where the puck lay to its goal the gripper opens wide for 5-8 steps and
  the hand backs off 3-7 cm, the puck drops, and the policy grasps it again and succeeds (pick-place-v3);
- ``failed-place``: the puck carried to a point 10-15 cm off the goal and let go there (the gripper wide open for 6
  steps, then at rest), the hand lifted away: it never reaches its goal (pick-place-v3).

And one a person records between demos, planted only when ``--kinds`` names it:

- ``reset``: the task undone, as an operator puts the scene back -- the puck starts on its goal (on the table) and
  the task's policy carries it to where the layout put it (push-v3, pick-place-v3).  Unlike a demo played
  backwards, it runs forwards: the arm starts at home, reaches, grasps or pushes, and lets go as in any demo.

Clean demos are the scripted policy on a variation of the task (Meta-World's goal and object positions) that
no other episode of the task's scene uses while the 50 last, kept only when the policy succeeds.  (Before,
variations were drawn with replacement: a reset of the same variation replays the same episode, so the datasets
made then hold exact copies -- ``democheck audit`` names them.)  Episodes run in spawned worker processes, each
with one live env at a time (see ``_env``: datasets made before that hold clean demos rendered from another
camera with the scene's textures gone, about a third of them); the same seed gives the same episodes.
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing as mp
import os
import shutil
import time
import warnings
from pathlib import Path

import numpy as np

TASKS = {  # Meta-World env -> (the task as a LeRobot dataset names it, the scripted policy's class)
    "reach-v3": ("reach the red goal with the gripper", "SawyerReachV3Policy"),
    "push-v3": ("push the puck to the goal", "SawyerPushV3Policy"),
    "pick-place-v3": ("pick up the puck and place it at the goal", "SawyerPickPlaceV3Policy"),
    "door-open-v3": ("open the door", "SawyerDoorOpenV3Policy"),
    "drawer-open-v3": ("open the drawer", "SawyerDrawerOpenV3Policy"),
    "drawer-close-v3": ("close the drawer", "SawyerDrawerCloseV3Policy"),
    "button-press-topdown-v3": ("press the button from the top", "SawyerButtonPressTopdownV3Policy"),
    "window-open-v3": ("open the window", "SawyerWindowOpenV3Policy"),
    "window-close-v3": ("close the window", "SawyerWindowCloseV3Policy"),
    "coffee-button-v3": ("press the coffee machine's button", "SawyerCoffeeButtonV3Policy"),
}
KINDS = ("idle", "random", "wrong-task", "gave-up", "occluded")
MORE_KINDS = ("jittery", "frozen-camera", "lagged", "dropped", "detour", "drop-regrasp", "failed-place", "reset")
WAY = ("detour", "drop-regrasp", "failed-place")  # the policy, but for what ``_way`` has it do on the way
PLANTS = {"drop-regrasp": ("pick-place-v3",), "failed-place": ("pick-place-v3",),  # the tasks a kind fits
          "reset": ("push-v3", "pick-place-v3")}
RESET_NEAR = 0.07  # m: a reset is done where the puck ends this near where the layout put it
FAULTS = ("frozen-camera", "lagged", "dropped")  # a clean episode, recorded wrongly (``_fault``)
CAMERA = "corner"
FPS = 80

_W: dict = {}


def _init(size: int) -> None:
    import metaworld

    warnings.filterwarnings("ignore")
    _W["mt"] = metaworld.MT50(seed=0)
    _W["size"] = size


def _env(name: str):
    """The worker's environment for ``name``.  One at a time: MuJoCo renderers of several live Meta-World envs in
    one process clobber each other's GL state -- after a third env is made, an older one renders another camera
    with the scene's textures and meshes gone -- so the last env is closed before the next one is made."""
    if _W.get("name") != name:
        if "env" in _W:
            _W["env"].close()
        env = _W["mt"].train_classes[name](render_mode="rgb_array", camera_name=CAMERA, width=_W["size"],
                                           height=_W["size"])
        # Shadows, multisampling and reflections off: ~7x faster on a software renderer, the scene the same.
        env.model.vis.quality.shadowsize = 0
        env.model.vis.quality.offsamples = 0
        env.model.mat_reflectance[:] = 0
        _W.update(name=name, env=env, variations=[t for t in _W["mt"].train_tasks if t.env_name == name])
    return _W["env"], _W["variations"]


def _way(kind: str, steps: int, rng: np.random.Generator) -> dict:
    """What a ``WAY`` demo does and when, drawn once; ``at`` (the detour's start) is a share of the time the policy
    takes to succeed on the layout (``_episode`` sets it)."""
    if kind == "detour":
        turn = rng.uniform(0, 2 * np.pi)
        aside = rng.uniform(0.08, 0.15) * np.r_[np.cos(turn), np.sin(turn), 0] + np.r_[0, 0, rng.uniform(0.05, 0.1)]
        return {"at": rng.uniform(0.25, 0.45), "length": int(rng.integers(15, 26)), "aside": aside}
    if kind == "drop-regrasp":  # let go a share of the way from where the puck lay to its goal
        # How long and how far the hand backs off is drawn too: two drops on one layout (its policy is
        # deterministic) would otherwise be exact copies.
        return {"share": rng.uniform(0.3, 0.6), "open": int(rng.integers(5, 9)), "back": rng.uniform(0.03, 0.07)}
    turn = rng.uniform(np.pi, 2 * np.pi)  # beside the goal or nearer the robot: within the hand's reach
    return {"off": rng.uniform(0.1, 0.15) * np.r_[np.cos(turn), np.sin(turn), 0]}


OPEN_STEPS = 6  # a gripper that lets its puck go off the goal opens wide (-1) this long, then rests at 0


def _way_action(kind: str, plan: dict, t: int, obs: np.ndarray, policy) -> np.ndarray:
    """The action at step ``t`` of a ``WAY`` demo: the policy's, but for what ``plan`` has it do (its moves with the
    scripted policies' own ``move`` and gain; ``_rollout`` clips the action)."""
    from metaworld.policies.policy import move

    hand, puck, goal = obs[0:3], obs[4:7], obs[-3:]
    plan.setdefault("puck", puck.copy())  # where the puck lay at the start
    if kind == "detour" and plan["at"] <= t < plan["at"] + plan["length"]:
        plan.setdefault("to", hand + plan["aside"])
        return np.r_[move(hand, plan["to"], p=10.0), plan.get("grip", 0.0)]
    if kind == "drop-regrasp" and "dropped" not in plan:
        lifted = puck[2] > plan["puck"][2] + 0.02
        if lifted and np.linalg.norm(puck - plan["puck"]) > plan["share"] * np.linalg.norm(goal - plan["puck"]):
            plan["dropped"], plan["up"] = t, hand + np.r_[0, 0, plan["back"]]
    if kind == "drop-regrasp" and "dropped" in plan and t < plan["dropped"] + plan["open"]:
        return np.r_[move(hand, plan["up"], p=10.0), -1.0]  # the gripper opens and the hand backs off a little
    if kind == "failed-place":
        if "let go" in plan:
            wide = t < plan["let go at"] + OPEN_STEPS
            return np.r_[move(hand, plan["let go"], p=10.0), -1.0 if wide else 0.0]
        seen = obs.copy()
        seen[-3:] = goal + plan["off"]  # the policy carries the puck to a goal beside the real one
        if puck[2] > plan["puck"][2] + 0.02 and np.linalg.norm(hand - seen[-3:]) < 0.02:
            plan["let go"], plan["let go at"] = hand + np.r_[0, 0, 0.1], t
            return np.r_[0.0, 0.0, 0.0, -1.0]
        obs = seen
    a = policy.get_action(obs)
    plan["grip"] = a[3]
    return a


def _rollout(name: str, kind: str, steps: int, rng: np.random.Generator, layout: tuple[int, int] | None = None,
             stop: int | None = None, when: int | None = None) -> dict | None:
    """One episode of ``kind`` on a layout (task variation, reset seed) drawn from ``rng`` or given; the policy
    acts until ``stop``, the arm is still after it; a detour starts its share of ``when`` steps in."""
    import metaworld.policies as P

    env, variations = _env(name)
    layout = layout or (int(rng.integers(len(variations))), int(rng.integers(1 << 31)))
    env.set_task(variations[layout[0] % len(variations)])
    obs, _ = env.reset(seed=layout[1])
    policy = getattr(P, TASKS[name][1])()
    stop = steps if stop is None else stop
    jitter = rng.uniform(0.2, 0.4) if kind == "jittery" else 0.0  # drawn only here: old seeds give what they gave
    way = _way(kind, steps, rng) if kind in WAY else None
    if kind == "detour":
        way["at"] = int(way["at"] * (when or steps))
    back = None
    if kind == "reset":  # the puck on its goal, at the table's height; the policy sent where the layout put it
        back = obs[4:7].copy()
        env._set_obj_xyz(np.r_[obs[-3:][:2], back[2]])
        for _ in range(2):  # the observation's previous frame too
            obs, *_ = env.step(np.zeros(4, np.float32))
    frames, state, actions, success, first = [], [], [], False, None
    for t in range(steps):
        frames.append(env.render()[::-1].copy())  # MuJoCo renders bottom-up
        state.append(obs.astype(np.float32))
        if kind == "idle" or t >= stop:
            a = np.zeros(4, np.float32)
        elif kind == "random":
            a = rng.uniform(-1, 1, 4).astype(np.float32)
        elif kind == "jittery":
            a = np.clip(policy.get_action(obs) + rng.normal(0, jitter, 4), -1, 1).astype(np.float32)
        elif way is not None:
            a = np.clip(_way_action(kind, way, t, obs, policy), -1, 1).astype(np.float32)
        elif back is not None:
            a = np.clip(policy.get_action(np.r_[obs[:-3], back]), -1, 1).astype(np.float32)
        else:
            a = np.clip(policy.get_action(obs), -1, 1).astype(np.float32)
        actions.append(a)
        obs, _, _, _, info = env.step(a)
        if back is not None:
            info["success"] = bool(np.linalg.norm(obs[4:7] - back) < RESET_NEAR)
        if info["success"] and first is None:
            first = t + 1
        success = success or bool(info["success"])
    if kind in ("clean", "wrong-task", "occluded", "detour", "drop-regrasp", "reset", *FAULTS) and not success:
        return None  # a failed expert demo is not a clean one, nor a detour or a regrasp: draw again
    if kind == "drop-regrasp" and not (way.get("dropped") is not None and first is not None and first > way["dropped"]):
        return None  # the puck never dropped, or reached its goal before it did: draw again
    if kind == "failed-place" and ("let go" not in way or success):
        return None  # the puck never let go off its goal: draw again
    return {"frames": np.stack(frames), "state": np.stack(state), "actions": np.stack(actions), "layout": layout,
            "first_success": first, "success": success}


def _cover(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    h, w = frames.shape[1:3]
    share = rng.uniform(0.4, 0.6)
    ch, cw = int(h * np.sqrt(share)), int(w * np.sqrt(share))
    r, c = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    out = frames.copy()
    out[:, r:r + ch, c:c + cw] = np.uint8(rng.integers(90, 160))
    return out


def _fault(rec: dict, kind: str, rng: np.random.Generator) -> dict:
    """A clean recording with ``kind``'s fault (see the module docstring)."""
    frames, state, actions = rec["frames"], rec["state"], rec["actions"]
    n = len(actions)
    if kind == "frozen-camera":
        at = int(n * rng.uniform(0.2, 0.5))
        frames = np.concatenate([frames[:at], np.repeat(frames[at - 1:at], n - at, axis=0)])
    elif kind == "lagged":
        lag = int(rng.integers(8, 17))
        actions = np.concatenate([np.repeat(actions[:1], lag, axis=0), actions[:-lag]])
    elif kind == "dropped":
        length = int(n * rng.uniform(0.2, 0.3))
        at = int(rng.integers(n // 4, n - n // 4 - length))
        keep = np.r_[0:at, at + length:n]
        frames, state, actions = frames[keep], state[keep], actions[keep]
    return {**rec, "frames": frames, "state": state, "actions": actions}


def _episode(job: tuple) -> dict:
    index, name, kind, other, steps, seed, variation, spare = job
    rng = np.random.default_rng([seed, index])
    for attempt in range(20):
        # The episode's own variation first; should the expert fail on it, one no other episode was given (another
        # episode's would replay it: an exact copy), else a random one.
        chosen = variation if attempt == 0 else spare[(index + attempt) % len(spare)] if spare else None
        layout = None if chosen is None else (chosen, int(rng.integers(1 << 31)))
        if kind == "detour":  # where the expert succeeds on this layout, then the same layout with a detour on the way
            full = _rollout(name, "clean", steps, rng, layout)
            rec = None if full is None else _rollout(name, kind, steps, rng, full["layout"], when=full["first_success"])
        elif kind == "gave-up":  # where the expert succeeds on this layout, then the same layout stopped short of it
            full = _rollout(name, "clean", steps, rng, layout)
            rec = None if full is None else _rollout(name, kind, steps, rng, full["layout"],
                                                     stop=int(full["first_success"] * rng.uniform(0.3, 0.6)))
            rec = None if rec is None or rec["success"] else rec
        else:
            rec = _rollout(other if kind == "wrong-task" else name, kind, steps, rng, layout)
        if rec is not None:
            break
    else:
        raise RuntimeError(f"episode {index}: the {name} policy failed 20 times")
    if kind == "occluded":
        rec["frames"] = _cover(rec["frames"], rng)
    elif kind in FAULTS:
        rec = _fault(rec, kind, rng)
    return {"index": index, "task": TASKS[name][0], "label": kind,
            **{k: rec[k] for k in ("frames", "state", "actions")}}


VARIATIONS = 50  # Meta-World's training variations (goal and object positions) of each task


def plan(names: list[str], demos: int, plant: int, steps: int, seed: int, kinds: tuple[str, ...] = KINDS
         ) -> list[tuple]:
    """(episode index, env, kind, other env, steps, seed, variation, the env's spare variations) of every episode:
    ``demos`` per task,
    ``plant`` of each of ``kinds`` in all, on tasks drawn by the seed.  Every episode of an env gets a variation of its
    own (a reset of the same variation replays the same episode, bit for bit), clean demos first, until the
    env's ``VARIATIONS`` are used up; a planted demo may then share one with a clean demo (it is not a copy:
    its actions or frames differ)."""
    rng = np.random.default_rng([seed, 1])
    planted = kinds
    kinds = ["clean"] * (demos * len(names)) + [k for k in planted for _ in range(plant)]
    tasks = [n for n in names for _ in range(demos)] + list(rng.choice(names, size=plant * len(planted)))
    fits = np.random.default_rng([seed, 2])  # a kind that fits some tasks only draws among them (old seeds as before)
    for j, kind in enumerate(kinds):
        if kind in PLANTS:
            among = [n for n in names if n in PLANTS[kind]]
            if not among:
                raise SystemExit(f"--kinds {kind} needs one of the tasks {', '.join(PLANTS[kind])}")
            tasks[j] = str(fits.choice(among))
    order = rng.permutation(len(kinds))
    # Clean demos take their variations first: two clean demos on one variation would be exact copies.
    draw = sorted(range(len(order)), key=lambda i: kinds[order[i]] != "clean")
    shuffled: dict[str, list[int]] = {}
    jobs: list[tuple] = [()] * len(order)
    for i in draw:
        j = order[i]
        name, kind = tasks[j], kinds[j]
        # Another task of the dataset; a dataset of one task borrows another Meta-World task's recording.
        other = str(rng.choice([n for n in names if n != name] or [n for n in TASKS if n != name]))
        env = other if kind == "wrong-task" else str(name)
        if not shuffled.get(env):
            shuffled[env] = list(rng.permutation(VARIATIONS))
        jobs[i] = (i, str(name), kind, other, steps, seed, int(shuffled[env].pop()))
    # A failed episode tries again on the variations no episode of its env was given.
    return [(*j, tuple(int(v) for v in shuffled[j[3] if j[2] == "wrong-task" else j[1]])) for j in jobs]


def write(out: Path, episodes: list[dict], size: int) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        f"observation.images.{CAMERA}": {"dtype": "video", "shape": (size, size, 3),
                                         "names": ["height", "width", "channels"]},
        "observation.state": {"dtype": "float32", "shape": (39,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "gripper"]},
    }
    ds = LeRobotDataset.create(repo_id=f"local/{out.name}", fps=FPS, features=features, root=out,
                               robot_type="sawyer", use_videos=True)
    for ep in episodes:
        for t in range(len(ep["actions"])):
            ds.add_frame({f"observation.images.{CAMERA}": ep["frames"][t], "observation.state": ep["state"][t],
                          "action": ep["actions"][t], "task": ep["task"]})
        ds.save_episode()
    ds.finalize()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--tasks", default="mt10", help="mt10 (the ten tasks of TASKS), or comma-separated env names")
    ap.add_argument("--demos", type=int, default=20, help="clean demos per task")
    ap.add_argument("--plant", type=int, default=7, help="bad demos of each kind, in all")
    ap.add_argument("--kinds", default=",".join(KINDS),
                    help=f"the bad kinds to plant, comma-separated, of {', '.join(KINDS + MORE_KINDS)}")
    ap.add_argument("--steps", type=int, default=120)
    ap.add_argument("--size", type=int, default=128, help="camera image size in pixels")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--force", action="store_true")
    args = ap.parse_args()
    names = list(TASKS) if args.tasks == "mt10" else [n.strip() for n in args.tasks.split(",")]
    if args.out.exists():
        if not args.force:
            raise SystemExit(f"{args.out}: exists (--force replaces it)")
        shutil.rmtree(args.out)
    kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
    unknown = sorted(set(kinds) - set(KINDS + MORE_KINDS))
    if unknown:
        raise SystemExit(f"unknown kind {', '.join(unknown)}; kinds: {', '.join(KINDS + MORE_KINDS)}")
    jobs = plan(names, args.demos, args.plant, args.steps, args.seed, kinds)
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(args.workers, initializer=_init, initargs=(args.size,)) as pool:
        episodes = []
        # Dealt out grouped by the env they run in, so that a worker seldom switches envs (see ``_env``).
        by_env = sorted(jobs, key=lambda j: (j[3] if j[2] == "wrong-task" else j[1], j[0]))
        for ep in pool.imap_unordered(_episode, by_env, chunksize=4):
            episodes.append(ep)
            if len(episodes) % 25 == 0 or len(episodes) == len(jobs):
                print(f"simulated {len(episodes)}/{len(jobs)} episodes ({time.perf_counter() - t0:.0f} s)", flush=True)
    episodes.sort(key=lambda ep: ep["index"])
    write(args.out, episodes, args.size)
    labels = args.out.with_name(args.out.name + ".labels.csv")
    with labels.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode_index", "label"])
        for i, ep in enumerate(episodes):
            w.writerow([i, ep["label"]])
    counts = {k: sum(e["label"] == k for e in episodes) for k in ("clean", *kinds)}
    print(f"{args.out}: {len(episodes)} episodes of {len(names)} tasks {counts} in {time.perf_counter() - t0:.0f} s; "
          f"labels: {labels}")


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main()
