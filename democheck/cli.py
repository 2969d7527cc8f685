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
    defects: Annotated[Optional[str], typer.Option(help="Replace demos by bad ones, labelled with their kind: e.g. idle=4,wrong-object=10 (kinds: idle, random, wrong-object, both-objects, occluded, gave-up).")] = None,
    defect_rate: Annotated[Optional[float], typer.Option(help="Replace this share of all demos by the four semantic defects (wrong-object, both-objects, occluded, gave-up) in equal parts.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it already exists.")] = False,
) -> None:
    """Generate a simulated pushing suite (scripted expert demos in MuJoCo) as a LeRobot v3 dataset."""
    with _user_errors():
        from democheck.sim.suite import generate, load_recipe

        recipe = load_recipe(suite).with_overrides(tasks=tasks, demos=demos, steps=steps, size=size, seed=seed,
                                                   defects=_parse_counts(defects, "--defects") if defects else None,
                                                   defect_rate=defect_rate)
        if workers < 1:
            raise DemocheckError("--workers must be at least 1")
        with _episode_bar(f"synth {recipe.name}", recipe.n_episodes) as on_progress:
            summary = generate(recipe, out, workers=workers, force=force, on_progress=on_progress)
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


@contextmanager
def _episode_bar(label: str, total: int) -> Iterator:
    """A progress bar over episodes; yields the ``on_progress(done, total)`` callback to feed it."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    cols = (TextColumn(f"[bold]{label}[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
            TimeRemainingColumn())
    with Progress(*cols, console=err_console, transient=True) as bar:
        job = bar.add_task(label, total=total)
        yield lambda done, n: bar.update(job, completed=done, total=n)


@app.command()
def probe(
    dataset: Annotated[Path, typer.Argument(help="Source dataset; probes re-simulate its demos from their sim records.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder for the probe dataset (LeRobot v3, label = kind).")],
    kinds: Annotated[str, typer.Option(help="Comma-separated: no-action (arm still), random (random torques), no-objects (objects removed, actions replayed), hidden (squares cover the view). Without sim records only no-action and hidden.")] = "no-action,random,no-objects,hidden",
    per_kind: Annotated[int, typer.Option(help="Probes per kind, each from a different clean source demo.")] = 50,
    seed: Annotated[int, typer.Option(help="Seed for the choice of sources, random torques and squares.")] = 0,
    workers: Annotated[int, typer.Option(help="Parallel worker processes.")] = 2,
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it already exists.")] = False,
) -> None:
    """Make out-of-distribution probes from a dataset's demos: the labelled negatives `bench` measures detectors on."""
    with _user_errors():
        from democheck.sim.probes import make_probes

        kind_list = [k.strip() for k in kinds.split(",") if k.strip()]
        if workers < 1:
            raise DemocheckError("--workers must be at least 1")
        with _episode_bar("probe", per_kind * len(kind_list)) as on_progress:
            summary = make_probes(dataset, out, kind_list, per_kind=per_kind, seed=seed, workers=workers,
                                  camera=camera, force=force, on_progress=on_progress)
    console.print(f"{summary['episodes']} probes ({', '.join(f'{k}: {n}' for k, n in summary['kinds'].items())}) "
                  f"from {dataset} in {summary['wall_s']:.1f} s -> {out}")
    console.print(f"measure detectors on them: democheck bench {dataset} {out} --out <dir>")


