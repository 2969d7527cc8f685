"""The audit's Rerun recording: what a reviewer looks at.  The only module that imports ``rerun``.

Entities:
    suspects                      the ranked suspect list (markdown)
    suspects/<rank>_ep<e>/video   the suspect's camera video on the ``frame`` timeline
    suspects/<rank>_ep<e>/sigma   its task standard deviation per embedding dimension (bar chart)
    suspects/<rank>_ep<e>/actions its actions, one series per joint
    suspects/<rank>_ep<e>/state   its robot state, one series per dimension
    map/demos                     2-D t-SNE map of every demo's task mean, size ~ sigma, colour = task
    map/suspects                  the top suspects on that map, labelled
    scores/task_uncertainty       histogram of the task-uncertainty scores
    scores/suspicion              histogram of the ranking (-log10 of the combined tail probability)

The bench's recording (``write_bench_rrd``):
    bench                         bench.md: the tables, the verdicts, the figures' numbers (markdown)
    figure_5a/mean, figure_5a/std task standard deviation per kind (bar charts, kinds in the order of ``kinds``)
    figure_5b/mean_sigma          task standard deviation vs number of cues, on the ``cues`` timeline

The meta-test's recording (``write_eval_rrd``):
    eval                          success rates (markdown)
    rollouts/<outcome>/<n>/video, actions, state, sigma   a few rollouts per outcome (listed in ``eval``)
"""

from __future__ import annotations

import colorsys
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import rerun as rr
import rerun.blueprint as rrb

from democheck.audit.scorers import SCORERS
from democheck.data.demo import Demo
from democheck.data.video import VideoWriter
from democheck.evaluate.meta_test import fmt_rate


def _task_colours(tasks: np.ndarray) -> np.ndarray:
    """A stable colour per task string."""
    out = np.zeros((len(tasks), 3), np.uint8)
    for i, t in enumerate(tasks):
        h = (zlib.crc32(str(t).encode()) % 360) / 360.0
        out[i] = np.array(colorsys.hsv_to_rgb(h, 0.75, 0.95)) * 255
    return out


