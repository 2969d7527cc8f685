"""``democheck audit``, ``view`` and ``demo``: score a dataset's demos, look at the report, run the whole job."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from democheck.cli.common import BY_ID, REVISION_HELP, Bar, app, console, err_console, local_dataset, short, user_errors
from democheck.errors import DemocheckError
from democheck.resources import DEFAULT_MODEL

MODEL_HELP = f"Model folder, or the name of a shipped model (default: {DEFAULT_MODEL}, shipped with democheck)."


@app.command()
def audit(
    dataset: Annotated[str, typer.Argument(help="Dataset to audit: LeRobot v3.0/v2.1 folder or robomimic .hdf5 file." + BY_ID)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder: scores.parquet/.csv, summary.json, suspects.txt, report.rrd.")],
    model: Annotated[Optional[Path], typer.Option(help=MODEL_HELP)] = None,
    top: Annotated[int, typer.Option(help="How many top suspects to show and to record with their evidence.")] = 20,
    fail_on: Annotated[Optional[int], typer.Option(help="Exit with status 3 when more than this many demos are flagged (for CI gates).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON instead of a table.")] = False,
    camera: Annotated[Optional[str], typer.Option(
        help="The camera the model and the time checks read, where there are several (default: the first); the "
             "picture checks (frozen video, frame jumps, view, colours) read every camera.")] = None,
    task: Annotated[Optional[str], typer.Option(help="Task string for robomimic files that do not name their task.")] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    actions: Annotated[bool, typer.Option("--actions/--no-actions", help="Also score how badly the model's controller explains each demo's actions (catches arms that never moved, flailed or stopped half-way). Decodes every demo in full: --no-actions is the fast pass on cue frames only.")] = True,
    fpr: Annotated[float, typer.Option(help="Flag the demos at least as suspect as at most this share of the reference demos -- the audited demos' robust core, believed clean -- so that about this share of clean demos is flagged (the summary states the level and the expected number of false flags).")] = 0.01,
    no_model: Annotated[bool, typer.Option("--no-model", help="Use the model-free checks alone (idle, pauses, motion, grasps, jerk, frozen video, frame jumps, frozen state sensors, NaN values, duplicates, saturation, action-state dynamics, action lag, state-action coupling, timestamps, view, colours, outcome, what moved, how each demo begins, ends and goes): works on any robot before any model is trained. Automatic, with a warning, when the shipped model cannot read the data.")] = False,
    keep_list: Annotated[Optional[Path], typer.Option(help="Also write the unflagged episode indices to this file as [0, 2, 5] (what a dataset-editing tool takes).")] = None,
    drop_list: Annotated[Optional[Path], typer.Option(help="Also write the flagged episode indices to this file as [0, 2, 5], e.g. for lerobot-edit-dataset --operation.type delete_episodes --operation.episode_indices \"$(cat FILE)\".")] = None,
    workers: Annotated[Optional[int], typer.Option(help="Processes for the cue pass and the pass that decodes every demo, started once for both (default: the machine's cores; small datasets stay in one). The scores are the same for any number.")] = None,
    engine: Annotated[str, typer.Option(help="Who reads the cues and decodes the demos: local (worker processes on this machine) or ray (Ray Data actors, one CPU each, --workers of them: a local Ray instance, or the cluster at --ray-address; every node needs democheck and the dataset at the same path). Needs pip install 'democheck\\[ray]'. The scores are the same.")] = "local",
    ray_address: Annotated[Optional[str], typer.Option(help="With --engine ray: the Ray cluster's address (e.g. ray://head:10001 or auto); default: start a local instance.")] = None,
    revision: Annotated[Optional[str], typer.Option(help=REVISION_HELP)] = None,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue an interrupted audit of the same data and options from the shards it finished "
                         "(kept beside --out until the report is written): the scores of a run that never stopped.")
                      ] = False,
    force: Annotated[bool, typer.Option(
        "--force", help="Replace --out if it exists (and discard an interrupted audit's work).")] = False,
) -> None:
    """Score every demonstration -- task uncertainty, novelty, consistency, action error and model-free checks --
    combine them into one tail probability, rank the suspects and flag those below --fpr.  A model's score votes
    only where it passes its test on your data (summary.json: model_tests and warnings)."""
    with user_errors():
        if top < 1:
            raise DemocheckError("--top must be at least 1")
        if no_model and model is not None:
            raise DemocheckError("--no-model and --model together: choose one")
        if ray_address and engine != "ray":
            raise DemocheckError("--ray-address needs --engine ray")
        from democheck.pool import usable_cores
        from democheck.workflows import audit_dataset

        dataset = local_dataset(dataset, revision)
        with Bar("audit", "demos", info=True) as bar:
            summary = audit_dataset(dataset, out, model=model, top=top, camera=camera, task=task, device=device,
                                    force=force, on_progress=lambda stage, d, n, info="": bar.update(d, n, stage, info),
                                    actions=actions, fpr=fpr, no_model=no_model, keep_list=keep_list,
                                    drop_list=drop_list, workers=workers or usable_cores(), engine=engine,
                                    ray_address=ray_address, resume=resume)
    if json_out:
        console.print_json(json.dumps(summary))
    else:
        print_audit(summary, out)
    if fail_on is not None and summary["flagged"] > fail_on:
        err_console.print(f"{summary['flagged']} demos flagged, more than --fail-on {fail_on}")
        raise typer.Exit(3)


def print_audit(summary: dict, out: Path) -> None:
    """The top suspects as a table that fits 80 columns: each one's rank, episode, task, suspicion, flag and the
    score that drove it most (every score is in scores.csv and the report; the reasons of the first three follow
    the table)."""
    from rich import box

    flag = summary["flag"]
    table = Table(title=f"top suspects of {summary['demos']} demos", box=box.SIMPLE_HEAD, pad_edge=False)
    for col in ("rank", "episode", "task", "suspicion", "flag", "driven by"):
        table.add_column(col, justify="left" if col in ("task", "driven by") else "right", no_wrap=True,
                         overflow="ellipsis", max_width=24 if col == "task" else None,
                         min_width=None if col == "task" else max(len(col), 12 if col == "driven by" else 0))
    for r in summary["top_suspects"]:
        driver = r.get("driven_by") or ""
        table.add_row(str(r["rank"]), str(r["episode_index"]), r["task"],
                      short(r["suspicion"]) if r.get("suspicion") is not None
                      else "inf" if r.get("p_value") == 0 else "n/a",  # a broken recording: suspect regardless
                      "[red]yes[/]" if r["is_anomaly"] else "", driver)
    console.print(table)
    level = flag.get("p_value_at_level")
    apart = {"broken recordings": flag.get("broken_recordings", 0), "exact copies": flag.get("exact_copies", 0)}
    scored = max(summary["flagged"] - sum(apart.values()), 0)
    console.print(f"{summary['flagged']} flagged at --fpr {flag['fpr']:g}: "
                  + "".join(f"{n} {what}, " for what, n in apart.items() if n)
                  + f"{scored} by their scores"
                  + (f" (on this data: a p_value at most {level:.3g})" if level is not None else "")
                  + (f"; about {flag['expected_false_flags']:.1f} false flags expected among those"
                     if not flag.get("too_small") else ""), highlight=False)
    if flag.get("one_task"):
        console.print(flag["one_task"], highlight=False)
    for w in summary.get("warnings", []):
        console.print(f"[yellow]warning:[/] {w}", highlight=False)
    for r in summary["top_suspects"][:3]:
        if r.get("reason"):
            console.print(f"rank {r['rank']} (episode {r['episode_index']}): {r['reason']}", highlight=False)
    observed = flag.get("observed")
    if observed and observed["recall"]:
        console.print(f"with the labels: {observed['clean_flagged']} clean demos flagged "
                      f"({100 * observed['clean_share_flagged']:.1f}%); recall "
                      + ", ".join(f"{k} {v:.2f}" for k, v in observed["recall"].items()), highlight=False)
    t = summary["timing"]
    rate = f"{t['demos_per_s']:.2g} demos/s" + (f", {t['frames_per_s']:,.0f} frames/s" if "frames_per_s" in t else "")
    if summary.get("model"):
        console.print(f"scored {summary['demos']} demos in {t['score_s']:.1f} s ({rate})"
                      + (f", their actions in {t['actions_s']:.1f} s" if "actions_s" in t else "")
                      + f"; model load {t['model_load_s']:.1f} s, t-SNE {t['tsne_s']:.1f} s")
    else:
        console.print(f"checked {summary['demos']} demos without a model in {t.get('actions_s', 0):.1f} s ({rate})")
    if summary.get("no_model") and summary["no_model"] not in summary.get("warnings", []):
        console.print(f"no model: {summary['no_model']}", highlight=False)
    console.print(f"report: {out}/ (scores.parquet, scores.csv, summary.json, suspects.txt)")
    console.print(f"look at it: democheck view {out}")


@app.command()
def clean(
    dataset: Annotated[str, typer.Argument(help="The LeRobot v3.0 dataset that was audited." + BY_ID)],
    report: Annotated[Path, typer.Option("--report", "-r", help="The audit's report folder (democheck audit --out).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the cleaned dataset (LeRobot v3.0).")],
    drop: Annotated[str, typer.Option(help="What to drop: flagged (the report's flags), fpr:X (what the audit would flag at --fpr X), top:K (its K most suspect), or list:FILE (episode indices as [3, 17] or one per line).")] = "flagged",
    revision: Annotated[Optional[str], typer.Option(help=REVISION_HELP)] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """Write the dataset without the demos the audit flagged (or another choice): episodes re-indexed, meta/
    consistent, videos copied so the kept episodes decode to the same frames; the input is not touched."""
    with user_errors():
        from democheck.workflows import clean_dataset

        got = clean_dataset(local_dataset(dataset, revision), report, out, drop=drop, force=force)
    shown = ", ".join(map(str, got["dropped_episodes"][:12])) + (" ..." if len(got["dropped_episodes"]) > 12 else "")
    console.print(f"{out}: {got['kept']} episodes kept ({got['frames']} frames), {got['dropped']} dropped"
                  + (f" ({shown})" if shown else "") + f"; audit it again: democheck audit {out} --out <report>",
                  highlight=False)


@app.command()
def view(
    report: Annotated[Path, typer.Argument(help="A report folder written by audit (or an .rrd file).")],
    bind: Annotated[str, typer.Option(help="Address the viewer's own server listens on: this machine only by default; 0.0.0.0 lets other machines connect to it.")] = "127.0.0.1",
) -> None:
    """Open the Rerun viewer on a report's recording (prints the command when there is no display)."""
    with user_errors():
        rrd = report / "report.rrd" if report.is_dir() else report
        if not rrd.is_file():
            raise DemocheckError(f"{rrd}: no recording here; run democheck audit first")
        viewer = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
        has_display = sys.platform == "darwin" or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
        if shutil.which("ffmpeg") is None:
            console.print("note: no ffmpeg program here: the Rerun viewer decodes the suspects' H.264 video with it, so "
                          "their videos will not play (Debian/Ubuntu: sudo apt-get install ffmpeg; macOS: brew "
                          "install ffmpeg)", highlight=False)
        if not has_display or not Path(viewer).exists():
            console.print(f"no display here; on a machine with one (pip install rerun-sdk) run:\n  rerun {rrd}\n"
                          f"or serve it to a browser on this machine only:\n  rerun --web-viewer --bind 127.0.0.1 {rrd}",
                          highlight=False)
            return
        # The viewer runs on in its own session, its log in a file: nothing it prints reaches this terminal.
        log = Path(tempfile.gettempdir()) / "democheck-viewer.log"
        with open(log, "ab") as sink:
            subprocess.Popen([viewer, "--bind", bind, str(rrd)], stdin=subprocess.DEVNULL, stdout=sink, stderr=sink,
                             start_new_session=True)
        console.print(f"opened {rrd} in the Rerun viewer (listening on {bind}; its log: {log})", highlight=False)


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the demo's dataset (data/) and report (report/).")] = Path("demo"),
    model: Annotated[Optional[Path], typer.Option(help=MODEL_HELP)] = None,
    workers: Annotated[int, typer.Option(help="Worker processes for generating the demos.")] = 2,
    force: Annotated[bool, typer.Option("--force", help="Replace --out if it exists.")] = False,
) -> None:
    """The whole job, small: simulate push-mini with 8 planted bad demos, audit it, and show where they rank."""
    t0 = time.perf_counter()
    with user_errors():
        from democheck.workflows import run_demo

        with Bar("demo") as bar:
            summary = run_demo(out, model=model, workers=workers, force=force, on_stage=bar.say,
                               on_progress=bar.callback())
    print_audit(summary, out / "report")
    ranks = ", ".join(f"{r['label']} ep{r['episode_index']} #{r['rank']}"
                      for r in sorted(summary["planted_ranks"], key=lambda r: r["rank"]))
    console.print(f"planted demos rank: {ranks}")
    det = summary["detection"]["suspicion"]
    console.print("precision at k (k = number planted): " + ", ".join(
        f"{kind} {d['p_at_k']:.2f}" for kind, d in det.items()) + "; AUROC " + ", ".join(
        f"{kind} {d['auroc']:.2f}" for kind, d in det.items()))
    console.print(f"done in {time.perf_counter() - t0:.0f} s")
