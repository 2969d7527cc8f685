"""A second simulator democheck did not make: the Fetch arm of Gymnasium-Robotics, four tasks done by scripted
oracles on the simulator's own state, written by LeRobot's own writer, with planted bad demos.  Runs in LeRobot's
virtual environment (LeRobot pins an older torch), never in democheck's:

    python3.11 -m venv /tmp/lerobot-venv
    /tmp/lerobot-venv/bin/pip install lerobot==0.4.4 gymnasium-robotics==1.4.2 mujoco==3.3.7
    MUJOCO_GL=egl /tmp/lerobot-venv/bin/python benchmarks/foreign/fetch_lerobot.py OUT --demos 40 --plant 6 --seed 0

OUT is a LeRobot v3.0 dataset: camera ``observation.images.head`` (AV1 as LeRobot writes it), a 28-d state (the
Fetch observation and the goal, named), a 10-d ``observation.environment_state`` (the block's position and its
quaternion as the simulator holds it, the goal; named), 4-d actions (gripper motion and opening), 25 fps;
``OUT.labels.csv`` beside it holds the ground truth.  The tasks: reach the goal with the gripper, push the block to
the goal, pick the block and place it at the goal, lift the block.  Episodes last 50-110 steps by task
(``--length-scale`` stretches them, the arm holding once done; ``--size 480x640`` records as hub datasets do).  Planted
kinds, each replacing a demo of the task it is labelled with:

- ``idle``: the arm never moves; ``random``: uniformly random actions;
- ``wrong-task``: another task's oracle in this task's scene (e.g. the block lifted where it should be pushed);
- ``gave-up``: the oracle until 30-60% of the steps it needs, then still;
- ``occluded``: a clean demo whose camera a grey card covers over 35-55% of the view;
- ``jerky``: a shaky teleoperator -- the oracle's actions plus Gaussian noise of SD 0.3-0.5, executed.

On request (``--kinds``), what operators do on the way, each in an episode as long as its task's clean ones:

- ``detour``: 25-45% of the way in, the gripper leaves for an empty spot 12-20 cm aside and 5-10 cm up for 15-25
  steps, holding what it holds, then the oracle resumes and succeeds (any task);
- ``drop-regrasp``: 4-10 steps into the carry the gripper opens for 6 steps, the block drops, and the oracle
  grasps it again and succeeds (pick-place, lift);
- ``failed-place``: the block carried to a point 8-15 cm off the goal, let go there and the gripper lifted away:
  the block lies off its goal (pick-place).

And one a person records between demos (``--kinds reset``): the task undone, as an operator puts the scene back --
the block starts on its goal (on the table) and the task's oracle carries it to where the layout put it (push,
pick-place).  Unlike a demo played backwards (``reversed``), it runs forwards: the arm starts at home, reaches,
pushes or grasps as in any demo.

With ``--cameras head,side,gripper`` (of ``CAMERAS``) the dataset records several cameras, as hub datasets do, and
``--kinds frozen-camera`` plants a clean demo whose ``--freeze-camera`` (default: the second) stops delivering at
20-50% of the episode, its last picture repeated.

With ``--spread S`` every block and goal lies within S times the simulator's own range (``RANGE``) of one layout the
seed draws, as a real recording puts its objects back about where they stood; ``--tasks pick-place`` records that
task alone; ``--operator`` moves each demo its own way (speed, how high it comes down onto the block, a smooth
wander), as people's demos differ where a scripted oracle's do not; ``--home`` has every pick-and-place demo put
the block down on a goal on the table, open and take the arm back to where it began (``HOME_STEPS`` more steps),
as people's demos end -- so that a reset is the task with its two places swapped, and a failed place a block put
down off its goal.

Clean demos are kept only where the oracle succeeds, on a layout whose goal the arm has to move to meet.  The same seed gives the same dataset.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import record  # noqa: E402
from record import episode, planted_action  # noqa: E402

TASKS = {  # name -> (the task as the dataset names it, Gymnasium-Robotics env, steps)
    "reach": ("reach the goal with the gripper", "FetchReach-like", 50),
    "push": ("push the block to the goal", "FetchPush-v4", 90),
    "pick-place": ("pick up the block and place it at the goal", "FetchPickAndPlace-v4", 110),
    "lift": ("lift the block", "FetchPickAndPlace-v4", 80),
}
CAMERA = "head"
HOME_STEPS = 90  # the steps ``--home`` adds to a pick-and-place demo: the block put down, the arm taken home
CARRY = 0.1  # m: how high above the table ``--home`` carries the block and lifts the arm after letting go
RANGE = 0.15  # how far the simulator draws the block and the goal from the gripper's start (m, each axis)
# The cameras a dataset may record (--cameras): the first the simulator's default view, the others the model's own.
CAMERAS = {"head": (None, "the scene from the front, as the simulator shows it"),
           "gripper": ("gripper_camera_rgb", "on the gripper, looking down its fingers"),
           "side": ("external_camera_0", "a fixed camera at the table's side"),
           "robot": ("head_camera_rgb", "the robot's own head camera")}
FPS = 25
STATE_NAMES = ["grip.x", "grip.y", "grip.z", "block.x", "block.y", "block.z", "block_rel.x", "block_rel.y",
               "block_rel.z", "finger.left", "finger.right", "block.roll", "block.pitch", "block.yaw", "block.vx",
               "block.vy", "block.vz", "block.wx", "block.wy", "block.wz", "grip.vx", "grip.vy", "grip.vz",
               "finger.vleft", "finger.vright", "goal.x", "goal.y", "goal.z"]
ENV_NAMES = ["block.x", "block.y", "block.z", "block.qw", "block.qx", "block.qy", "block.qz", "goal.x", "goal.y",
             "goal.z"]

_W: dict = {}


def _env(task: str):
    """The worker's environment for ``task`` (reach runs in the pick-and-place scene with the block left
    alone), one live at a time, rendering without shadows, multisampling or reflections."""
    import gymnasium as gym
    import gymnasium_robotics

    env_id = "FetchPickAndPlace-v4" if task in ("reach", "lift") else TASKS[task][1]
    if _W.get("id") != env_id:
        if "env" in _W:
            _W["env"].close()
        gym.register_envs(gymnasium_robotics)
        env = gym.make(env_id, render_mode="rgb_array", width=_W["size"][1], height=_W["size"][0],
                       max_episode_steps=1000).unwrapped
        env.model.vis.quality.shadowsize = 0
        env.model.vis.quality.offsamples = 0
        env.model.mat_reflectance[:] = 0
        _W.update(id=env_id, env=env)
    return _W["env"]


def _init(size: tuple[int, int], scale: float = 1.0, cameras: tuple[str, ...] = (CAMERA,),
          spread: float | None = None, seed: int = 0, operator: bool = False, home: bool = False) -> None:
    warnings.filterwarnings("ignore")
    _W.update(size=size, scale=scale, cameras=cameras, spread=spread, seed=seed, operator=operator, home=home)


def _near(env, rng: np.random.Generator) -> dict:
    """The observation once the block and the goal lie within ``spread`` times the simulator's own range (RANGE)
    of the dataset's one layout, which its seed draws: a block put back about where it stood, as in a real
    recording."""
    import mujoco

    grip = env.initial_gripper_xpos[:2]
    if "layout" not in _W:
        draw = np.random.default_rng([_W["seed"], 3])
        while True:
            block, goal = grip + draw.uniform(-RANGE, RANGE, (2, 2))
            if np.linalg.norm(block - grip) >= 0.1 and np.linalg.norm(goal - block) >= 0.15:
                break
        _W["layout"] = block, goal
    block, goal = _W["layout"]
    q = env._utils.get_joint_qpos(env.model, env.data, "object0:joint").copy()
    q[:2] = block + rng.uniform(-1, 1, 2) * RANGE * _W["spread"]
    env._utils.set_joint_qpos(env.model, env.data, "object0:joint", q)
    env.goal[:2] = goal + rng.uniform(-1, 1, 2) * RANGE * _W["spread"]
    mujoco.mj_forward(env.model, env.data)
    return env._get_obs()


def _views(env) -> dict[str, np.ndarray]:
    """The pictures of the cameras asked for: the environment's own view first, then each named camera's."""
    import mujoco

    out = {}
    for name in _W["cameras"]:
        if CAMERAS[name][0] is None:
            out[name] = env.render().copy()
            continue
        model, renderer = _W.get("renderer", (None, None))
        if model is not env.model:  # one renderer per live environment
            if renderer is not None:
                renderer.close()
            renderer = mujoco.Renderer(env.model, *_W["size"])
            _W["renderer"] = (env.model, renderer)
        renderer.update_scene(env.data, camera=CAMERAS[name][0])
        out[name] = renderer.render().copy()
    return out


def _goal(task: str, env, obs: dict, rng: np.random.Generator) -> np.ndarray:
    block = obs["observation"][3:6]
    if task == "reach":
        return block + np.r_[_within(rng, -0.12, 0.12, 2), _within(rng, 0.08, 0.2)]
    if task == "lift":
        return block + np.r_[0.0, 0.0, 0.15]
    if task == "pick-place":
        up = 0.0 if _W.get("home") else _within(rng, 0.05, 0.2)
        return np.r_[obs["desired_goal"][:2], block[2] + up]
    return obs["desired_goal"].copy()


def _within(rng: np.random.Generator, lo: float, hi: float, n: int | None = None):
    """Uniform in [lo, hi], narrowed about its middle to ``spread`` of its width where the layout is held."""
    if _W.get("spread") is None:
        return rng.uniform(lo, hi, n)
    half = (hi - lo) / 2 * _W["spread"]
    return (lo + hi) / 2 + rng.uniform(-half, half, n)


PLANTS = {"detour": tuple(TASKS), "drop-regrasp": ("pick-place", "lift"), "failed-place": ("pick-place",),
          "reset": ("push", "pick-place")}


# How the oracle moves: its gain toward a target and how high above the block it comes down from.  ``--operator``
# draws them per demo, with a smooth wander added to its motion (``_operator``), as people's demos differ.
STYLE = {"gain": 10.0, "above": 0.08, "wander": 0.0}


def _operator(seed: int) -> dict:
    """One demo's way of moving, drawn from its layout's seed: gain 5-12, coming down from 5-11 cm, a wander of
    SD 0.05-0.2 (of the motion's range of 1)."""
    rng = np.random.default_rng([seed, 2])
    return {"gain": rng.uniform(5, 12), "above": rng.uniform(0.05, 0.11), "wander": rng.uniform(0.05, 0.2)}


def head_for(grip: np.ndarray, target: np.ndarray, gain: float = 10.0) -> np.ndarray:
    """The gripper motion [dx, dy, dz] that heads for ``target``."""
    return np.clip((target - grip) * gain, -1, 1)


def oracle(task: str, obs: np.ndarray, goal: np.ndarray, memory: dict) -> np.ndarray:
    """The scripted action [dx, dy, dz, gripper] for ``task`` from the Fetch observation and the goal."""
    grip, block = obs[0:3], obs[3:6]

    style = _W.get("style", STYLE)

    def toward(target, gain=None):
        return head_for(grip, target, gain or style["gain"])

    if task == "reach":
        return np.r_[toward(goal), 1.0]
    if task == "push":
        d = goal[:2] - block[:2]
        if np.linalg.norm(d) < 0.015:  # there: hold still
            return np.r_[0.0, 0.0, 0.0, -1.0]
        u = d / max(np.linalg.norm(d), 1e-6)
        behind = np.r_[block[:2] - 0.06 * u, block[2]]
        if not memory.get("behind"):
            above = behind + np.r_[0, 0, style["above"]]
            if np.linalg.norm(grip[:2] - behind[:2]) > 0.015:
                return np.r_[toward(above), -1.0]
            if grip[2] - behind[2] > 0.01:
                return np.r_[toward(behind), -1.0]
            memory["behind"] = True
        if np.linalg.norm(grip[:2] - (block[:2] - 0.04 * u)) > 0.05:  # lost the block: go round again
            memory["behind"] = False
        return np.r_[toward(np.r_[goal[:2] - 0.035 * u, block[2]], 6.0), -1.0]
    # pick-place and lift: above the block, down, close, carry to the goal
    phase = memory.setdefault("phase", 0)
    if phase == 0:
        above = block + np.r_[0, 0, style["above"]]
        if np.linalg.norm(grip - above) > 0.012:
            return np.r_[toward(above), 1.0]
        memory["phase"] = 1
    if memory["phase"] == 1:
        if np.linalg.norm(grip - block) > 0.008:
            return np.r_[toward(block), 1.0]
        memory["phase"], memory["closing"] = 2, 0
    if memory["phase"] == 2:
        memory["closing"] += 1
        if memory["closing"] < 8:
            return np.r_[0, 0, 0, -1.0]
        memory["phase"] = 3
    if not (_W.get("home") and task == "pick-place"):
        return np.r_[toward(goal), -1.0]
    # --home: carry the block aloft to above its goal, put it down there, let go, rise and take the arm back to
    # where it began
    aloft = goal + np.r_[0, 0, CARRY]
    if memory["phase"] == 3:
        if np.linalg.norm(grip - aloft) > 0.02:
            return np.r_[toward(aloft), -1.0]
        memory["phase"] = 4
    if memory["phase"] == 4:
        if np.linalg.norm(grip - goal) > 0.012:
            return np.r_[toward(goal), -1.0]
        memory["phase"], memory["opening"] = 5, 0
    if memory["phase"] == 5:
        memory["opening"] += 1
        if memory["opening"] < 6:
            return np.r_[0, 0, 0, 1.0]
        memory["phase"] = 6
    if memory["phase"] == 6:
        if np.linalg.norm(grip - aloft) > 0.02:
            return np.r_[toward(aloft), 1.0]
        memory["phase"] = 7
    return np.r_[toward(_W["start"]), 1.0]


def way(kind: str, steps: int, rng: np.random.Generator) -> dict:
    """What a ``record.WAY_KINDS`` demo does and when, drawn once.  The episode keeps its task's length, as every
    clean one does, so that no check can tell the kind by its length."""
    if kind == "detour":
        turn = rng.uniform(0, 2 * np.pi)
        aside = rng.uniform(0.12, 0.2) * np.r_[np.cos(turn), np.sin(turn), 0] + np.r_[0, 0, rng.uniform(0.05, 0.1)]
        length = int(rng.integers(15, 26))
        return {"at": int(steps * rng.uniform(0.25, 0.45)), "length": length, "aside": aside}
    if kind == "drop-regrasp":
        return {"carried": int(rng.integers(4, 11)), "open": 6}
    turn = rng.uniform(0, 2 * np.pi)
    return {"off": rng.uniform(0.08, 0.15) * np.r_[np.cos(turn), np.sin(turn), 0]}


def way_action(kind: str, plan: dict, t: int, task: str, obs: np.ndarray, goal: np.ndarray, memory: dict
               ) -> np.ndarray:
    """The action at step ``t`` of a ``record.WAY_KINDS`` demo: the oracle's, but for what ``plan`` has it do."""
    grip = obs[0:3]
    if kind == "detour" and plan["at"] <= t < plan["at"] + plan["length"]:
        plan.setdefault("to", grip + plan["aside"])
        return np.r_[head_for(grip, plan["to"]), plan.get("hold", 1.0)]
    if kind == "drop-regrasp" and memory.get("phase") == 3 and not plan.get("done"):
        plan["carry"] = plan.get("carry", 0) + 1
        if plan["carry"] > plan["carried"]:
            if plan["carry"] <= plan["carried"] + plan["open"]:
                return np.r_[0.0, 0.0, 0.0, 1.0]
            plan["done"] = True
            memory.clear()  # grasp it again from above
    if kind == "failed-place" and _W.get("home"):  # put down off its goal, the arm taken home as in any demo
        return oracle(task, obs, goal + plan["off"], memory)
    if kind == "failed-place":
        if "let go" in plan:
            return np.r_[head_for(grip, plan["let go"]), 1.0]
        off = goal + plan["off"]
        if memory.get("phase") == 3 and np.linalg.norm(grip - off) < 0.02:
            plan["let go"] = grip + np.r_[0, 0, 0.12]
            return np.r_[0.0, 0.0, 0.0, 1.0]
        goal = off
    a = oracle(task, obs, goal, memory)
    plan["hold"] = a[3]
    return a


def _success(task: str, obs: dict, goal: np.ndarray) -> bool:
    """The gripper (reach) or the block within 4 cm of the goal; with ``--home``, a pick-and-place block also let
    go, resting on the table (within 5 mm of the height it began at), and the gripper back within 3 cm of where it
    began."""
    o = obs["observation"]
    where = o[0:3] if task == "reach" else o[3:6]
    if not np.linalg.norm(where - goal) < 0.04:
        return False
    return _done(o) if _W.get("home") and task == "pick-place" else True


def _done(o: np.ndarray) -> bool:
    """``--home``: the block resting on the table (within 5 mm of the height it began at) and the gripper back
    within 3 cm of where it began."""
    return bool(abs(o[5] - _W["rest"]) < 0.005 and np.linalg.norm(o[0:3] - _W["start"]) < 0.03)


def _rollout(task: str, scene: str, kind: str, rng: np.random.Generator, seed: int, stop: int | None = None
             ) -> dict:
    """One episode in ``scene``'s environment: ``task``'s oracle (or ``kind``'s behaviour) toward ``scene``'s
    goal, the arm still from ``stop`` on."""
    import mujoco

    env = _env(scene)
    obs, _ = env.reset(seed=seed)
    if _W.get("spread") is not None:
        obs = _near(env, np.random.default_rng([seed, 1]))
    goal = _goal(scene, env, obs, np.random.default_rng(seed))
    other_goal = _goal(task, env, obs, np.random.default_rng(seed + 1)) if task != scene else goal
    aim = goal  # where the demo's block (the reach's gripper) should end
    if kind == "reset":  # the block on its goal, on the table; the oracle sent where the layout put it
        aim = other_goal = obs["observation"][3:6].copy()
        q = env._utils.get_joint_qpos(env.model, env.data, "object0:joint").copy()
        q[:2] = goal[:2]
        env._utils.set_joint_qpos(env.model, env.data, "object0:joint", q)
        mujoco.mj_forward(env.model, env.data)
        obs = env._get_obs()
    _W["start"], _W["rest"] = obs["observation"][0:3].copy(), float(obs["observation"][5])
    steps = TASKS[scene][2] + (HOME_STEPS if _W.get("home") and scene == "pick-place" else 0)
    steps = int(round(steps * _W.get("scale", 1.0)))
    plan = way(kind, steps, rng) if kind in record.WAY_KINDS else None
    noise = rng.uniform(0.3, 0.5) if kind == "jerky" else 0.0
    _W["style"] = _operator(seed) if _W.get("operator") else STYLE
    wander, drift = _W["style"]["wander"], np.zeros(3)
    memory: dict = {}
    views: dict[str, list] = {name: [] for name in _W["cameras"]}
    state, env_state, actions, first = [], [], [], None
    for t in range(steps):
        for name, picture in _views(env).items():
            views[name].append(picture)
        o = obs["observation"]
        q = env._utils.get_joint_qpos(env.model, env.data, "object0:joint")
        state.append(np.r_[o, goal].astype(np.float32))
        env_state.append(np.r_[q[:3], q[3:7], goal].astype(np.float32))
        if plan is not None:
            a = way_action(kind, plan, t, task, o, other_goal, memory)
        else:
            a = planted_action(kind, t, stop, rng, noise, 4, lambda: oracle(task, o, other_goal, memory))
        if wander and kind not in ("idle", "random") and (stop is None or t < stop):
            drift = 0.85 * drift + np.random.default_rng([seed, 4, t]).normal(0, wander * 0.53, 3)
            a = np.r_[np.clip(np.asarray(a[:3]) + drift, -1, 1), a[3]]
        actions.append(np.asarray(a, np.float32))
        obs, *_ = env.step(np.asarray(a, np.float32))
        if first is None and _success(scene, obs, aim):
            first = t + 1
    first_camera, *others = _W["cameras"]
    return {"frames": np.stack(views[first_camera]), "views": {k: np.stack(views[k]) for k in others},
            "state": np.stack(state), "env_state": np.stack(env_state), "actions": np.stack(actions),
            "first_success": first, "success": _success(scene, obs, aim),
            "planted": _planted(kind, plan, obs["observation"])}


def _planted(kind: str, plan: dict | None, o: np.ndarray) -> bool:
    """Whether a kind on the way did what it says: a drop's block let go on the way; with ``--home``, a failed
    place's block put down and the arm back home, as any demo ends."""
    if kind == "drop-regrasp":
        return bool(plan.get("done"))
    return _done(o) if kind == "failed-place" and _W.get("home") else True


def _episode(job: tuple) -> dict:
    # A layout whose goal is met before the arm has moved (5 steps) holds no demo of the task.
    return episode(job, _rollout, {name: words for name, (words, *_) in TASKS.items()}, min_first=5)


def features(size: tuple[int, int], scale: float = 1.0, cameras: tuple[str, ...] = (CAMERA,), *_) -> dict:
    return record.features(list(cameras), size, STATE_NAMES, ENV_NAMES, ["dx", "dy", "dz", "gripper"])


def parser():
    ap = record.parser(__doc__, demos=40, size="96")
    ap.add_argument("--length-scale", type=float, default=1.0,
                    help="episode lengths times this (the oracle done, the arm holds): 3 gives 150-330 steps")
    ap.add_argument("--cameras", default=CAMERA,
                    help="comma-separated, of " + "; ".join(f"{k} ({v[1]})" for k, v in CAMERAS.items()))
    ap.add_argument("--spread", type=float,
                    help="hold the layout: every block and goal within this share of the simulator's own range "
                         "of one layout the seed draws (0.2: +-3 cm), as a real recording puts its objects back")
    ap.add_argument("--operator", action="store_true",
                    help="each demo moved its own way, as people's differ: speed, how high it comes down from, a "
                         "smooth wander (drawn per demo)")
    ap.add_argument("--home", action="store_true",
                    help="every pick-and-place demo puts the block down on a goal on the table and takes the arm "
                         "back to where it began, as people's demos end")
    ap.add_argument("--freeze-camera", help="the camera a frozen-camera demo's stops on (default: the second)")
    return ap


def cameras(args) -> tuple[str, ...]:
    return record.listed("--cameras", args.cameras, CAMERAS)


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    record.main(parser(), list(TASKS), _episode, _init, features, FPS, "fetch",
                init_args=lambda args: (args.length_scale, cameras(args), args.spread, args.seed, args.operator,
                                           args.home),
                plants=PLANTS)