def embed_2d(table: pd.DataFrame, top: int, max_points: int = 1500, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The map's layout: t-SNE of the task means; above ``max_points`` demos, the suspects plus a random sample
    of the rest.  Returns positions [M, 2] and the ``table`` rows they are of."""
    from sklearn.manifold import TSNE
    from threadpoolctl import threadpool_limits

    n = len(table)
    rows = np.arange(n)
    if "mu" not in table:  # audited without a model: no task embedding to map
        return np.zeros((0, 2)), rows[:0]
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


def suspect_path(rank: int, episode_index: int) -> str:
    return f"suspects/{rank:03d}_ep{episode_index}"


def suspects_markdown(table: pd.DataFrame, top: int, title: str) -> str:
    """The ranked list: what a reviewer decides by first (the ranking, the flag, the reason), then the task and
    every other registered score the table has, and what each column means."""
    cols = [n for n, s in SCORERS.items() if s.in_audit and n in table and n != "suspicion"]
    lines = [f"# {title}", "", "| rank | episode | suspicion | flagged | reason | task | "
             + " | ".join(c.replace("_", " ") for c in cols) + " |",
             "|---:|---:|---:|:---:|---|---|" + "---:|" * len(cols)]
    for r in table.head(top).to_dict(orient="records"):
        cells = ["n/a" if not np.isfinite(r[c]) else f"{r[c]:.4g}" for c in ["suspicion", *cols]]
        reason, task = (str(x).replace("|", "\\|") for x in (r.get("reason", ""), r["task"]))  # "mean |action|"
        lines.append(f"| {r['rank']} | {r['episode_index']} | {cells[0]} | {'yes' if r['is_anomaly'] else ''} | "
                     f"{reason} | {task} | " + " | ".join(cells[1:]) + " |")
    lines += ["", *[f"- {c.replace('_', ' ')}: {SCORERS[c].description}" for c in ["suspicion", *cols]],
              "- flagged: a combined tail probability (p value, 10^-suspicion) at most the false-positive rate "
              "asked for, or an exact copy of another demo (see summary.json, flag)"]
    return "\n".join(lines)


def _histogram(rec: rr.RecordingStream, path: str, values: np.ndarray, bins: int = 40) -> None:
    values = values[np.isfinite(values)]
    if not len(values):
        return
    try:
        counts, edges = np.histogram(values, bins=bins)
    except ValueError:  # all values (nearly) equal: too narrow a range for that many bins, so one bar
        counts, edges = np.histogram(values, bins=1, range=(values.min() - 0.5, values.max() + 0.5))
    rec.log(path, rr.BarChart(counts, abscissa=(edges[:-1] + edges[1:]) / 2), static=True)


def _log_demo(rec: rr.RecordingStream, base: str, demo: Demo, sigma: np.ndarray | None, fps: float) -> None:
    t = np.arange(len(demo))
    with tempfile.TemporaryDirectory() as tmp:
        size = demo.frames.shape[1]
        pix = "yuv420p" if size % 2 == 0 and demo.frames.shape[2] == size else "yuv444p"
        if demo.frames.shape[1] == demo.frames.shape[2]:
            with VideoWriter(Path(tmp) / "v.mp4", int(round(fps)), size, pix_fmt=pix, crf=18) as vw:
                vw.write(demo.frames)
            asset = rr.AssetVideo(contents=(Path(tmp) / "v.mp4").read_bytes(), media_type="video/mp4")
            rec.log(f"{base}/video", asset, static=True)
            stamps = asset.read_frame_timestamps_nanos()
            rec.send_columns(f"{base}/video", indexes=[rr.TimeColumn("frame", sequence=t[:len(stamps)])],
                             columns=rr.VideoFrameReference.columns_nanos(stamps))
        else:  # non-square frames: plain images
            for i, img in enumerate(demo.frames):
                rec.set_time("frame", sequence=i)
                rec.log(f"{base}/video", rr.Image(img))
    if sigma is not None:
        rec.log(f"{base}/sigma", rr.BarChart(sigma), static=True)
    frame = [rr.TimeColumn("frame", sequence=t)]
    rec.send_columns(f"{base}/actions", indexes=frame, columns=rr.Scalars.columns(scalars=demo.actions))
    rec.send_columns(f"{base}/state", indexes=frame, columns=rr.Scalars.columns(scalars=demo.state))


def write_report_rrd(path: Path, table: pd.DataFrame, suspects: list[Demo], embedding: np.ndarray,
                     embedded_rows: np.ndarray, fps: float, title: str) -> None:
    """One recording with a reviewer's blueprint: suspect list, suspects' evidence, embedding map, score histograms.

    ``suspects`` are the top demos in rank order; ``embedding`` [M, 2] are t-SNE positions of ``table`` rows
    ``embedded_rows``.
    """
    rec = rr.RecordingStream("democheck")
    rec.save(str(path))
    top = len(suspects)
    rec.log("suspects", rr.TextDocument(suspects_markdown(table, max(top, 20), title),
                                        media_type=rr.MediaType.MARKDOWN), static=True)
    sigma = np.stack(table["sigma"].to_numpy()) if len(table) and "sigma" in table else None
    score = table["task_uncertainty"].to_numpy() if "task_uncertainty" in table else None
    if len(embedded_rows):
        sub = table.iloc[embedded_rows]
        s = score[embedded_rows]
        radii = 0.3 + 1.7 * (s - s.min()) / max(s.max() - s.min(), 1e-9)  # point size ~ sigma
        rec.log("map/demos", rr.Points2D(embedding, radii=radii, colors=_task_colours(sub["task"].to_numpy()),
                                         class_ids=sub["rank"].to_numpy()), static=True)
        is_top = sub["rank"].to_numpy() <= top
        if is_top.any():
            rec.log("map/suspects", rr.Points2D(embedding[is_top], radii=radii[is_top] + 0.5,
                                                colors=[255, 40, 40],
                                                labels=[f"#{r} ep{e}" for r, e in zip(sub["rank"][is_top],
                                                                                      sub["episode_index"][is_top])]),
                    static=True)
    _histogram(rec, "scores/suspicion", table["suspicion"].to_numpy(dtype=float))
    if score is not None:
        _histogram(rec, "scores/task_uncertainty", score)
    tabs = []
    for demo, row in zip(suspects, table.head(top).itertuples()):
        base = suspect_path(row.rank, row.episode_index)
        _log_demo(rec, base, demo, None if sigma is None else sigma[row.Index], fps)
        plots = [rrb.TimeSeriesView(origin=f"{base}/actions", name="actions"),
                 rrb.TimeSeriesView(origin=f"{base}/state", name="state")]
        if sigma is not None:
            plots.insert(0, rrb.BarChartView(origin=f"{base}/sigma", name="sigma"))
        tabs.append(rrb.Vertical(rrb.Spatial2DView(origin=f"{base}/video", name="video"), rrb.Horizontal(*plots),
                                 name=f"#{row.rank} ep{row.episode_index}"))
    hist = [rrb.BarChartView(origin="scores/suspicion", name="suspicion histogram (-log10 p)")]
    if score is not None:
        hist.append(rrb.BarChartView(origin="scores/task_uncertainty", name="task uncertainty histogram"))
    views = [rrb.TextDocumentView(origin="suspects", name="ranked suspects")]
    if len(embedded_rows):
        views.append(rrb.Spatial2DView(origin="map", name="task embedding (t-SNE of mu)"))
    left = rrb.Vertical(*views, rrb.Horizontal(*hist))
    body = rrb.Horizontal(left, rrb.Tabs(*tabs, name="suspects")) if tabs else left
    rec.send_blueprint(rrb.Blueprint(body, collapse_panels=True))
    rec.flush()


def write_bench_rrd(path: Path, summary: dict, text: str) -> None:
    """The bench's figures: 5A (sigma per kind) as bar charts, 5B (sigma vs number of cues) as a curve.

    ``text`` is bench.md, shown beside them.
    """
    rec = rr.RecordingStream("democheck_bench")
    rec.save(str(path))
    fig_a = summary["figure_5a"]
    kinds = list(fig_a)
    text += "\nFigure 5A bars, left to right: " + ", ".join(kinds) + "\n"
    rec.log("bench", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
    rec.log("figure_5a/mean", rr.BarChart([fig_a[k]["mean"] for k in kinds]), static=True)
    rec.log("figure_5a/std", rr.BarChart([fig_a[k]["std"] for k in kinds]), static=True)
    curve = summary["figure_5b"]
    if curve:
        rec.send_columns("figure_5b/mean_sigma", indexes=[rr.TimeColumn("cues", sequence=[c["cues"] for c in curve])],
                         columns=rr.Scalars.columns(scalars=[c["mean_sigma"] for c in curve]))
    rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(
        rrb.TextDocumentView(origin="bench", name="AUROC"),
        rrb.Vertical(rrb.BarChartView(origin="figure_5a/mean", name="Figure 5A: mean sigma per kind"),
                     rrb.BarChartView(origin="figure_5a/std", name="Figure 5A: spread (std) per kind")),
        rrb.TimeSeriesView(origin="figure_5b", name="Figure 5B: sigma vs number of cues")), collapse_panels=True))
    rec.flush()


def write_eval_rrd(path: Path, summary: dict, rollouts: list, fps: float, per_outcome: int = 3) -> None:
    """A few closed-loop rollouts per outcome (success/failure) with the cue's sigma, and the success rates."""
    rec = rr.RecordingStream("democheck_eval")
    rec.save(str(path))
    lines = ["# democheck eval", "", f"model {summary['model']}: success {fmt_rate(summary['model_success'])}; "
             f"scripted expert on the same layouts {fmt_rate(summary['expert'])}"]
    if summary.get("flagged"):
        lines.append(f"cues flagged by the OCSVM: {fmt_rate(summary['flagged'])}; "
                     f"not flagged: {fmt_rate(summary['unflagged'])}")
    tabs, shown = [], {"success": 0, "failure": 0}
    lines.append("Rollouts shown:")
    for trial, row in rollouts:
        outcome = "success" if row["success"] else "failure"
        if shown[outcome] >= per_outcome:
            continue
        shown[outcome] += 1
        base = f"rollouts/{outcome}/{shown[outcome]}"
        lines.append(f"- `{base}`: {trial.task}, trial {trial.trial}, cue task uncertainty {trial.task_uncertainty:.4f}")
        demo = Demo(episode_index=-1, task=trial.task, frames=row["frames"], state=row["state"], actions=row["actions"])
        sigma = np.asarray(trial.sigma if trial.sigma else [np.nan], np.float32)
        _log_demo(rec, base, demo, sigma, fps)
        tabs.append(rrb.Vertical(rrb.Spatial2DView(origin=f"{base}/video", name="video"),
                                 rrb.Horizontal(rrb.BarChartView(origin=f"{base}/sigma", name="cue sigma"),
                                                rrb.TimeSeriesView(origin=f"{base}/actions", name="actions")),
                                 name=f"{outcome} {shown[outcome]}"))
    rec.log("eval", rr.TextDocument("\n\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)
    body = rrb.Horizontal(rrb.TextDocumentView(origin="eval", name="success"), *([rrb.Tabs(*tabs)] if tabs else []))
    rec.send_blueprint(rrb.Blueprint(body, collapse_panels=True))
    rec.flush()
