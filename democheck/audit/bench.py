"""``democheck bench``: how well each scorer tells every labelled kind of bad demo from the clean ones.

The datasets given are pooled (e.g. a suite with injected defects plus the
probes made from it); every demo keeps its task, so task consistency and the
kNN baseline compare it with the other demos of its task across the pool.
For every scorer and every label kind versus ``clean``: AUROC, AUPRC and
precision at k (k = the number of that kind).  Scorers: democheck's own
(sigma, the paper's; consistency; suspicion; the OCSVM flag, a single operating
point) and the baselines of ``democheck.audit.baselines``.

Figure 5A of the paper: mean and spread of the task standard deviation per
kind.  Figure 5B: the task standard deviation of the product of Gaussians of
1..6 clean cues of one task.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np
import pandas as pd

from democheck.errors import DemocheckError

OURS = ("sigma", "sigma_head", "consistency", "action_error", "suspicion", "ocsvm_flag")
BASELINES = ("tecnet_knn", "heuristic", "random")
SCORER_NOTES = {
    "sigma": "PETNet task uncertainty: mean task standard deviation of the cue, both parts of the variance",
    "sigma_head": "the paper's task uncertainty: sigma from the variance head alone, without the novelty part",
    "consistency": "distance of the cue's task mean from the other demos of its task (democheck)",
    "action_error": "how badly PETNet's controller, told the task by the other demos, explains the demo's actions",
    "suspicion": "max of sigma, consistency and action error, robustly standardised (democheck's ranking)",
    "ocsvm_flag": "linear one-class SVM flag, nu from the model (one operating point)",
    "tecnet_knn": "TecNets embedding: mean distance to the 5 nearest other demos of the task",
    "heuristic": "linter rules: max |robust z| of idle fraction, action energy, jerk",
    "random": "uniform random score",
}
MAX_CUES = 6


def figure_5a(table: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Mean, standard deviation and quartiles of the task standard deviation (score) per label."""
    out = {}
    for kind, s in table.groupby("label")["score"]:
        q = np.percentile(s, [25, 50, 75])
        out[str(kind)] = {"mean": float(s.mean()), "std": float(s.std(ddof=0)), "q25": float(q[0]),
                          "median": float(q[1]), "q75": float(q[2]), "n": int(len(s))}
    return out


def figure_5b(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray, draws: int = 20, seed: int = 0,
              max_cues: int = MAX_CUES) -> list[dict[str, float]]:
    """Mean task standard deviation of the product of Gaussians of n clean cues of one task, n = 1..max_cues."""
    rng = np.random.default_rng([seed, 0x5B])
    groups = [np.flatnonzero(tasks == t) for t in np.unique(tasks)]
    out = []
    for n in range(1, max_cues + 1):
        vals = []
        for idx in groups:
            if len(idx) < n:
                continue
            for _ in range(draws):
                pick = rng.choice(idx, size=n, replace=False)
                v = 1.0 / (1.0 / var[pick]).sum(0)
                vals.append(float(np.sqrt(v).mean()))
        if vals:
            out.append({"cues": n, "mean_sigma": float(np.mean(vals)), "std": float(np.std(vals)),
                        "tasks": int(sum(len(i) >= n for i in groups))})
    return out


def detection_table(table: pd.DataFrame, scorers: list[str]) -> dict[str, dict[str, dict[str, float]]]:
    """{scorer: {kind: {auroc, auprc, p_at_k, n}}} for every non-clean label (and ``all``) versus clean."""
    from democheck.audit.metrics import by_label

    return {name: by_label(table, name) for name in scorers}


def verdicts(results: dict[str, dict[str, dict[str, float]]], kinds: list[str]) -> dict[str, dict[str, Any]]:
    """Per kind: democheck's best scorer and AUROC, the best baseline and AUROC, and whether ours is at least as good."""
    out = {}
    for kind in kinds:
        def best(names):
            got = [(results[n][kind]["auroc"], n) for n in names if n in results and kind in results[n]
                   and np.isfinite(results[n][kind]["auroc"])]
            return max(got) if got else (float("nan"), None)
        ours, base = best(OURS), best(BASELINES)
        out[kind] = {"best_democheck": ours[1], "auroc": ours[0], "best_baseline": base[1],
                     "baseline_auroc": base[0], "democheck_at_least_as_good": bool(ours[0] >= base[0])}
    return out


