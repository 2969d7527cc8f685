"""The audit's Rerun recording: what a reviewer decides from.  The only module that imports ``rerun``.

Entities:
    suspects                      the ranked list (markdown): rank, episode, suspicion, flagged, why, task, scores
    suspects/<rank>_ep<e>/about   the suspect's scores, flag and full reason (markdown)
    suspects/<rank>_ep<e>/video   its camera video on the ``frame`` timeline
    suspects/<rank>_ep<e>/cameras/<name>  each other camera's video, where the dataset records several
    suspects/<rank>_ep<e>/sigma   its task standard deviation per embedding dimension over the median of the
                                  unflagged demos' (1 = typical), with a model
    suspects/<rank>_ep<e>/actions its actions, one series per dimension, named as the dataset names them
    suspects/<rank>_ep<e>/state   its robot state, likewise
    typical/<task>/video, actions the unflagged demo of each suspect's task that the ranking finds least
                                  suspect, shown beside the suspect to compare with
    map/demos                     2-D t-SNE map of every demo's task mean, coloured by suspicion (hover: rank,
                                  episode, task); map/flagged the flagged demos on top, the first few labelled
    scores/<name>/all, /flagged   a histogram per score (bars as wide as their bins; the flagged demos' share
                                  of each bar in red); suspicion on a log axis with the flag level as a bar
                                  (scores/suspicion/level)

Every flagged demo gets a tab (at least the top ``--top``, at most ``MAX_TABS``); frames over ``MAX_SIDE``
pixels are scaled down for the recording.

The bench's recording (``write_bench_rrd``):
    bench                         bench.md: the tables, the verdicts, the figures' numbers (markdown)
    figure_5a/mean, figure_5a/std task standard deviation per kind (bar charts, kinds in the order of ``kinds``)
    figure_5b/mean_sigma          task standard deviation vs number of cues, on the ``cues`` timeline

The meta-test's recording (``write_eval_rrd``):
    eval                          success rates (markdown)
    rollouts/<outcome>/<n>/video, actions, state, sigma   a few rollouts per outcome (listed in ``eval``)
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import rerun as rr
import rerun.blueprint as rrb

from democheck.audit.findings import check_of
from democheck.audit.flagging import flag_level
from democheck.audit.scorers import SCORERS, ranking_recipe
from democheck.data.demo import Demo
from democheck.data.video import VideoWriter
from democheck.evaluate.meta_test import fmt_rate

FLAG_RED = [230, 40, 40]
BAR_BLUE = [90, 140, 220]
LEVEL_GREY = [200, 200, 200]
# Scores shown as histograms, and how: on a log10 scale where the score's right tail is long (suspicion,
# itself -log10 of a probability, as log10(1 + suspicion): hundreds beside a flag level of 2-4).
HISTOGRAMS = {"suspicion": True, "task_uncertainty": False, "consistency": False, "action_error": True,
              "motion": False, "idle": False, "novelty": True, "outcome": True}
MAX_TABS = 200  # suspects recorded with their evidence: every flagged demo up to this many
MAX_SIDE = 320  # frames larger than this (either side) are scaled down in the recording
MAP_LABELS = 5  # flagged demos named on the map (more labels overlap; hover names the rest)


def _ramp(values: np.ndarray) -> np.ndarray:
    """Colours for values by rank: dark blue (least suspect) through teal to yellow (most); never red, which
    marks the flagged demos."""
    v = np.asarray(values, np.float64)
    order = np.argsort(np.argsort(np.nan_to_num(v, nan=-np.inf)))
    t = order / max(len(v) - 1, 1)
    stops = np.array([[40, 50, 120], [30, 140, 150], [120, 200, 90], [250, 230, 60]], np.float64)
    x = t * (len(stops) - 1)
    i = np.minimum(x.astype(int), len(stops) - 2)
    f = (x - i)[:, None]
    return (stops[i] * (1 - f) + stops[i + 1] * f).astype(np.uint8)


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


def short_reason(reason: str) -> str:
    """The reason as the ranked list shows it: the driving score, how rare, where (the details are in each
    suspect's tab)."""
    text = str(reason).split("; also ")[0]
    text = re.sub(r"as unusual as 1 clean demo in ([\d,]+)", r"1 in \1", text)
    text = re.sub(r"far beyond the clean demos \(tail probability ([^)]+)\)", r"p \1", text)
    return text


def _cell(value) -> str:
    if isinstance(value, (float, np.floating)):
        return f"{value:.3g}" if np.isfinite(value) else "inf" if value > 0 else "n/a"
    return str(value)


def suspects_markdown(table: pd.DataFrame, top: int, title: str, fpr: float | None = None,
                      warnings: list[str] | None = None, tabs: int = 0) -> str:
    """The ranked list: the audit's warnings first, then what a reviewer decides by (rank, episode, the ranking,
    the flag, why), the task and every other registered score the table has, and how to read the report;
    ``tabs``: how many of the most suspect have a tab of their own."""
    cols = [n for n, s in SCORERS.items() if s.in_audit and n in table and n != "suspicion"]
    n_flagged = int(table["is_anomaly"].sum())
    every = "every flagged one" if tabs >= n_flagged else f"{n_flagged - tabs} flagged ones have none"
    lines = [f"# {title}", "", f"**{n_flagged} of {len(table)} demos flagged.** The {tabs} most suspect ({every}) "
             "have a tab on the right: why, its video beside a clean demo of its task, its "
             "actions and state (hover a curve for the dataset's name of it). "
             + ("The map places demos by the model's task embedding, colour = suspicion (yellow = most suspect), "
                "red = flagged; hover a point for its episode. " if "mu" in table else "")
             + "In the histograms red is the flagged demos' part of a bar; suspicion is drawn as "
             "log10(1 + suspicion), with a grey bar where the flags start.", ""]
    if warnings:
        lines += ["## Warnings", "", *[f"- {w}" for w in warnings], ""]
    lines += ["| rank | episode | suspicion | flagged | why | task | "
              + " | ".join(c.replace("_", " ") for c in cols) + " |",
              "|---:|---:|---:|:---:|---|---|" + "---:|" * len(cols)]
    for r in table.head(top).to_dict(orient="records"):
        why, task = (str(x).replace("|", "\\|") for x in (short_reason(r.get("reason", "")), r["task"]))
        lines.append(f"| {r['rank']} | {r['episode_index']} | {_cell(r['suspicion'])} | "
                     f"{'**yes**' if r['is_anomaly'] else ''} | {why} | {task} | "
                     + " | ".join(_cell(r[c]) for c in cols) + " |")
    level = f"at most {fpr:g}" if fpr is not None else "at most the false-positive rate asked for"
    lines += ["", *[f"- {c.replace('_', ' ')}: {SCORERS[c].description}" for c in ["suspicion", *cols]],
              f"- flagged: a share of the reference demos (the audited demos' robust core, believed clean) at least as "
              f"suspect (p_reference) {level}, an exact copy of another demo, or a broken recording (summary.json, flag)",
              "- why: what happened in the demo, then the check that says so and how rare that is among clean demos"]
    return "\n".join(lines)


def _suspect_markdown(row: dict, cols: list[str], clean: int | None = None) -> str:
    head = f"## #{row['rank']}: episode {row['episode_index']} -- {'FLAGGED' if row['is_anomaly'] else 'not flagged'}"
    scores = ", ".join(f"{c.replace('_', ' ')} {_cell(row[c])}" for c in ["suspicion", *cols] if c in row)
    reason = str(row.get("details") or row.get("reason", "")).replace("; also ", "\n\nalso ")
    beside = f"\n\nBeside it: episode {clean}, the least suspect unflagged demo of the same task." if clean is not None else ""
    return f"{head}\n\ntask: {row['task']}\n\n{reason}\n\n{scores}{beside}"


def _histogram(rec: rr.RecordingStream, path: str, values: np.ndarray, flagged: np.ndarray, bins: int = 30,
               level: float | None = None) -> None:
    """Bars as wide as their bins (``path/all``), the flagged demos' part of each bar (``path/flagged``), and
    ``level`` (where the flags start) as a thin bar as high as the tallest (``path/level``)."""
    ok = np.isfinite(values)
    if not ok.any():
        return
    v, f = values[ok], flagged[ok]
    lo, hi = float(v.min()), float(v.max())
    if level is not None and np.isfinite(level):
        lo, hi = min(lo, level), max(hi, level)
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    edges = np.linspace(lo, hi, bins + 1)
    centres, widths = (edges[:-1] + edges[1:]) / 2, np.diff(edges) * 0.95
    counts = np.histogram(v, edges)[0]
    rec.log(f"{path}/all", rr.BarChart(counts, abscissa=centres, widths=widths, color=BAR_BLUE), static=True)
    rec.log(f"{path}/flagged", rr.BarChart(np.histogram(v[f], edges)[0], abscissa=centres, widths=widths,
                                           color=FLAG_RED), static=True)
    if level is not None and np.isfinite(level):
        rec.log(f"{path}/level", rr.BarChart([int(counts.max())], abscissa=[level], widths=[(hi - lo) / 200],
                                             color=LEVEL_GREY), static=True)


def fit_frames(frames: np.ndarray) -> np.ndarray:
    """Frames no larger than ``MAX_SIDE`` on either side, for the recording (frames that fit, as they are)."""
    h, w = frames.shape[1:3]
    if not frames.size or max(h, w) <= MAX_SIDE:  # no camera (``NO_CAMERA``), or frames that fit
        return frames
    import cv2

    k = MAX_SIDE / max(h, w)
    size = (max(2, int(round(w * k / 2)) * 2), max(2, int(round(h * k / 2)) * 2))
    return np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames])


