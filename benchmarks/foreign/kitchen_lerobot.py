"""A third simulator democheck did not make: the Franka kitchen of Gymnasium-Robotics (a 7-joint Panda commanded
by joint velocities), four tasks done by a scripted oracle on the simulator's own state, written by LeRobot's own
writer, with planted bad demos.  Runs in LeRobot's virtual environment, never in democheck's:

    python3.11 -m venv /tmp/lerobot-venv
    /tmp/lerobot-venv/bin/pip install lerobot==0.4.4 gymnasium-robotics==1.4.2 mujoco==3.3.7
    MUJOCO_GL=egl /tmp/lerobot-venv/bin/python benchmarks/foreign/kitchen_lerobot.py OUT --demos 40 --seed 0

OUT is a LeRobot v3.0 dataset at the simulator's 12 fps: camera ``observation.images.kitchen``, an 18-d state (the
arm's and fingers' joint positions and velocities, with the simulator's sensor noise), a 21-d
``observation.environment_state`` (every knob, switch, door and the kettle's position and quaternion, as the
simulator's observation holds them, noise included), 9-d actions (joint velocities, normalised to [-1, 1]);
``OUT.labels.csv`` beside it holds the ground truth.  The tasks: open the slide cabinet, the microwave, the hinge
cabinet's right door, and push the kettle toward the back of the stove.  The oracle moves the hand through waypoints
beside the handle or the kettle by damped least-squares inverse kinematics; each demo starts from its own arm pose
and kettle place and goes at its own speed.  Planted kinds, each replacing a demo of the task it is labelled with:
``idle`` (the arm never moves), ``random`` (uniformly random joint velocities), ``wrong-task`` (another task's
oracle), ``gave-up`` (the oracle until 30-60% of the steps it needs, then still), ``occluded`` (a grey card over
35-55% of the view), ``jerky`` (the oracle's actions plus Gaussian noise of SD 0.3-0.5, executed); on request
(``--kinds``), ``detour`` (on its way to the handle or the kettle the hand first goes to an empty spot 15-25 cm
aside and 5-15 cm up and back, then on as the oracle goes, 35 steps longer), and ``reset`` (a cabinet or door left
open as the oracle leaves it, the arm from its own start pose, and the hand pushing it shut again: the task undone,
as an operator puts the scene back between demos; the microwave and the hinge cabinet, kept only where the oracle
opened it and the hand shut it).  Clean demos are kept only where the oracle succeeds.  The same seed gives the same
dataset.
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

TASKS = {  # name -> (the task as the dataset names it, steps)
    "slide": ("open the slide cabinet", 60),
    "microwave": ("open the microwave door", 80),
    "hinge": ("open the right door of the hinge cabinet", 80),
    "kettle": ("push the kettle toward the back of the stove", 80),
}
CAMERA = "kitchen"
FPS = 12  # the simulator's own: 40 physics steps of 2 ms per control step
STATE_NAMES = ([f"joint{i}" for i in range(1, 8)] + ["finger.left", "finger.right"]
               + [f"joint{i}.vel" for i in range(1, 8)] + ["finger.left.vel", "finger.right.vel"])
ENV_NAMES = ["knob1", "burner1", "knob2", "burner2", "knob3", "burner3", "knob4", "burner4", "light_switch",
             "light", "slide_cabinet", "hinge.left", "hinge.right", "microwave", "kettle.x", "kettle.y", "kettle.z",
             "kettle.qw", "kettle.qx", "kettle.qy", "kettle.qz"]
ACTION_NAMES = [f"joint{i}.vel" for i in range(1, 8)] + ["finger.left.vel", "finger.right.vel"]
KETTLE = slice(23, 30)  # the kettle's free joint in qpos
JOINT = {"slide": 19, "microwave": 22, "hinge": 21}
HANDLE = {"microwave": "microhandle_site", "hinge": "hinge_site2"}  # the sites the hand pushes a door shut at
PLANTS = {"detour": tuple(TASKS), "reset": tuple(HANDLE)}  # the slide cabinet opened is beyond the arm's reach
SHUT = 0.1  # a reset leaves its cabinet or door within this of shut (radians: about 6 degrees ajar)
DETOUR_STEPS = 35

_W: dict = {}


def _env():
    import gymnasium as gym
    import gymnasium_robotics

    if "env" not in _W:
        gym.register_envs(gymnasium_robotics)
        env = gym.make("FrankaKitchen-v1", render_mode="rgb_array", width=_W["size"][1], height=_W["size"][0]
                       ).unwrapped
        env.model.vis.quality.shadowsize = 0
        env.model.vis.quality.offsamples = 0
        env.model.mat_reflectance[:] = 0
        _W["env"] = env
    return _W["env"]


def _init(size: tuple[int, int]) -> None:
    warnings.filterwarnings("ignore")
    _W["size"] = size


def _site(env, name: str) -> np.ndarray:
    import mujoco

    return env.data.site_xpos[mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_SITE, name)].copy()


def waypoints(task: str, env, rng: np.random.Generator) -> list[np.ndarray]:
    """Where the hand goes, in order: beside the handle (or behind the kettle), then along the way it opens."""
    jitter = lambda: rng.normal(0, 0.01, 3)  # noqa: E731
    if task == "slide":
        s = _site(env, "slide_site")
        return [s + [-0.10, -0.12, 0] + jitter(), s + [-0.07, 0, 0], s + [rng.uniform(0.3, 0.4), 0, 0]]
    if task == "microwave":
        h = _site(env, "microhandle_site")
        return [h + [0, -0.12, 0] + jitter(), h + [0.05, 0.02, 0], h + [0.15, -0.25, 0] + jitter(),
                h + [0.3, -0.4, 0]]
    if task == "hinge":
        h = _site(env, "hinge_site2")
        return [h + [0.12, -0.12, 0] + jitter(), h + [0.05, 0.03, 0], h + [0.2, -0.15, 0] + jitter(),
                h + [0.35, -0.3, 0]]
    k = env.data.qpos[KETTLE][:3].copy()  # over the stove's rim, behind the kettle's body
    z = rng.uniform(0.18, 0.24)
    return [k + [0, -0.25, z + 0.05] + jitter(), k + [0, -0.14, z], k + [rng.uniform(-0.03, 0.03), 0.35, z]]


def undo_waypoints(task: str, env, shut: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Where the hand goes to shut a door the task left open (the microwave's, the hinge cabinet's): in front of its
    handle where it is now, then to where the handle is shut (``shut``), then back off it, as a hand lets go of a door
    it has shut."""
    h = _site(env, HANDLE[task])
    return [h + [0, -0.12, 0] + rng.normal(0, 0.01, 3), h + [0, -0.03, 0], shut + [0, -0.01, 0],
            shut + [0, -0.15, 0] + rng.normal(0, 0.01, 3)]


