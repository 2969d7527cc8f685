"""Checkpoints: a folder with ``config.json`` + ``model.safetensors`` (+ ``README.md``, the model card).

Loading reads the JSON config, builds the module, and loads tensors with
safetensors: nothing in a checkpoint is ever unpickled or executed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from democheck import resources
from democheck.errors import DemocheckError
from democheck.petnet.blocks import ModelConfig
from democheck.petnet.model import build_model

FORMAT = "democheck-model"
FORMAT_VERSION = 1


class CheckpointError(DemocheckError):
    """A folder or file that is not a loadable democheck checkpoint."""


@dataclass
class Normalisation:
    """State/action statistics of the training data; the controller sees and predicts normalised values."""

    state_mean: list[float]
    state_std: list[float]
    action_mean: list[float]
    action_std: list[float]

    def state(self, x: np.ndarray) -> np.ndarray:
        return (x - np.float32(self.state_mean)) / np.float32(self.state_std)

    def action(self, x: np.ndarray) -> np.ndarray:
        return (x - np.float32(self.action_mean)) / np.float32(self.action_std)

    def unaction(self, y: np.ndarray) -> np.ndarray:
        """The controller's normalised output back in the dataset's action units (inverse of ``action``)."""
        return y * np.float32(self.action_std) + np.float32(self.action_mean)

    @classmethod
    def fit(cls, state: np.ndarray, actions: np.ndarray) -> "Normalisation":
        def std(x):
            return np.maximum(x.std(0), 1e-3).tolist()

        return cls(state.mean(0).tolist(), std(state), actions.mean(0).tolist(), std(actions))


@dataclass
class Checkpoint:
    """A loaded model with everything needed to use it."""

    model: torch.nn.Module
    config: ModelConfig
    norm: Normalisation
    meta: dict[str, Any] = field(default_factory=dict)  # data fingerprint, training summary, OCSVM, ...
    path: Path | None = None


def save_checkpoint(folder: Path, model: torch.nn.Module, config: ModelConfig, norm: Normalisation,
                    meta: dict[str, Any], card: str | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"format": FORMAT, "format_version": FORMAT_VERSION, "model": config.to_dict(),
           "normalisation": norm.__dict__, **meta}
    (folder / "config.json").write_text(json.dumps(doc, indent=2, sort_keys=False))
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(tensors, str(folder / "model.safetensors"), metadata={"format": FORMAT})
    if card is not None:
        (folder / "README.md").write_text(card)


def model_folder(folder: str | Path | None = None) -> Path:
    """A model folder: the path given, else the shipped model of that name (``democheck.resources``), else
    (``None``) the default shipped model."""
    if folder is None:
        return resources.shipped_model()
    path = Path(folder)
    if not path.exists() and len(path.parts) == 1 and resources.shipped_model(path.name).is_dir():
        return resources.shipped_model(path.name)
    return path


def load_checkpoint(folder: str | Path | None = None, device: str | torch.device = "cpu") -> Checkpoint:
    """Build the module from ``config.json`` and load ``model.safetensors``; clear errors otherwise.

    ``folder``: a model folder, the name of a shipped model, or None for the default shipped model."""
    folder = model_folder(folder)
    if not folder.exists():
        shipped = ", ".join(resources.shipped_models()) or "none"
        raise CheckpointError(f"{folder}: no such model folder (shipped models: {shipped}; train one with "
                              "`democheck train`)")
    if folder.is_file():
        raise CheckpointError(f"{folder}: a model is a folder holding config.json and model.safetensors, not a file")
    cfg_path, weights = folder / "config.json", folder / "model.safetensors"
    try:
        doc = json.loads(cfg_path.read_text())
    except FileNotFoundError:
        raise CheckpointError(f"{cfg_path}: missing; not a democheck model folder") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise CheckpointError(f"{cfg_path}: not valid JSON; not a democheck model") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"{cfg_path}: not a democheck model config (no \"format\": \"{FORMAT}\")")
    if doc.get("format_version", 0) > FORMAT_VERSION:
        raise CheckpointError(f"{cfg_path}: made by a newer democheck (format {doc['format_version']})")
    try:
        known = {f.name for f in fields(ModelConfig)}
        config = ModelConfig(**{k: v for k, v in doc["model"].items() if k in known})
        norm = Normalisation(**doc["normalisation"])
        model = build_model(config)
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{cfg_path}: malformed model config ({exc})") from None
    try:
        tensors = load_file(str(weights))
    except FileNotFoundError:
        raise CheckpointError(f"{weights}: missing") from None
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{weights}: not a safetensors file ({str(exc).splitlines()[0]})") from None
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1].strip() if len(str(exc).splitlines()) > 1 else str(exc)
        raise CheckpointError(f"{weights}: tensors do not match config.json ({first})") from None
    model.eval().to(device)
    meta = {k: v for k, v in doc.items() if k not in ("format", "format_version", "model", "normalisation")}
    return Checkpoint(model=model, config=config, norm=norm, meta=meta, path=folder)