def _parse_counts(text: str, option: str) -> dict[str, int]:
    out = {}
    for part in text.split(","):
        key, _, value = part.partition("=")
        if not key.strip() or not value.strip().isdigit():
            raise DemocheckError(f"{option} takes kind=count pairs separated by commas, e.g. idle=4,random=4; got {text!r}")
        out[key.strip()] = int(value)
    return out


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
        if "success" in eps and eps["success"].notna().any():
            table.add_row("success", f"{eps['success'].dropna().astype(float).mean():.1%}")
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
    contrastive_weight: Annotated[float, typer.Option(help="PETNet option: weight of the task-matching loss, which trains mu and var to find a cue's task among others (0: the paper's loss).")] = 0.0,
    mean_hinge_weight: Annotated[float, typer.Option(help="PETNet option: weight of TecNets' hinge loss on the unit-normalised task means (0: off).")] = 0.0,
    partial_cue_weight: Annotated[float, typer.Option(help="PETNet option: weight of the task-matching loss on partial cues (first frame + a frame at a random time), which teaches the variance to grow when a cue shows less of its task (0: off).")] = 0.0,
    partial_kl_weight: Annotated[float, typer.Option(help="PETNet option, with --init: weight of KL(q0(z | cue) || q(z | the cue cut at a random time)), q0 the starting model's encoder held fixed; a cue that shows less of its task must cover every task it could be, so sigma grows with what is missing (0: off).")] = 0.0,
    broken_cue_weight: Annotated[float, typer.Option(help="PETNet option: weight of a hinge that makes broken cues (first and last frame from two scenes, or played backwards) at least twice as uncertain as real ones (0: off).")] = 0.0,
    novelty: Annotated[bool, typer.Option("--novelty/--no-novelty", help="PETNet: after training, fit the density of the training cues' features that widens the task variance of unfamiliar cues (--no-novelty: the paper's variance head alone).")] = True,
    init: Annotated[Optional[Path], typer.Option(help="Start from this model folder's weights and normalisation (same architecture) instead of a fresh network.")] = None,
    hard_negatives: Annotated[bool, typer.Option("--hard-negatives", help="Fill batches with look-alike tasks (in democheck suites: the two orders of one object pair), so the embedding must read which object was pushed.")] = False,
    keypoints: Annotated[bool, typer.Option("--keypoints", help="Controller: last two conv layers at stride 1 and a spatial softmax (expected x, y per channel) instead of a flattened 4x4 map.")] = False,
    shift: Annotated[int, typer.Option(help="Augment training images by a random shift of up to this many pixels each way (0: off).")] = 0,
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
        if shift < 0:
            raise DemocheckError(f"--shift must be 0 or more pixels, not {shift}")
        from democheck.workflows import train_model
        from democheck.petnet.train import TrainConfig

        tc = TrainConfig(steps=steps, batch_tasks=batch_tasks, timesteps=timesteps, lr=lr, kl_weight=kl_weight,
                         kl_target=kl_target, contrastive_weight=contrastive_weight, hard_negatives=hard_negatives, mean_hinge_weight=mean_hinge_weight,
                         partial_cue_weight=partial_cue_weight, partial_kl_weight=partial_kl_weight, broken_cue_weight=broken_cue_weight, novelty=novelty, init=str(init) if init else None, keypoints=keypoints, shift=shift, seed=seed, val_every=val_every, ckpt_every=ckpt_every, device=device)
        cols = (TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn())
        with Progress(*cols, console=err_console, transient=True) as bar:
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


