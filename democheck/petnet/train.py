"""The training loop of PETNet (and the TecNets baseline), on decoded episode arrays.

Each step draws a batch (``batches.Batches``: per task, a cue demo and a
different demo's trajectory), shifts its images when asked
(``batches.augment``), and takes an Adam step on the objective
(``regularisers.objective``: the model's own loss plus the recipe's named
terms).  What a run does is a ``TrainConfig``, read from a training recipe
(``democheck.petnet.recipe``).

The run's state (weights, Adam moments, both RNGs, history) is saved every
``ckpt_every`` steps into a work folder beside the output
(``run_state``); ``resume=True`` continues from it and reaches the same
weights as an uninterrupted run.
"""

from __future__ import annotations

import copy
import math
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from democheck.data.cache import EpisodeArrays
from democheck.errors import DemocheckError
from democheck.fsutil import atomic_output_dir, work_dir
from democheck.petnet import regularisers
from democheck.petnet.batches import (Batches, PosedFrames, ResidentArrays, augment, standardise, task_rows,
                                      to_device, val_pairs)
from democheck.petnet.checkpoint import Normalisation, load_checkpoint, save_checkpoint
from democheck.petnet.finish import finish_petnet
from democheck.petnet.blocks import TASK_FUSIONS, ModelConfig
from democheck.petnet.model import build_model
from democheck.petnet.posterior import TaskPosterior
from democheck.petnet.run_state import load_state, save_state

MODEL_TYPES = ("petnet", "tecnet")
LR_SCHEDULES = ("constant", "cosine")
WARMUP_SHARE = 0.02  # of the steps, for the cosine schedule


def learning_rate(tc: "TrainConfig", step: int) -> float:
    """The learning rate of step ``step`` (0-based) under the run's schedule: a function of the step alone, so a
    resumed run follows the same curve."""
    if tc.lr_schedule == "constant":
        return tc.lr
    warm = max(1, int(WARMUP_SHARE * tc.steps))
    if step < warm:
        return tc.lr * (step + 1) / warm
    return 0.5 * tc.lr * (1.0 + math.cos(math.pi * (step - warm) / max(1, tc.steps - warm)))


