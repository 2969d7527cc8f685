"""What PETNet's and TecNets' networks are made of (``democheck.petnet.model``): the model's configuration, the
convolution and fully connected stacks, the spatial softmax that turns a map into feature points, and how frames
and cues become network input."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn


NOVELTY_VIEWS = ("cue", "last")  # what the novelty density can read of a cue (``novelty_input``)
TASK_FUSIONS = ("late", "shift", "tile")  # where the controller reads the task variable (``Controller``)


@dataclass
class ModelConfig:
    """Everything needed to rebuild the network; stored in the checkpoint's config.json."""

    model_type: str = "petnet"  # "petnet" | "tecnet"
    image_size: int = 64
    state_dim: int = 17
    action_dim: int = 7
    z_dim: int = 10  # PETNet: 10 means + 10 variances; TecNets: a 20-d embedding
    conv_channels: int = 16
    conv_layers: int = 4
    kernel: int = 5
    fc_units: int = 200
    fc_layers: int = 3
    var_floor: float = 1e-4
    # Controller only: last two conv layers at stride 1 and a spatial softmax (expected x, y of each channel)
    # instead of flattening a 4x4 map, so object and fingertip positions survive to the FC layers.
    keypoints: bool = False
    # PETNet encoder only: the task variance has a second, epistemic part that grows with the distance of the
    # cue's conv features from the training cues' (``TaskEncoder``); fitted after training, ``petnet.novelty``.
    novelty: bool = False
    # The novelty density on the features of a cue autoencoder's encoder (``novelty_conv``, trained to
    # reconstruct the training cues) instead of the task encoder's own conv features, which the task loss makes
    # blind to what the task does not need -- an empty scene lies inside them (``petnet.novelty``).
    novelty_autoencoder: bool = False
    # What of the cue the novelty density reads (``novelty_input``): "last", its last frame in both places -- how
    # familiar the demo's end looks; "cue", the cue as it is (models fitted before "last").  ``petnet.novelty``.
    novelty_view: str = "cue"
    # The novelty density reads the demo's state at its last step beside the view's image features (one Gaussian
    # over both, the state standardised over the training demos' ends): where the arm ended, which a frame cannot
    # show once the arm has left the view.  False in models fitted before it.  ``petnet.novelty``.
    novelty_state: bool = False
    # Where the controller reads the task variable (``TASK_FUSIONS``): "late", beside the state after the
    # convolutions (models made before the choice existed); "shift", a learnt per-channel shift of the first
    # convolution; "tile", z tiled onto the input image as extra channels (TecNets).  Late fusion cannot tell the
    # feature points which object the cue named (docs/results.md, the controller).
    task_fusion: str = "late"
    # Controller only: a linear read-out of the recorded environment state (the objects' poses) from the
    # convolutions' features, trained beside the actions so the feature points find the objects; 0: none.
    readout_dim: int = 0
    # Controller only, with keypoints: the feature points read off a map half the image's side (``conv_stack``'s
    # ``fine``) instead of a quarter -- finer object positions, about 3x the compute at 16 channels.
    fine_points: bool = False

    def __post_init__(self) -> None:
        if self.fine_points and not self.keypoints:
            raise ValueError("fine_points reads feature points: it needs keypoints")
        if self.novelty_view not in NOVELTY_VIEWS:
            raise ValueError(f"unknown novelty view {self.novelty_view!r}; views: {', '.join(NOVELTY_VIEWS)}")
        if self.task_fusion not in TASK_FUSIONS:
            raise ValueError(f"unknown task fusion {self.task_fusion!r}; choices: {', '.join(TASK_FUSIONS)}")

    @property
    def embed_dim(self) -> int:
        return self.z_dim if self.model_type == "petnet" else 2 * self.z_dim

    def to_dict(self) -> dict:
        return asdict(self)


class SpatialSoftmax(nn.Module):
    """[B, C, H, W] -> [B, 2C]: the expected (x, y) in [-1, 1] of each channel's softmax over the image."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        p = F.softmax(x.reshape(b, c, h * w), dim=-1).reshape(b, c, h, w)
        xs = torch.linspace(-1.0, 1.0, w, device=x.device, dtype=x.dtype)
        ys = torch.linspace(-1.0, 1.0, h, device=x.device, dtype=x.dtype)
        return torch.cat([(p.sum(2) * xs).sum(-1), (p.sum(3) * ys).sum(-1)], dim=-1)


def _strides(cfg: ModelConfig, keypoints: bool, fine: bool = False) -> list[int]:
    if fine:
        return [2] + [1] * (cfg.conv_layers - 1)
    return [2 if i < 2 or not keypoints else 1 for i in range(cfg.conv_layers)]


def conv_stack(in_ch: int, cfg: ModelConfig, keypoints: bool = False, fine: bool = False) -> nn.Sequential:
    """4 conv layers, 5x5, 16 channels, stride 2, ReLU (no normalisation: a demo's score must not depend on its batch).

    ``keypoints``: the last two layers at stride 1, then a spatial softmax instead of flattening; ``fine``
    (with keypoints): every layer after the first 3x3 at stride 1, so the points are read off a map half the
    image's side.
    """
    layers: list[nn.Module] = []
    ch = in_ch
    for i, stride in enumerate(_strides(cfg, keypoints, fine)):
        k = 3 if fine and i > 0 else cfg.kernel
        layers += [nn.Conv2d(ch, cfg.conv_channels, k, stride=stride, padding=k // 2), nn.ReLU()]
        ch = cfg.conv_channels
    layers.append(SpatialSoftmax() if keypoints else nn.Flatten())
    return nn.Sequential(*layers)


def conv_out_dim(cfg: ModelConfig, keypoints: bool = False) -> int:
    if keypoints:
        return 2 * cfg.conv_channels
    side = cfg.image_size
    for stride in _strides(cfg, False):
        side = (side + 2 * (cfg.kernel // 2) - cfg.kernel) // stride + 1
    return cfg.conv_channels * side * side


def mlp(in_dim: int, out_dim: int, cfg: ModelConfig) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(cfg.fc_layers):
        layers += [nn.Linear(d, cfg.fc_units), nn.ReLU()]
        d = cfg.fc_units
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def to_input(frames: torch.Tensor) -> torch.Tensor:
    """uint8 [..., H, W, C] -> float [..., C, H, W] in [-0.5, 0.5], channels_last for fast CPU convs."""
    x = frames.permute(*range(frames.dim() - 3), -1, -3, -2).float().div_(255.0).sub_(0.5)
    return x.contiguous(memory_format=torch.channels_last) if x.dim() == 4 else x


def cue_input(cues: torch.Tensor) -> torch.Tensor:
    """uint8 [B, 2, H, W, 3] (first, last frame) -> float [B, 6, H, W]."""
    b, _, h, w, _ = cues.shape
    x = cues.permute(0, 1, 4, 2, 3).reshape(b, 6, h, w).float().div_(255.0).sub_(0.5)
    return x.contiguous(memory_format=torch.channels_last)


def novelty_input(x: torch.Tensor, view: str) -> torch.Tensor:
    """What the novelty density reads of a cue input [B, 6, H, W] (``cue_input``): the cue itself (``view``
    "cue") or its last frame in both places ("last")."""
    if view == "cue":
        return x
    if view == "last":
        return torch.cat([x[:, 3:], x[:, 3:]], 1).contiguous(memory_format=torch.channels_last)
    raise ValueError(f"unknown novelty view {view!r}; views: {', '.join(NOVELTY_VIEWS)}")
