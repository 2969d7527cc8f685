"""A third simulator democheck did not make: OGBench's manipulation scene (a 6-DoF arm with a gripper, a cube, two
buttons that lock a drawer and a window), seven tasks done by OGBench's own Markovian oracles, written by LeRobot's
own writer, with planted bad demos.  Runs in LeRobot's virtual environment with OGBench and the MuJoCo 4 it needs
(Fetch and the kitchen want MuJoCo 3.3.7: give each its own environment, or reinstall between them):

    /tmp/lerobot-venv/bin/pip install ogbench==1.2.2
    /tmp/lerobot-venv/bin/pip install --force-reinstall --no-deps mujoco==4.0.1 mujoco-core==4.0.1 mujoco-studio==4.0.1
    MUJOCO_GL=egl /tmp/lerobot-venv/bin/python benchmarks/foreign/scene_lerobot.py OUT --demos 24 --plant 6 --seed 0

OUT is a LeRobot v3.0 dataset: camera ``observation.images.front``, a 19-d state (joint positions and velocities,
the hand's position, yaw, opening, its speed and contact; named), a 13-d ``observation.environment_state`` (the
cube's position and quaternion as the simulator holds it, each button's state and travel, the drawer's and the
window's slide; named), 5-d actions (hand motion, yaw, gripper), 20 fps.  The tasks: move the cube to its target,
press the left or the right button (each press toggles it, and so the lock it holds), open or close the drawer,
open or close the window.  An episode lasts until the oracle is done (its hand parked at a random place), so
lengths vary by demo and task.  Planted kinds as in ``record.py``: idle, random, wrong-task (another task's oracle
in this task's scene), gave-up, occluded, jerky.  ``OUT.labels.csv`` holds the ground truth; the same seed gives
the same dataset.
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

TASKS = {  # name -> (the task as the dataset names it, OGBench's target task, the steps a planted demo lasts)
    "cube": ("move the cube to its target", "cube", 90),
    "button-left": ("press the left button", "button", 40),
    "button-right": ("press the right button", "button", 40),
    "drawer-open": ("open the drawer", "drawer", 60),
    "drawer-close": ("close the drawer", "drawer", 60),
    "window-open": ("open the window", "window", 60),
    "window-close": ("close the window", "window", 60),
}
MAX_STEPS = 150
CAMERA = "front"
FPS = 20
STATE_NAMES = [*(f"joint{i}.pos" for i in range(6)), *(f"joint{i}.vel" for i in range(6)), "hand.x", "hand.y",
               "hand.z", "hand.yaw", "gripper.opening", "gripper.vel", "gripper.contact"]
ENV_NAMES = ["cube.x", "cube.y", "cube.z", "cube.qw", "cube.qx", "cube.qy", "cube.qz", "button0_state",
             "button0_pos", "button1_state", "button1_pos", "drawer_pos", "window_pos"]

_W: dict = {}


def _init(size: tuple[int, int]) -> None:
    import gymnasium as gym
    import ogbench  # noqa: F401  (registers the environments)

    warnings.filterwarnings("ignore")
    env = gym.make("scene-v0", mode="data_collection", terminate_at_goal=False, visualize_info=False,
                   width=size[1], height=size[0], render_mode="rgb_array").unwrapped
    env._model.vis.quality.shadowsize = 0
    env._model.vis.quality.offsamples = 0
    env._model.mat_reflectance[:] = 0
    _W["env"] = env


def _oracle(task: str):
    from ogbench.manipspace.oracles.markov.button_markov import ButtonMarkovOracle
    from ogbench.manipspace.oracles.markov.cube_markov import CubeMarkovOracle
    from ogbench.manipspace.oracles.markov.drawer_markov import DrawerMarkovOracle
    from ogbench.manipspace.oracles.markov.window_markov import WindowMarkovOracle

    kind = TASKS[task][1]
    return {"cube": CubeMarkovOracle, "button": ButtonMarkovOracle, "drawer": DrawerMarkovOracle,
            "window": WindowMarkovOracle}[kind](env=_W["env"])


def _matches(task: str, env) -> bool:
    """Whether the target OGBench drew is ``task``'s."""
    kind = TASKS[task][1]
    if env._target_task != kind:
        return False
    if kind == "button":
        return env._target_button == (0 if task == "button-left" else 1)
    if kind == "drawer":
        return (env._target_drawer_pos < -0.08) == (task == "drawer-open")
    if kind == "window":
        return (env._target_window_pos > 0.1) == (task == "window-open")
    return True


