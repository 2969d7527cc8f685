"""``democheck bench``, ``eval`` and ``dagger``: measure the detector and the controller, train the controller further."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from democheck.cli.audit import MODEL_HELP
from democheck.cli.common import Bar, app, console, user_errors
from democheck.errors import DemocheckError
from democheck.resources import EVAL_MODEL


@app.command()
def bench(
    datasets: Annotated[list[Path], typer.Argument(help="One or more labelled datasets, pooled (e.g. a suite made with --defect-rate and the probes made from it).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for bench.json, bench.md, bench.rrd and scores.parquet.")],
    model: Annotated[Optional[Path], typer.Option(help=MODEL_HELP)] = None,
    tecnet: Annotated[Optional[Path], typer.Option(help="TecNets model trained on the same data, for the kNN baseline (democheck train --recipe tecnet; shipped: tecnet-push-v1); left out if not given.")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the random scorer and of Figure 5B's cue draws.")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    camera: Annotated[Optional[str], typer.Option(help="Image feature to use when there are several.")] = None,
    labels: Annotated[Optional[list[Path]], typer.Option("--labels", help="Your own labels: a CSV file of episode_index,label (episodes it does not list are clean), one per dataset in the order given; without it, the labels democheck's synth and probe write.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """Measure every registered scorer (PETNet's and the baselines') on labelled bad demos: AUROC, AUPRC, precision at k."""
    with user_errors():
        from democheck.audit.scorers import SCORERS
        from democheck.workflows import bench_datasets

        with Bar("bench", "demos") as bar:
            summary = bench_datasets(datasets, out, model=model, tecnet=tecnet, device=device, seed=seed, force=force,
                                     camera=camera, labels=labels,
                                     on_progress=lambda stage, d, n, info="": bar.update(d, n, stage, info))
    # A row per scorer and a column per kind: there are more scorers than kinds, and rows need not fit 80 columns.
    table = Table(title="AUROC, each kind versus clean (bench.md: AUPRC, precision at k, scorers explained)")
    table.add_column("scorer", no_wrap=True)
    for kind in summary["kinds"]:
        table.add_column(kind, justify="right")
    for name, per in summary["scorers"].items():
        table.add_row(SCORERS[name].short, *[f"{per[k]['auroc']:.2f}" if per.get(k, {}).get("auroc") is not None
                                              else "n/a" for k in summary["kinds"]],
                      style="bold" if name == "suspicion" else None)
    console.print(table)
    console.print(f"{out}/bench.md, bench.json, bench.rrd (Figures 5A and 5B), scores.parquet")


@app.command(name="eval")
def eval_(
    model: Annotated[Optional[Path], typer.Argument(help=f"Model folder, or the name of a shipped model (default: {EVAL_MODEL}, shipped with democheck: 70% one-shot success on held-out objects).")] = None,
    data: Annotated[Path, typer.Option(help="Suite to draw cue demos and tasks from (made by democheck synth; e.g. democheck synth push-v2-test --out data/push-v2-test).")] = Path("data/push-v2-test"),
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for eval.json, eval.md, trials.parquet, eval.rrd.")] = Path("runs/eval"),
    split: Annotated[str, typer.Option(help="Which tasks: test (meta-test, held-out objects), val or train.")] = "test",
    trials: Annotated[int, typer.Option(help="Rollouts per task, each on a new layout with its own cue draw.")] = 6,
    shots: Annotated[int, typer.Option(help="Cue demos per trial (combined by product of Gaussians).")] = 1,
    workers: Annotated[int, typer.Option(help="Parallel rollout processes.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed for cue draws and layouts.")] = 0,
    device: Annotated[str, typer.Option(help="Device for inferring z from the cues (rollouts run on CPU).")] = "auto",
    gate: Annotated[bool, typer.Option("--gate", help="Also run the paper's safety gate: act on a cue only when its task uncertainty is within the range of held-out real cues', else ask for another demonstration of the task; reports success of executed cues, the refused share, what refused cues would have scored, and success after asking.")] = False,
    false_refusal: Annotated[float, typer.Option(help="With --gate: the share of real cues the gate refuses by construction.")] = 0.05,
    gate_cues: Annotated[int, typer.Option(help="With --gate: ask for more demonstrations until this many cues in all.")] = 4,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """Closed-loop meta-test: one-shot success on held-out tasks, and success by cue uncertainty (with --gate, under the run-time safety gate)."""
    with user_errors():
        from democheck.evaluate.meta_test import fmt_rate
        from democheck.workflows import evaluate_model

        if not data.exists():
            raise DemocheckError(f"{data}: no such dataset; generate it: democheck synth push-v2-test --out {data}")
        with Bar("eval", "rollouts") as bar:
            s = evaluate_model(model, data, out, split=split, trials=trials, shots=shots, workers=workers, seed=seed,
                               device=device, force=force, on_progress=bar.callback(),
                               gate=false_refusal if gate else None, gate_cues=gate_cues)
    table = Table(title=f"{s['model']} on {s['tasks']} {split} tasks, {shots}-shot, {trials} trials each",
                  show_header=False)
    table.add_row("model success", fmt_rate(s["model_success"]))
    table.add_row("expert, same layouts", fmt_rate(s["expert"]))
    if s.get("flagged"):
        table.add_row("cues flagged (OCSVM)", fmt_rate(s["flagged"]))
        table.add_row("cues not flagged", fmt_rate(s["unflagged"]))
    for q in s.get("sigma_quartiles", []):
        table.add_row(f"sigma quartile {q['quartile']}", fmt_rate(q))
    if s.get("gate"):
        g = s["gate"]
        table.add_row("gate: acted on at once", fmt_rate(g["executed"]))
        table.add_row(f"gate: refused ({100 * g['refused_share']:.1f}%), had they run", fmt_rate(g["refused_would_have"]))
        table.add_row("gate: refused, after asking", fmt_rate(g["after_asking"]))
        table.add_row("gate: every trial it acted on", fmt_rate(g["gated"]))
    console.print(table)
    console.print(f"{out}/eval.md, eval.json, trials.parquet, eval.rrd ({s['rollouts_per_s']:.1f} rollouts/s)")


@app.command()
def dagger(
    model: Annotated[Path, typer.Argument(help="Model folder (PETNet or TecNets) trained on --data by democheck train.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Model folder to write: the same model with the controller trained further.")],
    data: Annotated[Path, typer.Option(help="The model's training suite (made by democheck synth): its training tasks are rolled out.")] = Path("data/push-v1"),
    recipe: Annotated[str, typer.Option(help="Recovery recipe: a shipped name (dagger: 4 rounds, the expert acting on 30% of steps, 2,000 controller steps a round) or a path to a .toml file.")] = "dagger",
    set_: Annotated[Optional[list[str]], typer.Option("--set", help="Override one recipe key, e.g. --set rounds=6 --set beta=0.5 (keys: rounds, episodes_per_task, beta, steps, batch_tasks, timesteps, lr, seed).")] = None,
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
    with user_errors():
        from democheck.evaluate.dagger import dagger as run_dagger, load_recipe

        cfg, resolved = load_recipe(recipe, set_, workers=workers, device=device)
        with Bar("dagger") as bar:
            s = run_dagger(model, data, out, cfg, resume=resume, force=force, cache_dir=cache_dir,
                           command="democheck " + shlex.join(sys.argv[1:]), on_stage=bar.say,
                           on_progress=bar.callback(), recipe=resolved)
    table = Table(title=f"recovery training of {model} ({s['wall_s'] / 60:.1f} min)")
    for col in ("round", "rollouts", "mixed success", "demo mse", "recovery mse"):
        table.add_column(col, justify="right")
    for h in s["history"]:
        table.add_row(str(h["round"]), str(h["rollouts"]), f"{h['mixed_success']:.1%}", f"{h['demo_mse']:.4f}",
                      f"{h['recovery_mse']:.4f}")
    console.print(table)
    console.print(f"{out}: measure it with democheck eval {out} --data {data}")