@dataclass
class TrainConfig:
    """One training run, as a recipe resolves it (``democheck.petnet.recipe`` names the TOML keys)."""

    model_type: str = "petnet"  # "petnet" | "tecnet"
    steps: int = 20_000
    batch_tasks: int = 16  # tasks per step; each gives one cue and one demonstrated trajectory
    timesteps: int = 8  # timesteps of the demonstrated trajectory per task per step
    lr: float = 5e-4
    # PETNet: weight of each optional term of the objective, by name (``regularisers.REGULARISERS``); empty: the
    # paper's loss.
    regularisers: dict[str, float] = field(default_factory=dict)
    # Batches of look-alike tasks (see ``Batches``), when the data says which tasks look alike (democheck suites).
    hard_negatives: bool = False
    # Random-shift augmentation of training images (``batches.random_shift``): up to this many pixels each way.
    shift: int = 0
    keypoints: bool = False  # controller architecture option, see ModelConfig.keypoints
    task_fusion: str = "late"  # where the controller reads z, see ModelConfig.task_fusion
    conv_channels: int = 16  # channels of every convolution, encoder and controller
    fine_points: bool = False  # controller architecture option, see ModelConfig.fine_points
    z_dim: int = 10  # the task variable's dimensions (ModelConfig.z_dim; tiled, each is one more input channel)
    fc_units: int = 200  # units of every fully connected layer (ModelConfig.fc_units)
    # Decoupled weight decay (AdamW) of every weight; 0: Adam, as every recipe before it.
    weight_decay: float = 0.0
    # "constant", or "cosine": a linear warm-up over the first 2% of the steps, then a cosine decay to 0.
    lr_schedule: str = "constant"
    # Weight of the controller's read-out of the recorded environment state (the objects' poses, standardised)
    # from its conv features; 0: none.  Needs data that records an environment state.
    object_readout: float = 0.0
    # Frames rendered for each training demo with the arm posed as in other demos, its objects where they began
    # (``democheck.sim.posed``; a pushing suite's layouts), which the read-out learns on too: there the arm cannot
    # stand in for the objects, nor anything but z say which object is the target.  0: none.
    posed_frames: int = 0
    # The model's input size: every frame resized to image_size x image_size (``data.resize_frames``) for training
    # and, by the audit, for scoring; None: the camera's own size.
    image_size: int | None = None
    # PETNet: after training, fit the novelty density that adds the epistemic part of the task variance
    # (``democheck.petnet.novelty``); off leaves the paper's variance head alone.
    novelty: bool = True
    # Of the training cues, the share the novelty density leaves out as outliers (``novelty.fit_novelty``): for
    # a user's own data, which may hold the bad demos the audit is to find.
    novelty_trim: float = 0.0
    # The novelty density over a cue autoencoder's features (``novelty.train_cue_autoencoder``), trained after
    # the model on its training cues; off: over the task encoder's own conv features, as models before it.
    novelty_autoencoder: bool = True
    # The novelty density reads each demo's state at its last step beside its last frame (``novelty.fit_novelty``
    # with end states); off: the frame alone.  On the one-task Meta-World sets (55 demos, 39 state numbers) the
    # state blurred three occluded demos' frames (the model card).
    novelty_state: bool = True
    # Start from this model folder's weights and normalisation instead of a fresh network (same architecture).
    init: str | None = None
    # TecNets' own objective: hinge margin, and the hinge's weight.  At 1 the unit-norm embedding collapses at
    # initialisation (every cue maps to one point, where the hinge loss has no gradient) and never recovers on
    # push-v1; at 10 it separates within ~50 steps.
    tecnet_margin: float = 0.1
    tecnet_weight: float = 10.0
    seed: int = 0
    val_every: int = 500
    ckpt_every: int = 1000
    # The last this share of ``steps`` draws from every demo, the validation demos too, so that an audit of the
    # training data compares demos the model has all learnt (held-out ones otherwise look unfamiliar: on a
    # Meta-World set the OCSVM flagged 7 of 19 held-out clean demos and 2 of 181 trained ones).  Validation
    # stops where this phase starts; the novelty density and the OCSVM are then fitted on every demo.
    final_all_share: float = 0.0
    device: str = "auto"

    def partial_cues(self) -> bool:
        """Whether batches carry cues cut short (``partial_cue``), which some regularisers need."""
        return self.model_type == "petnet" and any(r.partial_cues for r in regularisers.active(self.regularisers))

    def check(self) -> None:
        """One clear line for a configuration no run can follow."""
        if self.model_type not in MODEL_TYPES:
            raise DemocheckError(f"model_type must be petnet or tecnet, not {self.model_type!r}")
        if min(self.steps, self.batch_tasks, self.timesteps, self.val_every, self.ckpt_every) < 1:
            raise DemocheckError("steps, batch_tasks, timesteps, val_every and ckpt_every must be positive")
        if self.image_size is not None and not 8 <= self.image_size <= 512:
            raise DemocheckError(f"image_size must be between 8 and 512 pixels, not {self.image_size}")
        if not 0.0 <= self.novelty_trim < 0.5:
            raise DemocheckError(f"novelty_trim is a share of the training cues below 0.5, not {self.novelty_trim}")
        if self.shift < 0:
            raise DemocheckError(f"shift must be 0 or more pixels, not {self.shift}")
        if not 0.0 <= self.final_all_share < 1.0:
            raise DemocheckError(f"final_all_share is a share of the steps below 1, not {self.final_all_share}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise DemocheckError(f"lr_schedule must be {' or '.join(LR_SCHEDULES)}, not {self.lr_schedule!r}")
        if self.task_fusion not in TASK_FUSIONS:
            raise DemocheckError(f"task_fusion must be one of {', '.join(TASK_FUSIONS)}, not {self.task_fusion!r}")
        if self.object_readout < 0:
            raise DemocheckError(f"object_readout is a weight, 0 or more, not {self.object_readout}")
        if self.posed_frames < 0 or (self.posed_frames and not self.object_readout):
            raise DemocheckError("posed_frames trains the object read-out: 0 or more frames a demo, with "
                                 f"object_readout above 0 (not posed_frames {self.posed_frames}, object_readout "
                                 f"{self.object_readout})")
        if self.fine_points and not self.keypoints:
            raise DemocheckError("fine_points reads feature points: set model.keypoints = true too")
        if self.conv_channels < 1:
            raise DemocheckError(f"conv_channels must be positive, not {self.conv_channels}")
        if not self.lr >= 0:
            raise DemocheckError(f"lr must be 0 or more, not {self.lr}")
        regularisers.check_weights(self.regularisers)
        if self.model_type != "petnet" and regularisers.active(self.regularisers):
            raise DemocheckError("regularisers are terms of PETNet's objective; a TecNets model has its own")
        needs_init = [r.name for r in regularisers.active(self.regularisers) if r.needs_init]
        if needs_init and not self.init:
            raise DemocheckError(f"{', '.join(needs_init)} needs a starting model (init): its target is that "
                                 "model's encoder, held fixed")


def resolve_device(name: str) -> torch.device:
    """``auto`` (CUDA when there is one), ``cpu`` or ``cuda``; one clear line otherwise."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise DemocheckError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise DemocheckError(f"--device must be auto, cpu or cuda, not {name!r}")
    return torch.device(name)


@torch.no_grad()
def validate(model, val: Batches, tc: TrainConfig, device: torch.device, pairs: dict[str, np.ndarray],
             teacher: torch.nn.Module | None = None) -> dict[str, float]:
    """The objective's terms on the fixed validation pairs, with z = mu."""
    model.eval()
    tot, n = {}, 0
    for s in range(0, len(pairs["cue_rows"]), 32):
        sl = slice(s, s + 32)
        ends = pairs["ends"][sl] if tc.partial_cues() else None
        batch = to_device(val.gather(pairs["cue_rows"][sl], pairs["traj_rows"][sl], pairs["steps"][sl], ends), device)
        out = objective(model, batch, tc, sample=False, teacher=teacher)
        m = len(pairs["cue_rows"][sl])
        for key, v in out.items():
            tot[key] = tot.get(key, 0.0) + float(v) * m
        n += m
    model.train()
    return {k: v / max(n, 1) for k, v in tot.items()}


def objective(model, batch: dict[str, torch.Tensor], tc: TrainConfig, sample: bool = True,
              teacher: torch.nn.Module | None = None) -> dict[str, torch.Tensor]:
    """``regularisers.objective`` with this run's weights."""
    return regularisers.objective(model, batch, tc.regularisers, sample=sample, teacher=teacher,
                                  tecnet_margin=tc.tecnet_margin, tecnet_weight=tc.tecnet_weight,
                                  readout=tc.object_readout)


@dataclass
class TrainResult:
    model: torch.nn.Module
    config: ModelConfig
    norm: Normalisation
    history: list[dict[str, float]] = field(default_factory=list)
    metrics: dict[str, Any] = field(default_factory=dict)


def env_standardisation(arrays: EpisodeArrays, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and SD of each environment-state dimension over the training rows' frames, for the read-out's target
    (a dimension that never moves gets an SD of 1)."""
    spans = np.concatenate([np.arange(arrays.offsets[r], arrays.offsets[r] + arrays.lengths[r]) for r in rows])
    x = arrays.env_state[spans].astype(np.float64)
    mean, sd = np.nanmean(x, 0), np.nanstd(x, 0)
    return np.nan_to_num(mean).astype(np.float32), np.where(np.isfinite(sd) & (sd > 1e-6), sd, 1.0).astype(np.float32)


def _start_from(model: torch.nn.Module, cfg: ModelConfig, folder: str) -> Normalisation:
    """Load ``folder``'s weights into ``model`` (which must have its architecture); returns its normalisation."""
    start = load_checkpoint(folder)
    # The novelty density belongs to the trained weights; training changes them, so it is dropped and refitted.
    diff = sorted(k for k, v in cfg.to_dict().items()
                  if start.config.to_dict().get(k) != v and not k.startswith("novelty"))
    if diff:
        raise DemocheckError(f"init {folder}: its architecture differs from this run's ({', '.join(diff)})")
    own = model.state_dict().keys()
    model.load_state_dict({k: v for k, v in start.model.state_dict().items() if k in own})
    return start.norm


def every_row(train_rows: dict[str, np.ndarray], val_rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every demo of every task, validation demos included: what the final phase (``final_all_share``) learns."""
    none = np.zeros(0, np.int64)
    return {t: np.sort(np.concatenate([train_rows.get(t, none), val_rows.get(t, none)]))
            for t in set(train_rows) | set(val_rows)}


def names_splits(arrays: EpisodeArrays) -> bool:
    """Whether the data names its splits (a democheck suite's sidecar) rather than democheck holding out demos."""
    return bool("split" in arrays.episodes and arrays.episodes["split"].notna().any())


def final_steps(arrays: EpisodeArrays, tc: TrainConfig, val_rows: dict[str, np.ndarray]) -> int:
    """The steps of the final phase that learns every demo (``final_all_share``): only where validation holds out
    demos of tasks that are trained on -- a split the data names stays as it is."""
    return int(round(tc.final_all_share * tc.steps)) if val_rows and not names_splits(arrays) else 0


def finish_rows(arrays: EpisodeArrays, tc: TrainConfig, train_rows: dict[str, np.ndarray],
                val_rows: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
    """The rows the novelty density and the OCSVM are fitted on, and the held-out rows the density's reference
    distance comes from (None: the fitted rows themselves): every demo and None when the final phase learnt
    every demo -- the audit then compares demos the model has all seen -- else the training and validation rows.
    ``democheck fit-novelty`` refits a model the same way."""
    if final_steps(arrays, tc, val_rows) > 0:
        return np.concatenate(list(every_row(train_rows, val_rows).values())), None
    return np.concatenate(list(train_rows.values())), (np.concatenate(list(val_rows.values())) if val_rows else None)


def train(arrays: EpisodeArrays, out: Path, tc: TrainConfig, resume: bool = False, force: bool = False,
          meta: dict[str, Any] | None = None, on_progress: Callable[[int, int, dict[str, float]], None] | None = None,
          card: Callable[[dict[str, Any]], str] | None = None, stop_after: int | None = None,
          reference: Callable[[TaskPosterior, np.ndarray], dict[str, Any]] | None = None,
          task_groups: dict[str, str] | None = None,
          on_novelty: Callable[[int, int], None] | None = None, resident: bool | None = None,
          posed: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None) -> TrainResult | None:
    """Train and write the checkpoint folder ``out`` (atomically).

    ``resident``: gather training batches from a copy of the data on the training device (``ResidentArrays``);
    None: on a GPU.  The batches, and so the weights, are the same either way.

    ``posed(rows)``: renders ``tc.posed_frames`` frames of each of those training rows' layouts with the arm posed
    as in other demos (frames [N, K, H, W, 3], the objects' poses there [N, K, E]); needed where the recipe asks
    for posed frames.

    ``reference(posterior, tasks)`` of the training demos, when given, is stored in the checkpoint (the audit
    keeps its one-class SVM there).  ``stop_after`` ends the run early after saving its state at that step,
    as an interruption would (used by tests of ``resume``); it then returns None.
    """
    tc.check()
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
    left_out = sorted(set(arrays.episodes["task"]) - set(train_rows))
    h = arrays.frames.shape[1]
    if tc.object_readout > 0 and arrays.env_state is None:
        raise DemocheckError("object_readout reads the recorded environment state (observation.environment_state), "
                             "which this dataset does not record; set model.object_readout = 0")
    readout_dim = arrays.env_state.shape[1] if tc.object_readout > 0 else 0
    cfg = ModelConfig(model_type=tc.model_type, image_size=h, state_dim=arrays.state.shape[1],
                      action_dim=arrays.actions.shape[1], keypoints=tc.keypoints,
                      task_fusion=tc.task_fusion, conv_channels=tc.conv_channels, readout_dim=readout_dim,
                      fine_points=tc.fine_points, z_dim=tc.z_dim, fc_units=tc.fc_units)
    model = build_model(cfg).to(device)
    teacher = None
    if tc.init:
        norm = _start_from(model, cfg, tc.init)
        if any(r.needs_init for r in regularisers.active(tc.regularisers)):
            teacher = copy.deepcopy(model.encoder).eval().requires_grad_(False)
    else:
        spans = np.concatenate([np.arange(arrays.offsets[r], arrays.offsets[r] + arrays.lengths[r]) for r in all_train])
        norm = Normalisation.fit(arrays.state[spans], arrays.actions[spans])
    model.train()
    opt = (torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay) if tc.weight_decay
           else torch.optim.Adam(model.parameters(), lr=tc.lr))
    groups = task_groups if tc.hard_negatives else None
    env_norm = env_standardisation(arrays, all_train) if readout_dim else None
    source = ResidentArrays(arrays, norm, device, env_norm) \
        if (device.type == "cuda" if resident is None else resident) else arrays
    posed_frames = None
    if tc.posed_frames:
        if posed is None:
            raise DemocheckError("posed_frames renders the training demos' layouts again: only a democheck pushing "
                                 "suite records them; set model.posed_frames = 0")
        frames, poses = posed(all_train)
        posed_frames = PosedFrames(all_train, frames, standardise(poses, env_norm))
    batches = Batches(source, train_rows, norm, groups, env_norm, posed_frames)
    val = Batches(arrays, val_rows, norm, env_norm=env_norm)
    pairs = val_pairs(val, tc.seed) if val_rows else None
    every = every_row(train_rows, val_rows)
    final_from = tc.steps - final_steps(arrays, tc, val_rows)
    batches_all = Batches(source, every, norm, groups, env_norm) if final_from < tc.steps else batches

    step, history, wall_before = 0, [], 0.0
    if resume:
        step, rng, doc = load_state(work, model, opt)
        # Options added since the run was saved count as their defaults (what the run was made with).
        saved = {**asdict(TrainConfig()), **doc.get("train_config", {})}
        if saved != {**asdict(tc), "steps": saved["steps"]}:
            raise DemocheckError(f"{work}: saved with other training options; resume with the same options")
        if doc.get("fingerprint") != arrays.fingerprint:
            raise DemocheckError(f"{work}: saved from another dataset; resume on the same dataset")
        history, wall_before = doc.get("history", []), float(doc.get("wall_s", 0.0))
    work.mkdir(parents=True, exist_ok=True)

    def save(at: int, wall: float) -> None:
        save_state(work, model, opt, at, rng, {"train_config": asdict(tc), "model_config": cfg.to_dict(),
                                               "fingerprint": arrays.fingerprint, "history": history, "wall_s": wall})

    t0 = time.perf_counter()
    running: dict[str, float] = {}
    report: dict[str, float] = {}
    while step < tc.steps:
        drawn = batches_all if step >= final_from else batches
        batch = to_device(drawn.sample(rng, tc.batch_tasks, tc.timesteps, partial=tc.partial_cues()), device)
        for g in opt.param_groups:
            g["lr"] = learning_rate(tc, step)
        out_l = objective(model, augment(batch, tc.shift), tc, teacher=teacher)
        opt.zero_grad(set_to_none=True)
        out_l["loss"].backward()
        opt.step()
        step += 1
        for key, v in out_l.items():
            v = float(v.detach())
            running[key] = 0.98 * running.get(key, v) + 0.02 * v
        report = {f"train_{k}": v for k, v in running.items()}
        if pairs is not None and step <= final_from and (step % tc.val_every == 0 or step == final_from):
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
        fit_rows, held = finish_rows(arrays, tc, train_rows, val_rows)
        extra = finish_petnet(model, arrays, fit_rows, held, tc.seed, device, tc.novelty, tc.novelty_trim, reference,
                              autoencoder=None if tc.novelty_autoencoder else 0, on_novelty=on_novelty,
                              end_state=tc.novelty_state)
        metrics["task_sigma"] = extra.pop("task_sigma")
        meta.update(extra)
    # Which tasks the model learnt: the audit warns about the others, the card names them.
    tasks = {"trained": sorted(train_rows), "left_out": left_out,
             "validation": "the data's val split" if names_splits(arrays) else "held-out demos of every task"
             + (f", learnt too in the last {tc.steps - final_from} steps" if final_from < tc.steps else "")}
    meta = {**meta, "data": {**meta.get("data", {}), "fingerprint": arrays.fingerprint, "task_split": tasks},
            "training": asdict(tc), "metrics": metrics, "history": history}
    with atomic_output_dir(out, force=True) as tmp:
        save_checkpoint(tmp, model, cfg, norm, meta, card(meta) if card else None)
    shutil.rmtree(work, ignore_errors=True)
    return TrainResult(model, cfg, norm, history, metrics)
