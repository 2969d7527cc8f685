"""The pushing scene, composed in code with ``mujoco.MjSpec``.

Parts: a table, a fixed goal disc, a 7-DoF torque-driven arm ending in a
spherical fingertip, a *target* and a *distractor* object on planar joints
(slide x, slide y, hinge z), and one fixed camera.  Each part is added by its
own function, so probes can build the same scene without the objects.

Physics choices (see synth/README.md):
- The arm's links carry full gravity compensation (``gravcomp=1``), so the arm
  behaves as in a gravity-free pusher while the world keeps gravity.
- Objects have no vertical freedom and do not touch the table; table friction
  is modelled as joint damping and friction loss on their planar joints, which
  makes pushing quasi-static and keeps contact work small.
- Only the fingertip and the objects collide with each other (and the tip
  with the table), so the arm's links never snag on the scene.
"""

from __future__ import annotations


import mujoco
import numpy as np

from democheck.sim.catalog import ObjectSpec

# Bump when the arm, table, camera or physics change: it goes into every sim record.
SCENE_VERSION = 1

TIMESTEP = 0.01
FRAME_SKIP = 5  # control at 20 Hz
FPS = int(round(1.0 / (TIMESTEP * FRAME_SKIP)))
TORQUE_LIMIT = 2.0
TIP_RADIUS = 0.018

GOAL_XY = np.array([0.70, 0.0])
GOAL_RADIUS = 0.06
# Objects start inside this box (x range, y range); outside it is out of distribution.
WORKSPACE = np.array([[0.38, 0.56], [-0.24, 0.24]])

ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "upper_arm_roll", "elbow_flex", "forearm_roll", "wrist_flex", "wrist_roll")
ARM_HOME = np.array([0.0, -0.6, 0.0, 2.0, 0.0, 1.1, 0.0])  # fingertip at (0.30, 0, 0.12)
SHOULDER = np.array([0.0, 0.0, 0.28])
LINKS = (0.40, 0.34, 0.10)  # upper arm, forearm, wrist

# Collision bits: tip<->objects, objects<->objects, tip<->table.
_OBJ_BIT, _TABLE_BIT = 2, 4

CAMERA_POS = np.array([0.56, -0.50, 0.78])
CAMERA_LOOKAT = np.array([0.54, 0.02, 0.0])


OCCLUDER_HALF = (0.075, 0.075, 0.004)  # a grey card, large enough to hide any catalog object from the camera
OCCLUDER_RGBA = (0.42, 0.42, 0.45, 1.0)
OCCLUDER_FRACTION = 0.3  # where on the camera ray it hovers: this share of the way from the target to the camera


def _xyaxes(pos: np.ndarray, lookat: np.ndarray) -> list[float]:
    fwd = lookat - pos
    fwd /= np.linalg.norm(fwd)
    x = np.cross(fwd, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(x, fwd)
    return [*x, *y]


def add_table(spec: mujoco.MjSpec) -> None:
    wb = spec.worldbody
    wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.6, 0.5, 0.01], pos=[0.45, 0.0, -0.01],
                rgba=[0.50, 0.44, 0.38, 1.0], contype=_TABLE_BIT, conaffinity=_TABLE_BIT)
    wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1], pos=[0, 0, -0.4],
                rgba=[0.25, 0.27, 0.3, 1.0], contype=0, conaffinity=0)


def add_goal(spec: mujoco.MjSpec) -> None:
    spec.worldbody.add_geom(name="goal", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[GOAL_RADIUS, 0.001],
                            pos=[GOAL_XY[0], GOAL_XY[1], 0.001], rgba=[0.82, 0.82, 0.78, 1.0], contype=0, conaffinity=0)


def add_arm(spec: mujoco.MjSpec) -> None:
    wb = spec.worldbody
    wb.add_geom(name="pedestal", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.06, SHOULDER[2] / 2],
                pos=[0, 0, SHOULDER[2] / 2], rgba=[0.3, 0.3, 0.32, 1], contype=0, conaffinity=0)
    grey, dark = [0.75, 0.75, 0.78, 1.0], [0.35, 0.35, 0.4, 1.0]

    def joint(body, name, axis):
        body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=axis, damping=1.0, armature=0.05,
                       range=[-2.8, 2.8])

    shoulder = wb.add_body(name="shoulder", pos=SHOULDER.tolist(), gravcomp=1.0)
    joint(shoulder, "shoulder_pan", [0, 0, 1])
    shoulder.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.05, 0, 0], rgba=dark, contype=0, conaffinity=0)
    upper = shoulder.add_body(name="upper_arm", gravcomp=1.0)
    joint(upper, "shoulder_lift", [0, 1, 0])
    joint(upper, "upper_arm_roll", [1, 0, 0])
    upper.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, LINKS[0], 0, 0], size=[0.03, 0, 0],
                   rgba=grey, contype=0, conaffinity=0, density=300)
    fore = upper.add_body(name="forearm", pos=[LINKS[0], 0, 0], gravcomp=1.0)
    joint(fore, "elbow_flex", [0, 1, 0])
    joint(fore, "forearm_roll", [1, 0, 0])
    fore.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, LINKS[1], 0, 0], size=[0.025, 0, 0],
                  rgba=grey, contype=0, conaffinity=0, density=300)
    wrist = fore.add_body(name="wrist", pos=[LINKS[1], 0, 0], gravcomp=1.0)
    joint(wrist, "wrist_flex", [0, 1, 0])
    joint(wrist, "wrist_roll", [1, 0, 0])
    wrist.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, LINKS[2], 0, 0], size=[0.016, 0, 0],
                   rgba=dark, contype=0, conaffinity=0, density=300)
    wrist.add_geom(name="fingertip", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[TIP_RADIUS, 0, 0],
                   pos=[LINKS[2], 0, 0], rgba=[0.15, 0.15, 0.15, 1.0], contype=_OBJ_BIT | _TABLE_BIT,
                   conaffinity=_OBJ_BIT, friction=[0.3, 0.005, 0.0001], density=300)
    wrist.add_site(name="tip", pos=[LINKS[2], 0, 0], size=[0.005, 0, 0])
    for name in ARM_JOINTS:
        spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT, gear=[1, 0, 0, 0, 0, 0],
                          ctrllimited=True, ctrlrange=[-TORQUE_LIMIT, TORQUE_LIMIT])


