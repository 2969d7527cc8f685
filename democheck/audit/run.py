"""Audit demos with a PETNet model: gather the evidence, run the registered scorers, rank, flag, summarise.

The cue pass reads only the first and last frame of each demo, in batches,
so memory does not grow with the dataset beyond one row of numbers per demo;
scorers that need every frame (the action error, the linter heuristics)
share one decoding pass.  ``democheck.workflows`` writes what this computes
into a report folder (tables, summary, Rerun recording); what the summary says
beside the table is ``democheck.audit.summary``'s.
"""

from __future__ import annotations

import functools
import hashlib

import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from democheck import pool
from democheck.audit import reasons, scorers as registry, shards, trust
from democheck.audit.evidence import Evidence, Scorer
from democheck.audit.findings import camera_column
from democheck.audit.ocsvm import ocsvm_margin
from democheck.audit.flagging import DEFAULT_FPR, conformal_p, flagged_regardless, flags
from democheck.audit.scores import rank_order
from democheck.audit.summary import flag_summary, unreadable_files, warnings
from democheck.data.cache import dataset_fingerprint
from democheck.data.demo import DemoSet, camera_name
from democheck.errors import DatasetError, DemocheckError
from democheck.fsutil import to_json
from democheck.petnet.checkpoint import Checkpoint
from democheck.petnet.encode import encode, encode_demos, reads_end_states
from democheck.petnet.posterior import TaskPosterior

Progress = Callable[[str, int, int], None]  # (stage, done, total)


def for_model(ds: DemoSet, ckpt: Checkpoint) -> DemoSet:
    """``ds`` as ``ckpt`` reads it -- frames resized to the model's input size, as its training resized them --
    or one clear line when the model cannot read this dataset at all.  Only the model reads these frames: the
    model-free checks read the camera's own, with or without a model."""
    cfg = ckpt.config
    ds.require_camera("the model")
    train = f"train a model on this data: democheck train {ds.root} --out models/<name>"
    if cfg.model_type != "petnet":
        raise DemocheckError(f"{ckpt.path}: a {cfg.model_type} model has no task uncertainty; audit needs a PETNet model")
    if ds.image_shape[2] != 3:
        raise DemocheckError(f"{ds.root}: camera {ds.camera} gives {ds.image_shape[2]}-channel images; the model "
                             f"reads RGB")
    for what, have, want in (("actions", ds.action_dim, cfg.action_dim), ("states", ds.state_dim, cfg.state_dim)):
        if have != want:
            raise DemocheckError(f"{ds.root}: {what} have {have} dimensions but {ckpt.path} was trained on {want}; "
                                 + train)
    return ds.resized(cfg.image_size)


def cue_posteriors(ds: DemoSet, model, device, batch: int | None = None,
                   on_progress: Callable[[int, int], None] | None = None) -> TaskPosterior:
    """The task posterior of every demo's cue, in ``ds.episode_indices`` order, in batches of ``batch`` (default
    ``shards.CUE_BATCH``), in this process (the audit's own cue pass runs in shards: ``shards.sharded_cues``, the
    same numbers)."""
    eps = ds.episode_indices
    batch = batch or shards.CUE_BATCH
    parts = []
    for s in range(0, len(eps), batch):
        parts.append(encode_demos(model, ds, eps[s:s + batch], device))
        if on_progress:
            on_progress(min(s + batch, len(eps)), len(eps))
    return TaskPosterior.concat(parts)


def cue_sample(n: int) -> np.ndarray:
    """The positions of the ``trust.STILL_SAMPLE`` evenly spread demos of ``n`` whose cues the model's tests encode
    (all of them where there are fewer)."""
    return np.unique(np.linspace(0, n - 1, min(n, trust.STILL_SAMPLE)).astype(int))


