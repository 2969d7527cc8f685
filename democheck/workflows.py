"""The library functions behind the CLI commands that join several parts: open the data, load the model, call the
parts, write the command's output folder.

``audit``, ``bench`` and ``eval`` compute and return their results; their
folders (tables, JSON, the Rerun recording ``viz`` makes) are written here,
atomically.  Commands that belong to one part -- ``synth`` and ``probe``
(sim), ``train``'s loop (petnet), ``dagger`` (evaluate) -- write their own
folder through ``fsutil.atomic_output_dir``.  The CLI parses, calls one
function, and prints.  Over 400 lines: one function per such command.
"""

from __future__ import annotations

import json
import shlex
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import torch

from democheck import __version__, pool, resources
from democheck.audit.bench import bench, markdown as bench_markdown
from democheck.audit.metrics import by_label
from democheck.audit.run import audit, finish_summary, for_model, suspects, write_tables
from democheck.audit.ocsvm import reference
from democheck.audit.flagging import DEFAULT_FPR, flagged_regardless, flags
from democheck.data import open_dataset
from democheck.data.demo import DemoSet
from democheck.data.cache import build_cache, dataset_fingerprint
from democheck.data.subset import write_subset
from democheck.errors import DatasetError, DemocheckError
from democheck.evaluate.meta_test import markdown as eval_markdown, meta_test
from democheck.fsutil import atomic_output_dir, refuse_existing, to_json, work_dir, write_json
from democheck.petnet.batches import task_rows
from democheck.petnet.card import git_commit, model_card
from democheck.petnet.checkpoint import load_checkpoint, save_checkpoint
from democheck.petnet.finish import finish_petnet
from democheck.petnet.gate import Gate
from democheck.petnet.encode import encode_demos
from democheck.petnet.recipe import DEFAULT_RECIPE, load_recipe, training_config
from democheck.petnet.train import TrainConfig, TrainResult, finish_rows, resolve_device, train
from democheck.sim.env import STATE_NAMES
from democheck.sim.posed import render_posed
from democheck.sim.scene import ARM_JOINTS
from democheck.sim.suite import generate, load_recipe as load_suite
from democheck.viz.report import MAX_TABS, embed_2d, write_bench_rrd, write_eval_rrd, write_report_rrd
from democheck.viz.suspects import Suspects, Typical


def train_model(dataset: str | Path, out: str | Path, tc: TrainConfig, resume: bool = False, force: bool = False,
                camera: str | None = None, cache_dir: Path | None = None, recipe: dict[str, Any] | None = None,
                on_decode: Callable[[int, int], None] | None = None,
                on_step: Callable[[int, int, dict], None] | None = None,
                stop_after: int | None = None,
                on_novelty: Callable[[int, int], None] | None = None,
                on_posed: Callable[[int, int], None] | None = None) -> TrainResult | None:
    """Open ``dataset``, decode it into the frame cache, train, and write the model folder ``out``.

    ``recipe``: the resolved training recipe ``tc`` came from (``petnet.recipe.load_recipe``), recorded in the
    model's config.json and card.  ``on_posed``: progress of the posed frames a recipe may ask for, per demo."""
    ds = open_dataset(dataset, camera=camera, image_size=tc.image_size).require_camera("training")
    if ds.episodes.groupby("task").size().max() < 2:
        raise DatasetError(f"{ds.root}: every task has a single demo; training needs two or more per task (a cue and "
                           "a trajectory to imitate); democheck audit can still score these demos with a trained model")
    arrays = build_cache(ds, cache_dir, on_progress=on_decode)
    data: dict[str, Any] = {"path": str(dataset), "episodes": len(ds), "tasks": len(ds.tasks), "camera": ds.camera,
                            "camera_shape": list(ds.native_shape), "fps": ds.fps, "format": ds.format}
    suite = Path(dataset) / "meta" / "democheck" / "suite.json"
    if suite.exists():
        data["recipe"] = json.loads(suite.read_text())["recipe"]
    device = resolve_device(tc.device)
    if device.type == "cpu":
        torch.set_num_threads(pool.usable_cores())  # torch's default is the machine's cores, not this process's
    meta = {"data": data, "command": command_line(), "commit": git_commit(Path(__file__).parent),
            "democheck_version": __version__, "torch_version": torch.__version__, "device": str(device),
            "threads": torch.get_num_threads() if device.type == "cpu" else None}
    if recipe is not None:
        meta["recipe"] = recipe
    return train(arrays, Path(out), tc, resume=resume, force=force, meta=meta, on_progress=on_step,
                 card=lambda m: model_card(Path(out).name, m), stop_after=stop_after, reference=reference,
                 task_groups=object_pair_groups(ds), on_novelty=on_novelty,
                 posed=posed_renderer(ds, arrays, tc.posed_frames, tc.seed, on_posed) if tc.posed_frames else None)