@app.command(name="fit-novelty")
def fit_novelty(
    model: Annotated[Path, typer.Argument(help="A trained PETNet model folder.")],
    data: Annotated[Path, typer.Option("--data", help="The dataset the model was trained on (its train split fits the density, its val split the reference distance).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model folder to write: the same weights with the density, the card's numbers and the audit's reference redone.")],
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    camera: Annotated[Optional[str], typer.Option(help="Image feature the model was trained on when there are several.")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option(help="Where decoded frames are cached (default ~/.cache/democheck).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out.")] = False,
) -> None:
    """Give a trained PETNet model the epistemic part of its task variance, without retraining.

    A Gaussian fitted to the encoder's conv features of the training cues; a cue far from them gets a wider task posterior. democheck train fits it itself; this is for models trained with --no-novelty or before it existed.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    with _user_errors():
        from democheck.workflows import refit_novelty

        with Progress(TextColumn("decode frames"), BarColumn(), MofNCompleteColumn(), console=err_console,
                      transient=True) as bar:
            job = bar.add_task("decode", total=None)
            meta = refit_novelty(model, data, out, camera=camera, cache_dir=cache_dir, device=device, force=force,
                                 on_decode=lambda d, n: bar.update(job, completed=d, total=n))
    table = Table(title=f"{model} + novelty -> {out}", show_header=False)
    nov = meta["novelty"]
    table.add_row("reference d2", f"{nov['d2_ref']:.1f} ({nov['quantile']:.0%} of {nov['held_out_cues']} held-out cues)")
    for name, v in meta["metrics"]["task_sigma"].items():
        table.add_row(f"mean sigma: {name}", f"{v:.4f}")
    console.print(table)


@app.command()
def audit(
    dataset: Annotated[Path, typer.Argument(help="Dataset to audit: LeRobot v3.0/v2.1 folder or robomimic .hdf5 file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder: scores.parquet/.csv, summary.json, suspects.txt, report.rrd.")],
    model: Annotated[Optional[Path], typer.Option(help="Model folder (default: the shipped models/petnet-push-v1).")] = None,
    top: Annotated[int, typer.Option(help="How many top suspects to show and to record with their evidence.")] = 20,
    fail_on: Annotated[Optional[int], typer.Option(help="Exit with status 3 when more than this many demos are flagged (for CI gates).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON instead of a table.")] = False,
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    task: Annotated[Optional[str], typer.Option(help="Task string for robomimic files that do not name their task.")] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    actions: Annotated[bool, typer.Option("--actions/--no-actions", help="Also score how badly the model's controller explains each demo's actions (catches arms that never moved, flailed or stopped half-way). Decodes every demo in full: --no-actions is the fast pass on cue frames only.")] = True,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """Score every demonstration by task uncertainty, consistency and action error; rank the suspects, flag anomalies."""
    import json

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    with _user_errors():
        if top < 1:
            raise DemocheckError("--top must be at least 1")
        from democheck.workflows import audit_dataset

        with Progress(TextColumn("[bold]audit[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("demos"),
                      console=err_console, transient=True) as bar:
            job = bar.add_task("audit", total=None)
            summary = audit_dataset(dataset, out, model=model, top=top, camera=camera, task=task, device=device,
                                    force=force, on_progress=lambda d, n: bar.update(job, completed=d, total=n),
                                    actions=actions)
    if json_out:
        console.print_json(json.dumps(summary))
    else:
        _print_audit(summary, out)
    if fail_on is not None and summary["flagged"] > fail_on:
        err_console.print(f"{summary['flagged']} demos flagged, more than --fail-on {fail_on}")
        raise typer.Exit(3)


def _short(x: float) -> str:
    """A score in at most 5 characters: 3 significant digits, whole numbers from 100 up."""
    return f"{x:.3g}" if abs(x) < 100 else f"{x:.0f}"


def _print_audit(summary: dict, out: Path) -> None:
    table = Table(title=f"top suspects of {summary['demos']} demos ({summary['flagged']} flagged)")
    # Short headers and a clipped task column keep the table readable in an 80-column terminal.
    acts = "action_error" in summary["scores"]
    for col in ("rank", "ep", "task", "score", "cons.", *(["act."] if acts else []), "susp.", "flag"):
        # Numbers keep their width; the task string gives way.
        table.add_column(col, justify="left" if col == "task" else "right", no_wrap=True, overflow="ellipsis",
                         max_width=24 if col == "task" else None, min_width=None if col == "task" else 4)
    for r in summary["top_suspects"]:
        cons = "n/a" if r["consistency"] is None else f"{r['consistency']:.2f}"
        table.add_row(str(r["rank"]), str(r["episode_index"]), r["task"], f"{r['score']:.3f}", cons,
                      *([_short(r["action_error"])] if acts else []), _short(r["suspicion"]),
                      "[red]yes[/]" if r["is_anomaly"] else "")
    console.print(table)
    t = summary["timing"]
    console.print(f"scored {summary['demos']} demos in {t['score_s']:.1f} s ({t['demos_per_s']:.0f}/s)"
                  + (f", their actions in {t['actions_s']:.1f} s" if acts else "")
                  + f"; model load {t['model_load_s']:.1f} s, t-SNE {t['tsne_s']:.1f} s")
    console.print(f"report: {out}/ (scores.parquet, scores.csv, summary.json, suspects.txt)")
    console.print(f"look at it: democheck view {out}")


@app.command()
def bench(
    datasets: Annotated[list[Path], typer.Argument(help="One or more labelled datasets, pooled (e.g. a suite made with --defect-rate and the probes made from it).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for bench.json, bench.md, bench.rrd and scores.parquet.")],
    model: Annotated[Optional[Path], typer.Option(help="PETNet model folder (default: the shipped models/petnet-push-v1).")] = None,
    tecnet: Annotated[Optional[Path], typer.Option(help="TecNets model trained on the same data, for the kNN baseline (democheck train --model-type tecnet); left out if not given.")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the random scorer and of Figure 5B's cue draws.")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """Measure every scorer (PETNet's and the baselines') on labelled bad demos: AUROC, AUPRC, precision at k."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    with _user_errors():
        from democheck.audit.bench import bench as run_bench

        with Progress(TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(), console=err_console,
                      transient=True) as bar:
            job = bar.add_task("bench", total=None)
            summary = run_bench(datasets, out, model=model, tecnet=tecnet, device=device, seed=seed, force=force,
                                camera=camera, on_progress=lambda stage, d, n: bar.update(job, description=stage,
                                                                                          completed=d, total=n))
    table = Table(title="AUROC, each kind versus clean (bench.md: AUPRC, precision at k, scorers explained)")
    table.add_column("kind", no_wrap=True)
    short = {"consistency": "consist.", "suspicion": "suspic.", "ocsvm_flag": "ocsvm", "tecnet_knn": "tecnet",
             "heuristic": "heurist."}
    for name in summary["scorers"]:
        table.add_column(short.get(name, name), justify="right")
    for kind in summary["kinds"]:
        table.add_row(kind, *[f"{per[kind]['auroc']:.2f}" if per.get(kind, {}).get("auroc") is not None else "n/a"
                              for per in summary["scorers"].values()])
    console.print(table)
    console.print(f"{out}/bench.md, bench.json, bench.rrd (Figures 5A and 5B), scores.parquet")