def still_cues(ds: DemoSet, model, device) -> tuple[np.ndarray, np.ndarray]:
    """The task uncertainty of ``trust.STILL_SAMPLE`` evenly spread demos' cues cut short (their first frame and
    the one ``trust.STILL_AT`` of the way in, with the state there: a demo that stopped almost at once) and of
    their real cues, for the test task uncertainty must pass to rank."""
    eps = ds.episode_indices
    pick = [eps[i] for i in cue_sample(len(eps))]
    reads = reads_end_states(model)
    short = encode(model, ds.cue_frames_many(pick, at=trust.STILL_AT), device,
                   end_states=ds.end_states(pick, at=trust.STILL_AT) if reads else None).task_uncertainty()
    real = encode(model, ds.cue_frames_many(pick), device, end_states=ds.end_states(pick) if reads else None)
    return short, real.task_uncertainty()


def backwards_cues(sets: list[DemoSet], model, device) -> tuple[np.ndarray, TaskPosterior]:
    """Up to ``trust.STILL_SAMPLE`` evenly spread demos of each of ``sets`` (pooled in order), their cues played
    backwards -- the last frame first, and the state they began in as the state they ended in -- and those demos'
    rows in the pooled order, for the test the novelty and the consistency must pass to rank."""
    rows, parts, start = [], [], 0
    for ds in sets:
        eps = ds.episode_indices
        at = cue_sample(len(eps))
        pick = [eps[i] for i in at]
        if pick:
            cues = ds.cue_frames_many(pick)[:, ::-1]
            parts.append(encode(model, np.ascontiguousarray(cues), device,
                                end_states=ds.end_states(pick, at=0.0) if reads_end_states(model) else None))
            rows.append(start + at)
        start += len(ds)
    return np.concatenate(rows) if rows else np.zeros(0, np.int64), TaskPosterior.concat(parts)


def readable_cameras(ds: DemoSet, ev: Evidence) -> dict[str, DemoSet]:
    """``ds``'s other cameras (``DemoSet.other_cameras``) whose video files are all there and whose sample decodes;
    each of the others, and what is wrong with it, in ``ev.unread_cameras``."""
    out = {}
    for camera, seen in ds.other_cameras().items():
        _, problems = seen.camera_files()
        if problems:
            ev.unread_cameras[camera] = f"{problems[0]}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1
                                                            else "")
        else:
            out[camera] = seen
    return out


