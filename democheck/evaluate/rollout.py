"""A model's controller acting in ``PushEnv``, and the worker processes that roll it out.

``democheck eval`` and ``democheck dagger`` both run rollouts in spawned
worker processes (``democheck.pool``): ``init_worker`` loads the model once
per process and keeps one simulator, and their shards find both in
``pool.state``.
"""

from __future__ import annotations

import numpy as np
import torch

from democheck import pool
from democheck.petnet.checkpoint import load_checkpoint
from democheck.sim.variants import EnvCache


class ControllerPolicy:
    """The model's controller acting on the env's latest observation under a fixed task variable z."""

    def __init__(self, env, model, norm, z: np.ndarray):
        self.env, self.model, self.norm = env, model, norm
        self.z = torch.as_tensor(np.asarray(z, np.float32))[None]

    def act(self) -> np.ndarray:
        obs = self.env.last_obs
        frame = torch.from_numpy(np.ascontiguousarray(obs["image"]))[None, None]
        state = torch.from_numpy(self.norm.state(obs["state"]).astype(np.float32))[None, None]
        with torch.no_grad():
            y = self.model.controller.act(frame, state, self.z)[0, 0].numpy()
        return np.clip(self.norm.unaction(y), -1.0, 1.0).astype(np.float32)


def init_worker(model: str, image_size: int) -> None:
    """Per rollout process: the model (``pool.state["ckpt"]``) and a simulator cache (``pool.state["envs"]``)."""
    torch.set_num_threads(1)  # one core per worker process
    pool.state.update(ckpt=load_checkpoint(model), envs=EnvCache(image_size))
