"""Audit a dataset with a PETNet model: score every demo, rank, flag, and write the report folder.

Demos are streamed in batches (cue frames only: first and last frame), so
memory does not grow with the dataset beyond one row of numbers per demo.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from democheck.data.demo import DemoSet
from democheck.errors import DemocheckError

REPORT_FILES = ("scores.parquet", "scores.csv", "summary.json", "suspects.txt", "report.rrd")


def check_compatible(ds: DemoSet, ckpt) -> None:
    """One clear line when the model cannot read this dataset."""
    cfg = ckpt.config
    where = f"{ds.root}"
    if cfg.model_type != "petnet":
        raise DemocheckError(f"{ckpt.path}: a {cfg.model_type} model has no task uncertainty; audit needs a PETNet model")
    h, w, c = ds.image_shape
    if (h, w) != (cfg.image_size, cfg.image_size) or c != 3:
        raise DemocheckError(f"{where}: camera {ds.camera} gives {h}x{w}x{c} images but {ckpt.path} was trained on "
                             f"{cfg.image_size}x{cfg.image_size}x3; train a model on this data: "
                             f"democheck train {ds.root} --out models/<name>")
    if ds.action_dim != cfg.action_dim:
        raise DemocheckError(f"{where}: actions have {ds.action_dim} dimensions but {ckpt.path} was trained on "
                             f"{cfg.action_dim}; train a model on this data: democheck train {ds.root} --out models/<name>")


def posteriors(ds: DemoSet, model, device, batch: int = 256,
               on_progress: Callable[[int, int], None] | None = None, parts: bool = False) -> tuple[np.ndarray, ...]:
    """Task posterior (mu, var) of every demo's cue, in ``ds.episode_indices`` order; ``parts``: (mu, var_task,
    var_novel), as ``task_posteriors``."""
    from democheck.petnet.train import task_posteriors

    eps = ds.episode_indices
    cols: list[list[np.ndarray]] = []
    for s in range(0, len(eps), batch):
        out = task_posteriors(model, ds.cue_frames_many(eps[s:s + batch]), device, parts=parts)
        cols = cols or [[] for _ in out]
        for col, x in zip(cols, out):
            col.append(x)
        if on_progress:
            on_progress(min(s + batch, len(eps)), len(eps))
    return tuple(np.concatenate(c) for c in cols)


ACTION_STEPS = 25  # timesteps per demo at which the controller's actions are compared with the demo's


def controller_z(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray) -> np.ndarray:
    """The task variable each demo's actions are judged under: its task's other demos' posterior mean (own mu if alone)."""
    from democheck.audit.scores import others_posterior

    m, _ = others_posterior(mu, var, tasks)
    return np.where(np.isfinite(m), m, mu).astype(np.float32)


def action_errors(demos, ckpt, z: np.ndarray, device, steps: int = ACTION_STEPS, batch: int = 32) -> np.ndarray:
    """Per demo (an iterable, in ``z``'s order): mean squared error between its normalised actions and the
    controller's under its ``z``, at ``steps`` evenly spaced timesteps (all of them when it is shorter)."""
    import torch

    out = np.full(len(z), np.nan)
    pending: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []

    def flush() -> None:
        frames = torch.from_numpy(np.stack([p[1] for p in pending])).to(device)
        state = torch.from_numpy(np.stack([p[2] for p in pending])).to(device)
        rows = np.array([p[0] for p in pending])
        with torch.no_grad():
            pred = ckpt.model.controller.act(frames, state, torch.from_numpy(z[rows]).to(device)).cpu().numpy()
        out[rows] = ((pred - np.stack([p[3] for p in pending])) ** 2).mean(axis=(1, 2))
        pending.clear()

    for i, demo in enumerate(demos):
        t = np.unique(np.linspace(0, len(demo.actions) - 1, steps).round().astype(np.int64))
        if len(t) < steps:  # a short demo: repeat its timesteps so a batch stacks
            t = np.resize(t, steps)
        pending.append((i, demo.frames[t], ckpt.norm.state(demo.state[t]).astype(np.float32),
                        ckpt.norm.action(demo.actions[t]).astype(np.float32)))
        if len(pending) == batch:
            flush()
    if pending:
        flush()
    return out