def _log_demo(rec: rr.RecordingStream, base: str, demo: Demo, sigma: np.ndarray | None, fps: float,
              names: dict[str, list[str]] | None = None) -> None:
    t = np.arange(len(demo))
    if demo.frames.size:  # else a dataset without a camera (``NO_CAMERA``): its state and actions alone
        _log_video(rec, f"{base}/video", fit_frames(demo.frames), fps, t)
    for camera, frames in demo.extra.get("cameras", {}).items():
        _log_video(rec, f"{base}/cameras/{camera}", fit_frames(frames), fps, t)
    if sigma is not None:
        rec.log(f"{base}/sigma", rr.BarChart(sigma), static=True)
    frame = [rr.TimeColumn("frame", sequence=t)]
    for what, values in (("actions", demo.actions), ("state", demo.state)):
        given = (names or {}).get("action" if what == "actions" else "state")
        if given and len(given) == values.shape[1]:
            rec.log(f"{base}/{what}", rr.SeriesLines(names=given), static=True)
        rec.send_columns(f"{base}/{what}", indexes=frame, columns=rr.Scalars.columns(scalars=values))


def _log_video(rec: rr.RecordingStream, path: str, frames: np.ndarray, fps: float, t: np.ndarray) -> None:
    """A demo's frames as an H.264 video asset (square frames) or as images, on the ``frame`` timeline."""
    with tempfile.TemporaryDirectory() as tmp:
        size = frames.shape[1]
        pix = "yuv420p" if size % 2 == 0 and frames.shape[2] == size else "yuv444p"
        if frames.shape[1] == frames.shape[2]:
            with VideoWriter(Path(tmp) / "v.mp4", int(round(fps)), size, pix_fmt=pix, crf=18) as vw:
                vw.write(frames)
            asset = rr.AssetVideo(contents=(Path(tmp) / "v.mp4").read_bytes(), media_type="video/mp4")
            rec.log(path, asset, static=True)
            stamps = asset.read_frame_timestamps_nanos()
            rec.send_columns(path, indexes=[rr.TimeColumn("frame", sequence=t[:len(stamps)])],
                             columns=rr.VideoFrameReference.columns_nanos(stamps))
        else:  # non-square frames: JPEG images (a hub camera's raw frames would be a gigabyte a suspect)
            for i, img in enumerate(frames):
                rec.set_time("frame", sequence=i)
                rec.log(path, rr.Image(img).compress(jpeg_quality=90))