def _opened(task: str, layout_seed: int) -> float | None:
    """The task's joint where its oracle leaves it on this layout (a clean demo's end); None where it fails there."""
    env = _env()
    env.reset(seed=layout_seed)
    layout = np.random.default_rng(layout_seed)
    memory = _start(env, task, layout)
    start = env.data.qpos.copy()
    for _ in range(TASKS[task][1]):
        env.step(oracle(env, memory))
    return float(env.data.qpos[JOINT[task]]) if _success(task, env, start) else None


def _start(env, task: str, layout: np.random.Generator) -> dict:
    """The layout's arm pose and kettle place, and the oracle's memory for ``task`` on it."""
    import mujoco

    env.data.qpos[:7] += layout.normal(0, 0.06, 7)
    env.data.qpos[KETTLE][:2] += layout.uniform(-0.03, 0.03, 2)
    mujoco.mj_forward(env.model, env.data)
    ee = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
    return {"points": waypoints(task, env, layout), "next": 0, "speed": layout.uniform(0.04, 0.07),
            "rot": env.data.site_xmat[ee].reshape(3, 3).copy()}


def oracle(env, memory: dict) -> np.ndarray:
    """The joint velocities that take the hand toward the next waypoint at the demo's speed, keeping the hand's
    orientation from the start (damped least squares on the hand site's Jacobian)."""
    import mujoco

    m, d = env.model, env.data
    ee = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
    x, rot = d.site_xpos[ee], d.site_xmat[ee].reshape(3, 3)
    points = memory["points"]
    memory["spent"] = memory.get("spent", 0) + 1
    # On to the next waypoint once there, or after 25 steps short of one it cannot reach (a handle in the way).
    if memory["next"] < len(points) - 1 and (np.linalg.norm(points[memory["next"]] - x) < 0.015
                                             or memory["spent"] > 25):
        memory["next"], memory["spent"] = memory["next"] + 1, 0
    target = points[memory["next"]]
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jp, jr, ee)
    jac = np.vstack([jp, jr])[:, :7]
    err = target - x
    err *= min(1.0, memory["speed"] / max(np.linalg.norm(err), 1e-9))
    turn = 0.5 * sum(np.cross(rot[:, i], memory["rot"][:, i]) for i in range(3))
    dq = jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(6), np.r_[err, 0.5 * turn])
    return np.r_[np.clip(dq / 0.08, -1, 1), 1.0, 1.0]


