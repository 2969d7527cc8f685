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
from democheck.sim.env import ENV_STATE_DIM, Layout, PushEnv
from democheck.sim.scene import ARM_JOINTS


def render_posed(sims: Sequence[dict], arm_poses: np.ndarray, per_demo: int, seed: int,
                 on_progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each demo's sim record (its ``target``, ``distractor``, ``layout`` and ``image_size``), ``per_demo``
    frames of its layout with the arm's joints set to poses drawn from ``arm_poses`` [M, 7] (no physics step: the
    scene as posed).  Returns uint8 frames [N, per_demo, H, W, 3] and the objects' poses there [N, per_demo, 6]
    (target x, y, yaw, distractor x, y, yaw: ``observation.environment_state``'s order).  The same ``seed``
    renders the same frames."""
    arm_poses = np.asarray(arm_poses, np.float64)
    if arm_poses.ndim != 2 or arm_poses.shape[1] != len(ARM_JOINTS) or not len(arm_poses):
        raise ValueError(f"arm_poses must be [M, {len(ARM_JOINTS)}] joint positions, not {arm_poses.shape}")
    rng = np.random.default_rng([seed, 0x905E])
    frames, poses, env = [], np.zeros((len(sims), per_demo, ENV_STATE_DIM), np.float32), None
    try:
        for n, sim in enumerate(sims):
            pair = (OBJECTS[sim["target"]], OBJECTS[sim["distractor"]])
            if env is None:
                env = PushEnv(pair, image_size=int(sim["image_size"]))
            else:
                env.set_task(pair)
            layout = Layout.from_dict(sim["layout"])
            for arm in arm_poses[rng.integers(0, len(arm_poses), per_demo)]:
                posed = Layout(layout.target, layout.distractor, tuple(float(a) for a in arm))
                frames.append(env.reset(options={"layout": posed})[0]["image"])
            poses[n] = np.asarray(layout.target + layout.distractor, np.float32)
            if on_progress:
                on_progress(n + 1, len(sims))
    finally:
        if env is not None:
            env.close()
    if not frames:
        return np.zeros((0, per_demo, 0, 0, 3), np.uint8), poses
    return np.stack(frames).reshape(len(sims), per_demo, *frames[0].shape), poses