def markdown(summary: dict[str, Any]) -> str:
    res = summary["scorers"]
    kinds = summary["kinds"]
    lines = [f"# democheck bench", "", f"datasets: {', '.join(summary['datasets'])}  ",
             f"model: {summary['model']}" + (f"; TecNets baseline: {summary['tecnet']}" if summary["tecnet"] else ""),
             "", "demos per label: " + ", ".join(f"{k} {n}" for k, n in summary["labels"].items()), ""]
    for metric, title in (("auroc", "AUROC"), ("auprc", "AUPRC"), ("p_at_k", "precision at k (k = number of the kind)")):
        lines += [f"## {title} (each kind versus clean)", "", "| scorer | " + " | ".join(kinds) + " |",
                  "|---|" + "---:|" * len(kinds)]
        for name, per in res.items():
            cells = [f"{per[k][metric]:.3f}" if per.get(k, {}).get(metric) is not None else "n/a" for k in kinds]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["## Best democheck scorer vs best baseline (AUROC)", "", "| kind | democheck | baseline | ours >= baseline |",
              "|---|---|---|:---:|"]
    for kind, v in summary["verdicts"].items():
        lines.append(f"| {kind} | {v['best_democheck']} {v['auroc']:.3f} | {v['best_baseline']} "
                     f"{v['baseline_auroc']:.3f} | {'yes' if v['democheck_at_least_as_good'] else 'NO'} |")
    lines += ["", "## Figure 5A: task standard deviation per kind", "", "| kind | n | mean | std | median |",
              "|---|---:|---:|---:|---:|"]
    for kind, f in summary["figure_5a"].items():
        lines.append(f"| {kind} | {f['n']} | {f['mean']:.4f} | {f['std']:.4f} | {f['median']:.4f} |")
    lines += ["", "## Figure 5B: task standard deviation vs number of clean cues (product of Gaussians)", "",
              "| cues | mean sigma | std | tasks |", "|---:|---:|---:|---:|"]
    for f in summary["figure_5b"]:
        lines.append(f"| {f['cues']} | {f['mean_sigma']:.4f} | {f['std']:.4f} | {f['tasks']} |")
    lines += ["", "## Scorers", ""] + [f"- `{n}`: {SCORER_NOTES[n]}" for n in res]
    return "\n".join(lines) + "\n"