def gather_evidence(sets: list[DemoSet], ckpt: Checkpoint | None, scorers: list[Scorer], device: Any,
                    tecnet: Checkpoint | None = None, episodes: pd.DataFrame | None = None, seed: int = 0,
                    on_progress: Progress | None = None, timings: dict[str, float] | None = None,
                    workers: int = 1, engine: str = "local", ray_address: str | None = None,
                    still: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
                    backwards: Callable[[], tuple[np.ndarray, TaskPosterior]] | None = None,
                    journal: shards.Journal | None = None) -> Evidence:
    """Score the demos of ``sets``, pooled in order, with ``scorers``: the cue pass (PETNet, when ``ckpt`` is
    given, and TecNets when given), one decoding pass per dataset for the scorers that need every frame (every
    camera for those that read the pictures alone), then each scorer.

    ``episodes``: the pooled demos' table (default: the datasets' episode tables one after the other).
    ``timings`` gets ``score_s`` (cue pass) and ``actions_s`` (decoding pass).  Both passes run in shards
    (``shards``): ``workers`` > 1 runs those of datasets large enough (``shards.pays``) in that many
    spawned processes, started once for both (``shards.runner``); ``engine`` "ray" in that many Ray actors
    (``pool.RayWorkers``) on the cluster at ``ray_address`` (default: a local instance); otherwise this process
    runs them (``shards.Here``): the same results each way.  ``journal`` keeps each shard as it is done, and
    skips those it holds (``--resume``).  The TecNets baseline's cue pass (bench only) stays in this process.
    """
    pool.check_engine(engine)
    t = timings if timings is not None else {}

    def stage(name: str, ds: DemoSet) -> Callable[[int, int], None] | None:
        return (lambda d, n: on_progress(f"{name} {ds.root.name}", d, n)) if on_progress else None

    model = str(ckpt.path) if ckpt is not None else None

    def spread(ds: DemoSet, cues: bool) -> bool:  # the cue pass reads two frames a demo, the decoding pass all
        h, w, _ = ds.native_shape
        frames = 2 * len(ds) if cues else int(ds.episodes["length"].sum())
        shard = shards.CUE_SHARD if cues else shards.decode_shard(len(ds), ckpt is not None)
        return shards.pays(len(ds), shard, engine, workers, frames * max(h * w, 1) * (1 + len(ds.cameras[1:])))

    decodes = any(s.decode is not None for s in scorers)
    parallel = any(ckpt is not None and spread(ds, cues=True) or decodes and spread(ds, cues=False) for ds in sets)
    with shards.runner(parallel, engine, workers, model, str(device), ray_address) as runner, \
            shards.Here(ckpt, device) as here:
        def run_on(spreads: bool) -> shards.Run:
            by = runner if spreads and runner is not None else here
            if journal is not None:
                return lambda name, jobs, total, progress: journal.run(by, name, jobs, total, progress)
            return lambda name, jobs, total, progress: by.run(jobs, shards._run_shard, total, progress)

        t0 = time.perf_counter()
        post = None
        if ckpt is not None:  # each model reads frames at its own size; the decoding pass, the camera's
            parts = []
            for k, ds in enumerate(sets):
                seen = ds.resized(ckpt.config.image_size)
                here.know(seen)
                parts.append(shards.sharded_cues(seen, run_on(spread(ds, cues=True)), f"cues-{k}",
                                                 shards.CUE_BATCH, stage("PETNet", ds)))
            post = TaskPosterior.concat(parts)
        embedding = None
        if tecnet is not None:
            embedding = np.concatenate([cue_posteriors(ds.resized(tecnet.config.image_size), tecnet.model, device,
                                                       on_progress=stage("TecNets", ds)).mu for ds in sets])
        t["score_s"] = time.perf_counter() - t0
        if episodes is None:
            episodes = pd.concat([ds.episodes.reset_index() for ds in sets], ignore_index=True)
        ev = Evidence(episodes=episodes, posterior=post, model=ckpt, embedding=embedding, seed=seed,
                      frames=all(ds.has_camera for ds in sets), still=still, backwards=backwards)
        decoding = {}
        for s in scorers:  # scorers that share a behaviour key share its consumer
            if s.can_decode(ev):
                decoding.setdefault(s.source, s)
        views = [readable_cameras(ds, ev) if ev.frames and any(s.per_camera for s in decoding.values()) else {}
                 for ds in sets]
        ev.camera = camera_name(sets[0].camera) if ev.frames and sets[0].camera else ""
        ev.cameras = tuple(c for c in views[0] if all(c in v for v in views)) if views else ()
        for s in list(decoding.values()):
            for camera in ev.cameras if s.per_camera else ():
                decoding.setdefault(camera_column(s.source, camera), s)
        if decoding:
            t1 = time.perf_counter()
            got: dict[str, list] = {key: [] for key in decoding}
            start = 0
            for k, (ds, seen) in enumerate(zip(sets, views)):
                rows = slice(start, start + len(ds))  # each dataset's rows of the pooled evidence
                seen = {c: seen[c] for c in ev.cameras}
                here.know(ds, *seen.values())
                run = run_on(spread(ds, cues=False))
                progress = stage("decoding" if ckpt is None else "actions", ds)
                for key, part in shards.sharded_decoding(ds, ev, rows, decoding, run, f"decode-{k}", progress,
                                                         seen).items():
                    got[key].append(part)
                start += len(ds)
            for key, parts in got.items():
                ev.behaviour[key] = shards.concat(parts)
            t["actions_s"] = time.perf_counter() - t1
    return registry.compute(ev, scorers)


