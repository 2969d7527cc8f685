"""Frames of a pushing suite's layouts with the arm posed as in other demos.

In a demo the expert's arm heads for the target, so a network that learns where the objects are from demo frames
can read the target off the arm -- and in closed loop, where the arm goes wherever the controller sends it, such a
network reports the controller's own intention back (docs/results.md, "The points read the arm").  These frames
break the link: each demo's objects where they began, the arm posed as at a random step of another demo.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from democheck.sim.catalog import OBJECTS
from democheck.sim.env import ENV_STATE_DIM, STATE_DIM, Layout, PushEnv
from democheck.sim.scene import ARM_JOINTS


def render_posed(sims: Sequence[dict], arm_poses: np.ndarray, per_demo: int, seed: int,
                 on_progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each demo's sim record (its ``target``, ``distractor``, ``layout`` and ``image_size``), ``per_demo``
    frames of its layout with the arm's joints set to poses drawn from ``arm_poses`` [M, 7] (``render_layouts``).
    The same ``seed`` renders the same frames."""
    arm_poses = np.asarray(arm_poses, np.float64)
    if arm_poses.ndim != 2 or arm_poses.shape[1] != len(ARM_JOINTS) or not len(arm_poses):
        raise ValueError(f"arm_poses must be [M, {len(ARM_JOINTS)}] joint positions, not {arm_poses.shape}")
    rng = np.random.default_rng([seed, 0x905E])
    arms = np.stack([arm_poses[rng.integers(0, len(arm_poses), per_demo)] for _ in sims]) if len(sims) else \
        np.zeros((0, per_demo, len(ARM_JOINTS)))
    return render_layouts(sims, arms, on_progress)[:2]


def render_layouts(sims: Sequence[dict], arms: np.ndarray, on_progress: Callable[[int, int], None] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each demo's layout (its sim record's) with the arm posed as each of ``arms[n]`` [N, K, 7] in turn, the scene
    as posed (no physics step).  Returns uint8 frames [N, K, H, W, 3], the objects' poses there [N, K, 6] (target
    x, y, yaw, distractor x, y, yaw: ``observation.environment_state``'s order) and the robot's state [N, K, 17]
    (``observation.state``: the arm at rest)."""
    arms = np.asarray(arms, np.float64)
    k = arms.shape[1] if arms.ndim == 3 else 0
    frames, states, poses, env = [], [], np.zeros((len(sims), k, ENV_STATE_DIM), np.float32), None
    try:
        for n, sim in enumerate(sims):
            pair = (OBJECTS[sim["target"]], OBJECTS[sim["distractor"]])
            if env is None:
                env = PushEnv(pair, image_size=int(sim["image_size"]))
            else:
                env.set_task(pair)
            layout = Layout.from_dict(sim["layout"])
            for arm in arms[n]:
                posed = Layout(layout.target, layout.distractor, tuple(float(a) for a in arm))
                obs = env.reset(options={"layout": posed})[0]
                frames.append(obs["image"])
                states.append(obs["state"])
            poses[n] = np.asarray(layout.target + layout.distractor, np.float32)
            if on_progress:
                on_progress(n + 1, len(sims))
    finally:
        if env is not None:
            env.close()
    if not frames:
        return np.zeros((len(sims), k, 0, 0, 3), np.uint8), poses, np.zeros((len(sims), k, STATE_DIM), np.float32)
    return (np.stack(frames).reshape(len(sims), k, *frames[0].shape), poses,
            np.stack(states).reshape(len(sims), k, -1))
