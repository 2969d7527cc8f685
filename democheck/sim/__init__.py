"""The MuJoCo pushing suite: scene, objects, environment, scripted expert, suite generation."""

import os

# Headless by default; must be set before mujoco is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")
