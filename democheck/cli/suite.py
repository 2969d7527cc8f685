"""``democheck synth``, ``probe`` and ``info``: make and describe datasets."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from democheck.cli.common import BY_ID, REVISION_HELP, Bar, app, console, local_dataset, parse_counts, user_errors
from democheck.errors import DemocheckError


ENGINE_HELP = ("Who renders the episodes: local (worker processes on this machine) or ray (Ray Data actors, one CPU "
               "each, --workers of them: a local Ray instance, or the cluster at --ray-address; every node needs "
               "democheck, the input and the output folder's parent at the same path). Needs pip install "
               "'democheck\\[ray]'. The files are the same.")
RAY_ADDRESS_HELP = ("With --engine ray: the Ray cluster's address (e.g. ray://head:10001 or auto); default: start a "
                    "local instance.")


@app.command()
def synth(
    suite: Annotated[str, typer.Argument(help="Recipe name (push-v1, push-v1-test, push-v2, push-v2-test, push-mini) or a path to a .toml file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder for the LeRobot v3 dataset (must not exist).")],
    tasks: Annotated[Optional[int], typer.Option(help="Total number of tasks, split train/val/test in the recipe's proportions.")] = None,
    demos: Annotated[Optional[int], typer.Option(help="Demonstrations per task.")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Control steps per episode (20 Hz).")] = None,
    size: Annotated[Optional[int], typer.Option(help="Square image size in pixels (64 default, 125 on request).")] = None,
    workers: Annotated[int, typer.Option(help="Parallel worker processes (each renders with its own GL context).")] = 2,
    seed: Annotated[Optional[int], typer.Option(help="Seed for tasks, layouts and arm noise; same seed, same dataset.")] = None,
    defects: Annotated[Optional[str], typer.Option(help="Replace demos by bad ones, labelled with their kind: e.g. idle=4,wrong-object=10 (kinds: idle, random, wrong-object, both-objects, occluded, gave-up).")] = None,
    defect_rate: Annotated[Optional[float], typer.Option(help="Replace this share of all demos by the four semantic defects (wrong-object, both-objects, occluded, gave-up) in equal parts.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it already exists.")] = False,
    engine: Annotated[str, typer.Option(help=ENGINE_HELP)] = "local",
    ray_address: Annotated[Optional[str], typer.Option(help=RAY_ADDRESS_HELP)] = None,
) -> None:
    """Generate a simulated pushing suite (scripted expert demos in MuJoCo) as a LeRobot v3 dataset."""
    with user_errors():
        from democheck.sim.suite import generate, load_recipe

        recipe = load_recipe(suite).with_overrides(tasks=tasks, demos=demos, steps=steps, size=size, seed=seed,
                                                   defects=parse_counts(defects, "--defects") if defects else None,
                                                   defect_rate=defect_rate)
        if workers < 1:
            raise DemocheckError("--workers must be at least 1")
        with Bar(f"synth {recipe.name}", "episodes") as bar:
            summary = generate(recipe, out, workers=workers, force=force, on_progress=bar.callback(), engine=engine,
                               ray_address=ray_address)
    table = Table(title=f"{recipe.name} -> {out}", show_header=False)
    ex = summary["expert"]
    table.add_row("tasks (train/val/test)", "/".join(str(summary["tasks"][s]) for s in ("train", "val", "test")))
    table.add_row("episodes x steps", f"{summary['episodes']} x {recipe.steps}  ({recipe.image_size}x{recipe.image_size} px)")
    table.add_row("expert success, first try", f"{ex['first_attempt_success']:.1%}")
    table.add_row("demos kept successful", f"{ex['kept_success']:.1%}")
    if summary["defects"]:
        table.add_row("defects (label)", ", ".join(f"{k}: {n}" for k, n in summary["defects"].items()))
    table.add_row("speed", f"{summary['frames_per_s']:.0f} frames/s on {workers} worker(s), {summary['wall_s']:.1f} s")
    console.print(table)


@app.command()
def probe(
    dataset: Annotated[Path, typer.Argument(help="Source dataset; probes re-simulate its demos from their sim records.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder for the probe dataset (LeRobot v3, label = kind).")],
    kinds: Annotated[Optional[str], typer.Option(help="Comma-separated: no-action (arm still), random (random torques), no-objects (objects removed, actions replayed), hidden (squares cover the view); on request, reversed (the recording played backwards: a reset recorded as a demo) and hesitates (a pause put in). Default: no-action, random, no-objects and hidden where the data allows (without democheck's sim records: no-action and hidden).")] = None,
    per_kind: Annotated[int, typer.Option(help="Probes per kind, each from a different clean source demo.")] = 50,
    seed: Annotated[int, typer.Option(help="Seed for the choice of sources, random torques and squares.")] = 0,
    workers: Annotated[int, typer.Option(help="Parallel worker processes.")] = 2,
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it already exists.")] = False,
    engine: Annotated[str, typer.Option(help=ENGINE_HELP)] = "local",
    ray_address: Annotated[Optional[str], typer.Option(help=RAY_ADDRESS_HELP)] = None,
) -> None:
    """Make out-of-distribution probes from a dataset's demos: the labelled negatives `bench` measures detectors on."""
    with user_errors():
        from democheck.sim.probes import make_probes

        kind_list = [k.strip() for k in kinds.split(",") if k.strip()] if kinds else None
        if workers < 1:
            raise DemocheckError("--workers must be at least 1")
        with Bar("probe", "episodes") as bar:
            summary = make_probes(dataset, out, kind_list, per_kind=per_kind, seed=seed, workers=workers,
                                  camera=camera, force=force, on_progress=bar.callback(), engine=engine,
                                  ray_address=ray_address)
    console.print(f"{summary['episodes']} probes ({', '.join(f'{k}: {n}' for k, n in summary['kinds'].items())}) "
                  f"from {dataset} in {summary['wall_s']:.1f} s -> {out}")
    console.print(f"measure detectors on them: democheck bench {dataset} {out} --out <dir>")