@app.command(name="eval")
def eval_(
    model: Annotated[Optional[Path], typer.Argument(help="Model folder (default: the shipped models/petnet-push-v1).")] = None,
    data: Annotated[Path, typer.Option(help="Suite to draw cue demos and tasks from (made by democheck synth; e.g. democheck synth push-v1 --out data/push-v1).")] = Path("data/push-v1"),
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for eval.json, eval.md, trials.parquet, eval.rrd.")] = Path("runs/eval"),
    split: Annotated[str, typer.Option(help="Which tasks: test (meta-test, held-out objects), val or train.")] = "test",
    trials: Annotated[int, typer.Option(help="Rollouts per task, each on a new layout with its own cue draw.")] = 6,
    shots: Annotated[int, typer.Option(help="Cue demos per trial (combined by product of Gaussians).")] = 1,
    workers: Annotated[int, typer.Option(help="Parallel rollout processes.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed for cue draws and layouts.")] = 0,
    device: Annotated[str, typer.Option(help="Device for inferring z from the cues (rollouts run on CPU).")] = "auto",
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """Closed-loop meta-test: one-shot success on held-out tasks, and success by cue uncertainty."""
    with _user_errors():
        from democheck.evaluate.meta_test import evaluate

        if not data.exists():
            raise DemocheckError(f"{data}: no such dataset; generate it: democheck synth push-v1 --out {data}")
        with _episode_bar("eval", 0) as on_progress:
            s = evaluate(model, data, out, split=split, trials=trials, shots=shots, workers=workers, seed=seed,
                         device=device, force=force, on_progress=on_progress)
    table = Table(title=f"{s['model']} on {s['tasks']} {split} tasks, {shots}-shot, {trials} trials each",
                  show_header=False)

    from democheck.evaluate.meta_test import fmt_rate as pct

    table.add_row("model success", pct(s["model_success"]))
    table.add_row("expert, same layouts", pct(s["expert"]))
    if s.get("flagged"):
        table.add_row("cues flagged (OCSVM)", pct(s["flagged"]))
        table.add_row("cues not flagged", pct(s["unflagged"]))
    for q in s.get("sigma_quartiles", []):
        table.add_row(f"sigma quartile {q['quartile']}", pct(q))
    console.print(table)
    console.print(f"{out}/eval.md, eval.json, trials.parquet, eval.rrd ({s['rollouts_per_s']:.1f} rollouts/s)")


@app.command()
def dagger(
    model: Annotated[Path, typer.Argument(help="Model folder (PETNet or TecNets) trained on --data by democheck train.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model folder to write: the same model with the controller trained further.")],
    data: Annotated[Path, typer.Option(help="The model's training suite (made by democheck synth): its training tasks are rolled out.")] = Path("data/push-v1"),
    rounds: Annotated[int, typer.Option(help="DAgger rounds: each rolls the controller out, has the expert label what it saw, and trains on it.")] = 4,
    episodes_per_task: Annotated[int, typer.Option(help="Rollouts per training task per round.")] = 1,
    beta: Annotated[float, typer.Option(help="Probability that the expert takes a step of a rollout (0: the controller alone).")] = 0.3,
    steps: Annotated[int, typer.Option(help="Controller training steps per round.")] = 2000,
    batch_tasks: Annotated[int, typer.Option(help="Demo trajectories per step (and as many recovery trajectories).")] = 16,
    timesteps: Annotated[int, typer.Option(help="Timesteps of each trajectory per step.")] = 8,
    lr: Annotated[float, typer.Option(help="Adam learning rate.")] = 5e-4,
    seed: Annotated[int, typer.Option(help="Seed for cue draws, layouts, expert hand-overs and batches.")] = 0,
    workers: Annotated[int, typer.Option(help="Parallel rollout processes.")] = 2,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda (training; rollouts run on CPU).")] = "auto",
    resume: Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last complete round.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace --out, or discard an interrupted run and start over.")] = False,
    cache_dir: Annotated[Optional[Path], typer.Option(help="Where decoded frames are cached (default ~/.cache/democheck).")] = None,
) -> None:
    """Recovery training: DAgger rounds that teach a model's controller to recover from its own mistakes.

    The scripted expert labels the states the controller itself reaches; only the
    controller learns, so the task encoder, sigma, consistency and the one-class SVM
    stay as they were (the action error is the new controller's).
    """
    import shlex
    import sys

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with _user_errors():
        from democheck.petnet.dagger import DaggerConfig, dagger as run_dagger

        cfg = DaggerConfig(rounds=rounds, episodes_per_task=episodes_per_task, beta=beta, steps=steps,
                           batch_tasks=batch_tasks, timesteps=timesteps, lr=lr, seed=seed, workers=workers,
                           device=device)
        cols = (TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
        with Progress(*cols, console=err_console, transient=True) as bar:
            job = bar.add_task("dagger", total=None)
            s = run_dagger(model, data, out, cfg, resume=resume, force=force, cache_dir=cache_dir,
                           command="democheck " + shlex.join(sys.argv[1:]),
                           on_stage=lambda text: bar.update(job, description=text, completed=0, total=None),
                           on_progress=lambda d, n: bar.update(job, completed=d, total=n))
    table = Table(title=f"recovery training of {model} ({s['wall_s'] / 60:.1f} min)")
    for col in ("round", "rollouts", "mixed success", "demo mse", "recovery mse"):
        table.add_column(col, justify="right")
    for h in s["history"]:
        table.add_row(str(h["round"]), str(h["rollouts"]), f"{h['mixed_success']:.1%}", f"{h['demo_mse']:.4f}",
                      f"{h['recovery_mse']:.4f}")
    console.print(table)
    console.print(f"{out}: measure it with democheck eval {out} --data {data}")


@app.command()
def view(
    report: Annotated[Path, typer.Argument(help="A report folder written by audit (or an .rrd file).")],
) -> None:
    """Open the Rerun viewer on a report's recording (prints the command when there is no display)."""
    import os
    import shutil
    import subprocess

    with _user_errors():
        rrd = report / "report.rrd" if report.is_dir() else report
        if not rrd.is_file():
            raise DemocheckError(f"{rrd}: no recording here; run democheck audit first")
        viewer = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
        has_display = sys.platform == "darwin" or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
        if not has_display or not Path(viewer).exists():
            console.print(f"no display here; on a machine with one (pip install rerun-sdk) run:\n  rerun {rrd}\n"
                          f"or serve it to a browser from here:\n  rerun --web-viewer {rrd}")
            return
        subprocess.Popen([viewer, str(rrd)])
        console.print(f"opened {rrd} in the Rerun viewer")


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the demo's dataset (data/) and report (report/).")] = Path("demo"),
    model: Annotated[Optional[Path], typer.Option(help="Model folder (default: the shipped models/petnet-push-v1).")] = None,
    workers: Annotated[int, typer.Option(help="Worker processes for generating the demos.")] = 2,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """The whole job, small: simulate push-mini with 8 planted bad demos, audit it, and show where they rank."""
    import time

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    t0 = time.perf_counter()
    with _user_errors():
        from democheck.workflows import run_demo

        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), console=err_console,
                      transient=True) as bar:
            job = bar.add_task("", total=None)
            summary = run_demo(out, model=model, workers=workers, force=force,
                               on_stage=lambda s: (bar.update(job, description=s, completed=0, total=None),
                                                   err_console.print(s)),
                               on_progress=lambda d, n: bar.update(job, completed=d, total=n))
    _print_audit(summary, out / "report")
    ranks = ", ".join(f"{r['label']} ep{r['episode_index']} #{r['rank']}" for r in sorted(summary["planted_ranks"], key=lambda r: r["rank"]))
    console.print(f"planted demos rank: {ranks}")
    det = summary["detection"]["suspicion"]
    console.print("precision at k (k = number planted): " + ", ".join(
        f"{kind} {d['p_at_k']:.2f}" for kind, d in det.items()) + f"; AUROC " + ", ".join(
        f"{kind} {d['auroc']:.2f}" for kind, d in det.items()))
    console.print(f"done in {time.perf_counter() - t0:.0f} s")


def main() -> None:  # pragma: no cover - console-script entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