def score_posteriors(episodes: pd.DataFrame, post: TaskPosterior, model: Checkpoint | None = None,
                     behaviour: dict[str, Any] | None = None, scorers: list[Scorer] | None = None) -> pd.DataFrame:
    """The ScoreTable of task posteriors already computed (one per row of ``episodes``: episode_index, task),
    with the decoding pass's results when given (e.g. ``{"action_error": values}``): the Python API's way to
    rank demos without a dataset on disk."""
    ev = Evidence(episodes=episodes.reset_index(drop=True), posterior=post, model=model,
                  behaviour=dict(behaviour or {}))
    return score_table(registry.compute(ev, scorers or registry.select()))


def score_table(ev: Evidence, fpr: float = DEFAULT_FPR) -> pd.DataFrame:
    """The ScoreTable: one row per demo, every computed score, ranked by suspicion (rank 1 = most suspect);
    ``p_value`` is the combined tail probability the suspicion is -log10 of, ``reference`` whether the demo is in
    the robust core those tails were fitted on, ``p_reference`` the share of that core at least as suspect
    (``flagging.conformal_p``) and ``is_anomaly`` a p_reference at most ``fpr`` (or a demo flagged regardless:
    ``flagging.flagged_regardless``)."""
    eps = ev.episodes
    table = pd.DataFrame({"episode_index": eps["episode_index"].to_numpy(np.int64), "task": ev.tasks})
    for name in registry.SCORERS:  # each check, then its columns on the other cameras
        for column in [name, *(camera_column(name, c) for c in ev.cameras)]:
            if column in ev.scores:
                table[column] = ev.scores[column]
    if "suspicion" not in table:
        table["suspicion"] = np.nan
    suspicion = table["suspicion"].to_numpy(np.float64)
    table["p_value"] = 10.0 ** -suspicion
    # The reference the flags are calibrated on: the robust core the ranking's tails were fitted on.
    ranked = registry.combination(ev) if "suspicion" in ev.scores else None
    table["reference"] = ranked.core if ranked is not None else np.zeros(len(table), bool)
    table["p_reference"] = conformal_p(suspicion, table["reference"].to_numpy())
    told = registry.explanation(ev, fpr) if ranked is not None else None
    table["details"] = told.details if told else ""
    table["driven_by"] = told.driven_by if told else ""
    table["finding"] = told.lead if told else ""
    if ranked is not None:  # each ranked check's own tail probability and flag: columns that compare
        for name, values in ranked.per_check(fpr).items():
            table[name] = values
    table["is_anomaly"] = flags(table["p_reference"].to_numpy(), fpr, flagged_regardless(table))
    table["reason"] = [reasons.brief(r) for r in table["details"]]
    if ev.posterior is not None:
        ref = (ev.model.meta.get("reference") or {}).get("ocsvm") if ev.model is not None else None
        sigma = ev.posterior.sigma
        table["ocsvm_margin"] = ocsvm_margin(ref, sigma) if ref else np.full(len(table), np.nan)
        table["sigma"] = list(sigma.astype(np.float32))
        table["mu"] = list(ev.posterior.mu.astype(np.float32))
    for col in ("label", "split", "dataset", "source_index"):
        if col in eps:
            table[col] = eps[col].to_numpy()
    table = table.iloc[rank_order(table["suspicion"].to_numpy(), table["episode_index"].to_numpy())]
    table = table.reset_index(drop=True)
    table.insert(2, "rank", np.arange(1, len(table) + 1))
    return table


def write_tables(folder: Path, table: pd.DataFrame, suspects: list[int]) -> None:
    """scores.parquet, scores.csv (vectors as space-separated numbers) and suspects.txt."""
    table.to_parquet(folder / "scores.parquet", index=False)
    csv = table.copy()
    for col in [c for c in ("sigma", "mu") if c in csv]:
        csv[col] = [" ".join(f"{v:.6g}" for v in x) for x in csv[col]]
    csv.to_csv(folder / "scores.csv", index=False)
    (folder / "suspects.txt").write_text("".join(f"{e}\n" for e in suspects))