_GEOM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "ellipsoid": mujoco.mjtGeom.mjGEOM_ELLIPSOID,
}


def add_object(spec: mujoco.MjSpec, role: str, obj: ObjectSpec) -> None:
    """A catalog object on a planar joint, named by its role ("target"/"distractor")."""
    body = spec.worldbody.add_body(name=role, pos=[0.0, 0.0, obj.half_height])
    body.add_joint(name=f"{role}_x", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1, 0, 0], damping=1.5, frictionloss=0.05)
    body.add_joint(name=f"{role}_y", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 1, 0], damping=1.5, frictionloss=0.05)
    body.add_joint(name=f"{role}_yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], damping=0.02,
                   frictionloss=0.002)
    for i, (kind, size, (ox, oy)) in enumerate(obj.parts()):
        geom = dict(name=f"{role}_geom{i}", type=_GEOM_TYPES[kind], pos=[ox, oy, 0.0], rgba=list(obj.rgba),
                    contype=_OBJ_BIT, conaffinity=_OBJ_BIT, friction=[0.4, 0.005, 0.0001], density=400)
        if kind == "capsule":
            geom["fromto"] = [ox - size[1], oy, 0.0, ox + size[1], oy, 0.0]
            geom["size"] = [size[0], 0, 0]
        else:
            geom["size"] = list(size) + [0.0] * (3 - len(size))
        body.add_geom(**geom)


def add_camera(spec: mujoco.MjSpec) -> None:
    spec.worldbody.add_camera(name="main", pos=CAMERA_POS.tolist(), xyaxes=_xyaxes(CAMERA_POS, CAMERA_LOOKAT), fovy=48)
    spec.worldbody.add_light(name="key", pos=[0.4, -0.3, 1.5], dir=[0, 0.2, -1], diffuse=[0.8, 0.8, 0.8],
                             castshadow=False)


def add_occluder(spec: mujoco.MjSpec) -> None:
    """A visual-only card on a mocap body, facing the camera; the env keeps it on the target's camera ray."""
    body = spec.worldbody.add_body(name="occluder", mocap=True, pos=[0.0, 0.0, 1.0],
                                   xyaxes=_xyaxes(CAMERA_POS, CAMERA_LOOKAT))  # parallel to the image plane
    body.add_geom(name="occluder", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(OCCLUDER_HALF), rgba=list(OCCLUDER_RGBA),
                  contype=0, conaffinity=0)


def occluder_pos(target_xyz: np.ndarray) -> np.ndarray:
    """The occluder's position for a target at ``target_xyz``: between it and the camera."""
    return target_xyz + OCCLUDER_FRACTION * (CAMERA_POS - target_xyz)


def build_spec(target: ObjectSpec | None, distractor: ObjectSpec | None, image_size: int = 64,
               occluder: bool = False) -> mujoco.MjSpec:
    """The whole scene; pass ``None`` objects to build it empty (the No-Objects probe).

    ``occluder`` adds a card that hides the target from the camera (the occluded defect).
    """
    spec = mujoco.MjSpec()
    spec.modelname = "democheck_push"
    spec.compiler.degree = False  # every angle in this file is in radians
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # Software rendering: shadows, reflections and multisampling cost ~30x.
    spec.visual.quality.shadowsize = 0
    spec.visual.quality.offsamples = 0
    # Coarse tessellation: invisible at 64x64, and it halves the software renderer's work.
    spec.visual.quality.numslices = 14
    spec.visual.quality.numstacks = 8
    spec.visual.global_.offwidth = max(image_size, 16)
    spec.visual.global_.offheight = max(image_size, 16)
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    add_table(spec)
    add_goal(spec)
    add_arm(spec)
    if target is not None:
        add_object(spec, "target", target)
    if distractor is not None:
        add_object(spec, "distractor", distractor)
    if occluder:
        add_occluder(spec)
    add_camera(spec)
    return spec