def train_from_recipe(dataset: str | Path, out: str | Path, recipe: str | Path = DEFAULT_RECIPE,
                      sets: list[str] | None = None, **options: Any) -> TrainResult | None:
    """``train_model`` with the ``TrainConfig`` of a training recipe and its ``--set`` overrides; ``options``:
    the everyday ones (``steps``, ``seed``, ``device``, ``image_size``; None = the recipe's) and ``train_model``'s."""
    everyday = {k: options.pop(k) for k in ("steps", "seed", "device", "image_size") if k in options}
    tc, resolved = load_recipe(recipe, sets, **everyday)
    return train_model(dataset, out, tc, recipe=resolved, **options)


def refit_novelty(model: str | Path, dataset: str | Path, out: str | Path, camera: str | None = None,
                  cache_dir: Path | None = None, device: str = "auto", force: bool = False,
                  trim: float | None = None, on_decode: Callable[[int, int], None] | None = None,
                  on_novelty: Callable[[int, int], None] | None = None, end_state: bool | None = None
                  ) -> dict[str, Any]:
    """Fit (or refit) a trained PETNet model's novelty density on ``dataset`` -- its training data -- and write
    the model, weights unchanged, to ``out`` with the card's numbers and the audit's reference redone.
    ``trim``: the share of training cues the density leaves out as outliers (default: the model's recipe's);
    ``end_state``: whether it reads the demos' states at their last step too (default: the recipe's)."""
    out = Path(out)
    refuse_existing(out, force)  # before the decoding, not only when writing
    dev = resolve_device(device)
    ckpt = load_checkpoint(model, device=dev)
    ds = for_model(open_dataset(dataset, camera=camera), ckpt)
    arrays = build_cache(ds, cache_dir, on_progress=on_decode)
    trained_on = ckpt.meta.get("data", {}).get("fingerprint")
    if trained_on is not None and trained_on != arrays.fingerprint:
        raise DemocheckError(f"{ds.root}: not the data {ckpt.path} was trained on (fingerprint {arrays.fingerprint}, "
                             f"the model's {trained_on}); the density must describe what the model saw")
    seed = int(ckpt.meta.get("training", {}).get("seed", 0))
    train_rows, val_rows = task_rows(arrays, "train", seed), task_rows(arrays, "val", seed)
    if not train_rows:
        raise DemocheckError(f"{ds.root}: no training tasks with two or more demos")
    recipe = training_config(ckpt.meta.get("training", {}))
    fit_rows, held = finish_rows(arrays, recipe, train_rows, val_rows)  # the rows its training fitted it on
    trim = recipe.novelty_trim if trim is None else trim
    if not 0.0 <= trim < 0.5:
        raise DemocheckError(f"--trim is a share of the training cues below 0.5, not {trim}")
    extra = finish_petnet(ckpt.model, arrays, fit_rows, held, seed, dev,
                          novelty=True, novelty_trim=trim, reference=reference,
                          autoencoder=None if recipe.novelty_autoencoder else 0, on_novelty=on_novelty,
                          end_state=recipe.novelty_state if end_state is None else end_state)
    meta = dict(ckpt.meta)
    meta["metrics"] = {**meta.get("metrics", {}), "task_sigma": extra.pop("task_sigma")}
    meta.update(extra)
    meta["novelty"].update(command=command_line(), commit=git_commit(Path(__file__).parent))
    with atomic_output_dir(out, force=force) as tmp:
        save_checkpoint(tmp, ckpt.model, ckpt.config, ckpt.norm, meta, model_card(out.name, meta))
    return meta


def command_line() -> str:
    """The command that is running, as the user would type it."""
    return "democheck " + shlex.join(sys.argv[1:]) if sys.argv[0].endswith("democheck") else shlex.join(sys.argv)