def journal_key(ds: DemoSet, ckpt: Checkpoint | None, actions: bool) -> dict[str, Any]:
    """What an audit's shards depend on: the data (its files' fingerprint, the camera), the model (its weights'
    digest), whether every demo is decoded, and how the passes are cut."""
    weights = ckpt.path / "model.safetensors" if ckpt is not None else None
    stat = ds.root.stat()
    return {"dataset": str(ds.root.resolve()), "camera": ds.camera,
            "fingerprint": dataset_fingerprint(ds) if ds.root.is_dir() else f"{stat.st_size}:{stat.st_mtime_ns}",
            "model": None if weights is None else hashlib.sha256(weights.read_bytes()).hexdigest()[:16],
            "actions": actions,
            "shards": [shards.CUE_SHARD, shards.CUE_BATCH, shards.decode_shard(len(ds), ckpt is not None)]}


def audit(ds: DemoSet, ckpt: Checkpoint | None, top: int = 20, device: Any = "cpu", actions: bool = True,
          fpr: float = DEFAULT_FPR, on_progress: Progress | None = None, timings: dict[str, float] | None = None,
          why_no_model: str | None = None, workers: int = 1, engine: str = "local",
          ray_address: str | None = None, work: Path | None = None) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Score every demo of ``ds`` with ``ckpt`` -- or, with ``ckpt`` None, with the model-free checks alone --
    and flag those whose combined tail probability is at most ``fpr``: the ScoreTable and the summary.
    ``actions`` adds the scores that decode every demo (the action error and the model-free checks: slower).
    ``why_no_model``: the sentence the summary gives for auditing without a model.  ``work``: a folder where the
    passes keep each shard as it is done (``shards.Journal``); an audit of the same data and options in it
    continues from there."""
    if not 0 < fpr < 1:
        raise DemocheckError(f"--fpr {fpr:g}: the share of clean demos to flag must lie between 0 and 1")
    seen = for_model(ds, ckpt) if ckpt is not None else ds  # the frames the model reads
    if ckpt is None and not actions:
        raise DemocheckError("without a model every score decodes the demos: --no-actions leaves nothing to score")
    if not actions:  # no decoding pass reports a broken recording: refuse it, as before the readers repaired it
        ds.strict()
    t = dict(timings or {})
    chosen = [s for s in registry.select() if actions or "demos" not in s.needs]
    # Encoded only if the data holds too few hardly-moving demos to test task uncertainty on (``trust.untrusted``),
    # and then once.
    # The cues played backwards, encoded where the model has a novelty or consistency to test, and then once.
    still = backwards = None
    if ckpt is not None and ds.has_camera:
        still = functools.cache(lambda: still_cues(seen, ckpt.model, device))
        backwards = functools.cache(lambda: backwards_cues([seen], ckpt.model, device))
    journal = None if work is None else shards.Journal(work, journal_key(ds, ckpt, actions))
    ev = gather_evidence([ds], ckpt, chosen, device, on_progress=on_progress, timings=t, workers=workers,
                         engine=engine, ray_address=ray_address, still=still, backwards=backwards, journal=journal)
    broken = registry.broken_rows(ev)
    if len(broken) and broken.all():  # nothing left to compare a demo with: the dataset, not a demo, is what is broken
        raise DatasetError(f"{ds.root}: every episode is broken, e.g. episode "
                           f"{int(ev.episodes['episode_index'].iloc[0])}: {ev.reasons['broken'][0]}")
    table = score_table(ev, fpr)
    fingerprint = dataset_fingerprint(ds) if (ds.root / "meta").is_dir() else None
    meta = ckpt.meta if ckpt is not None else {}
    trained_on = meta.get("data", {}).get("fingerprint")
    ref = meta.get("reference") or {}
    shown = [n for n in registry.SCORERS if n in ev.scores]
    flagged = int(table["is_anomaly"].sum())
    summary = {
        "dataset": str(ds.root), "format": ds.format, "camera": ds.camera, "dataset_fingerprint": fingerprint,
        # every camera the picture checks read (short names), the first the one the model and the other checks read
        "cameras": [c for c in (ev.camera, *ev.cameras) if c],
        "frames": {"camera": list(ds.native_shape), "model": list(seen.image_shape),
                   "resized": seen.image_size is not None, "count": int(ds.episodes["length"].sum())},
        "model": str(ckpt.path) if ckpt is not None else None,
        "model_trained_on_this_dataset": fingerprint is not None and fingerprint == trained_on,
        "demos": len(table), "tasks": int(table["task"].nunique()), "flagged": flagged,
        "suspects_txt": flagged, "top": top,
        "flag": flag_summary(table, fpr, ev.untrusted),
        "scores": {n: registry.SCORERS[n].description for n in shown} | {
            camera_column(n, c): f"{registry.SCORERS[n].description}; on the {c} camera" for n in shown
            for c in ev.cameras if camera_column(n, c) in ev.scores} | {
            "p_value": "the combined tail probability of the ranking's scores (suspicion = -log10 p_value)",
            "reason": "what put the demo where it ranks: first what happened, in the words of a check beyond every "
                      "clean demo that says what the demo did (the check and how rare after), then others while it "
                      "stays short",
            "details": "the reason whole: up to three checks' words, each with how rare",
            "driven_by": "the check the reason names first (broken, duplicate: flagged regardless)",
            "finding": "what that check found, as check:kind (the kinds: each check's vocabulary)",
            "reference": "in the robust core the ranking's tails were fitted on: the demos believed clean, which "
                         "the flags are calibrated on",
            "p_reference": "the share of the reference demos at least as suspect (conformal; beyond the most "
                           "suspect of them, the combined tail probability's own decay)",
            "is_anomaly": f"p_reference at most the false-positive rate asked for ({fpr:g}), an exact copy of "
                          "another demo, or a broken recording"},
        "top_suspects": table.head(top)[["rank", "episode_index", "task",
                                         *[n for n in shown if n != "novelty"], "p_value",
                                         "is_anomaly", "driven_by", "reason"]].to_dict(orient="records"),
        "timing": t,
    }
    if ckpt is not None:
        summary["model_tests"] = trust.backwards_tests(ev.read_backwards())
        summary["reference"] = {k: v for k, v in ref.items() if k != "ocsvm"}
        summary["ocsvm"] = {k: ref.get("ocsvm", {}).get(k) for k in ("nu", "offset", "n_fit", "flagged_fraction_on_fit")}
        summary["scores"]["ocsvm_margin"] = ("the paper's linear one-class SVM on 1/sigma^2, fitted on the model's "
                                             "training demos (negative = its anomaly side)")
    else:
        summary["no_model"] = why_no_model or "audited with the model-free checks alone (--no-model)"
    if "label" in table:
        summary["labels"] = table["label"].value_counts().to_dict()
    summary["warnings"] = (unreadable_files(ev.episodes["episode_index"].to_numpy(), ev.findings.get("broken"))
                           + [f"the {c} camera is not read: {why}" for c, why in ev.unread_cameras.items()]
                           + warnings(table, ckpt, ev.untrusted, fpr))
    if "suspicion" in ev.scores:  # how the ranking was made, as data (``ranking.RankingConfig``)
        summary["ranking"] = registry.combination(ev).config.to_dict()
    return table, summary


def suspects(table: pd.DataFrame) -> list[int]:
    """What a dataset-editing tool should drop (suspects.txt): the flagged demos, most suspect first."""
    return table.loc[table["is_anomaly"], "episode_index"].tolist()


def finish_summary(summary: dict[str, Any], timings: dict[str, float]) -> dict[str, Any]:
    """The summary with its timings rounded, and demos and frames per second (of the cue pass; without a model, of
    the decoding pass), as plain JSON."""
    t = {k: round(v, 3) for k, v in timings.items()}
    spent = max(timings["score_s"] if summary.get("model") else timings.get("actions_s", timings["score_s"]), 1e-9)
    rates = {"demos_per_s": float(f"{summary['demos'] / spent:.3g}")}
    if summary.get("frames", {}).get("count"):
        rates["frames_per_s"] = float(f"{summary['frames']['count'] / spent:.3g}")
    return to_json({**summary, "timing": t | rates})