def write_report_rrd(path: Path, table: pd.DataFrame, suspects: Sequence[Demo], embedding: np.ndarray,
                     embedded_rows: np.ndarray, fps: float, title: str, names: dict[str, list[str]] | None = None,
                     fpr: float | None = None, warnings: list[str] | None = None,
                     typical: Mapping[str, Demo] | None = None) -> None:
    """One recording with a reviewer's blueprint: the ranked list beside each suspect's evidence, the map and the
    score histograms.

    ``suspects`` are the top demos in rank order (read one at a time); ``embedding`` [M, 2] are t-SNE positions of
    ``table`` rows ``embedded_rows``; ``names``: the dataset's names of its ``state`` and ``action`` dimensions;
    ``fpr``: the flag's level (a bar on the suspicion histogram); ``warnings``: the audit's, at the head of the
    ranked list (an unreadable file among them); ``typical``: per task, a clean demo to show beside its suspects.
    """
    rec = rr.RecordingStream("democheck")
    rec.save(str(path))
    top = len(suspects)
    flagged = table["is_anomaly"].to_numpy(bool)
    text = suspects_markdown(table, max(top, 20), title, fpr, warnings, tabs=top)
    rec.log("suspects", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
    if len(embedded_rows):
        sub = table.iloc[embedded_rows]
        labels = [f"#{r} ep{e}: {t}" for r, e, t in zip(sub["rank"], sub["episode_index"], sub["task"])]
        rec.log("map/demos", rr.Points2D(embedding, radii=0.6, colors=_ramp(sub["suspicion"].to_numpy()),
                                         labels=labels, show_labels=False, draw_order=1.0), static=True)
        is_flagged = flagged[embedded_rows]
        if is_flagged.any():
            named = np.flatnonzero(is_flagged)[:MAP_LABELS]  # rows are in rank order: the most suspect
            rec.log("map/flagged", rr.Points2D(embedding[is_flagged], radii=1.1, colors=FLAG_RED,
                                               labels=[f"#{r} ep{e}" for r, e in zip(sub["rank"][is_flagged],
                                                                                   sub["episode_index"][is_flagged])],
                                               show_labels=False, draw_order=2.0), static=True)
            rec.log("map/named", rr.Points2D(embedding[named], radii=1.1, colors=FLAG_RED, draw_order=3.0,
                                             labels=[f"#{r}" for r in sub["rank"].to_numpy()[named]],
                                             show_labels=True), static=True)
    hist_views = []
    for name, log10 in HISTOGRAMS.items():
        if name not in table:
            continue
        values = table[name].to_numpy(np.float64)
        level = None
        if name == "suspicion":
            values = np.log10(1 + np.maximum(values, 0))
            p = flag_level(table, fpr) if fpr is not None else None
            level = np.log10(1 - np.log10(p)) if p else None  # p of 0: below what a float holds, no bar
            what = "suspicion, log10(1+x)"
        else:
            if log10:
                values = np.log10(np.maximum(values, 1e-12))
            what = name.replace("_", " ") + (", log10" if log10 else "")
        _histogram(rec, f"scores/{name}", values, flagged, level=level)
        hist_views.append(rrb.BarChartView(origin=f"scores/{name}", name=what, plot_legend=rrb.PlotLegend(visible=False)))
    sigma = np.stack(table["sigma"].to_numpy()) if len(table) and "sigma" in table else None
    typical_sigma = np.median(sigma[~flagged] if (~flagged).any() else sigma, axis=0) if sigma is not None else None
    shown = {}  # task -> the typical demo's entity path and episode
    for k, (task, demo) in enumerate((typical or {}).items()):
        shown[task] = (f"typical/{k:03d}", demo.episode_index, bool(demo.frames.size))
        _log_demo(rec, shown[task][0], demo, None, fps, names)
    recipe = ranking_recipe()["scores"]
    cols = [c for c in table.columns if check_of(c) in recipe]  # each ranked check, on every camera
    tabs = []
    for demo, row in zip(suspects, table.head(top).to_dict(orient="records")):
        base = suspect_path(row["rank"], row["episode_index"])
        other = shown.get(row["task"])
        rec.log(f"{base}/about", rr.TextDocument(_suspect_markdown(row, cols, other and other[1]),
                                                 media_type=rr.MediaType.MARKDOWN), static=True)
        ratio = None if sigma is None else np.asarray(row["sigma"], np.float64) / np.maximum(typical_sigma, 1e-12)
        _log_demo(rec, base, demo, ratio, fps, names)
        plots = [rrb.TimeSeriesView(origin=f"{base}/{what}", name=what, plot_legend=rrb.PlotLegend(visible=False))
                 for what in ("actions", "state")]
        if sigma is not None:
            plots.insert(0, rrb.BarChartView(origin=f"{base}/sigma", name="sigma (1 = typical)",
                                             plot_legend=rrb.PlotLegend(visible=False)))
        top_row = [rrb.TextDocumentView(origin=f"{base}/about", name="why")]
        if demo.frames.size:
            first = f": {demo.extra['camera']}" if demo.extra.get("camera") else ""
            top_row.append(rrb.Spatial2DView(origin=f"{base}/video", name=f"ep {row['episode_index']}{first}"))
        cameras = [rrb.Spatial2DView(origin=f"{base}/cameras/{c}", name=f"ep {row['episode_index']}: {c}")
                   for c in demo.extra.get("cameras", {})]
        if cameras:  # the other cameras one above the other, beside the first
            top_row.append(rrb.Vertical(*cameras))
        if other is not None:
            plots.append(rrb.TimeSeriesView(origin=f"{other[0]}/actions", name=f"clean ep {other[1]}: actions",
                                            plot_legend=rrb.PlotLegend(visible=False)))
            if other[2]:
                top_row.append(rrb.Spatial2DView(origin=f"{other[0]}/video", name=f"clean ep {other[1]}"))
        tabs.append(rrb.Vertical(rrb.Horizontal(*top_row, column_shares=[4] + [3] * (len(top_row) - 1)),
                                 rrb.Horizontal(*plots), row_shares=[3, 2],
                                 name=f"#{row['rank']} ep{row['episode_index']}{' FLAGGED' if row['is_anomaly'] else ''}"))
    # Only the list itself: each suspect's "about" document lives under it too.
    left = [rrb.TextDocumentView(origin="suspects", contents="$origin", name="ranked suspects")]
    bottom = []
    if len(embedded_rows):
        bottom.append(rrb.Spatial2DView(origin="map", name="map of the task embedding"))
    if hist_views:
        bottom.append(rrb.Tabs(*hist_views, name="score histograms"))
    if bottom:
        left.append(rrb.Horizontal(*bottom))
    body_left = rrb.Vertical(*left, row_shares=[1, 1][:len(left)])
    body = rrb.Horizontal(body_left, rrb.Tabs(*tabs, name="suspects"), column_shares=[2, 3]) if tabs else body_left
    rec.send_blueprint(rrb.Blueprint(body, rrb.TimePanel(fps=fps, timeline="frame", state="collapsed"),
                                     collapse_panels=True))
    rec.flush()


def write_bench_rrd(path: Path, summary: dict, text: str) -> None:
    """The bench's figures: 5A (sigma per kind) as bar charts, one named bar per kind so the legend says which,
    5B (sigma vs number of cues) as a curve on the ``cues`` timeline.

    ``text`` is bench.md, shown beside them.
    """
    rec = rr.RecordingStream("democheck_bench")
    rec.save(str(path))
    fig_a = summary["figure_5a"]
    kinds = list(fig_a)
    text += "\nFigure 5A bars, left to right: " + ", ".join(kinds) + "\n"
    rec.log("bench", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
    colours = _ramp(np.arange(len(kinds), dtype=np.float64))
    for i, kind in enumerate(kinds):
        colour = [150, 150, 150] if kind == "clean" else colours[i].tolist()
        for stat in ("mean", "std"):
            rec.log(f"figure_5a/{stat}/{kind}", rr.BarChart([fig_a[kind][stat]], abscissa=[float(i)], widths=[0.8],
                                                            color=colour), static=True)
    curve = summary["figure_5b"]
    if curve:
        rec.log("figure_5b/mean_sigma", rr.SeriesLines(names="mean sigma of the product of N clean cues"),
                static=True)
        rec.send_columns("figure_5b/mean_sigma", indexes=[rr.TimeColumn("cues", sequence=[c["cues"] for c in curve])],
                         columns=rr.Scalars.columns(scalars=[c["mean_sigma"] for c in curve]))
    rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(
        rrb.TextDocumentView(origin="bench", name="AUROC"),
        rrb.Vertical(rrb.BarChartView(origin="figure_5a/mean", name="Figure 5A: mean sigma per kind (legend: kind)"),
                     rrb.BarChartView(origin="figure_5a/std", name="Figure 5A: spread (std) per kind")),
        rrb.TimeSeriesView(origin="figure_5b", name="Figure 5B: sigma vs number of cues"), column_shares=[2, 2, 1]),
        rrb.TimePanel(timeline="cues", state="collapsed"), collapse_panels=True))
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
    rec.send_blueprint(rrb.Blueprint(body, rrb.TimePanel(fps=fps, timeline="frame", state="collapsed"),
                                     collapse_panels=True))
    rec.flush()
