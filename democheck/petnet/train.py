"""Training PETNet (and the TecNets baseline) from decoded episode arrays.

One step: a batch of tasks; for each, a *cue* demo and a *demonstrated
trajectory* that are different demos of the task; ``z ~ N(mu, var)`` from the
cue; loss = MSE of the controller's actions on K random timesteps of the
trajectory (+ an optional KL term).  Adam, lr 5e-4.

The run's state (weights, Adam moments, both RNGs, history) is saved every
``ckpt_every`` steps into a work folder beside the output; ``resume=True``
continues from it and reaches the same weights as an uninterrupted run.
"""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

from democheck.data.cache import EpisodeArrays
from democheck.errors import DemocheckError
from democheck.fsutil import refuse_existing
from democheck.petnet.checkpoint import Normalisation, save_checkpoint
from democheck.petnet.model import (ModelConfig, TaskEncoder, build_model, cue_input, hinge_embedding_loss,
                                    kl_diag, product_of_gaussians)


@dataclass
class TrainConfig:
    steps: int = 20_000
    batch_tasks: int = 16
    timesteps: int = 8  # timesteps of the demonstrated trajectory per task per step
    lr: float = 5e-4
    kl_weight: float = 0.0  # 0: the paper's loss
    kl_target: str = "prior"  # "prior": KL(q(z|cue) || N(0, I)); "np": KL(q(z|cue, target) || q(z|cue))
    margin: float = 0.1  # TecNets hinge margin
    # TecNets hinge loss weight.  At 1 the unit-norm embedding collapses at initialisation (every cue maps to one
    # point, where the hinge loss has no gradient) and never recovers on push-v1; at 10 it separates within ~50 steps.
    embed_weight: float = 10.0
    # PETNet option (0 = the paper's loss): weight of the task-matching loss (see ``task_matching_loss``), which makes
    # the embedding carry the task, and its variance say how well, from the first steps instead of waiting for the
    # controller to need it.
    contrastive_weight: float = 0.0
    # Batches of look-alike tasks (see ``Batches``), when the data says which tasks look alike (democheck suites).
    hard_negatives: bool = False
    # PETNet option: TecNets' hinge loss on the unit-normalised task means (cue vs another demo of the task).
    mean_hinge_weight: float = 0.0
    # PETNet option: weight of the task-matching loss on *partial* cues, each the first frame and the frame at a
    # random timestep of a training demo.  A cue that shows only the start of a task cannot say which of its
    # look-alikes it is, so the loss teaches the variance to grow with what the cue leaves out -- the meaning of
    # task uncertainty -- from clean demos alone, no labelled defects.
    partial_cue_weight: float = 0.0
    # PETNet option, with ``init``: weight of KL(q0(z | full cue) || q(z | the same cue cut at a random timestep)),
    # where q0 is the starting model's encoder, frozen.  A cut cue must *cover* every task its beginning is
    # consistent with: averaged over training demos, the best q(z | cut cue) has the mean of their posteriors and
    # their variance plus the spread of their means, so sigma grows with what the cue leaves out (the Neural
    # Process view: less context, wider posterior).  Clean demos only; no defect kind is shown to the model.  The
    # target must be fixed: taken from the encoder being trained, every widening of cut cues leaks into whole
    # ones, which the next step must cover again, and sigma runs away (push-v1: mean val sigma 39 after 1,000
    # steps at weight 0.1, 2.6e7 after 3,000 at weight 1).  Measured and not shipped: from petnet-push-v1, 5,000
    # steps at weight 1 left sigma flat over the cut time (0.359-0.360) and lowered the KL the cheaper way, by
    # making mu ignore the last frame (a cut at t=0 moved mu by 0.77 sigma, against 1.58 before).
    partial_kl_weight: float = 0.0
    # PETNet option: weight of the broken-cue loss (``broken_cue_loss``): cues that break what every demonstration
    # obeys -- one scene from start to end, time running forwards -- must be more uncertain than real ones.
    broken_cue_weight: float = 0.0
    # PETNet: after training, fit the novelty density that adds the epistemic part of the task variance
    # (``democheck.petnet.novelty``); off leaves the paper's variance head alone.
    novelty: bool = True
    # Start from this model folder's weights and normalisation instead of a fresh network (same architecture).
    init: str | None = None
    keypoints: bool = False  # controller architecture option, see ModelConfig.keypoints
    # Random-shift augmentation of training images (``random_shift``): up to this many pixels each way, 0 = off.
    shift: int = 0
    seed: int = 0
    val_every: int = 500
    ckpt_every: int = 1000
    device: str = "auto"

    def partial_cues(self, model_type: str) -> bool:
        """Whether batches carry cues cut short (``partial_cue``), for either partial-cue loss."""
        return model_type == "petnet" and (self.partial_cue_weight > 0 or self.partial_kl_weight > 0)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise DemocheckError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise DemocheckError(f"--device must be auto, cpu or cuda, not {name!r}")
    return torch.device(name)


