"""The ``democheck`` command line.  Commands parse, call one library function, print.

Heavy libraries (mujoco, torch, av) are imported inside the commands so that
``democheck --help`` stays fast.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Iterator, Optional

import typer
from rich.console import Console
from rich.table import Table

from democheck.errors import DemocheckError

app = typer.Typer(
    name="democheck",
    help="Audit robot demonstration datasets: find the demos a learner cannot tell the task from.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)


@contextmanager
def _user_errors() -> Iterator[None]:
    """Bad input becomes one line on stderr and exit status 2, never a traceback."""
    try:
        yield
    except DemocheckError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(2) from None
    except KeyboardInterrupt:
        err_console.print("interrupted; nothing was written")
        raise typer.Exit(130) from None


@app.command()
def synth(
    suite: Annotated[str, typer.Argument(help="Recipe name from synth/ (push-v1, push-mini) or a path to a .toml file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder for the LeRobot v3 dataset (must not exist).")],
    tasks: Annotated[Optional[int], typer.Option(help="Total number of tasks, split train/val/test in the recipe's proportions.")] = None,
    demos: Annotated[Optional[int], typer.Option(help="Demonstrations per task.")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Control steps per episode (20 Hz).")] = None,
    size: Annotated[Optional[int], typer.Option(help="Square image size in pixels (64 default, 125 on request).")] = None,
    workers: Annotated[int, typer.Option(help="Parallel worker processes (each renders with its own GL context).")] = 2,
    seed: Annotated[Optional[int], typer.Option(help="Seed for tasks, layouts and arm noise; same seed, same dataset.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it already exists.")] = False,
) -> None:
    """Generate a simulated pushing suite (scripted expert demos in MuJoCo) as a LeRobot v3 dataset."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with _user_errors():
        from democheck.sim.suite import generate, load_recipe

        recipe = load_recipe(suite).with_overrides(tasks=tasks, demos=demos, steps=steps, size=size, seed=seed)
        if workers < 1:
            raise DemocheckError("--workers must be at least 1")
        cols = (TextColumn("[bold]synth[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("episodes"), TimeRemainingColumn())
        with Progress(*cols, console=err_console, transient=True) as bar:
            job = bar.add_task(recipe.name, total=recipe.n_episodes)
            summary = generate(recipe, out, workers=workers, force=force,
                               on_progress=lambda done, total: bar.update(job, completed=done))
    table = Table(title=f"{recipe.name} -> {out}", show_header=False)
    ex = summary["expert"]
    table.add_row("tasks (train/val/test)", "/".join(str(summary["tasks"][s]) for s in ("train", "val", "test")))
    table.add_row("episodes x steps", f"{summary['episodes']} x {recipe.steps}  ({recipe.image_size}x{recipe.image_size} px)")
    table.add_row("expert success, first try", f"{ex['first_attempt_success']:.1%}")
    table.add_row("demos kept successful", f"{ex['kept_success']:.1%}")
    table.add_row("speed", f"{summary['frames_per_s']:.0f} frames/s on {workers} worker(s), {summary['wall_s']:.1f} s")
    console.print(table)


@app.command()
def info(
    dataset: Annotated[Path, typer.Argument(help="Dataset folder (LeRobot v3.0 or v2.1).")],
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    state_key: Annotated[Optional[str], typer.Option(help="Feature holding the robot state (default: observation.state).")] = None,
    action_key: Annotated[Optional[str], typer.Option(help="Feature holding the actions (default: action).")] = None,
) -> None:
    """Describe a dataset as democheck sees it: format, episodes, tasks, camera, splits, labels."""
    with _user_errors():
        from democheck.data import open_dataset

        ds = open_dataset(dataset, camera=camera, state_key=state_key, action_key=action_key)
        eps = ds.episodes
        table = Table(title=str(dataset), show_header=False)
        table.add_row("format", ds.format)
        table.add_row("episodes / tasks", f"{len(ds)} / {len(ds.tasks)}")
        table.add_row("frames", f"{int(eps['length'].sum())} at {ds.fps:g} fps")
        h, w, c = ds.image_shape
        table.add_row("camera", f"{ds.camera} ({h}x{w}x{c})")
        table.add_row("state / action dims", f"{ds.state_dim} / {ds.action_dim}")
        for col in ("split", "label"):
            if col in eps:
                table.add_row(col, ", ".join(f"{k}: {v}" for k, v in eps[col].value_counts().sort_index().items()))
        if "success" in eps:
            table.add_row("success", f"{eps['success'].astype(float).mean():.1%}")
        console.print(table)


@app.command()
def train(
    dataset: Annotated[Path, typer.Argument(help="Training dataset (LeRobot v3.0/v2.1); tasks need two or more demos.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model folder to write (config.json, model.safetensors, README.md).")],
    model_type: Annotated[str, typer.Option(help="petnet (probabilistic task embedding) or tecnet (the TecNets baseline).")] = "petnet",
    steps: Annotated[int, typer.Option(help="Optimiser steps.")] = 20_000,
    batch_tasks: Annotated[int, typer.Option(help="Tasks per step; each gives one cue and one demonstrated trajectory.")] = 16,
    timesteps: Annotated[int, typer.Option(help="Timesteps of each demonstrated trajectory per step.")] = 8,
    lr: Annotated[float, typer.Option(help="Adam learning rate.")] = 5e-4,
    kl_weight: Annotated[float, typer.Option(help="Weight of a KL term on the task posterior (0: the paper's loss).")] = 0.0,
    kl_target: Annotated[str, typer.Option(help="prior: KL to N(0, I); np: Neural-Process style, cue vs cue+target.")] = "prior",
    seed: Annotated[int, typer.Option(help="Seed for initialisation, sampling and noise.")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    val_every: Annotated[int, typer.Option(help="Validate on the val split every this many steps.")] = 500,
    ckpt_every: Annotated[int, typer.Option(help="Save the run's state for --resume every this many steps.")] = 1000,
    resume: Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last saved state.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace --out, or discard an interrupted run and start over.")] = False,
    camera: Annotated[Optional[str], typer.Option(help="Image feature to train on when there are several.")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option(help="Where decoded frames are cached (default ~/.cache/democheck).")] = None,
) -> None:
    """Train PETNet (or the TecNets baseline) on a dataset; writes a safetensors checkpoint with a model card."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with _user_errors():
        if model_type not in ("petnet", "tecnet"):
            raise DemocheckError(f"--model-type must be petnet or tecnet, not {model_type!r}")
        if kl_target not in ("prior", "np"):
            raise DemocheckError(f"--kl-target must be prior or np, not {kl_target!r}")
        if min(steps, batch_tasks, timesteps, val_every, ckpt_every) < 1:
            raise DemocheckError("--steps, --batch-tasks, --timesteps, --val-every and --ckpt-every must be positive")
        from democheck.workflows import train_model
        from democheck.petnet.train import TrainConfig

        tc = TrainConfig(steps=steps, batch_tasks=batch_tasks, timesteps=timesteps, lr=lr, kl_weight=kl_weight,
                         kl_target=kl_target, seed=seed, val_every=val_every, ckpt_every=ckpt_every, device=device)
        cols = (TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn())
        with Progress(*cols, console=err_console) as bar:
            job = bar.add_task("decode", total=None, info="")

            def on_decode(done: int, total: int) -> None:
                bar.update(job, completed=done, total=total, description="decode frames")

            def on_step(step: int, total: int, report: dict) -> None:
                info = f"loss {report.get('train_loss', float('nan')):.4f}"
                if "val_mse" in report:
                    on_step.val = f"  val mse {report['val_mse']:.4f}"
                bar.update(job, completed=step, total=total, description="train", info=info + on_step.val)

            on_step.val = ""
            result = train_model(dataset, out, tc, model_type=model_type, resume=resume, force=force, camera=camera,
                                 cache_dir=cache_dir, on_decode=on_decode, on_step=on_step)
    table = Table(title=f"{model_type} -> {out}", show_header=False)
    final = result.metrics["final"]
    for key in ("train_mse", "val_mse", "val_embed"):
        if key in final:
            table.add_row(key.replace("_", " "), f"{final[key]:.4f}")
    for name, v in result.metrics.get("task_sigma", {}).items():
        table.add_row(f"mean sigma: {name}", f"{v:.4f}")
    table.add_row("wall time", f"{result.metrics['wall_s'] / 60:.1f} min")
    console.print(table)


def main() -> None:  # pragma: no cover - console-script entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