def embed_2d(table: pd.DataFrame, top: int, max_points: int = 1500, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """t-SNE of the task means; above ``max_points`` demos, the suspects plus a random sample of the rest."""
    from sklearn.manifold import TSNE
    from threadpoolctl import threadpool_limits

    n = len(table)
    rows = np.arange(n)
    if n > max_points:
        rng = np.random.default_rng(seed)
        rest = rng.choice(np.arange(top, n), size=max_points - top, replace=False)
        rows = np.sort(np.concatenate([np.arange(min(top, n)), rest]))
    if len(rows) < 5:
        return np.zeros((len(rows), 2)), rows
    mu = np.stack(table["mu"].to_numpy()[rows]).astype(np.float64)
    # One thread: with torch's OpenMP pool in the same process, sklearn's threads spin against it (20x slower).
    with threadpool_limits(1):
        xy = TSNE(n_components=2, perplexity=min(30.0, (len(rows) - 1) / 3), init="pca",
                  random_state=seed).fit_transform(mu)
    return xy, rows


def write_tables(folder: Path, table: pd.DataFrame, suspects: list[int]) -> None:
    table.to_parquet(folder / "scores.parquet", index=False)
    csv = table.copy()
    for col in ("sigma", "mu"):
        csv[col] = [" ".join(f"{v:.6g}" for v in x) for x in csv[col]]
    csv.to_csv(folder / "scores.csv", index=False)
    (folder / "suspects.txt").write_text("".join(f"{e}\n" for e in suspects))


def audit(ds: DemoSet, ckpt, out: Path, top: int = 20, device: str = "cpu", force: bool = False,
          on_progress: Callable[[int, int], None] | None = None, timings: dict[str, float] | None = None,
          actions: bool = True) -> dict[str, Any]:
    """Score ``ds`` with ``ckpt`` and write the report folder ``out`` atomically; returns the summary.

    ``actions`` adds the action error (every demo decoded in full: slower than the cue-only scores)."""
    import torch

    from democheck.audit.scores import SUSPICION_FLAG, score_table
    from democheck.data.cache import dataset_fingerprint
    from democheck.fsutil import atomic_output_dir
    from democheck.viz.report import write_report_rrd

    check_compatible(ds, ckpt)
    t = dict(timings or {})
    t0 = time.perf_counter()
    mu, var_task, var_novel = posteriors(ds, ckpt.model, torch.device(device), on_progress=on_progress, parts=True)
    var = var_task + var_novel
    t["score_s"] = time.perf_counter() - t0
    episodes = ds.episodes.reset_index()  # rows in ds.episode_indices order, as mu and var are
    ref = ckpt.meta.get("reference")
    err = None
    if actions:
        t1 = time.perf_counter()
        z = controller_z(mu, var, episodes["task"].to_numpy())
        err = action_errors(_counting(ds, on_progress), ckpt, z, torch.device(device))
        t["actions_s"] = time.perf_counter() - t1
    table = score_table(episodes, mu, var, ref, err)
    if ckpt.config.novelty:
        # How unfamiliar the cue's images are: d2 / d2_ref (1 = the 90th percentile of held-out real cues).
        ratio = (var_novel / ckpt.model.encoder.prior_var.cpu().numpy()).mean(1)
        table["novelty"] = ratio[pd.Index(episodes["episode_index"]).get_indexer(table["episode_index"])]
    # suspects.txt: what a dataset-editing tool should drop -- the flagged demos, most suspect first.
    suspects = table.loc[table["is_anomaly"], "episode_index"].tolist()
    fingerprint = dataset_fingerprint(ds) if (ds.root / "meta").is_dir() else None
    trained_on = ckpt.meta.get("data", {}).get("fingerprint")
    with atomic_output_dir(out, force=force) as tmp:
        write_tables(tmp, table, suspects)
        t1 = time.perf_counter()
        xy, rows = embed_2d(table, top)
        t["tsne_s"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        demos = [ds[int(e)] for e in table.head(top)["episode_index"]]
        write_report_rrd(tmp / "report.rrd", table, demos, xy, rows, ds.fps, f"democheck audit of {ds.root}")
        t["rrd_s"] = time.perf_counter() - t2
        summary = {
            "dataset": str(ds.root), "format": ds.format, "camera": ds.camera, "dataset_fingerprint": fingerprint,
            "model": str(ckpt.path), "model_trained_on_this_dataset": fingerprint is not None and fingerprint == trained_on,
            "demos": len(table), "tasks": int(table["task"].nunique()), "flagged": int(table["is_anomaly"].sum()),
            "suspects_txt": len(suspects), "top": top,
            "scores": {
                "score": "mean over embedding dimensions of the task standard deviation sqrt(var) of the demo's cue",
                "consistency": "RMS over dimensions of (mu - m)/sqrt(v + var), (m, v) the product-of-Gaussians "
                               "posterior of the other demos of the same task",
                "suspicion": "max of score, consistency (and action_error) each standardised by the median and "
                             "1.4826*MAD of this dataset's demos",
                "is_anomaly": "linear one-class SVM on 1/sigma^2, fitted on the model's training demos, or suspicion "
                              f"above {SUSPICION_FLAG:g}",
            } | ({"novelty": "squared Mahalanobis distance of the cue's conv features from the training cues', over "
                             "the model's reference distance (the novelty part of the variance is prior_var times "
                             "this); above 1: less familiar than 9 in 10 real cues of new tasks"}
                 if ckpt.config.novelty else {}) | ({"action_error": f"mean squared error between the demo's normalised actions and the controller's at "
                                  f"{ACTION_STEPS} evenly spaced timesteps, under the task posterior mean of the other "
                                  "demos of its task"} if actions else {}),
            "reference": {k: v for k, v in (ref or {}).items() if k != "ocsvm"},
            "ocsvm": {k: (ref or {}).get("ocsvm", {}).get(k) for k in ("nu", "offset", "n_fit", "flagged_fraction_on_fit")},
            "top_suspects": table.head(top)[["rank", "episode_index", "task", "score", "consistency",
                                             *(["action_error"] if actions else []), "suspicion",
                                             "is_anomaly"]].to_dict(orient="records"),
            "timing": {k: round(v, 3) for k, v in t.items()} | {"demos_per_s": round(len(table) / max(t["score_s"], 1e-9), 1)},
        }
        if "label" in table:
            summary["labels"] = table["label"].value_counts().to_dict()
        summary = to_json(summary)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
    return summary


def _counting(ds: DemoSet, on_progress: Callable[[int, int], None] | None):
    """Iterate a DemoSet's demos in ``ds.episode_indices`` order, reporting progress."""
    n = len(ds)
    for i, demo in enumerate(ds):
        yield demo
        if on_progress and (i % 50 == 49 or i == n - 1):
            on_progress(i + 1, n)


def to_json(x: Any) -> Any:
    """Plain JSON values: numpy scalars unwrapped, NaN and inf as null."""
    if isinstance(x, dict):
        return {str(k): to_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_json(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x