def _progress(task: str, env, start: np.ndarray) -> float:
    if task == "kettle":
        return float(env.data.qpos[KETTLE][1] - start[KETTLE][1])
    return float(env.data.qpos[JOINT[task]])


def _success(task: str, env, start: np.ndarray) -> bool:
    p = _progress(task, env, start)
    return {"slide": p > 0.25, "microwave": p < -0.3, "hinge": p > 0.2, "kettle": p > 0.04}[task]


def _rollout(task: str, scene: str, kind: str, rng: np.random.Generator, seed: int, stop: int | None = None
             ) -> dict:
    """One episode: ``task``'s oracle (or ``kind``'s behaviour) from the layout ``seed`` draws, judged as
    ``scene``; the arm still from ``stop`` on."""
    import mujoco

    env = _env()
    opened = _opened(task, seed) if kind == "reset" else None
    env.reset(seed=seed)
    closed = env.data.qpos.copy()
    layout = np.random.default_rng(seed)
    memory = _start(env, task, layout)
    if kind == "reset" and opened is not None:  # the cabinet or door as the task leaves it, the arm at its start
        shut = _site(env, HANDLE[task])
        env.data.qpos[JOINT[task]] = opened
        mujoco.mj_forward(env.model, env.data)
        memory["points"] = undo_waypoints(task, env, shut, layout)
    obs = env._get_obs(env.robot_env._get_obs())  # the first step's record of the pose and the objects set here
    start = env.data.qpos.copy()
    noise = rng.uniform(0.3, 0.5) if kind == "jerky" else 0.0
    steps = TASKS[scene][1]
    if kind == "reset":  # done where the task is undone: shut again (never where it was never opened)
        def done() -> bool:
            return opened is not None and abs(env.data.qpos[JOINT[task]] - closed[JOINT[task]]) < SHUT
    else:
        def done() -> bool:
            return _success(scene, env, start)
    if kind == "detour":  # from the approach to a spot aside and back, before the handle or the kettle
        turn = rng.uniform(0, 2 * np.pi)
        aside = rng.uniform(0.15, 0.25) * np.r_[np.cos(turn), np.sin(turn), 0] + np.r_[0, 0, rng.uniform(0.05, 0.15)]
        approach = memory["points"][0]
        memory["points"][1:1] = [approach + aside, approach.copy()]
        steps += DETOUR_STEPS
    frames, state, env_state, actions, first = [], [], [], [], None
    for t in range(steps):
        frames.append(env.render().copy())
        o = obs["observation"]
        state.append(o[:18].astype(np.float32))
        env_state.append(o[18:39].astype(np.float32))
        a = planted_action("clean" if kind in PLANTS else kind, t, stop, rng, noise, 9, lambda: oracle(env, memory))
        actions.append(np.asarray(a, np.float32))
        obs, *_ = env.step(np.asarray(a, np.float64))
        if first is None and done():
            first = t + 1
    return {"frames": np.stack(frames), "state": np.stack(state), "env_state": np.stack(env_state),
            "actions": np.stack(actions), "first_success": first, "success": done()}


def _episode(job: tuple) -> dict:
    return episode(job, _rollout, {name: words for name, (words, *_) in TASKS.items()})


def features(size: tuple[int, int]) -> dict:
    return record.features([CAMERA], size, STATE_NAMES, ENV_NAMES, ACTION_NAMES)


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    record.main(record.parser(__doc__, demos=40, size="96"), list(TASKS), _episode, _init, features, FPS, "franka",
                plants=PLANTS)
