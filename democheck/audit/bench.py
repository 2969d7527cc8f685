"""``democheck bench``: how well each scorer tells every labelled kind of bad demo from the clean ones.

The datasets given are pooled (e.g. a suite with injected defects plus the
probes made from it); every demo keeps its task, so task consistency and the
kNN baseline compare it with the other demos of its task across the pool.
For every registered scorer (``democheck.audit.scorers``: democheck's own and
the baselines) and every label kind versus ``clean``: AUROC, AUPRC and
precision at k (k = the number of that kind).

Figure 5A of the paper: mean and spread of the task standard deviation per
kind.  Figure 5B: the task standard deviation of the product of Gaussians of
1..6 clean cues of one task.
"""

from __future__ import annotations

import functools

import time
from typing import Any, Callable

import numpy as np
import pandas as pd

from democheck.audit import scorers as registry
from democheck.audit.metrics import by_label
from democheck.audit.run import backwards_cues, for_model, gather_evidence, score_table
from democheck.data.demo import DemoSet
from democheck.errors import DemocheckError
from democheck.fsutil import to_json
from democheck.petnet.checkpoint import Checkpoint
from democheck.petnet.posterior import product_of_gaussians

MAX_CUES = 6


def figure_5a(table: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Mean, standard deviation and quartiles of the task standard deviation (task uncertainty) per label."""
    out = {}
    for kind, s in table.groupby("label")["task_uncertainty"]:
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
                _, v = product_of_gaussians(mu[pick], var[pick])
                vals.append(float(np.sqrt(v).mean()))
        if vals:
            out.append({"cues": n, "mean_sigma": float(np.mean(vals)), "std": float(np.std(vals)),
                        "tasks": int(sum(len(i) >= n for i in groups))})
    return out


def detection_table(table: pd.DataFrame, scorers: list[str]) -> dict[str, dict[str, dict[str, float]]]:
    """{scorer: {kind: {auroc, auprc, p_at_k, n}}} for every non-clean label (and ``all``) versus clean."""
    return {name: by_label(table, name) for name in scorers}


def verdicts(results: dict[str, dict[str, dict[str, float]]], kinds: list[str]) -> dict[str, dict[str, Any]]:
    """Per kind: democheck's best scorer and AUROC, the best baseline and AUROC, and whether ours is at least as good."""
    out = {}
    for kind in kinds:
        def best(names):  # the highest AUROC; of equals, the ranking (suspicion), else the first in the registry
            got = [(results[n][kind]["auroc"], n == "suspicion", -i, n) for i, n in enumerate(names) if n in results
                   and kind in results[n] and np.isfinite(results[n][kind]["auroc"])]
            top = max(got) if got else (float("nan"), False, 0, None)
            return top[0], top[3]
        ours = best([n for n, sc in registry.SCORERS.items() if sc.family == "democheck"])
        base = best([n for n, sc in registry.SCORERS.items() if sc.family == "baseline"])
        out[kind] = {"best_democheck": ours[1], "auroc": ours[0], "best_baseline": base[1],
                     "baseline_auroc": base[0], "democheck_at_least_as_good": bool(ours[0] >= base[0])}
    return out


def markdown(summary: dict[str, Any]) -> str:
    res = summary["scorers"]
    kinds = summary["kinds"]
    lines = ["# democheck bench", "", f"datasets: {', '.join(summary['datasets'])}  ",
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
    lines += ["", "## Scorers", ""] + [f"- `{n}`: {registry.SCORERS[n].description}" for n in res]
    return "\n".join(lines) + "\n"


def bench(sets: list[DemoSet], ckpt: Checkpoint, tecnet: Checkpoint | None = None, device: Any = "cpu",
          seed: int = 0, on_progress: Callable[[str, int, int], None] | None = None,
          labels: list[dict[int, str]] | None = None) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Score every demo of the pooled labelled datasets ``sets`` with every registered scorer the evidence can
    feed; returns the scores table (one row per demo, ranked) and the summary (bench.json).

    ``labels``: per dataset, episode index -> label (unlisted: clean), for data without democheck's sidecar
    labels; None: the sidecar's."""
    if not sets:
        raise DemocheckError("bench needs at least one labelled dataset")
    if tecnet is not None and tecnet.config.model_type != "tecnet":
        raise DemocheckError(f"{tecnet.path}: --tecnet needs a TecNets model (democheck train --recipe tecnet)")
    for ds in sets:
        for_model(ds, ckpt)  # refuses a dataset the model cannot read; the audit resizes the model's frames alone
    if labels is not None and len(labels) != len(sets):
        raise DemocheckError(f"{len(labels)} label files for {len(sets)} datasets; give one --labels per dataset")
    parts = []
    for i, ds in enumerate(sets):
        part = ds.episodes.reset_index().assign(dataset=str(ds.root))
        if labels is not None:
            part["label"] = part["episode_index"].map(labels[i]).fillna("clean")
        elif "label" not in part:
            raise DemocheckError(f"{ds.root}: no labels; bench needs labelled demos (democheck synth --defect-rate, "
                                 "democheck probe, or --labels FILE.csv with episode_index,label)")
        parts.append(part)
    t0 = time.perf_counter()
    episodes = pd.concat(parts, ignore_index=True)
    episodes["label"] = episodes["label"].fillna("clean").astype(str)
    episodes = episodes.rename(columns={"episode_index": "source_index"})
    episodes.insert(0, "episode_index", np.arange(len(episodes)))  # pooled id: unique across datasets
    seen = [ds.resized(ckpt.config.image_size) for ds in sets]  # as the model reads them
    ev = gather_evidence(sets, ckpt, registry.select(audit=False), device, tecnet=tecnet, episodes=episodes,
                         seed=seed, on_progress=on_progress,
                         backwards=functools.cache(lambda: backwards_cues(seen, ckpt.model, device)))
    table = score_table(ev)
    names = [n for n in registry.SCORERS if n in ev.scores]
    kinds = sorted(set(table["label"]) - {"clean"})
    if not kinds or "clean" not in set(table["label"]):
        raise DemocheckError("bench needs clean demos and at least one other label among the datasets given")
    results = detection_table(table, names)
    kinds_all = kinds + (["all"] if len(kinds) > 1 else [])
    clean = (episodes["label"] == "clean").to_numpy()
    post = ev.posterior.take(clean)
    summary = {
        "datasets": [str(ds.root) for ds in sets], "model": str(ckpt.path), "tecnet": str(tecnet.path) if tecnet else None,
        "labels": table["label"].value_counts().sort_index().to_dict(), "kinds": kinds_all,
        "scorers": results, "verdicts": verdicts(results, kinds_all),
        "figure_5a": figure_5a(table),
        "figure_5b": figure_5b(post.mu, post.var, episodes["task"].to_numpy()[clean], seed=seed),
        "notes": {n: registry.SCORERS[n].description for n in names}, "seed": seed,
        "wall_s": round(time.perf_counter() - t0, 3),
    }
    keep = ["episode_index", "dataset", "source_index", "task", "label", *names, "reason", "sigma", "mu"]
    return table[keep], to_json(summary)