def bench(datasets: list[str | Path], out: str | Path, model: str | Path | None = None,
          tecnet: str | Path | None = None, device: str = "auto", seed: int = 0, force: bool = False,
          camera: str | None = None,
          on_progress: Callable[[str, int, int], None] | None = None) -> dict[str, Any]:
    """Score every demo of the pooled ``datasets`` with every scorer and write bench.json/bench.md/bench.rrd."""
    import torch

    from democheck.audit.baselines import heuristic_score, heuristic_table, knn_same_task, random_score
    from democheck.audit.run import _counting, action_errors, check_compatible, controller_z, posteriors, to_json
    from democheck.audit.scores import score_table, task_score
    from democheck.data import open_dataset
    from democheck.fsutil import atomic_output_dir
    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.petnet.train import resolve_device
    from democheck.viz.report import write_bench_rrd

    if not datasets:
        raise DemocheckError("bench needs at least one labelled dataset")
    dev = resolve_device(device)
    ckpt = load_checkpoint(model, device=dev)
    tec = load_checkpoint(tecnet, device=dev) if tecnet is not None else None
    if tec is not None and tec.config.model_type != "tecnet":
        raise DemocheckError(f"{tecnet}: --tecnet needs a TecNets model (democheck train --model-type tecnet)")
    sets = [open_dataset(p, camera=camera) for p in datasets]
    for ds in sets:
        check_compatible(ds, ckpt)
        if "label" not in ds.episodes:
            raise DemocheckError(f"{ds.root}: no labels; bench needs labelled demos (democheck synth --defect-rate, "
                                 "democheck probe)")
    t0 = time.perf_counter()
    parts, mus, vars_, heads, feats, embs, errs = [], [], [], [], [], [], []

    def report(stage: str, ds) -> Callable[[int, int], None] | None:
        return (lambda d, n: on_progress(f"{stage} {ds.root.name}", d, n)) if on_progress else None

    for ds in sets:
        # Every per-demo array below is in ds.episode_indices order, the order of ds.episodes' rows.
        mu, var_task, var_novel = posteriors(ds, ckpt.model, dev, on_progress=report("PETNet", ds), parts=True)
        mus.append(mu)
        vars_.append(var_task + var_novel)
        heads.append(var_task)
        if tec is not None:
            embs.append(posteriors(ds, tec.model, dev, on_progress=report("TecNets", ds))[0])
        parts.append(ds.episodes.reset_index().assign(dataset=str(ds.root)))
    episodes = pd.concat(parts, ignore_index=True)
    episodes["label"] = episodes["label"].fillna("clean").astype(str)
    episodes = episodes.rename(columns={"episode_index": "source_index"})
    episodes.insert(0, "episode_index", np.arange(len(episodes)))  # pooled id: unique across datasets
    mu, var = np.concatenate(mus), np.concatenate(vars_)
    z = controller_z(mu, var, episodes["task"].to_numpy())  # each demo judged under its task across the pool
    start = 0
    for ds in sets:
        # One decoding pass: the controller sees the frames, the heuristic keeps only state and actions.
        light: list[SimpleNamespace] = []

        def each(ds=ds, light=light):
            for demo in _counting(ds, report("actions", ds)):
                light.append(SimpleNamespace(state=demo.state, actions=demo.actions))
                yield demo

        errs.append(action_errors(each(), ckpt, z[start:start + len(ds)], dev))
        feats.append(heuristic_table(light))
        start += len(ds)
    table = score_table(episodes, mu, var, ckpt.meta.get("reference"), np.concatenate(errs))
    order = table["episode_index"].to_numpy()  # score_table sorts by suspicion: map pooled ids back
    # The scorer "sigma" is the paper's score (mean task standard deviation); the vector moves to sigma_vec.
    table = table.rename(columns={"sigma": "sigma_vec"})
    table["sigma"] = table["score"]
    table["sigma_head"] = task_score(np.sqrt(np.concatenate(heads)))[order]
    table["ocsvm_flag"] = (table["ocsvm_margin"] < 0).astype(float)  # the paper's flag alone
    table["heuristic"] = heuristic_score(np.concatenate(feats))[order]
    table["random"] = random_score(len(table), seed)
    scorers = list(OURS)
    if tec is not None:
        emb = np.concatenate(embs)
        table["tecnet_knn"] = knn_same_task(emb, episodes["task"].to_numpy())[order]
        scorers.append("tecnet_knn")
    scorers += ["heuristic", "random"]
    table["dataset"] = episodes["dataset"].to_numpy()[order]
    table["source_index"] = episodes["source_index"].to_numpy()[order]
    kinds = sorted(set(table["label"]) - {"clean"})
    if not kinds or "clean" not in set(table["label"]):
        raise DemocheckError("bench needs clean demos and at least one other label among the datasets given")
    results = detection_table(table, scorers)
    kinds_all = kinds + (["all"] if len(kinds) > 1 else [])
    clean = (episodes["label"] == "clean").to_numpy()
    summary = {
        "datasets": [str(ds.root) for ds in sets], "model": str(ckpt.path), "tecnet": str(tec.path) if tec else None,
        "labels": table["label"].value_counts().sort_index().to_dict(), "kinds": kinds_all,
        "scorers": results, "verdicts": verdicts(results, kinds_all),
        "figure_5a": figure_5a(table),
        "figure_5b": figure_5b(mu[clean], var[clean], episodes["task"].to_numpy()[clean], seed=seed),
        "notes": {n: SCORER_NOTES[n] for n in scorers}, "seed": seed,
        "wall_s": round(time.perf_counter() - t0, 3),
    }
    summary = to_json(summary)
    with atomic_output_dir(out, force=force) as tmp:
        keep = ["episode_index", "dataset", "source_index", "task", "label", *scorers, "sigma_vec", "mu"]
        table[keep].to_parquet(tmp / "scores.parquet", index=False)
        (tmp / "bench.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
        text = markdown(summary)
        (tmp / "bench.md").write_text(text)
        write_bench_rrd(tmp / "bench.rrd", summary, text)
    return summary
