"""Reading task posteriors off a trained model: the cues of uint8 arrays, of a DemoSet's demos, or of decoded
episodes' rows, in chunks, with each demo's end state where the model's novelty density reads it."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from democheck.petnet.blocks import cue_input
from democheck.petnet.model import TaskEncoder
from democheck.petnet.posterior import TaskPosterior


@torch.no_grad()
def encode(model: torch.nn.Module, cues: np.ndarray, device: torch.device | str = "cpu", chunk: int = 256,
           end_states: np.ndarray | None = None) -> TaskPosterior:
    """The task posterior of each of uint8 cues [N, 2, H, W, 3] under ``model`` (PETNet or TecNets).

    ``end_states``: each demo's state at its last step [N, S], which a PETNet whose novelty density reads it
    (``cfg.novelty_state``) needs.  A TecNets model has no variance: its embedding comes back as ``mu``, the
    variances zero.
    """
    cols: list[list[np.ndarray]] = [[], [], []]
    for s in range(0, len(cues), chunk):
        x = cue_input(torch.from_numpy(np.ascontiguousarray(cues[s:s + chunk])).to(device))
        if isinstance(model.encoder, TaskEncoder):
            end = None if end_states is None else torch.as_tensor(np.asarray(end_states[s:s + chunk]), device=device)
            out = model.encoder.parts(x, end)
        else:
            emb = model.encoder(x)
            out = (emb, torch.zeros_like(emb), torch.zeros_like(emb))
        for col, t in zip(cols, out):
            col.append(t.cpu().numpy())
    empty = np.zeros((0, model.cfg.embed_dim), np.float32)
    return TaskPosterior(*(np.concatenate(c) if c else empty for c in cols))


def reads_end_states(model: torch.nn.Module) -> bool:
    """Whether ``model``'s novelty density reads each demo's state at its last step (``ModelConfig.novelty_state``)."""
    return bool(model.cfg.novelty and model.cfg.novelty_state)


def encode_demos(model: torch.nn.Module, ds: Any, episodes: list[int], device: torch.device | str = "cpu"
                 ) -> TaskPosterior:
    """``encode`` of the cues of a DemoSet's ``episodes``, with their end states where the model reads them."""
    ends = ds.end_states(episodes) if reads_end_states(model) else None
    return encode(model, ds.cue_frames_many(episodes), device, end_states=ends)


def encode_rows(model: torch.nn.Module, arrays: Any, rows: np.ndarray, device: torch.device | str = "cpu"
                ) -> TaskPosterior:
    """``encode`` of the cues of decoded episodes' ``rows`` (``data.cache.EpisodeArrays``), with their end states
    where the model reads them."""
    ends = arrays.end_state(rows) if reads_end_states(model) else None
    return encode(model, arrays.cue(rows), device, end_states=ends)


__all__ = ["encode", "encode_demos", "encode_rows", "reads_end_states"]
