"""Training recipes: a TOML file names everything a training run does, so a checkpoint says how to make it again.

    democheck train DATA --out M --recipe petnet-push-v1 --set optim.lr=1e-3 --set regularisers.kl_prior=0.1

A recipe is a shipped name (``democheck/recipes/train/<name>.toml``; ``paper``
is the default) or a path.  Its keys, by section (``KEYS``), map onto
``TrainConfig``; ``--set section.key=value`` overrides one (the value is read
as TOML: ``1e-3``, ``true``, ``"text"``), and a key that is unique across
sections may drop its section.  The resolved recipe -- every key, defaults
included -- is written into the model's ``config.json`` and card.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

from democheck import resources
from democheck.errors import RecipeError
from democheck.petnet.regularisers import REGULARISERS
from democheck.petnet.train import TrainConfig

DEFAULT_RECIPE = "paper"

# section -> {TOML key: TrainConfig field}; [regularisers] is a table of name -> weight.
KEYS: dict[str, dict[str, str]] = {
    "": {"model_type": "model_type", "seed": "seed"},
    "optim": {"steps": "steps", "batch_tasks": "batch_tasks", "timesteps": "timesteps", "lr": "lr",
              "lr_schedule": "lr_schedule", "weight_decay": "weight_decay"},
    "batches": {"hard_negatives": "hard_negatives", "shift": "shift"},
    "model": {"keypoints": "keypoints", "task_fusion": "task_fusion", "conv_channels": "conv_channels",
              "object_readout": "object_readout", "posed_frames": "posed_frames", "fine_points": "fine_points",
              "z_dim": "z_dim",
              "fc_units": "fc_units",
              "novelty": "novelty", "novelty_trim": "novelty_trim",
              "novelty_autoencoder": "novelty_autoencoder", "novelty_state": "novelty_state", "init": "init",
              "image_size": "image_size"},
    "tecnet": {"margin": "tecnet_margin", "weight": "tecnet_weight"},
    "schedule": {"val_every": "val_every", "ckpt_every": "ckpt_every", "final_all_share": "final_all_share"},
}


def parse_set(item: str, example: str) -> tuple[str, Any]:
    """A ``--set key=value`` as (key, value), the value read as TOML (``parse_value``); ``example`` shows the form
    in the error a malformed one gets."""
    key, eq, text = item.partition("=")
    if not eq or not key.strip():
        raise RecipeError(f"--set takes key=value (e.g. {example}), not {item!r}")
    return key.strip(), parse_value(text.strip())


def parse_value(text: str) -> Any:
    """A ``--set`` value read as TOML (``1e-3``, ``true``, ``"text"``); a bare word is a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text  # a bare word: a string


def _field_of(key: str, where: str) -> tuple[str, str]:
    """(section, key) of a ``--set`` key: ``section.key``, or a key unique across sections."""
    section, _, name = key.rpartition(".")
    if section == "regularisers":
        if name not in REGULARISERS:
            raise RecipeError(f"{where}: unknown regulariser {name!r}; known: {', '.join(REGULARISERS)}")
        return section, name
    if section or key in KEYS[""]:
        if name not in KEYS.get(section, {}):
            raise RecipeError(f"{where}: unknown key {key!r}; keys: {', '.join(all_keys())}")
        return section, name
    hits = [s for s, keys in KEYS.items() if name in keys] + (["regularisers"] if name in REGULARISERS else [])
    if len(hits) != 1:
        raise RecipeError(f"{where}: {'ambiguous' if hits else 'unknown'} key {key!r}; keys: {', '.join(all_keys())}")
    return hits[0], name


def all_keys() -> list[str]:
    return ([k for k in KEYS[""]] + [f"{s}.{k}" for s, keys in KEYS.items() if s for k in keys]
            + [f"regularisers.{r}" for r in REGULARISERS])


