"""The scripted expert: operational-space pushing with torque commands.

The expert sees the simulator's true object poses (it is privileged, as a
human teleoperator would be).  It moves the fingertip with an end-effector PD
law mapped to joint torques through the Jacobian and the operational-space
inertia, holds the arm near its home posture in the null space, and follows
a small state machine:

1. *approach*: lift to a safe height and fly to a point behind the target on
   the goal-to-target line;
2. *descend* to pushing height;
3. *push*: keep the fingertip on that line, a little inside the object, so the
   target is pushed through its centre towards the goal; if the target slips
   off the line, go back to *approach*;
4. *retreat*: once the target is at the goal, back away and hold still.

``ScriptedExpert`` keeps its phase from step to step (with hysteresis), so the same simulator state can get
different actions -- labels a learner cannot fit from what it sees.  ``MarkovianExpert`` decides the phase
from the geometry of the current state alone, every step, and so also recovers from any state the arm can
reach (``benchmarks/expert_recovery.py`` measures it from random arm poses and object offsets mid-episode).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from democheck.sim import scene
from democheck.sim.env import PushEnv

Z_SAFE = 0.105
Z_PUSH = 0.022
KP, KD = 150.0, 22.0
KQ, KDQ = 1.5, 0.3
MAX_ERR = 0.12
PUSH_LEAD = 0.06  # how far ahead of the fingertip the push waypoint runs


class ScriptedExpert:
    """Call ``act(env)`` once per control step after ``env.reset``; returns normalised torques."""

    def __init__(self, env: PushEnv, role: str = "target"):
        self.env = env
        self.role = role
        self.phase = "approach"
        self._retreat_point = np.zeros(3)
        self._jac = np.zeros((3, env.model.nv))
        self._jminv = np.zeros((3, env.model.nv))

    def reset(self) -> None:
        self.phase = "approach"

    def _object_xy(self) -> np.ndarray:
        return self.env.data.qpos[self.env._obj_qadr[self.role][:2]].copy()

    def _object_radius(self) -> float:
        return (self.env.target if self.role == "target" else self.env.distractor).radius

    def waypoint(self) -> np.ndarray:
        """Where the fingertip should go next, updating the phase."""
        tip = self.env.tip_pos
        obj = self._object_xy()
        to_goal = scene.GOAL_XY - obj
        dist = math.hypot(*to_goal)
        u = to_goal / max(dist, 1e-9)
        r = self._object_radius()
        behind = obj - u * (r + scene.TIP_RADIUS + 0.02)
        if self.phase != "retreat" and dist < 0.012:
            self.phase = "retreat"
            # Back away along the last push direction and up, never across the object.
            self._retreat_point = np.array([*(tip[:2] - u * 0.05), Z_SAFE])
        if self.phase == "retreat":
            if dist < scene.GOAL_RADIUS * 0.7:
                return self._retreat_point
            self.phase = "approach"  # drifted out: push again
        if self.phase == "push":
            rel = obj - tip[:2]
            along = float(np.dot(-rel, u))
            cos = float(np.dot(rel, u)) / max(np.linalg.norm(rel), 1e-9)
            if along > -0.3 * r or cos < np.cos(np.radians(55)):
                self.phase = "approach"
            else:
                # A point on the push line just ahead of the fingertip: the PD law's pull is the push.
                # Slow down near the goal so the target does not overshoot.
                lead = float(np.clip(dist, 0.02, PUSH_LEAD))
                return np.array([*(obj + u * (along + lead)), Z_PUSH])
        if self.phase == "approach":
            if np.linalg.norm(tip[:2] - behind) < 0.02:
                self.phase = "descend"
            else:
                # Stay high while far from the pre-push point so the tip never sweeps through objects.
                return np.array([*behind, Z_SAFE])
        if self.phase == "descend":
            if np.linalg.norm(tip[:2] - behind) > 0.04:
                self.phase = "approach"
                return np.array([*behind, Z_SAFE])
            if tip[2] < Z_PUSH + 0.012:
                self.phase = "push"
                return np.array([*(behind + u * PUSH_LEAD), Z_PUSH])
            return np.array([*behind, Z_PUSH])
        raise AssertionError(self.phase)

    def act(self) -> np.ndarray:
        env, m, d = self.env, self.env.model, self.env.data
        goal = self.waypoint()
        dofs = env.arm_dofs
        mujoco.mj_jacSite(m, d, self._jac, None, env.tip_site)
        # J M^-1 from MuJoCo's own factorisation of M (the arm's block is independent of the objects').
        mujoco.mj_solveM(m, d, self._jminv, self._jac)
        J, JMinv = self._jac[:, dofs], self._jminv[:, dofs]
        lam = np.linalg.inv(J @ JMinv.T + 1e-4 * np.eye(3))  # operational-space inertia
        err = goal - d.site_xpos[env.tip_site]
        n = math.sqrt(float(err @ err))
        if n > MAX_ERR:
            err *= MAX_ERR / n
        qvel = d.qvel[dofs]
        force = lam @ (KP * err - KD * (J @ qvel))
        # Null space: stay near the home posture and damp internal motion, without disturbing the fingertip.
        posture = KQ * (scene.ARM_HOME - d.qpos[env._arm_qadr]) - KDQ * qvel
        torque = J.T @ force + posture - J.T @ (lam @ (JMinv @ posture))
        return np.clip(torque / scene.TORQUE_LIMIT, -1.0, 1.0).astype(np.float32)


# MarkovianExpert's geometry (metres): where each phase holds, decided afresh every step.
AT_GOAL = 0.5 * scene.GOAL_RADIUS  # the target this near the goal's centre: done, stay clear
PUSH_CONE = np.cos(np.radians(55))  # the fingertip within this cone behind the target pushes it
PUSH_REACH = 0.07  # ... and at most this far beyond touching it
NEAR_BEHIND, FAR_BEHIND = 0.02, 0.045  # the pre-push point: descend fully inside, stay high outside
LOW = Z_SAFE - 0.035  # below this, a fingertip that is not pushing goes straight up before it travels
CLEAR = 0.07  # how far from the target's centre the fingertip waits once the target is in


class MarkovianExpert(ScriptedExpert):
    """The same pushing expert with no memory: its action is a function of the simulator's current state."""

    def waypoint(self) -> np.ndarray:
        tip = self.env.tip_pos
        obj = self._object_xy()
        r = self._object_radius()
        to_goal = scene.GOAL_XY - obj
        dist = math.hypot(*to_goal)
        if dist < AT_GOAL:
            self.phase = "retreat"
            away = tip[:2] - obj  # away from the target, from where the fingertip is (else back along the push)
            n = float(np.linalg.norm(away))
            if n > 1e-3:
                away = away / n
            elif dist > 1e-3:
                away = -to_goal / dist
            else:
                away = np.array([-1.0, 0.0])
            if n >= r + CLEAR - 0.01 or tip[2] > LOW:  # clear of the target (or above it): wait up there
                return np.array([*(obj + away * (r + CLEAR)), Z_SAFE])
            return np.array([*(tip[:2] + away * 0.03), Z_SAFE])  # back off and up, never across the target
        u = to_goal / dist
        behind = obj - u * (r + scene.TIP_RADIUS + 0.02)
        rel = obj - tip[:2]
        along = float(np.dot(-rel, u))  # the fingertip's position along the push line (negative: behind)
        cos = float(np.dot(rel, u)) / max(float(np.linalg.norm(rel)), 1e-9)
        gap = float(np.linalg.norm(rel)) - r - scene.TIP_RADIUS
        low = tip[2] < Z_PUSH + 0.015
        if low and along <= -0.3 * r and cos >= PUSH_CONE and gap < PUSH_REACH:
            self.phase = "push"
            lead = float(np.clip(dist, 0.02, PUSH_LEAD))
            return np.array([*(obj + u * (along + lead)), Z_PUSH])
        off = float(np.linalg.norm(tip[:2] - behind))
        if off < FAR_BEHIND:
            # Over the pre-push point: descend, fully once within NEAR_BEHIND, in proportion between.
            self.phase = "descend"
            w = float(np.clip((FAR_BEHIND - off) / (FAR_BEHIND - NEAR_BEHIND), 0.0, 1.0))
            return np.array([*behind, Z_SAFE + w * (Z_PUSH - Z_SAFE)])
        self.phase = "approach"
        if tip[2] < LOW:  # low and not pushing: straight up first, so the fingertip never sweeps through objects
            return np.array([*tip[:2], Z_SAFE])
        return np.array([*behind, Z_SAFE])
