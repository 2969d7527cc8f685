"""PETNet and the TecNets baseline, in one file.

PETNet (Matsushima et al. 2020):

- ``TaskEncoder`` maps a *cue* (first and last frame of a demonstration,
  stacked on channels) to a Gaussian over task space: a mean and a variance
  per dimension.  The variance is the demonstration's *task uncertainty*.
- ``Controller`` maps the current frame, the robot state and a task variable
  ``z`` to normalised joint torques.
- Training draws ``z ~ N(mu, var)`` by reparameterisation from one demo of a
  task and clones the actions of *another* demo of the same task (MSE).
- Several cues of one task combine by the product of Gaussians.

TecNets (James et al. 2018): the same conv/FC shapes, a deterministic
L2-normalised embedding averaged over cues, trained with a hinge embedding
loss plus the same control loss.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from democheck.petnet.blocks import (ModelConfig, conv_out_dim, conv_stack, cue_input, mlp, novelty_input,
                                     to_input)
from democheck.petnet.posterior import product_of_gaussians


class TaskEncoder(nn.Module):
    """Cue -> (mu, var) of a diagonal Gaussian over task space.

    var = var_task + var_novel.  ``var_task`` is the paper's head: floor +
    softplus(raw); softplus grows linearly, not exponentially, so an
    out-of-distribution cue cannot blow the variance up to inf, and the floor
    keeps 1/var finite in the product of Gaussians.  The head is trained only
    on real cues and says nothing sure about others (a black image can get a
    smaller variance than any demo).  ``var_novel`` (``cfg.novelty``) is the
    part the training data cannot vouch for: prior_var * d2 / d2_ref, where
    d2 is the cue's squared Mahalanobis distance from the training cues' features
    (those of a cue autoencoder's encoder, ``novelty_features``; in models
    fitted before it, the task encoder's own conv features) of what
    ``cfg.novelty_view`` reads of a cue (its last frame; the whole cue in
    models fitted before), followed with ``cfg.novelty_state`` by the demo's
    standardised state at its last step (``end_state``), d2_ref a
    reference distance of real cues (held out, or the fitted ones where the
    model learnt every demo) and prior_var
    the variance of z over the training cues, per dimension -- an unfamiliar
    cue's posterior widens in proportion to how unfamiliar it is, in task-space
    units.  Fitted after training (``democheck.petnet.novelty``), zero until
    then; without it the encoder is exactly the paper's.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.conv = conv_stack(6, cfg)
        self.head = mlp(conv_out_dim(cfg), 2 * cfg.z_dim, cfg)
        if cfg.novelty:
            self.add_novelty()

    def add_novelty(self) -> None:
        """Register the (zero) buffers of the feature density, and with ``cfg.novelty_autoencoder`` the
        autoencoder's conv stack it is fitted on; ``petnet.novelty.fit_novelty`` fills them."""
        device = next(self.conv.parameters()).device  # where the model is (a GPU after training there)
        if not hasattr(self, "feature_mean"):
            d = conv_out_dim(self.cfg) + (self.cfg.state_dim if self.cfg.novelty_state else 0)
            self.register_buffer("feature_mean", torch.zeros(d, device=device))
            self.register_buffer("feature_precision", torch.zeros(d, d, device=device))
            self.register_buffer("novelty_ref", torch.ones((), device=device))
            self.register_buffer("prior_var", torch.zeros(self.cfg.z_dim, device=device))
            if self.cfg.novelty_state:
                self.register_buffer("end_state_mean", torch.zeros(self.cfg.state_dim, device=device))
                self.register_buffer("end_state_scale", torch.ones(self.cfg.state_dim, device=device))
        if self.cfg.novelty_autoencoder and not hasattr(self, "novelty_conv"):
            self.novelty_conv = conv_stack(6, self.cfg).to(device, memory_format=torch.channels_last)

    def image_features(self, cue: torch.Tensor, h: torch.Tensor | None = None) -> torch.Tensor:
        """The image part of the novelty features: the autoencoder's (``novelty_conv``) where the model has one,
        else the task encoder's own conv features (``h``, when given, are those of the cue as it is); both of what
        ``cfg.novelty_view`` reads of the cue (``novelty_input``)."""
        x = novelty_input(cue, self.cfg.novelty_view)
        if self.cfg.novelty_autoencoder:
            return self.novelty_conv(x)
        return self.conv(x) if h is None or x is not cue else h

    def novelty_features(self, cue: torch.Tensor, h: torch.Tensor | None = None,
                         end_state: torch.Tensor | None = None) -> torch.Tensor:
        """The features the novelty density is over: ``image_features``, and with ``cfg.novelty_state`` the
        demo's standardised state at its last step after them (``end_state`` [B, S], which such a model needs)."""
        f = self.image_features(cue, h)
        if not self.cfg.novelty_state:
            return f
        if end_state is None:
            raise ValueError("this model's novelty density reads each demo's state at its last step; pass end_state")
        return torch.cat([f, (end_state.to(f) - self.end_state_mean) / self.end_state_scale], 1)

    def distance2(self, features: torch.Tensor) -> torch.Tensor:
        """Squared Mahalanobis distance of novelty features [B, D] (``novelty_features``) from the training
        demos': [B]."""
        d = features - self.feature_mean
        return ((d @ self.feature_precision) * d).sum(-1)

    def head_posterior(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The paper's head on conv features [B, D]: (mu, var_task), var_task = floor + softplus(raw)."""
        mu, raw = self.head(features).chunk(2, dim=-1)
        return mu, self.cfg.var_floor + F.softplus(raw)

    def parts(self, cue: torch.Tensor, end_state: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(mu, var_task, var_novel); var_novel is zero without a fitted novelty density.  ``end_state``: each
        demo's state at its last step [B, S], which a density with ``cfg.novelty_state`` reads."""
        h = self.conv(cue)
        mu, var_task = self.head_posterior(h)
        if not self.cfg.novelty:
            return mu, var_task, torch.zeros_like(var_task)
        d2 = self.distance2(self.novelty_features(cue, h, end_state))
        return mu, var_task, self.prior_var * (d2 / self.novelty_ref)[:, None]

    def forward(self, cue: torch.Tensor, end_state: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        mu, var_task, var_novel = self.parts(cue, end_state)
        return mu, var_task + var_novel


class EmbeddingEncoder(nn.Module):
    """TecNets: cue -> L2-normalised deterministic embedding."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.conv = conv_stack(6, cfg)
        self.head = mlp(conv_out_dim(cfg), cfg.embed_dim, cfg)

    def forward(self, cue: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.head(self.conv(cue)), dim=-1)


class Controller(nn.Module):
    """(frame, state, z) -> normalised torques; the state joins after the convolutions, z where
    ``cfg.task_fusion`` says.

    Early fusion ("shift", "tile") lets the first convolution's features depend on the task, so the feature
    points can follow the object the cue named; for a spatially constant z, tiling it onto the image is a
    per-channel shift of the first convolution's pre-activations but at the padded border, which "shift"
    computes without the extra input channels.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.fusion = cfg.task_fusion
        self.conv = conv_stack(3 + (cfg.embed_dim if self.fusion == "tile" else 0), cfg, keypoints=cfg.keypoints,
                               fine=cfg.fine_points)
        self.z_shift = nn.Linear(cfg.embed_dim, cfg.conv_channels) if self.fusion == "shift" else None
        late = cfg.embed_dim if self.fusion == "late" else 0
        self.head = mlp(conv_out_dim(cfg, cfg.keypoints) + cfg.state_dim + late, cfg.action_dim, cfg)
        self.readout = nn.Linear(conv_out_dim(cfg, cfg.keypoints), cfg.readout_dim) if cfg.readout_dim else None

    def features(self, frame: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The convolutions' output for frames [B, 3, H, W] under task variables z [B, D]."""
        if self.fusion == "tile":
            b, _, h, w = frame.shape
            tiled = z[:, :, None, None].to(frame.dtype).expand(b, z.shape[1], h, w)
            return self.conv(torch.cat([frame, tiled], 1).contiguous(memory_format=torch.channels_last))
        if self.fusion == "shift":
            first = self.conv[0](frame) + self.z_shift(z)[:, :, None, None]
            return self.conv[1:](first)
        return self.conv(frame)

    def forward(self, frame: torch.Tensor, state: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self._head(self.features(frame, z), state, z)

    def _head(self, h: torch.Tensor, state: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([h, state] + ([z] if self.fusion == "late" else []), dim=-1))

    def act(self, frames: torch.Tensor, state: torch.Tensor, z: torch.Tensor, read: bool = False):
        """K steps of each of B trajectories under one task variable each: uint8 frames [B, K, H, W, 3],
        state [B, K, S], z [B, D] -> actions [B, K, A]; with ``read``, also the environment-state read-out
        [B, K, E] (``cfg.readout_dim``)."""
        b, k = frames.shape[:2]
        h, zk = self._features_k(frames, z)
        out = self._head(h, state.reshape(b * k, -1), zk).reshape(b, k, -1)
        return (out, self.readout(h).reshape(b, k, -1)) if read else out

    def _features_k(self, frames: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``features`` of uint8 frames [B, K, H, W, 3], each trajectory's K under its z [B, D]: [B * K, F], and
        the z each frame was read under [B * K, D]."""
        b, k = frames.shape[:2]
        zk = z[:, None].expand(b, k, z.shape[-1]).reshape(b * k, -1)
        return self.features(to_input(frames.reshape(b * k, *frames.shape[2:])), zk), zk

    def control_loss(self, batch: dict[str, torch.Tensor], z: torch.Tensor, readout_weight: float = 0.0
                     ) -> dict[str, torch.Tensor]:
        """The action MSE on the batch's demonstrated trajectory under z (``mse``), and with a read-out weight
        the read-out's MSE on the batch's standardised environment state where it is recorded (``readout``) and
        on its posed frames where it has them (``posed_readout``: the arm posed as in another demo, so that the
        objects must be seen, and which is the target known from z)."""
        if readout_weight <= 0 or self.readout is None or "env_state" not in batch:
            return {"mse": ((self.act(batch["frames"], batch["state"], z) - batch["actions"]) ** 2).mean()}
        actions, read = self.act(batch["frames"], batch["state"], z, read=True)
        target = batch["env_state"]
        known = torch.isfinite(target)
        err = torch.where(known, read - target.nan_to_num(), torch.zeros_like(read))
        out = {"mse": ((actions - batch["actions"]) ** 2).mean(),
               "readout": (err ** 2).sum() / known.sum().clamp(min=1)}
        if "posed_frames" in batch:
            h, _ = self._features_k(batch["posed_frames"], z)
            out["posed_readout"] = ((self.readout(h).reshape(batch["posed_env"].shape) - batch["posed_env"]) ** 2
                                    ).mean()
        return out


def kl_diag(mu_q: torch.Tensor, var_q: torch.Tensor, mu_p: torch.Tensor, var_p: torch.Tensor) -> torch.Tensor:
    """KL(q || p) for diagonal Gaussians, summed over the last dimension."""
    return 0.5 * (torch.log(var_p / var_q) + (var_q + (mu_q - mu_p) ** 2) / var_p - 1.0).sum(-1)


class PETNet(nn.Module):
    """Probabilistic task embedding + controller."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = TaskEncoder(cfg)
        self.controller = Controller(cfg)

    def task_posterior(self, cues: torch.Tensor, end_states: torch.Tensor | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """uint8 cues [B, N, 2, H, W, 3] (their demos' states at the last step [B, N, S]) -> the task posterior
        (mu, var) [B, z] of N cues each."""
        b, n = cues.shape[:2]
        ends = None if end_states is None else end_states.reshape(b * n, -1)
        mu, var = self.encoder(cue_input(cues.reshape(b * n, *cues.shape[2:])), ends)
        mu, var = mu.reshape(b, n, -1), var.reshape(b, n, -1)
        return product_of_gaussians(mu, var, dim=1) if n > 1 else (mu[:, 0], var[:, 0])

    def forward(self, cue: torch.Tensor, frames: torch.Tensor, state: torch.Tensor, sample: bool = True,
                cue_end_state: torch.Tensor | None = None):
        """cue uint8 [B, 2, H, W, 3]; frames uint8 [B, K, H, W, 3]; state [B, K, S] -> (actions [B, K, A], mu, var).
        ``cue_end_state``: the state at the cue demo's last step [B, S] (``TaskEncoder.parts``)."""
        mu, var = self.encoder(cue_input(cue), cue_end_state)
        z = mu + var.sqrt() * torch.randn_like(mu) if sample else mu
        return self.controller.act(frames, state, z), mu, var

    def loss(self, batch: dict[str, torch.Tensor], sample: bool = True,
             z_posterior: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None,
             terms: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], dict[str, torch.Tensor]] | None = None,
             readout_weight: float = 0.0) -> dict[str, torch.Tensor]:
        """The paper's objective on a batch: z ~ N(mu, var) of each task's cue by reparameterisation (z = mu when
        not ``sample``), then the mean squared error of the controller's actions on the demonstrated trajectory
        of another demo of the task.  Returns ``loss`` (= ``mse``) and the cues' mean ``sigma``.

        batch: ``cue`` uint8 [B, 2, H, W, 3] (and ``cue_end_state``, the state at its demo's last step [B, S],
        which a fitted density with end states reads); ``frames`` uint8 [B, K, H, W, 3], ``state`` [B, K, S] and
        normalised ``actions`` [B, K, A] at K timesteps of the trajectory.  Hooks for the optional terms
        (``democheck.petnet.regularisers``): ``z_posterior(mu, var)`` replaces the Gaussian z is drawn from;
        ``terms(mu, var, sigma)`` adds named terms, computed after z is drawn and before the controller runs.
        ``readout_weight``: the controller's environment-state read-out (``Controller.control_loss``) joins the loss.
        """
        mu, var = self.encoder(cue_input(batch["cue"]), batch.get("cue_end_state"))
        mu_s, var_s = z_posterior(mu, var) if z_posterior is not None and sample else (mu, var)
        z = mu_s + var_s.sqrt() * torch.randn_like(mu_s) if sample else mu_s
        sigma = var.sqrt()
        out = {"sigma": sigma.mean()}
        if terms is not None:
            out.update(terms(mu, var, sigma))
        out.update(self.controller.control_loss(batch, z, readout_weight))
        out["loss"] = out["mse"] + readout_weight * (out.get("readout", 0.0) + out.get("posed_readout", 0.0))
        return out


class TecNet(nn.Module):
    """TecNets baseline: deterministic normalised embedding + controller."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = EmbeddingEncoder(cfg)
        self.controller = Controller(cfg)

    def embed(self, cues: torch.Tensor) -> torch.Tensor:
        """uint8 cues [B, N, 2, H, W, 3] -> normalised mean embedding [B, D] of N cues each."""
        b, n = cues.shape[:2]
        e = self.encoder(cue_input(cues.reshape(b * n, *cues.shape[2:]))).reshape(b, n, -1)
        return F.normalize(e.mean(1), dim=-1)

    def forward(self, cue: torch.Tensor, frames: torch.Tensor, state: torch.Tensor, sample: bool = True):
        e = self.encoder(cue_input(cue))
        return self.controller.act(frames, state, e), e, None

    def loss(self, batch: dict[str, torch.Tensor], sample: bool = True, margin: float = 0.1,
             hinge_weight: float = 10.0, readout_weight: float = 0.0) -> dict[str, torch.Tensor]:
        """TecNets' objective: the control MSE under the cue's embedding plus ``hinge_weight`` times the hinge
        loss that keeps each demonstrated trajectory's embedding nearest its own task's cue (batch as
        ``PETNet.loss``, plus ``traj_cue``, the trajectory's own cue).  ``sample`` is ignored: the embedding is
        deterministic."""
        z = self.encoder(cue_input(batch["cue"]))
        out = {"tecnet_hinge": hinge_embedding_loss(z, self.encoder(cue_input(batch["traj_cue"])), margin)}
        out.update(self.controller.control_loss(batch, z, readout_weight))
        out["loss"] = out["mse"] + hinge_weight * out["tecnet_hinge"] + readout_weight * (
            out.get("readout", 0.0) + out.get("posed_readout", 0.0))
        return out


def hinge_embedding_loss(cue_emb: torch.Tensor, target_emb: torch.Tensor, margin: float = 0.1) -> torch.Tensor:
    """TecNets: each target demo must be closer (cosine) to its own task's cue than to any other task's by ``margin``."""
    sim = target_emb @ cue_emb.T  # [B, B]: target i vs cue j
    pos = sim.diagonal()[:, None]
    off = ~torch.eye(len(sim), dtype=torch.bool, device=sim.device)
    return F.relu(margin - pos + sim)[off].mean()


def build_model(cfg: ModelConfig) -> nn.Module:
    if cfg.model_type == "petnet":
        model: nn.Module = PETNet(cfg)
    elif cfg.model_type == "tecnet":
        model = TecNet(cfg)
    else:
        raise ValueError(f"unknown model type {cfg.model_type!r} (petnet, tecnet)")
    return model.to(memory_format=torch.channels_last)


__all__ = ["ModelConfig", "PETNet", "TecNet", "TaskEncoder", "Controller", "kl_diag", "hinge_embedding_loss",
           "build_model", "cue_input", "to_input"]
