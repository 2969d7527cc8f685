"""Offscreen rendering that keeps one GL context per process.

``mujoco.Renderer`` creates a GL context per model, which costs ~0.2 s on a
software renderer; the suite builds a new model per task, so we keep one
context for the life of the process and swap only the model-bound
``MjrContext``.  The context must never cross a ``fork``: workers that render
are started with the ``spawn`` method.
"""

from __future__ import annotations

import mujoco
import numpy as np

_GL = None  # the process's one GL context
_GL_SIZE = 0


def _gl_context(size: int):
    global _GL, _GL_SIZE
    if _GL is None or size > _GL_SIZE:
        from mujoco import gl_context

        if _GL is not None:
            _GL.free()
        _GL = gl_context.GLContext(max(size, 256), max(size, 256))
        _GL_SIZE = max(size, 256)
    _GL.make_current()
    return _GL


class FrameRenderer:
    """Renders square RGB frames of one camera of one model."""

    def __init__(self, model: mujoco.MjModel, size: int, camera: str = "main"):
        self.size = size
        _gl_context(size)
        self._model = model
        self._scene = mujoco.MjvScene(model=model, maxgeom=200)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self._camera.fixedcamid < 0:
            raise ValueError(f"the scene has no camera named {camera!r}")
        self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
        self._rect = mujoco.MjrRect(0, 0, size, size)
        self._buf = np.empty((size, size, 3), dtype=np.uint8)

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """One frame, uint8 [H, W, 3], top row first."""
        _GL.make_current()
        mujoco.mjv_updateScene(self._model, data, self._option, self._perturb, self._camera,
                               mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        mujoco.mjr_render(self._rect, self._scene, self._context)
        mujoco.mjr_readPixels(self._buf, None, self._rect, self._context)
        return np.flipud(self._buf).copy()

    def close(self) -> None:
        if self._context is not None:
            _GL.make_current()
            self._context.free()
            self._context = None