def task_rows(arrays: EpisodeArrays, split: str, seed: int) -> dict[str, np.ndarray]:
    """Rows of each task with at least two demos, in the given split.

    Datasets without splits use every task for training and hold out 10% of
    tasks (at least one, when there are ten or more) for validation.
    """
    eps = arrays.episodes
    if "split" in eps and eps["split"].notna().any():
        sel = eps[eps["split"] == split]
    else:
        tasks = np.array(sorted(eps["task"].unique()))
        held = set(np.random.default_rng([seed, 7]).permutation(tasks)[: len(tasks) // 10]) if len(tasks) >= 10 else set()
        sel = eps[eps["task"].isin(held)] if split == "val" else eps[~eps["task"].isin(held)] if split == "train" else eps[:0]
    groups = {t: np.asarray(idx) for t, idx in sel.groupby("task").indices.items()} if len(sel) else {}
    # groupby().indices are positions within ``sel``; map them back to rows of ``arrays``.
    return {t: sel.index.to_numpy()[pos] for t, pos in groups.items() if len(pos) >= 2}


def uniform_steps(rng: np.random.Generator, lengths: np.ndarray, k: int) -> np.ndarray:
    """k timesteps drawn uniformly from each trajectory of the given lengths: int64 [len(lengths), k]."""
    return (rng.random((len(lengths), k)) * lengths[:, None]).astype(np.int64)


class Batches:
    """Samples (cue, demonstrated trajectory) pairs of the same task.

    ``groups`` (task -> group key) marks tasks that are easy to confuse, e.g.
    the two orders of one object pair in a democheck suite; with it, a batch
    is made of whole groups where it can be, so the embedding losses must tell
    a task from its look-alikes, not only from random others.
    """

    def __init__(self, arrays: EpisodeArrays, rows: dict[str, np.ndarray], norm: Normalisation,
                 groups: dict[str, str] | None = None):
        self.a = arrays
        self.tasks = sorted(rows)
        self.rows = [rows[t] for t in self.tasks]
        self.norm = norm
        members: dict[str, list[int]] = {}
        for i, t in enumerate(self.tasks):
            if groups and t in groups:
                members.setdefault(groups[t], []).append(i)
        self.groups = [m for _, m in sorted(members.items()) if len(m) > 1]

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
        """A batch; ``partial`` adds ``partial_cue``: each cue cut short at a uniformly drawn timestep."""
        cue_rows, traj_rows = self.pick_rows(rng, n_tasks)
        steps = uniform_steps(rng, self.a.lengths[traj_rows], k)
        ends = uniform_steps(rng, self.a.lengths[cue_rows], 1)[:, 0] if partial else None
        return self.gather(cue_rows, traj_rows, steps, ends)

    def gather(self, cue_rows: np.ndarray, traj_rows: np.ndarray, steps: np.ndarray,
               cue_ends: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The batch of those rows at those trajectory timesteps; ``cue_ends`` adds the cues cut short there."""
        a = self.a
        lengths = a.lengths[traj_rows]
        idx = a.offsets[traj_rows][:, None] + np.minimum(steps, lengths[:, None] - 1)
        flat = idx.reshape(-1)
        extra = {} if cue_ends is None else {"partial_cue": a.cue(cue_rows, end=cue_ends)}
        return {**extra,
            "cue": a.cue(cue_rows),
            "traj_cue": a.cue(traj_rows),
            "frames": a.frames[flat].reshape(*idx.shape, *a.frames.shape[1:]),
            "state": self.norm.state(a.state[flat]).reshape(*idx.shape, -1),
            "actions": self.norm.action(a.actions[flat]).reshape(*idx.shape, -1),
        }


def task_matching_loss(mu_c: torch.Tensor, var_c: torch.Tensor, mu_t: torch.Tensor, var_t: torch.Tensor
                       ) -> torch.Tensor:
    """Cross-entropy of finding each cue's own task among the batch's tasks by Gaussian likelihood.

    Candidate j's task mean is scored under cue i's posterior widened by j's own variance,
    log N(mu_t_j; mu_c_i, var_c_i + var_t_j).  The variance gets a direct gradient: a cue whose mean lands
    among the wrong tasks lowers its loss by widening, a cue that pins its task down by narrowing.
    """
    v = var_c[:, None] + var_t[None]  # [B, B, z]
    logp = -0.5 * (((mu_c[:, None] - mu_t[None]) ** 2) / v + torch.log(v)).sum(-1)
    return F.cross_entropy(logp, torch.arange(len(mu_c), device=mu_c.device))


def broken_cues(cue: torch.Tensor) -> torch.Tensor:
    """Cues no demonstration can produce, made from a batch of real ones (uint8 [B, 2, H, W, C]): each cue's
    first frame with the next cue's last frame (two scenes; the batch's cues are of different tasks), and each
    cue played backwards.  Neither is a defect kind democheck injects or probes, so the benchmark stays unseen.
    """
    spliced = torch.stack([cue[:, 0], cue.roll(-1, 0)[:, 1]], dim=1)
    return torch.cat([spliced, cue.flip(1)])


def broken_cue_loss(sigma_real: torch.Tensor, sigma_broken: torch.Tensor, margin: float = math.log(2.0)
                    ) -> torch.Tensor:
    """Hinge on log task standard deviations ([N] each, the mean over dimensions): every broken cue must be at
    least ``exp(margin)`` times as uncertain as the batch's real cues on average.  Both sides get the gradient --
    broken cues up, real ones down -- so the loss ranks without setting a scale; the task-matching loss, which
    wants real cues sure of their task, sets it.  Two variants ran away or collapsed (push-v1, from
    petnet-push-v1, weight 1): with the real cues as a fixed reference, every rise leaked into them through the
    shared weights and sigma ran away (mean val sigma 56 after 500 steps, 4,700 after 3,000); with the prior's
    sigma 1 as the target, all cues rose to 1.3 together and task matching fell to chance (val 3.34 = ln 28).
    """
    return F.relu(margin - (sigma_broken.log() - sigma_real.log().mean())).mean()


def losses(model: torch.nn.Module, batch: dict[str, torch.Tensor], tc: TrainConfig, sample: bool = True,
           teacher: torch.nn.Module | None = None) -> dict[str, torch.Tensor]:
    """The training objective for either model type; ``sample=False`` uses z = mu (validation).

    ``teacher``: the frozen starting encoder, the partial-cue KL's target (``TrainConfig.partial_kl_weight``).
    """
    cfg: ModelConfig = model.cfg
    cue = cue_input(batch["cue"])
    frames, state = batch["frames"], batch["state"]
    out: dict[str, torch.Tensor] = {}
    if cfg.model_type == "petnet":
        mu, var = model.encoder(cue)
        if tc.kl_weight > 0 and tc.kl_target == "np":
            mu_t, var_t = model.encoder(cue_input(batch["traj_cue"]))
            mu_q, var_q = product_of_gaussians(torch.stack([mu, mu_t]), torch.stack([var, var_t]))
            out["kl"] = kl_diag(mu_q, var_q, mu, var).mean()
            mu_s, var_s = (mu_q, var_q) if sample else (mu, var)
        else:
            if tc.kl_weight > 0:
                out["kl"] = kl_diag(mu, var, torch.zeros_like(mu), torch.ones_like(var)).mean()
            mu_s, var_s = mu, var
        z = mu_s + var_s.sqrt() * torch.randn_like(mu_s) if sample else mu_s
        sigma = var.sqrt()
        out["sigma"] = sigma.mean()
        if tc.contrastive_weight > 0 or tc.mean_hinge_weight > 0 or tc.partial_cue_weight > 0:
            mu_t, var_t = model.encoder(cue_input(batch["traj_cue"]))
        if tc.contrastive_weight > 0:
            out["embed"] = task_matching_loss(mu, var, mu_t, var_t)
        if "partial_cue" in batch:
            mu_p, var_p = model.encoder(cue_input(batch["partial_cue"]))
            if tc.partial_cue_weight > 0:
                out["partial"] = task_matching_loss(mu_p, var_p, mu_t, var_t)
            if tc.partial_kl_weight > 0:
                if teacher is None:
                    raise ValueError("the partial-cue KL needs the frozen starting encoder (TrainConfig.init)")
                with torch.no_grad():
                    mu_0, var_0 = teacher(cue)
                out["partial_kl"] = kl_diag(mu_0, var_0, mu_p, var_p).mean()
            out["partial_sigma"] = var_p.sqrt().mean()
        if tc.broken_cue_weight > 0:
            _, var_b = model.encoder(cue_input(broken_cues(batch["cue"])))
            out["broken"] = broken_cue_loss(sigma.mean(-1), var_b.sqrt().mean(-1))
            out["broken_sigma"] = var_b.sqrt().mean()
        if tc.mean_hinge_weight > 0:
            out["hinge"] = hinge_embedding_loss(F.normalize(mu, dim=-1), F.normalize(mu_t, dim=-1), tc.margin)
    else:
        z = model.encoder(cue)
        out["embed"] = hinge_embedding_loss(z, model.encoder(cue_input(batch["traj_cue"])), tc.margin)
    out["mse"] = ((model.controller.act(frames, state, z) - batch["actions"]) ** 2).mean()
    weights = {"kl": tc.kl_weight,
               "embed": tc.embed_weight if cfg.model_type == "tecnet" else tc.contrastive_weight,
               "hinge": tc.mean_hinge_weight, "partial": tc.partial_cue_weight,
               "partial_kl": tc.partial_kl_weight, "broken": tc.broken_cue_weight}
    total = out["mse"]
    for key, weight in weights.items():
        if key in out:
            total = total + weight * out[key]
    out["loss"] = total
    return out


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
    frames = out["frames"]
    out["frames"] = random_shift(frames.reshape(-1, 1, *frames.shape[2:]), shift).reshape(frames.shape)
    return out


def to_device(batch: dict[str, np.ndarray], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.ascontiguousarray(v)).to(device, non_blocking=True) for k, v in batch.items()}


# ---------------------------------------------------------------------------
# run state (resume)
# ---------------------------------------------------------------------------

def _save_state(work: Path, model, opt, step: int, rng: np.random.Generator, info: dict[str, Any]) -> None:
    tmp = work / "state.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    osd = opt.state_dict()
    for i, st in osd["state"].items():
        for name, t in st.items():
            tensors[f"opt.{i}.{name}"] = t.detach().cpu().contiguous() if torch.is_tensor(t) else torch.tensor(t)
    tensors["rng.torch"] = torch.get_rng_state()
    save_file(tensors, str(tmp / "state.safetensors"))
    doc = {"step": step, "rng": rng.bit_generator.state, "param_groups": osd["param_groups"], **info}
    (tmp / "state.json").write_text(json.dumps(doc))
    cur, old = work / "state", work / "state.old"
    if cur.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(cur, old)
    os.replace(tmp, cur)
    shutil.rmtree(old, ignore_errors=True)


def _load_state(work: Path, model, opt) -> tuple[int, np.random.Generator, dict[str, Any]]:
    for cand in (work / "state", work / "state.old"):  # state.old: a kill between the two renames
        if (cand / "state.json").exists() and (cand / "state.safetensors").exists():
            break
    else:
        raise DemocheckError(f"{work}: no saved training state to resume from")
    doc = json.loads((cand / "state.json").read_text())
    tensors = load_file(str(cand / "state.safetensors"))
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, v in tensors.items():
        if key.startswith("opt."):
            _, i, name = key.split(".", 2)
            state.setdefault(int(i), {})[name] = v
    opt.load_state_dict({"state": state, "param_groups": doc["param_groups"]})
    torch.set_rng_state(tensors["rng.torch"])
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = doc["rng"]
    return int(doc["step"]), rng, doc


# ---------------------------------------------------------------------------
# evaluation helpers
# ---------------------------------------------------------------------------

@torch.no_grad()
def task_posteriors(model, cues: np.ndarray, device: torch.device, chunk: int = 256, parts: bool = False
                    ) -> tuple[np.ndarray, ...]:
    """Per-cue task posterior (mu, var), each [N, z], for uint8 cues [N, 2, H, W, 3].

    ``parts``: (mu, var_task, var_novel) instead -- the paper's head and the novelty part, var their sum
    (``TaskEncoder``).  A TecNets model has no variance: its embedding comes back as ``mu``, variances zero.
    """
    cols: list[list[np.ndarray]] = [[], [], []]
    for s in range(0, len(cues), chunk):
        x = cue_input(torch.from_numpy(np.ascontiguousarray(cues[s:s + chunk])).to(device))
        if isinstance(model.encoder, TaskEncoder):
            out = model.encoder.parts(x)
        else:
            emb = model.encoder(x)
            out = (emb, torch.zeros_like(emb), torch.zeros_like(emb))
        for col, t in zip(cols, out):
            col.append(t.cpu().numpy())
    mu, var_task, var_novel = (np.concatenate(c) if c else np.zeros((0, model.cfg.z_dim), np.float32) for c in cols)
    return (mu, var_task, var_novel) if parts else (mu, var_task + var_novel)


def task_sigma(model, cues: np.ndarray, device: torch.device) -> np.ndarray:
    """Per-cue task standard deviation vectors sqrt(var): [N, z]."""
    return np.sqrt(task_posteriors(model, cues, device)[1])


def finish_petnet(model, arrays: EpisodeArrays, train_rows: np.ndarray, held_rows: np.ndarray | None, seed: int,
                  device: torch.device, novelty: bool = True,
                  reference: Callable[[np.ndarray, np.ndarray, np.ndarray], dict[str, Any]] | None = None
                  ) -> dict[str, Any]:
    """What a trained PETNet model carries beside its weights, from its training cues (``train_rows``) and
    held-out real cues (``held_rows``, the val split; None: none): the novelty density (``novelty``, fitted in
    place), the mean task sigma of held-out and nonsense cues (``task_sigma``), and the audit's reference on the
    training demos (``reference``).  Also how an existing model gets its novelty density refitted."""
    out: dict[str, Any] = {}
    if novelty:
        from democheck.petnet.novelty import fit_novelty

        # Without held-out tasks the reference distance comes from the training cues themselves (a little low).
        out["novelty"] = fit_novelty(model, arrays.cue(train_rows),
                                     arrays.cue(held_rows if held_rows is not None else train_rows), device)
    real = arrays.cue(held_rows if held_rows is not None else train_rows[:500])
    sig = {"val demos" if held_rows is not None else "train demos": float(task_sigma(model, real, device).mean())}
    for name, cues in nonsense_cues(real[:200], np.random.default_rng(seed)).items():
        sig[name] = float(task_sigma(model, cues, device).mean())
    out["task_sigma"] = sig
    if reference is not None:
        mu, var = task_posteriors(model, arrays.cue(train_rows), device)
        out["reference"] = reference(mu, var, arrays.episodes["task"].to_numpy()[train_rows])
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


@torch.no_grad()
def validate(model, val: Batches, tc: TrainConfig, device: torch.device, pairs: dict[str, np.ndarray],
             teacher: torch.nn.Module | None = None) -> dict[str, float]:
    model.eval()
    tot, n = {}, 0
    for s in range(0, len(pairs["cue_rows"]), 32):
        sl = slice(s, s + 32)
        ends = pairs["ends"][sl] if tc.partial_cues(model.cfg.model_type) else None
        batch = to_device(val.gather(pairs["cue_rows"][sl], pairs["traj_rows"][sl], pairs["steps"][sl], ends), device)
        out = losses(model, batch, tc, sample=False, teacher=teacher)
        m = len(pairs["cue_rows"][sl])
        for key, v in out.items():
            tot[key] = tot.get(key, 0.0) + float(v) * m
        n += m
    model.train()
    return {k: v / max(n, 1) for k, v in tot.items()}


def _val_pairs(val: Batches, seed: int, per_task: int = 2, k: int = 10) -> dict[str, np.ndarray]:
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


# ---------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------

@dataclass
class TrainResult:
    model: torch.nn.Module
    config: ModelConfig
    norm: Normalisation
    history: list[dict[str, float]] = field(default_factory=list)
    metrics: dict[str, Any] = field(default_factory=dict)


def _start_from(model: torch.nn.Module, cfg: ModelConfig, folder: str) -> Normalisation:
    """Load ``folder``'s weights into ``model`` (which must have its architecture); returns its normalisation."""
    from democheck.petnet.checkpoint import load_checkpoint

    start = load_checkpoint(folder)
    # The novelty density belongs to the trained weights; training changes them, so it is dropped and refitted.
    diff = sorted(k for k, v in cfg.to_dict().items() if start.config.to_dict().get(k) != v and k != "novelty")
    if diff:
        raise DemocheckError(f"--init {folder}: its architecture differs from this run's ({', '.join(diff)})")
    own = model.state_dict().keys()
    model.load_state_dict({k: v for k, v in start.model.state_dict().items() if k in own})
    return start.norm


def work_dir(out: Path, resume: bool, force: bool) -> Path:
    """The folder beside ``out`` where a run keeps its state for ``--resume``, after checking ``out`` and it.

    Refuses an existing ``out`` without ``force``, and an interrupted run's folder without ``resume`` (or
    ``force``, which discards it).
    """
    work = out.parent / f".{out.name}.partial"
    refuse_existing(out, force)
    if work.exists() and not resume:
        if not force:
            raise DemocheckError(f"{work}: an interrupted run of this model is there; pass --resume to continue it "
                                 "or --force to start over")
        shutil.rmtree(work)
    return work


def train(arrays: EpisodeArrays, out: Path, tc: TrainConfig, model_type: str = "petnet", resume: bool = False,
          force: bool = False, meta: dict[str, Any] | None = None,
          on_progress: Callable[[int, int, dict[str, float]], None] | None = None,
          card: Callable[[dict[str, Any]], str] | None = None, stop_after: int | None = None,
          reference: Callable[[np.ndarray, np.ndarray, np.ndarray], dict[str, Any]] | None = None,
          task_groups: dict[str, str] | None = None) -> TrainResult | None:
    """Train and write the checkpoint folder ``out`` (atomically).

    ``reference(mu, var, tasks)`` of the training demos, when given, is stored
    in the checkpoint (the audit keeps its score scales and one-class SVM there).

    ``stop_after`` ends the run early after saving its state at that step, as
    an interruption would (used by tests of ``resume``); it then returns None.
    """
    from democheck.fsutil import atomic_output_dir

    out = Path(out)
    work = work_dir(out, resume, force)
    device = resolve_device(tc.device)
    torch.manual_seed(tc.seed)
    rng = np.random.default_rng(tc.seed)

    train_rows, val_rows = task_rows(arrays, "train", tc.seed), task_rows(arrays, "val", tc.seed)
    if not train_rows:
        raise DemocheckError("training needs at least one task with two or more demos (a cue and a trajectory); "
                             "this dataset has none")
    all_train = np.concatenate(list(train_rows.values()))
    h = arrays.frames.shape[1]
    cfg = ModelConfig(model_type=model_type, image_size=h, state_dim=arrays.state.shape[1],
                      action_dim=arrays.actions.shape[1], keypoints=tc.keypoints)
    model = build_model(cfg).to(device)
    teacher = None
    if tc.init:
        norm = _start_from(model, cfg, tc.init)
        if tc.partial_kl_weight > 0:
            teacher = copy.deepcopy(model.encoder).eval().requires_grad_(False)
    elif tc.partial_kl_weight > 0:
        raise DemocheckError("--partial-kl-weight needs --init: the KL's target is the starting model's encoder, "
                             "held fixed")
    else:
        spans = np.concatenate([np.arange(arrays.offsets[r], arrays.offsets[r] + arrays.lengths[r]) for r in all_train])
        norm = Normalisation.fit(arrays.state[spans], arrays.actions[spans])
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=tc.lr)
    groups = task_groups if tc.hard_negatives else None
    batches, val = Batches(arrays, train_rows, norm, groups), Batches(arrays, val_rows, norm)
    pairs = _val_pairs(val, tc.seed) if val_rows else None

    step, history, wall_before = 0, [], 0.0
    if resume:
        step, rng, doc = _load_state(work, model, opt)
        if doc.get("train_config", {}) != {**asdict(tc), "steps": doc["train_config"]["steps"]}:
            raise DemocheckError(f"{work}: saved with other training options; resume with the same options")
        if doc.get("fingerprint") != arrays.fingerprint:
            raise DemocheckError(f"{work}: saved from another dataset; resume on the same dataset")
        history, wall_before = doc.get("history", []), float(doc.get("wall_s", 0.0))
    work.mkdir(parents=True, exist_ok=True)

    def save(at: int, wall: float) -> None:
        _save_state(work, model, opt, at, rng, {"train_config": asdict(tc), "model_config": cfg.to_dict(),
                                                "fingerprint": arrays.fingerprint, "history": history, "wall_s": wall})

    t0 = time.perf_counter()
    running: dict[str, float] = {}
    while step < tc.steps:
        batch = to_device(batches.sample(rng, tc.batch_tasks, tc.timesteps,
                                         partial=tc.partial_cues(model_type)), device)
        out_l = losses(model, augment(batch, tc.shift), tc, teacher=teacher)
        opt.zero_grad(set_to_none=True)
        out_l["loss"].backward()
        opt.step()
        step += 1
        for key, v in out_l.items():
            v = float(v.detach())
            running[key] = 0.98 * running.get(key, v) + 0.02 * v
        report: dict[str, float] = {f"train_{k}": v for k, v in running.items()}
        if pairs is not None and (step % tc.val_every == 0 or step == tc.steps):
            report.update({f"val_{k}": v for k, v in validate(model, val, tc, device, pairs, teacher).items()})
            history.append({"step": step, **report})
        if on_progress:
            on_progress(step, tc.steps, report)
        if step % tc.ckpt_every == 0 or step == tc.steps or step == stop_after:
            save(step, wall_before + time.perf_counter() - t0)
        if stop_after is not None and step >= stop_after:
            return None
    wall = wall_before + time.perf_counter() - t0

    # Final numbers: losses, and how uncertain the model is about real vs nonsense cues.
    model.eval()
    metrics: dict[str, Any] = {"steps": step, "wall_s": round(wall, 1), "final": history[-1] if history else report}
    meta = dict(meta or {})
    if cfg.model_type == "petnet":
        held = np.concatenate(list(val_rows.values())) if val_rows else None
        extra = finish_petnet(model, arrays, all_train, held, tc.seed, device, tc.novelty, reference)
        metrics["task_sigma"] = extra.pop("task_sigma")
        meta.update(extra)
    meta = {**meta, "data": {**meta.get("data", {}), "fingerprint": arrays.fingerprint},
            "training": {**asdict(tc), "model_type": model_type}, "metrics": metrics, "history": history}
    with atomic_output_dir(out, force=True) as tmp:
        save_checkpoint(tmp, model, cfg, norm, meta, card(meta) if card else None)
    shutil.rmtree(work, ignore_errors=True)
    return TrainResult(model, cfg, norm, history, metrics)
