"""What ships inside the package: the trained models and the recipes, found with ``importlib.resources``.

    models/<name>/                      config.json, model.safetensors, README.md (the model card), as
                                        ``democheck.models``
    synth/<name>.toml                   suite recipes (``democheck synth NAME``), as ``democheck.synth``
    democheck/recipes/train/<name>.toml training recipes (``democheck train --recipe NAME``)
    democheck/recipes/dagger/<name>.toml recovery training recipes (``democheck dagger --recipe NAME``)
    democheck/recipes/ranking/<name>.toml how each check's score enters the ranking (``default``)

They are package data (``pyproject.toml`` maps the two top-level folders into the package), so a wheel installed
anywhere finds them; nothing is looked up relative to a source checkout.
"""

from __future__ import annotations

import tomllib
from importlib.resources import files
from pathlib import Path
from typing import Any

from democheck.errors import RecipeError

DEFAULT_MODEL = "petnet-push-v1"  # the audit's, bench's and demo's model
EVAL_MODEL = "petnet-push-v2"  # the closed-loop evaluation's and its gate's: the shipped controller that pushes
RECIPE_KINDS = ("synth", "train", "dagger", "ranking")


def _folder(package: str, *parts: str) -> Path:
    # Wheels install unpacked, so the package's files are real paths (a zipped install is not supported).
    return Path(str(files(package).joinpath(*parts)))


def shipped_model(name: str = DEFAULT_MODEL) -> Path:
    """The folder of a model shipped with democheck."""
    return _folder("democheck.models", name)


def shipped_models() -> list[str]:
    root = _folder("democheck.models")
    return sorted(p.name for p in root.iterdir() if (p / "config.json").is_file()) if root.is_dir() else []


def recipe_dir(kind: str) -> Path:
    """Where recipes of a ``kind`` are: ``synth`` (``synth/``), ``train``, ``dagger`` or ``ranking`` (``democheck/recipes/``)."""
    if kind not in RECIPE_KINDS:
        raise ValueError(f"recipe kind {kind!r}; kinds: {', '.join(RECIPE_KINDS)}")
    return _folder("democheck.synth") if kind == "synth" else _folder("democheck", "recipes", kind)


def recipe_file(kind: str, name: str) -> Path:
    """``<name>.toml`` among the recipes of a ``kind`` (it may not exist)."""
    return recipe_dir(kind) / f"{name}.toml"


def recipe_names(kind: str) -> list[str]:
    root = recipe_dir(kind)
    return sorted(p.stem for p in root.glob("*.toml")) if root.is_dir() else []


def read_recipe(kind: str, name_or_path: str | Path, what: str) -> tuple[Path, dict[str, Any]]:
    """A recipe of a ``kind`` by shipped name or by path to a .toml file, and its TOML read; a name that is not
    shipped, or a file that is not TOML, is one ``RecipeError`` line (``what``: the recipe's kind in words)."""
    path = Path(name_or_path)
    if not (path.suffix == ".toml" and path.exists()):
        path = recipe_file(kind, str(name_or_path))
        if not path.exists():
            raise RecipeError(f"no {what} recipe {str(name_or_path)!r}; known: "
                              f"{', '.join(recipe_names(kind)) or 'none'} (or give a path to a .toml file)")
    try:
        return path, tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecipeError(f"{path}: not valid TOML ({exc})") from None
