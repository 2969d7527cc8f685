"""``democheck train`` and ``fit-novelty``: make a model."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from democheck.cli.common import BY_ID, REVISION_HELP, Bar, app, console, local_dataset, user_errors

RECIPE_HELP = ("Training recipe: a shipped name (paper: the paper's loss, the default; your-data: for a dataset of your "
               "own, 64 px, ~15 min on 2 cores; petnet-push-v2: the controller that pushed on a GPU, on push-v2, about "
               "4 h on 2 CPU cores; tecnet-push-v2: the TecNets baseline beside it; petnet-push-v1, tecnet: the "
               "shipped models') "
               "or a path to a .toml file. Every option of a run is in it.")
SET_HELP = ("Override one recipe key, e.g. --set optim.lr=1e-3 --set regularisers.kl_prior=0.1 --set model.novelty=false "
            "--set model.init=models/my-petnet (repeatable; keys: democheck/recipes/train/paper.toml).")


@app.command()
def train(
    dataset: Annotated[str, typer.Argument(help="Training dataset (LeRobot v3.0/v2.1); tasks need two or more demos." + BY_ID)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model folder to write (config.json, model.safetensors, README.md).")],
    recipe: Annotated[str, typer.Option(help=RECIPE_HELP)] = "paper",
    set_: Annotated[Optional[list[str]], typer.Option("--set", help=SET_HELP)] = None,
    steps: Annotated[Optional[int], typer.Option(help="Optimiser steps (default: the recipe's).")] = None,
    image_size: Annotated[Optional[int], typer.Option(help="Train at this square image size: every frame resized (OpenCV area interpolation), and the audit resizes the same way (default: the recipe's; the paper recipe keeps the camera's size).")] = None,
    seed: Annotated[Optional[int], typer.Option(help="Seed for initialisation, sampling and noise (default: the recipe's, 0).")] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    resume: Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last saved state.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace --out, or discard an interrupted run and start over.")] = False,
    camera: Annotated[Optional[str], typer.Option(help="Image feature to train on when there are several.")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option(help="Where decoded frames are cached (default ~/.cache/democheck).")] = None,
    revision: Annotated[Optional[str], typer.Option(help=REVISION_HELP)] = None,
) -> None:
    """Train PETNet (or the TecNets baseline) on a dataset from a recipe; writes a safetensors checkpoint with a model card.

    The model's config.json and card record the whole resolved recipe, so the checkpoint says how to make it again.
    """
    with user_errors():
        from democheck.workflows import train_from_recipe

        dataset = local_dataset(dataset, revision)
        with Bar("train", info=True) as bar:
            val = {"text": ""}

            def on_step(step: int, total: int, report: dict) -> None:
                if "val_mse" in report:
                    val["text"] = f"  val mse {report['val_mse']:.4f}"
                bar.update(step, total, "train", f"loss {report.get('train_loss', float('nan')):.4f}{val['text']}")

            result = train_from_recipe(dataset, out, recipe, set_, steps=steps, seed=seed, device=device,
                                       image_size=image_size,
                                       resume=resume, force=force, camera=camera, cache_dir=cache_dir,
                                       on_decode=bar.callback("decode frames"), on_step=on_step,
                                       on_novelty=bar.callback("novelty autoencoder"),
                                       on_posed=bar.callback("posed frames"))
    table = Table(title=f"{result.config.model_type} -> {out}", show_header=False)
    final = result.metrics["final"]
    for key in ("train_mse", "val_mse", "val_task_matching", "val_tecnet_hinge"):
        if key in final:
            table.add_row(key.replace("_", " "), f"{final[key]:.4f}")
    for name, v in result.metrics.get("task_sigma", {}).items():
        table.add_row(f"mean sigma: {name}", f"{v:.4f}")
    table.add_row("wall time", f"{result.metrics['wall_s'] / 60:.1f} min")
    console.print(table)


@app.command(name="fit-novelty")
def fit_novelty(
    model: Annotated[Path, typer.Argument(help="A trained PETNet model folder.")],
    data: Annotated[Path, typer.Option("--data", help="The dataset the model was trained on. The density is fitted as training fitted it: on its train split, the val split giving the reference distance; or on every demo, the reference from them too, where the recipe's last phase learnt every demo (--recipe your-data, on data that names no split).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model folder to write: the same weights with the density, the card's numbers and the audit's reference redone.")],
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    camera: Annotated[Optional[str], typer.Option(help="Image feature the model was trained on when there are several.")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option(help="Where decoded frames are cached (default ~/.cache/democheck).")] = None,
    trim: Annotated[Optional[float], typer.Option(help="Leave out this share of the training cues farthest from a first fit, and fit again (for data that may hold bad demos; default: the model's recipe's novelty_trim).")] = None,
    end_state: Annotated[Optional[bool], typer.Option("--end-state/--no-end-state", help="Whether the density reads each demo's state at its last step beside its last frame (default: the model's recipe's, on unless it was trained with --set model.novelty_state=false). Off suits a small dataset with a wide state: on 55 demos of 39 state numbers the state blurred occluded frames.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out.")] = False,
) -> None:
    """Give a trained PETNet model the epistemic part of its task variance, without retraining.

    A cue autoencoder trained on the training cues, and one Gaussian fitted to its encoder's features of their last frames together with the demos' states at their last step; a demo whose end is far from theirs (in what the camera saw or where the arm ended) gets a wider task posterior. democheck train fits it itself; this is for models trained with --set model.novelty=false or before it existed, and to refit an older model's density (over the whole cue, or the last frame alone) on both.
    """
    with user_errors():
        from democheck.petnet.card import reference_cues
        from democheck.workflows import refit_novelty

        with Bar("decode frames", "episodes") as bar:
            meta = refit_novelty(model, data, out, camera=camera, cache_dir=cache_dir, device=device, force=force,
                                 trim=trim, on_decode=bar.callback(), on_novelty=bar.callback("novelty autoencoder"),
                                 end_state=end_state)
    table = Table(title=f"{model} + novelty -> {out}", show_header=False)
    nov = meta["novelty"]
    table.add_row("reference d2", f"{nov['d2_ref']:.1f} ({nov['quantile']:.0%} of {reference_cues(nov)})")
    for name, v in meta["metrics"]["task_sigma"].items():
        table.add_row(f"mean sigma: {name}", f"{v:.4f}")
    console.print(table)
