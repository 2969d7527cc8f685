"""What a trained PETNet model carries beside its weights, computed once its training ends.

- the novelty density (``democheck.petnet.novelty``), fitted on the training cues;
- the task uncertainty of held-out real cues, which the run-time gate reads (``petnet.gate``);
- the mean task sigma of those cues and of hand-made nonsense cues (black, noise, a still scene...), which the
  model card reports: a model surer of a black image than of a demo says so there;
- the audit's reference on the training demos (the one-class SVM), through the ``reference`` function the
  caller passes (the audit owns it; this package never imports it).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from democheck.data.cache import EpisodeArrays
from democheck.petnet.gate import reference_record
from democheck.petnet.encode import encode, encode_rows
from democheck.petnet.novelty import fit_novelty
from democheck.petnet.posterior import TaskPosterior


def mean_sigma(model: torch.nn.Module, cues: np.ndarray, device: torch.device, end_states: np.ndarray) -> float:
    """The mean task standard deviation of uint8 cues [N, 2, H, W, 3] (their demos' states at the last step
    ``end_states`` [N, S]), over cues and dimensions."""
    return float(encode(model, cues, device, end_states=end_states).sigma.mean())


def finish_petnet(model, arrays: EpisodeArrays, train_rows: np.ndarray, held_rows: np.ndarray | None, seed: int,
                  device: torch.device, novelty: bool = True, novelty_trim: float = 0.0,
                  reference: Callable[[TaskPosterior, np.ndarray], dict[str, Any]] | None = None,
                  autoencoder: int | None = None, on_novelty: Callable[[int, int], None] | None = None,
                  end_state: bool = True) -> dict[str, Any]:
    """What a trained PETNet model carries beside its weights, from its training cues (``train_rows``) and
    held-out real cues (``held_rows``, the val split; None: none): the novelty density (``novelty``, fitted in
    place), the mean task sigma of held-out and nonsense cues (``task_sigma``), and the audit's reference on the
    training demos (``reference``).  Also how an existing model gets its novelty density refitted.
    ``autoencoder``, ``on_novelty``: the cue autoencoder's steps and progress (``novelty.fit_novelty``);
    ``end_state``: the density reads the demos' states at their last step too."""
    out: dict[str, Any] = {}
    if novelty:
        # Without held-out tasks the reference distance comes from the training cues themselves (a little low).
        held = held_rows if held_rows is not None else train_rows
        out["novelty"] = fit_novelty(model, arrays.cue(train_rows), arrays.cue(held), device,
                                     trim=novelty_trim, autoencoder=autoencoder, seed=seed,
                                     on_progress=on_novelty,
                                     train_states=arrays.end_state(train_rows) if end_state else None,
                                     held_out_states=arrays.end_state(held) if end_state else None)
        out["novelty"]["reference_cues"] = "held-out" if held_rows is not None else "fitted"
    rows = held_rows if held_rows is not None else train_rows[:500]
    real, ends = arrays.cue(rows), arrays.end_state(rows)
    which = "val demos" if held_rows is not None else "train demos"
    post = encode(model, real, device, end_states=ends)
    sig = {which: float(post.sigma.mean())}
    out["gate"] = reference_record(post, which)
    for name, cues in nonsense_cues(real[:200], np.random.default_rng(seed)).items():
        sig[name] = mean_sigma(model, cues, device, ends[:200])
    out["task_sigma"] = sig
    if reference is not None:
        post = encode_rows(model, arrays, train_rows, device)
        out["reference"] = reference(post, arrays.episodes["task"].to_numpy()[train_rows])
    return out


def nonsense_cues(real: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Hand-made cues no demonstration could produce, shaped like ``real`` [N, 2, H, W, 3]."""
    n = len(real)
    h = real.shape[2]
    still = np.repeat(real[:, :1], 2, axis=1)  # the last frame equals the first: nothing happened
    shuffled = real.reshape(n, 2, -1, 3)[:, :, rng.permutation(h * h)].reshape(real.shape)
    # A scene seen at another scale: the centre half of each frame blown up 2x (another suite's framing).
    zoom = real[:, :, h // 4: h // 4 + h // 2, h // 4: h // 4 + h // 2].repeat(2, axis=2).repeat(2, axis=3)
    return {
        "black": np.zeros_like(real), "white": np.full_like(real, 255), "grey": np.full_like(real, 128),
        "noise": rng.integers(0, 256, real.shape, dtype=np.uint8), "still": still, "pixel-shuffled": shuffled,
        "zoomed": zoom[:, :, :h, :h],
    }
