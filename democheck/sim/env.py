"""``PushEnv``: the pushing task with the Gymnasium API.

Observation: ``image`` uint8 [H, W, 3] from the fixed camera and ``state``
float32 [17] = joint positions (7), joint velocities (7), fingertip xyz (3).
Action: 7 normalised joint torques in [-1, 1], scaled to +-2 N m.
Success: the target's centre lies within ``GOAL_RADIUS`` of the goal's centre
on at least ``SUCCESS_STEPS`` control steps of the episode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from democheck.sim import scene
from democheck.sim.catalog import ObjectSpec, Task
from democheck.sim.render import FrameRenderer

EPISODE_STEPS = 100
SUCCESS_STEPS = 10
STATE_DIM = 17
ACTION_DIM = 7
ENV_STATE_DIM = 6  # target (x, y, yaw), distractor (x, y, yaw)

STATE_NAMES = [f"{j}.pos" for j in scene.ARM_JOINTS] + [f"{j}.vel" for j in scene.ARM_JOINTS] + ["tip.x", "tip.y", "tip.z"]
ACTION_NAMES = [f"{j}.torque" for j in scene.ARM_JOINTS]
ENV_STATE_NAMES = ["target.x", "target.y", "target.yaw", "distractor.x", "distractor.y", "distractor.yaw"]


@dataclass(frozen=True)
class Layout:
    """Everything that differs between two episodes of one task: enough to re-simulate exactly."""

    target: tuple[float, float, float]
    distractor: tuple[float, float, float]
    arm_qpos: tuple[float, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"target": list(self.target), "distractor": list(self.distractor), "arm_qpos": list(self.arm_qpos)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Layout":
        return cls(tuple(d["target"]), tuple(d["distractor"]), tuple(d["arm_qpos"]))


def sample_layout(rng: np.random.Generator, target: ObjectSpec, distractor: ObjectSpec) -> Layout:
    """Object poses inside the workspace box, placed so the push corridor is clear of the distractor."""
    lo, hi = scene.WORKSPACE[:, 0], scene.WORKSPACE[:, 1]
    rt, rd = target.radius, distractor.radius
    for _ in range(10_000):
        t = rng.uniform(lo, hi)
        d = rng.uniform(lo, hi)
        to_goal = scene.GOAL_XY - t
        dist = np.linalg.norm(to_goal)
        if dist < scene.GOAL_RADIUS + 0.06:
            continue
        u = to_goal / dist
        behind = t - u * (rt + scene.TIP_RADIUS + 0.04)  # where the fingertip starts its push
        if np.linalg.norm(d - t) < rt + rd + 0.03 or np.linalg.norm(d - scene.GOAL_XY) < scene.GOAL_RADIUS + rd + 0.02:
            continue
        if _segment_distance(d, behind, scene.GOAL_XY) < rt + rd + 0.02:
            continue
        break
    else:  # pragma: no cover - the box is large enough that this never happens
        raise RuntimeError("could not place the objects")
    arm = scene.ARM_HOME + rng.normal(0.0, 0.03, size=7)
    yaw_t, yaw_d = rng.uniform(-np.pi, np.pi, size=2)
    return Layout((float(t[0]), float(t[1]), float(yaw_t)), (float(d[0]), float(d[1]), float(yaw_d)),
                  tuple(float(v) for v in arm))


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    s = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + s * ab)))


class PushEnv(gym.Env):
    """Push the task's target object into the goal disc with a 7-DoF torque-driven arm."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": scene.FPS}

    def __init__(self, task: Task | tuple[ObjectSpec, ObjectSpec], image_size: int = 64,
                 max_steps: int = EPISODE_STEPS, with_objects: bool = True, render_images: bool = True,
                 occluder: bool = False):
        self.image_size = int(image_size)
        self.max_steps = int(max_steps)
        self.with_objects = with_objects
        self.occluder = occluder and with_objects
        self.render_images = render_images
        self.render_mode = "rgb_array"
        self.observation_space = gym.spaces.Dict({
            "image": gym.spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8),
            "state": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32),
        })
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        self._renderer: FrameRenderer | None = None
        self.set_task(task)

    # -- scene -------------------------------------------------------------
    def set_task(self, task: Task | tuple[ObjectSpec, ObjectSpec]) -> None:
        """Rebuild the scene for another (target, distractor) pair, keeping the GL context."""
        target, distractor = (task.target, task.distractor) if isinstance(task, Task) else task
        self.target, self.distractor = target, distractor
        spec = scene.build_spec(target if self.with_objects else None, distractor if self.with_objects else None,
                                self.image_size, occluder=self.occluder)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        # Resolve names to addresses once, not per step.
        self._tip = m.site("tip").id
        self._arm_qadr = np.array([m.joint(j).qposadr[0] for j in scene.ARM_JOINTS])
        self._arm_vadr = np.array([m.joint(j).dofadr[0] for j in scene.ARM_JOINTS])
        self._obj_qadr = {}
        if self.with_objects:
            for role in ("target", "distractor"):
                self._obj_qadr[role] = np.array([m.joint(f"{role}_{a}").qposadr[0] for a in ("x", "y", "yaw")])
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self.render_images:
            self._renderer = FrameRenderer(self.model, self.image_size)

    # -- Gymnasium API -----------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        layout = options.get("layout")
        if layout is None:
            layout = sample_layout(self.np_random, self.target, self.distractor)
        elif isinstance(layout, dict):
            layout = Layout.from_dict(layout)
        self.layout = layout
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._arm_qadr] = layout.arm_qpos
        if self.with_objects:
            self.data.qpos[self._obj_qadr["target"]] = layout.target
            self.data.qpos[self._obj_qadr["distractor"]] = layout.distractor
        mujoco.mj_forward(self.model, self.data)
        self._follow_target()
        self.t = 0
        self.steps_in_goal = 0
        return self._observation(), self._info()

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.data.ctrl[:] = a * scene.TORQUE_LIMIT
        mujoco.mj_step(self.model, self.data, nstep=scene.FRAME_SKIP)
        self._follow_target()
        self.t += 1
        dist = self.target_to_goal()
        if dist < scene.GOAL_RADIUS:
            self.steps_in_goal += 1
        obs = self._observation()
        reward = -dist if self.with_objects else 0.0  # an empty scene has nothing to push
        return obs, float(reward), False, self.t >= self.max_steps, self._info(dist)

    def render(self) -> np.ndarray:
        if self._renderer is None:
            self._renderer = FrameRenderer(self.model, self.image_size)
        return self._renderer.render(self.data)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # -- helpers -----------------------------------------------------------
    def _follow_target(self) -> None:
        """Keep the occluder (when the scene has one) between the camera and the target."""
        if self.occluder:
            self.data.mocap_pos[0] = scene.occluder_pos(self.data.xpos[self.model.body("target").id])
            mujoco.mj_kinematics(self.model, self.data)  # so the frame rendered next shows it there

    def state(self) -> np.ndarray:
        d = self.data
        return np.concatenate([d.qpos[self._arm_qadr], d.qvel[self._arm_vadr], d.site_xpos[self._tip]]).astype(np.float32)

    def object_state(self) -> np.ndarray:
        """Target and distractor (x, y, yaw); NaN where the scene has no objects."""
        if not self.with_objects:
            return np.full(ENV_STATE_DIM, np.nan, dtype=np.float32)
        q = self.data.qpos
        return np.concatenate([q[self._obj_qadr["target"]], q[self._obj_qadr["distractor"]]]).astype(np.float32)

    def target_to_goal(self) -> float:
        if not self.with_objects:
            return float("inf")
        x, y = self.data.qpos[self._obj_qadr["target"][:2]]
        return math.hypot(x - scene.GOAL_XY[0], y - scene.GOAL_XY[1])

    @property
    def tip_pos(self) -> np.ndarray:
        return self.data.site_xpos[self._tip].copy()

    @property
    def tip_site(self) -> int:
        return self._tip

    @property
    def arm_dofs(self) -> np.ndarray:
        return self._arm_vadr

    def _observation(self) -> dict[str, np.ndarray]:
        image = self.render() if self.render_images else np.zeros((self.image_size,) * 2 + (3,), np.uint8)
        self.last_obs = {"image": image, "state": self.state()}  # what a closed-loop policy acts on
        return self.last_obs

    def _info(self, dist: float | None = None) -> dict[str, Any]:
        return {"success": self.steps_in_goal >= SUCCESS_STEPS, "steps_in_goal": self.steps_in_goal,
                "target_to_goal": self.target_to_goal() if dist is None else dist}