def _target(task: str, env) -> bool:
    """Draw OGBench targets until one is ``task``'s; False when none is in 60 draws (e.g. no drawer to close)."""
    for _ in range(60):
        env.set_new_target(return_info=False)
        if _matches(task, env):
            return True
    return False


def _goal(task: str, env, start: dict) -> dict:
    """What ``task``'s success is judged by, read from the scene before the demo."""
    return {"cube": env._data.mocap_pos[env._cube_target_mocap_ids[0]].copy(),
            "buttons": start["button_states"].copy()}


def _success(task: str, env, goal: dict) -> bool:
    kind = TASKS[task][1]
    if kind == "cube":
        return bool(np.linalg.norm(env._data.joint("object_joint_0").qpos[:3] - goal["cube"]) <= 0.04)
    if kind == "button":
        i = 0 if task == "button-left" else 1
        return bool(env._cur_button_states[i] != goal["buttons"][i])
    if kind == "drawer":
        q = env._data.joint("drawer_slide").qpos[0]
        return bool(q <= -0.12) if task == "drawer-open" else bool(q >= -0.04)
    q = env._data.joint("window_slide").qpos[0]
    return bool(q >= 0.16) if task == "window-open" else bool(q <= 0.04)


def _observe(info: dict) -> tuple[np.ndarray, np.ndarray]:
    state = np.concatenate([np.atleast_1d(info[k]) for k in ("proprio/joint_pos", "proprio/joint_vel", "proprio/effector_pos",
                                              "proprio/effector_yaw", "proprio/gripper_opening",
                                              "proprio/gripper_vel", "proprio/gripper_contact")])
    env_state = np.concatenate([np.atleast_1d(info[k]) for k in ("privileged/block_0_pos", "privileged/block_0_quat",
                                                  "privileged/button_0_state", "privileged/button_0_pos",
                                                  "privileged/button_1_state", "privileged/button_1_pos",
                                                  "privileged/drawer_pos", "privileged/window_pos")])
    return state.astype(np.float32), env_state.astype(np.float32)


def _rollout(task: str, scene: str, kind: str, rng: np.random.Generator, seed: int, stop: int | None = None
             ) -> dict:
    """One episode on layout ``seed`` with ``scene``'s target: ``task``'s oracle (or ``kind``'s behaviour) until
    the oracle is done, or for ``scene``'s planted length where no oracle leads; the arm still from ``stop`` on."""
    env = _W["env"]
    if task != scene and TASKS[task][1] == TASKS[scene][1] in ("drawer", "window"):
        task = "cube"  # opening what is to be closed cannot be drawn on one layout: the other wrong task
    for k in range(50):  # the first layout of this seed's sequence on which both targets can be drawn
        np.random.seed((seed + k) % (1 << 32))  # the oracles draw where to park the hand from NumPy's generator
        ob, info = env.reset(seed=seed + k)
        if not _target(scene, env):  # e.g. no drawer to close: it is closed already
            continue
        goal = _goal(scene, env, env.get_reset_info())
        if task == scene or _target(task, env):  # the other task's target, which its oracle reads
            break
    else:
        raise RuntimeError(f"layout {seed}: no {scene} target in 50 layouts")
    info = env.get_reset_info()
    oracle = _oracle(task)
    oracle.reset(ob, info)
    led = kind in ("clean", "occluded", "wrong-task", "jerky")
    steps = MAX_STEPS if led else TASKS[scene][2]
    noise = rng.uniform(0.3, 0.5) if kind == "jerky" else 0.0
    frames, state, env_state, actions, first = [], [], [], [], None
    for t in range(steps):
        frames.append(env.render().copy())
        s, e = _observe(info)
        state.append(s)
        env_state.append(e)
        a = planted_action(kind, t, stop, rng, noise, 5, lambda: oracle.select_action(ob, info))
        actions.append(np.asarray(a, np.float32))
        ob, _, _, _, info = env.step(np.asarray(a, np.float32))
        if first is None and _success(scene, env, goal):
            first = t + 1
        if led and oracle.done:
            break
    return {"frames": np.stack(frames), "state": np.stack(state), "env_state": np.stack(env_state),
            "actions": np.stack(actions), "first_success": first, "success": _success(scene, env, goal)}


def _episode(job: tuple) -> dict:
    return episode(job, _rollout, {name: words for name, (words, *_) in TASKS.items()}, min_first=3)


def features(size: tuple[int, int]) -> dict:
    return record.features([CAMERA], size, STATE_NAMES, ENV_NAMES, ["dx", "dy", "dz", "dyaw", "gripper"])


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    record.main(record.parser(__doc__, demos=24, size="128"), list(TASKS), _episode, _init, features, FPS,
                "ogbench-scene")