def load_recipe(name_or_path: str | Path = DEFAULT_RECIPE, sets: list[str] | None = None,
                **everyday: Any) -> tuple[TrainConfig, dict[str, Any]]:
    """The ``TrainConfig`` of a recipe with its ``--set`` overrides and the everyday options that are not None
    (``steps``, ``seed``, ``device``, ``val_every``...), and the resolved recipe as a document."""
    path, doc = resources.read_recipe("train", name_or_path, "training")
    values: dict[str, Any] = {}
    regs: dict[str, float] = {}
    for key, value in doc.items():
        if key in ("name", "description"):
            continue
        if isinstance(value, dict):
            if key == "regularisers":
                for name, w in value.items():
                    _field_of(f"regularisers.{name}", str(path))
                    regs[name] = w
                continue
            if key not in KEYS or not key:
                raise RecipeError(f"{path}: unknown section [{key}]; sections: "
                                  f"{', '.join(['regularisers', *[s for s in KEYS if s]])}")
            for name, v in value.items():
                _field_of(f"{key}.{name}", str(path))
                values[KEYS[key][name]] = v
        else:  # a key at the top: its own, or a section's written without the section
            section, name = _field_of(key, str(path))
            if section == "regularisers":
                regs[name] = value
            else:
                values[KEYS[section][name]] = value
    for item in sets or []:
        key, value = parse_set(item, "optim.lr=1e-3")
        section, name = _field_of(key, "--set")
        if section == "regularisers":
            regs[name] = value
        else:
            values[KEYS[section][name]] = value
    values.update({k: v for k, v in everyday.items() if v is not None})
    if values.get("init") == "":
        values["init"] = None
    if values.get("image_size") == 0:  # 0 in a recipe: the camera's own size
        values["image_size"] = None
    known = {f.name for f in fields(TrainConfig)}
    bad = sorted(set(values) - known)
    if bad:
        raise RecipeError(f"not training options: {', '.join(bad)}")
    where = f"{path}" + (" with --set " + " ".join(sets) if sets else "")
    try:
        tc = TrainConfig(**values, regularisers={k: float(v) for k, v in regs.items() if v})
    except (TypeError, ValueError) as exc:
        raise RecipeError(f"{where}: {exc}") from None
    _check_types(tc, where)
    tc.check()
    resolved = {"name": doc.get("name", path.stem), "description": doc.get("description", ""),
                "source": str(path) if path.parent != resources.recipe_dir("train") else path.stem,
                "set": list(sets or []), "config": asdict(tc)}
    return tc, resolved


def _check_types(tc: TrainConfig, where: str) -> None:
    """A recipe value of the wrong type is one clear line, not a failure deep in the loop."""
    for f in fields(TrainConfig):
        v = getattr(tc, f.name)
        default = getattr(TrainConfig(), f.name)
        if f.name in ("init", "regularisers", "image_size") or v is None:
            continue
        ok = isinstance(v, type(default)) or (isinstance(default, float) and isinstance(v, int))
        if not ok or (isinstance(default, int) and isinstance(v, bool) and not isinstance(default, bool)):
            raise RecipeError(f"{where}: {f.name} must be {type(default).__name__}, not {v!r}")
    if isinstance(tc.lr, int):
        tc.lr = float(tc.lr)


def recipe_toml(resolved: dict[str, Any]) -> str:
    """The resolved recipe as a TOML file that makes the same run (for the model card)."""
    cfg = resolved["config"]
    out = [f'name = "{resolved["name"]}"']
    for section, keys in KEYS.items():
        rows = [(k, cfg[f]) for k, f in keys.items() if cfg.get(f) is not None]
        if not rows:
            continue
        if section:
            out += ["", f"[{section}]"]
        out += [f"{k} = {_toml_value(v)}" for k, v in rows]
    out += ["", "[regularisers]"] + [f"{k} = {_toml_value(v)}" for k, v in cfg["regularisers"].items()]
    return "\n".join(out) + "\n"


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(v)


def training_config(record: dict[str, Any]) -> TrainConfig:
    """The ``TrainConfig`` a model's ``config.json`` records under ``training`` (a key this release does not know
    is left out)."""
    rec = dict(record)
    regs = dict(rec.pop("regularisers", {}) or {})
    known = {f.name for f in fields(TrainConfig)}
    return TrainConfig(**{k: v for k, v in rec.items() if k in known}, regularisers=regs)