def object_pair_groups(ds) -> dict[str, str]:
    """Task -> its unordered object pair, from a democheck suite's sim records (empty for other datasets)."""
    eps = ds.episodes
    if "sim" not in eps:
        return {}
    out = {}
    for task, sim in eps.groupby("task")["sim"].first().items():
        try:
            rec = json.loads(sim)
            out[str(task)] = "|".join(sorted((rec["target"], rec["distractor"])))
        except (TypeError, ValueError, KeyError):
            continue
    return out


def posed_renderer(ds: DemoSet, arrays, per_demo: int, seed: int, on_progress: Callable[[int, int], None] | None
                   ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``train``'s ``posed``: given cache rows, ``per_demo`` frames of each row's layout with the arm posed as at a
    random step of those rows' demos (``sim.posed.render_posed``), from a democheck pushing suite's sim records."""
    if "sim" not in ds.episodes or len(STATE_NAMES) != arrays.state.shape[1]:
        raise DatasetError(f"{ds.root}: posed frames render a democheck pushing suite's layouts again (its episodes' "
                           "sim records); this dataset is not one -- set model.posed_frames = 0")
    sims = ds.episodes["sim"]

    def render(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        spans = np.concatenate([np.arange(arrays.offsets[r], arrays.offsets[r] + arrays.lengths[r]) for r in rows])
        arms = np.asarray(arrays.state[spans])[:, :len(ARM_JOINTS)]  # the state begins with the arm's joint angles
        records = [json.loads(sims.loc[int(arrays.episodes["episode_index"].iloc[r])]) for r in rows]
        return render_posed(records, arms, per_demo, seed, on_progress)

    return render


def in_frames(ds: DemoSet, on_progress: Callable[..., None]) -> Callable[[str, int, int], None]:
    """``on_progress(stage, done, total)`` that also tells, as its fourth argument, how many frames a second the
    pass decodes -- of demos in the dataset's order, the unit a video's cost goes by."""
    frames = np.concatenate([[0], np.cumsum(ds.episodes.loc[ds.episode_indices, "length"].to_numpy())])
    began: dict[str, tuple[float, int]] = {}

    def progress(stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        t0, at = began.setdefault(stage, (now, done))
        if total != len(ds) or now - t0 < 1 or done <= at:
            return on_progress(stage, done, total)
        on_progress(stage, done, total, f"{(frames[done] - frames[at]) / (now - t0):,.0f} frames/s")

    return progress


def audit_dataset(dataset: str | Path, out: str | Path, model: str | Path | None = None, top: int = 20,
                  camera: str | None = None, task: str | None = None, device: str = "auto", force: bool = False,
                  on_progress: Callable[..., None] | None = None, actions: bool = True,
                  fpr: float = DEFAULT_FPR, no_model: bool = False, keep_list: str | Path | None = None,
                  drop_list: str | Path | None = None, workers: int = 1, engine: str = "local",
                  ray_address: str | None = None, resume: bool = False) -> dict[str, Any]:
    """Open ``dataset``, load the model (default: the shipped one), audit, and write the report folder ``out``
    atomically (scores.parquet/.csv, summary.json, suspects.txt, report.rrd); returns the summary.  The passes
    keep what they have done beside ``out`` (``fsutil.work_dir``) until it is written: ``resume`` continues an
    interrupted audit from there.

    ``no_model``: the model-free checks alone.  Without ``model``, a dataset the shipped model cannot read
    (other state or action dimensions) is audited model-free too, and the summary says why.
    ``keep_list``/``drop_list``: files listing the unflagged/flagged episode indices as ``[0, 2, 5]``, the form
    a dataset-editing tool takes (e.g. ``lerobot-edit-dataset --operation.episode_indices``).
    ``on_progress(stage, done, total, info="")``: the cue pass, then the decoding pass; ``info`` is the frames a
    second, once a pass has run for a second."""
    out = Path(out)
    work = work_dir(out, resume, force, what="audit")
    ds = open_dataset(dataset, camera=camera, task=task)
    dev = resolve_device(device)
    t0 = time.perf_counter()
    ckpt, why, lost = None, None, None
    files = ds.video_files()
    if files and not any(path.exists() for path in files):  # said before any long work, not after it
        gone = f"every video file of the camera {ds.camera} is missing (e.g. {next(iter(files))})"
        if model is not None and not no_model:
            raise DatasetError(f"{ds.root}: {gone}, and the model reads a demo by its frames")
        lost = f"{gone}: audited on its states and actions alone; democheck info lists the files"
        ds = ds.without_camera()
    if no_model:
        why = "audited with the model-free checks alone (--no-model)"
    elif model is None and not ds.has_camera:
        why = lost or ("the dataset records no camera, and the model reads a demo by its frames: audited with the "
                       "model-free checks of its states and actions alone")
    else:
        ckpt = load_checkpoint(model, device=dev)
        if model is None:
            try:
                for_model(ds, ckpt)
            except DemocheckError as exc:
                problem = str(exc).split("; train a model")[0].split(": ", 1)[-1]
                why = (f"the shipped model cannot read this data ({problem}): audited with the model-free checks "
                       f"alone; for the model's scores too, democheck train {ds.root} --out models/<name> "
                       "--recipe your-data")
                ckpt = None
    t = {"model_load_s": time.perf_counter() - t0}
    table, summary = audit(ds, ckpt, top=top, device=dev, actions=actions, fpr=fpr, timings=t,
                           on_progress=on_progress and in_frames(ds, on_progress), why_no_model=why,
                           workers=workers, engine=engine, ray_address=ray_address, work=work)
    if why and not no_model or lost:
        summary["warnings"].insert(0, lost or why)
    t.update(summary.pop("timing"))
    with atomic_output_dir(out, force=force) as tmp:
        write_tables(tmp, table, suspects(table))
        t1 = time.perf_counter()
        shown = min(max(top, int(table["is_anomaly"].sum())), MAX_TABS)  # every flagged demo gets a tab
        xy, rows = embed_2d(table, shown)
        t["tsne_s"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        demos = Suspects(ds, table.head(shown)["episode_index"].tolist())
        write_report_rrd(tmp / "report.rrd", table, demos, xy, rows, ds.fps, f"democheck audit of {ds.root}",
                         names={"state": ds.names("state"), "action": ds.names("action")}, fpr=fpr,
                         warnings=summary["warnings"], typical=Typical(ds, table, shown))
        t["rrd_s"] = time.perf_counter() - t2
        summary = finish_summary(summary, t)
        write_json(tmp / "summary.json", summary)
    shutil.rmtree(work, ignore_errors=True)  # the report is written: nothing left to resume
    for path, flagged in ((keep_list, False), (drop_list, True)):
        if path is not None:
            write_episode_list(path, table, flagged)
    return summary


def write_episode_list(path: str | Path, table: pd.DataFrame, flagged: bool) -> None:
    """The flagged (or unflagged) episode indices, ascending, as ``[0, 2, 5]``."""
    rows = table.loc[table["is_anomaly"].to_numpy(bool) == flagged, "episode_index"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(sorted(int(e) for e in rows)) + "\n")


def episodes_to_drop(report: Path, drop: str) -> list[int]:
    """The episodes ``democheck clean --drop`` names: ``flagged`` (the report's flags), ``fpr:X`` (those the
    report would flag at --fpr X: a p_reference at most X, an exact copy or a broken recording), ``top:K`` (its K most suspect) or
    ``list:FILE`` (episode indices as ``[3, 17]`` or one per line)."""
    table = pd.read_parquet(report / "scores.parquet")
    if drop == "flagged":
        return table.loc[table["is_anomaly"], "episode_index"].astype(int).tolist()
    kind, _, arg = drop.partition(":")
    if kind == "fpr":
        try:
            level = float(arg)
        except ValueError:
            level = -1.0
        if not 0 < level < 1:
            raise DemocheckError(f"--drop {drop}: the level must lie between 0 and 1")
        # Reports written before the conformal flags have no p_reference: their combined tail probability.
        p = table["p_reference"] if "p_reference" in table else table["p_value"]
        return table.loc[flags(p.to_numpy(), level, flagged_regardless(table)), "episode_index"].astype(int).tolist()
    if kind == "top" and arg.isdigit():
        return table.sort_values("rank").head(int(arg))["episode_index"].astype(int).tolist()
    if kind == "list" and arg:
        text = Path(arg).read_text() if Path(arg).is_file() else None
        if text is None:
            raise DemocheckError(f"--drop list:{arg}: no such file")
        try:
            got = json.loads(text) if text.strip().startswith("[") else [int(x) for x in text.split()]
            return [int(e) for e in got]
        except (ValueError, TypeError):
            raise DemocheckError(f"{arg}: not a list of episode indices ([3, 17] or one per line)") from None
    raise DemocheckError(f"--drop {drop!r}: one of flagged, fpr:X, top:K, list:FILE")


def clean_dataset(dataset: str | Path, report: str | Path, out: str | Path, drop: str = "flagged",
                  force: bool = False) -> dict[str, Any]:
    """Write ``dataset`` without the episodes ``drop`` names from the audit ``report`` (``data.subset``), after
    checking the report was made on this very dataset; returns what was kept and dropped."""
    report, out = Path(report), Path(out)
    refuse_existing(out, force)
    summary_path = report / "summary.json"
    if not summary_path.is_file():
        raise DemocheckError(f"{report}: no summary.json here; give the folder democheck audit wrote")
    summary = json.loads(summary_path.read_text())
    ds = open_dataset(dataset, camera=summary.get("camera"))
    if ds.format != "lerobot-v3.0":
        raise DemocheckError(f"{ds.root}: a {ds.format} dataset; democheck clean writes LeRobot v3.0 datasets")
    if summary.get("dataset_fingerprint") != dataset_fingerprint(ds):
        raise DemocheckError(f"{report} was made on another dataset than {ds.root} (fingerprint "
                             f"{summary.get('dataset_fingerprint')} vs {dataset_fingerprint(ds)}); audit this one first")
    dropped = sorted(set(episodes_to_drop(report, drop)))
    keep = [e for e in ds.episode_indices if e not in set(dropped)]
    if not keep:
        raise DemocheckError(f"--drop {drop} drops every episode of {ds.root}")
    with atomic_output_dir(out, force=force) as tmp:
        got = write_subset(ds.root, keep, tmp)
    return {**got, "dropped_episodes": dropped, "out": str(out), "source": str(ds.root), "drop": drop}


def read_labels(path: str | Path, ds) -> dict[int, str]:
    """``episode_index,label`` rows of a CSV file (unlisted episodes are clean), checked against ``ds``."""
    path = Path(path)
    try:
        table = pd.read_csv(path, dtype={"label": str})
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not a readable CSV file ({str(exc).splitlines()[0]})") from None
    if not {"episode_index", "label"} <= set(table.columns):
        raise DatasetError(f"{path}: needs the columns episode_index,label (has {', '.join(map(str, table.columns))})")
    index = pd.to_numeric(table["episode_index"], errors="coerce")
    if index.isna().any() or (index % 1 != 0).any():
        raise DatasetError(f"{path}: episode_index must be whole numbers (row {int(np.argmax(index.isna() | (index % 1 != 0))) + 2})")
    unknown = sorted(set(index.astype(int)) - set(ds.episode_indices))
    if unknown:
        raise DatasetError(f"{path}: episode {unknown[0]} is not in {ds.root}" + (f" (and {len(unknown) - 1} more)"
                                                                              if len(unknown) > 1 else ""))
    return dict(zip(index.astype(int), table["label"].fillna("clean").astype(str)))


def bench_datasets(datasets: list[str | Path], out: str | Path, model: str | Path | None = None,
                   tecnet: str | Path | None = None, device: str = "auto", seed: int = 0, force: bool = False,
                   camera: str | None = None, labels: list[str | Path] | None = None,
                   on_progress: Callable[[str, int, int], None] | None = None) -> dict[str, Any]:
    """Open the labelled ``datasets`` and the models, run ``audit.bench.bench`` and write bench.json, bench.md,
    bench.rrd and scores.parquet into ``out`` (atomically); returns the summary.  ``labels``: one CSV file
    (episode_index,label) per dataset, for data without democheck's labels."""
    out = Path(out)
    refuse_existing(out, force)
    dev = resolve_device(device)
    ckpt = load_checkpoint(model, device=dev)
    tec = load_checkpoint(tecnet, device=dev) if tecnet is not None else None
    sets = [open_dataset(p, camera=camera) for p in datasets]
    if labels and len(labels) != len(sets):
        raise DemocheckError(f"{len(labels)} --labels files for {len(sets)} datasets; give one per dataset, in order")
    read = [read_labels(p, ds) for p, ds in zip(labels, sets)] if labels else None
    table, summary = bench(sets, ckpt, tecnet=tec, device=dev, seed=seed, on_progress=on_progress, labels=read)
    with atomic_output_dir(out, force=force) as tmp:
        table.to_parquet(tmp / "scores.parquet", index=False)
        write_json(tmp / "bench.json", summary)
        text = bench_markdown(summary)
        (tmp / "bench.md").write_text(text)
        write_bench_rrd(tmp / "bench.rrd", summary, text)
    return summary


def evaluate_model(model: str | Path | None, dataset: str | Path, out: str | Path, split: str = "test",
                   trials: int = 6, shots: int = 1, workers: int = 2, seed: int = 0, device: str = "auto",
                   force: bool = False, on_progress: Callable[[int, int], None] | None = None,
                   gate: float | None = None, gate_cues: int = 4) -> dict[str, Any]:
    """The closed-loop meta-test (``evaluate.meta_test``), written as eval.json, eval.md, trials.parquet and
    eval.rrd into ``out`` (atomically); returns the summary.  ``gate``: the run-time gate's false-refusal rate
    (``petnet.gate``), asking for up to ``gate_cues`` cues in all."""
    out = Path(out)
    refuse_existing(out, force)
    dev = resolve_device(device)
    ckpt = load_checkpoint(resources.EVAL_MODEL if model is None else model, device=dev)
    ds = open_dataset(dataset).require_camera("the meta-test")
    the_gate = None if gate is None else model_gate(ckpt, ds, gate, gate_cues, dev)
    result = meta_test(ckpt, ds, split=split, trials=trials, shots=shots, workers=workers, seed=seed, device=dev,
                       on_progress=on_progress, gate=the_gate)
    with atomic_output_dir(out, force=force) as tmp:
        result.trials.to_parquet(tmp / "trials.parquet", index=False)
        write_json(tmp / "eval.json", result.summary)
        (tmp / "eval.md").write_text(eval_markdown(result.summary))
        write_eval_rrd(tmp / "eval.rrd", result.summary, result.kept, ds.fps)
    return result.summary


def model_gate(ckpt: Any, ds: Any, false_refusal: float, max_cues: int, device: Any) -> Gate:
    """The model's run-time gate; for a model that stores no reference cues, read from the clean demos of the
    dataset's val split (tasks of training objects the model did not train on), which the summary records."""
    try:
        return Gate.of(ckpt, false_refusal, max_cues)
    except DemocheckError:
        if ckpt.config.model_type != "petnet" or "split" not in ds.episodes:
            raise
    eps = ds.episodes
    val = eps[(eps["split"] == "val") & (eps.get("label", pd.Series("clean", index=eps.index)).fillna("clean")
                                         == "clean")]
    if not len(val):
        raise DemocheckError(f"{ckpt.path}: stores no reference cues for its gate, and {ds.root} has no clean "
                             "val demos to read them from")
    post = encode_demos(ckpt.model, ds, [int(e) for e in val.index], device)
    return Gate.fit(post.task_uncertainty(), false_refusal, max_cues)


DEMO_PLANT = {"idle": 4, "random": 4}


def run_demo(out: str | Path, model: str | Path | None = None, workers: int = 2, force: bool = False,
             on_stage: Callable[[str], None] | None = None,
             on_progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """The main job, small: push-mini with planted idle and random demos, audited with the shipped model.
    ``on_stage(text)`` starts each stage, ``on_progress(done, total)`` counts its demos."""
    out = Path(out)
    refuse_existing(out, force)
    recipe = load_suite("push-mini").with_overrides(defects=DEMO_PLANT)
    if on_stage:
        on_stage(f"generating {recipe.n_episodes} demos of push-mini ({sum(DEMO_PLANT.values())} planted bad ones)")
    synth = generate(recipe, out / "data", workers=workers, force=True, on_progress=on_progress)
    if on_stage:
        on_stage("auditing with the model")
    summary = audit_dataset(out / "data", out / "report", model=model, force=True,
                            on_progress=(lambda stage, d, n, info="": on_progress(d, n)) if on_progress else None)
    table = pd.read_parquet(out / "report" / "scores.parquet")
    summary["planted"] = DEMO_PLANT
    summary["detection"] = {col: by_label(table, col)
                            for col in ("suspicion", "task_uncertainty", "consistency", "action_error")}
    summary["synth"] = {k: synth[k] for k in ("episodes", "wall_s", "frames_per_s")}
    planted = table[table["label"] != "clean"]
    summary["planted_ranks"] = planted[["episode_index", "label", "rank"]].to_dict(orient="records")
    return to_json(summary)