@app.command()
def info(
    dataset: Annotated[str, typer.Argument(help="Dataset folder (LeRobot v3.0 or v2.1) or robomimic .hdf5 file." + BY_ID)],
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    state_key: Annotated[Optional[str], typer.Option(help="Feature holding the robot state (default: observation.state).")] = None,
    action_key: Annotated[Optional[str], typer.Option(help="Feature holding the actions (default: action).")] = None,
    revision: Annotated[Optional[str], typer.Option(help=REVISION_HELP)] = None,
) -> None:
    """Describe a dataset as democheck sees it: format, episodes, tasks and their sizes, episode lengths, every
    recorded stream and what the audit reads it as, splits, labels."""
    with user_errors():
        from rich.markup import escape

        from democheck.audit.evidence import GROUP_MIN_DEMOS
        from democheck.data import open_dataset

        dataset = local_dataset(dataset, revision)
        ds = open_dataset(dataset, camera=camera, state_key=state_key, action_key=action_key)
        eps = ds.episodes
        table = Table(title=str(dataset), show_header=False)
        table.add_row("format", ds.format)
        table.add_row("episodes / tasks", f"{len(ds)} / {len(ds.tasks)}")
        table.add_row("frames", f"{int(eps['length'].sum())} at {ds.fps:g} fps")
        h, w, c = ds.image_shape
        others = ds.other_cameras() if ds.has_camera else {}
        table.add_row("camera", (f"{ds.camera} ({h}x{w}x{c})" + (f"; the picture checks also read {', '.join(others)}"
                                                                 if others else "")) if ds.has_camera else
                      "none (states and actions only: democheck audit --no-model)")
        n_files, problems = 0, []
        for seen in (ds, *others.values()):  # every camera's files
            files, wrong = seen.camera_files()
            n_files, problems = n_files + files, problems + wrong
        if n_files:
            table.add_row("video files", f"{n_files}, " + ("every one there; a sample decodes" if not problems else
                                                          f"[red]{len(problems)} problem(s)[/], below"))
        table.add_row("state / action dims", f"{ds.state_dim} / {ds.action_dim}")
        per_task = eps.groupby("task").size()
        few = per_task[per_task < GROUP_MIN_DEMOS]
        table.add_row("demos per task", f"{per_task.min()}-{per_task.max()} (median {per_task.median():g})"
                      + (f"; {len(few)} task(s) under {GROUP_MIN_DEMOS}, judged together" if len(few) else ""))
        lengths = eps.groupby("task")["length"].median()
        table.add_row("episode length", f"{int(eps['length'].min())}-{int(eps['length'].max())} steps "
                      f"(median {eps['length'].median():g}; task medians {lengths.min():g}-{lengths.max():g})")
        for col in ("split", "label"):
            if col in eps:
                table.add_row(col, ", ".join(f"{k}: {v}" for k, v in eps[col].value_counts().sort_index().items()))
        if "success" in eps and eps["success"].notna().any():
            table.add_row("success", f"{eps['success'].dropna().astype(float).mean():.1%}")
        console.print(table)
        for problem in problems:
            console.print(f"[red]video:[/] {escape(problem)}", highlight=False)
        if problems:
            console.print("an audit reads the episodes of these files as broken recordings (black frames), and "
                          "refuses a dataset none of whose frames can be read: fix the files or info.json's "
                          "video_path first", highlight=False)
        streams = ds.streams()
        if streams:
            recorded = Table(title="what the audit reads", show_header=True)
            for col in ("stream", "width", "read as"):
                recorded.add_column(col)
            for row in streams:
                recorded.add_row(*row)
            console.print(recorded)
        if len(per_task) <= 20:
            tasks = Table(title="tasks", show_header=True)
            tasks.add_column("task")
            tasks.add_column("demos", justify="right")
            tasks.add_column("median length", justify="right")
            for name, n in per_task.items():
                tasks.add_row(escape(str(name)), str(n), f"{lengths[name]:g}")
            console.print(tasks)
