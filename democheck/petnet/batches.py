"""Training batches: which demos a step draws, and the images as the step sees them.

A step takes ``n_tasks`` tasks; for each, a *cue* demo and a *demonstrated
trajectory* that are different demos of the task, and ``k`` timesteps drawn
uniformly from the trajectory.  Rows index ``EpisodeArrays`` (the decoded
frame cache).  ``augment`` shifts training images at random.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from democheck.data.cache import EpisodeArrays
from democheck.petnet.checkpoint import Normalisation


VAL_SHARE = 0.1  # of each task's demos, held out for validation when the data names no split
VAL_MIN_TASK = 6  # demos a task needs to give some: at least 2 held out, at least 4 left to train on


def held_out_demos(episodes, seed: int) -> np.ndarray:
    """Which rows of ``episodes`` (episode_index, task) validation holds out when the data names no split: a tenth
    of each task's demos, at least 2 (a held-out cue needs a held-out trajectory), from every task with at least
    ``VAL_MIN_TASK`` demos.  Every task keeps most of its demos for training: no task is left out."""
    held = np.zeros(len(episodes), bool)
    rng = np.random.default_rng([seed, 7])
    for _, pos in sorted(episodes.groupby("task").indices.items()):
        if len(pos) >= VAL_MIN_TASK:
            k = max(2, int(round(VAL_SHARE * len(pos))))
            held[rng.choice(np.sort(pos), size=k, replace=False)] = True
    return held


def task_rows(arrays: EpisodeArrays, split: str, seed: int) -> dict[str, np.ndarray]:
    """Rows of each task with at least two demos, in the given split (``train`` or ``val``).

    A dataset that names its splits (a democheck suite's sidecar) is split as it says: a task of its val or
    test split is left out of training because the data says so.  A dataset that names none holds out demos
    within every task (``held_out_demos``), so every task is trained on.
    """
    eps = arrays.episodes
    if "split" in eps and eps["split"].notna().any():
        sel = eps[eps["split"] == split]
    else:
        held = held_out_demos(eps, seed)
        sel = eps[held] if split == "val" else eps[~held] if split == "train" else eps[:0]
    groups = {t: np.asarray(idx) for t, idx in sel.groupby("task").indices.items()} if len(sel) else {}
    # groupby().indices are positions within ``sel``; map them back to rows of ``arrays``.
    return {t: sel.index.to_numpy()[pos] for t, pos in groups.items() if len(pos) >= 2}


def uniform_steps(rng: np.random.Generator, lengths: np.ndarray, k: int) -> np.ndarray:
    """k timesteps drawn uniformly from each trajectory of the given lengths: int64 [len(lengths), k]."""
    return (rng.random((len(lengths), k)) * lengths[:, None]).astype(np.int64)


def standardise(x: np.ndarray, norm: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(x - mean) / sd, float32; NaN (not recorded) stays NaN."""
    return ((x - norm[0]) / norm[1]).astype(np.float32)


class ResidentArrays:
    """Decoded episodes held as tensors on the training device, state and actions normalised once: on a GPU a
    step gathers its batch where it trains instead of copying it from host memory (``train`` on CUDA).  Rows,
    offsets and lengths are those of the ``EpisodeArrays`` it was made from."""

    CHUNK = 65536  # frames copied to the device at a time, so the host never holds a second copy

    def __init__(self, arrays: EpisodeArrays, norm: Normalisation, device: torch.device,
                 env_norm: tuple[np.ndarray, np.ndarray] | None = None):
        self.host, self.device = arrays, device
        self.offsets, self.lengths, self.episodes = arrays.offsets, arrays.lengths, arrays.episodes
        self.frames = torch.empty(arrays.frames.shape, dtype=torch.uint8, device=device)
        for s in range(0, len(arrays.frames), self.CHUNK):
            self.frames[s:s + self.CHUNK] = torch.from_numpy(np.array(arrays.frames[s:s + self.CHUNK]))
        self.raw_state = torch.from_numpy(np.ascontiguousarray(arrays.state)).to(device)
        self.state = torch.from_numpy(norm.state(arrays.state).astype(np.float32)).to(device)
        self.actions = torch.from_numpy(norm.action(arrays.actions).astype(np.float32)).to(device)
        self.env_state = None if env_norm is None else \
            torch.from_numpy(standardise(arrays.env_state, env_norm)).to(device)

    def _index(self, idx: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(idx, dtype=np.int64)).to(self.device)

    def at(self, flat: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Frames, normalised state, normalised actions and the standardised environment state (None where it is
        not read) at flat frame indices."""
        i = self._index(flat)
        return self.frames[i], self.state[i], self.actions[i], None if self.env_state is None else self.env_state[i]

    def cue(self, rows: np.ndarray, end: np.ndarray | None = None) -> torch.Tensor:
        """``EpisodeArrays.cue`` on the device."""
        first, last = self.host.cue_index(rows, end)
        return torch.stack([self.frames[self._index(first)], self.frames[self._index(last)]], dim=1)

    def end_state(self, rows: np.ndarray) -> torch.Tensor:
        """``EpisodeArrays.end_state`` on the device (the state as recorded)."""
        return self.raw_state[self._index(self.host.last_index(rows))]


POSED_PER_TASK = 4  # posed frames (``PosedFrames``) a batch reads of each task's trajectory demo


class PosedFrames:
    """Frames of training demos' layouts with the arm posed as in other demos (``democheck.sim.posed``), K a demo,
    and the objects' poses there standardised as the read-out's targets: on them the arm says nothing of where the
    objects are, and only the task variable says which one is the target."""

    def __init__(self, rows: np.ndarray, frames: np.ndarray, env_state: np.ndarray):
        self.slot = {int(r): i for i, r in enumerate(rows)}
        self.frames, self.env_state = frames, env_state

    def pick(self, rng: np.random.Generator, rows: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``k`` of each row's frames [B, k, H, W, 3], drawn at random, and their targets [B, k, E]."""
        slots = np.array([self.slot[int(r)] for r in rows])[:, None]
        which = rng.integers(0, self.frames.shape[1], (len(rows), k))
        return self.frames[slots, which], self.env_state[slots, which]


class Batches:
    """Samples (cue, demonstrated trajectory) pairs of the same task.

    ``groups`` (task -> group key) marks tasks that are easy to confuse, e.g.
    the two orders of one object pair in a democheck suite; with it, a batch
    is made of whole groups where it can be, so the embedding losses must tell
    a task from its look-alikes, not only from random others.
    """

    def __init__(self, arrays: EpisodeArrays | ResidentArrays, rows: dict[str, np.ndarray], norm: Normalisation,
                 groups: dict[str, str] | None = None, env_norm: tuple[np.ndarray, np.ndarray] | None = None,
                 posed: PosedFrames | None = None):
        self.a = arrays
        self.env_norm = env_norm  # (mean, sd): batches carry the standardised environment state
        self.posed = posed  # with it, a sampled batch carries posed frames of its trajectory demos
        self.tasks = sorted(rows)
        self.rows = [rows[t] for t in self.tasks]
        self.norm = norm
        members: dict[str, list[int]] = {}
        for i, t in enumerate(self.tasks):
            if groups and t in groups:
                members.setdefault(groups[t], []).append(i)
        self.groups = [m for _, m in sorted(members.items()) if len(m) > 1]
        # Each row's task as a number: a batch says which of its items share a task (there may be fewer tasks
        # than items), so that the task-matching loss does not call a demo of the same task a wrong match.
        self.task_ids = pd.factorize(arrays.episodes["task"])[0].astype(np.int64) if len(arrays.episodes) else \
            np.zeros(0, np.int64)

    def _pick_tasks(self, rng: np.random.Generator, n_tasks: int) -> np.ndarray:
        if not self.groups:
            return rng.choice(len(self.tasks), size=n_tasks, replace=len(self.tasks) < n_tasks)
        picks: list[int] = []
        for g in rng.permutation(len(self.groups)):
            if len(picks) + 2 > n_tasks:
                break
            picks += list(rng.choice(self.groups[g], size=2, replace=False))
        rest = np.setdiff1d(np.arange(len(self.tasks)), picks)
        if len(picks) < n_tasks and len(rest):
            picks += list(rng.choice(rest, size=min(n_tasks - len(picks), len(rest)), replace=False))
        return np.asarray(picks[:n_tasks])

    def pick_rows(self, rng: np.random.Generator, n_tasks: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows of a cue demo and of a different demonstrated trajectory for each of ``n_tasks`` tasks."""
        cue_rows, traj_rows = [], []
        for t in self._pick_tasks(rng, n_tasks):
            c, d = rng.choice(self.rows[t], size=2, replace=False)
            cue_rows.append(c)
            traj_rows.append(d)
        return np.array(cue_rows), np.array(traj_rows)

    def sample(self, rng: np.random.Generator, n_tasks: int, k: int, partial: bool = False) -> dict[str, np.ndarray]:
        """A batch; ``partial`` adds ``partial_cue``: each cue cut short at a uniformly drawn timestep; with posed
        frames, ``posed_frames`` and ``posed_env`` (``PosedFrames.pick``) of each trajectory demo."""
        cue_rows, traj_rows = self.pick_rows(rng, n_tasks)
        steps = uniform_steps(rng, self.a.lengths[traj_rows], k)
        ends = uniform_steps(rng, self.a.lengths[cue_rows], 1)[:, 0] if partial else None
        batch = self.gather(cue_rows, traj_rows, steps, ends)
        if self.posed is not None:  # the trajectory demo's layout, not the cue's: z cannot carry where things are
            batch["posed_frames"], batch["posed_env"] = self.posed.pick(rng, traj_rows, POSED_PER_TASK)
        return batch

    def gather(self, cue_rows: np.ndarray, traj_rows: np.ndarray, steps: np.ndarray,
               cue_ends: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The batch of those rows at those trajectory timesteps; ``cue_ends`` adds the cues cut short there."""
        a = self.a
        lengths = a.lengths[traj_rows]
        idx = a.offsets[traj_rows][:, None] + np.minimum(steps, lengths[:, None] - 1)
        flat = idx.reshape(-1)
        extra = {} if cue_ends is None else {"partial_cue": a.cue(cue_rows, end=cue_ends)}
        if isinstance(a, ResidentArrays):
            frames, state, actions, env = a.at(flat)
        else:
            frames, state, actions = a.frames[flat], self.norm.state(a.state[flat]), self.norm.action(a.actions[flat])
            env = None if self.env_norm is None else standardise(a.env_state[flat], self.env_norm)
        if env is not None:
            extra["env_state"] = env.reshape(*idx.shape, -1)
        return {**extra,
            "task": self.task_ids[cue_rows],
            "cue": a.cue(cue_rows),
            "cue_end_state": a.end_state(cue_rows),  # where each cue's demo ended (a novelty density may read it)
            "traj_cue": a.cue(traj_rows),
            "frames": frames.reshape(*idx.shape, *a.frames.shape[1:]),
            "state": state.reshape(*idx.shape, -1),
            "actions": actions.reshape(*idx.shape, -1),
        }


def val_pairs(val: Batches, seed: int, per_task: int = 2, k: int = 10) -> dict[str, np.ndarray]:
    """Fixed validation draws: ``per_task`` (cue, trajectory) pairs of every task, ``k`` timesteps each, and a
    cut time per cue (for the partial-cue terms)."""
    rng = np.random.default_rng([seed, 11])
    cue_rows, traj_rows = [], []
    for rows in val.rows:
        for _ in range(per_task):
            c, d = rng.choice(rows, size=2, replace=False)
            cue_rows.append(c)
            traj_rows.append(d)
    cue_rows, traj_rows = np.array(cue_rows, dtype=np.int64), np.array(traj_rows, dtype=np.int64)
    lengths = val.a.lengths[traj_rows] if len(traj_rows) else np.zeros(0, np.int64)
    # Fixed draws from the same uniform distribution training samples from, so the two losses compare.
    steps = uniform_steps(rng, lengths, k)
    ends = uniform_steps(rng, val.a.lengths[cue_rows], 1)[:, 0] if len(cue_rows) else np.zeros(0, np.int64)
    return {"cue_rows": cue_rows, "traj_rows": traj_rows, "steps": steps, "ends": ends}


def random_shift(images: torch.Tensor, pad: int) -> torch.Tensor:
    """Each item of uint8 ``images`` [N, M, H, W, C] moved by its own random whole-pixel offset of at most ``pad``
    (the M images of an item, e.g. a cue's two frames, together); borders repeat the edge pixels.

    The translation augmentation of image-based RL and imitation (DrQ's random shift): the network must find
    things wherever they are in the frame instead of memorising pixel positions.  Draws from torch's RNG, which the
    training state saves, so a resumed run shifts as the uninterrupted one would.
    """
    if pad <= 0:
        return images
    n, h, w = images.shape[0], images.shape[-3], images.shape[-2]
    off = torch.randint(-pad, pad + 1, (2, n), device=images.device)
    rows = (torch.arange(h, device=images.device)[None] + off[0][:, None]).clamp_(0, h - 1)  # [N, H]
    cols = (torch.arange(w, device=images.device)[None] + off[1][:, None]).clamp_(0, w - 1)  # [N, W]
    idx = torch.arange(n, device=images.device)[:, None, None]
    moved = images.movedim(1, -1)[idx, rows[:, :, None], cols[:, None, :]]  # [N, H, W, C, M]
    return moved.movedim(-1, 1)


def augment(batch: dict[str, torch.Tensor], shift: int) -> dict[str, torch.Tensor]:
    """A training batch with every image randomly shifted: each cue as a whole, each controller frame alone."""
    if shift <= 0:
        return batch
    out = dict(batch)
    for key in ("cue", "traj_cue", "partial_cue"):
        if key in out:
            out[key] = random_shift(out[key], shift)
    for key in ("frames", "posed_frames"):
        if key in out:
            frames = out[key]
            out[key] = random_shift(frames.reshape(-1, 1, *frames.shape[2:]), shift).reshape(frames.shape)
    return out


def to_device(batch: dict[str, np.ndarray | torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """A batch's arrays as tensors on ``device`` (those gathered there already stay)."""
    return {k: v.to(device) if torch.is_tensor(v) else torch.from_numpy(np.ascontiguousarray(v)).to(device, non_blocking=True)
            for k, v in batch.items()}
