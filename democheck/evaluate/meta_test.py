"""Closed-loop meta-test (``democheck eval``): one-shot success from a cue, and whether uncertainty predicts failure.

For every task of a split, ``trials`` times: draw ``shots`` clean cue demos of
the task from the dataset, infer ``z = mu`` (product of Gaussians over the
shots; a TecNets model averages its normalised embeddings), and run the
controller in ``PushEnv`` for the episode length on a new layout; success is
the suite's rule (the target in the goal for ``SUCCESS_STEPS`` steps).  The
scripted expert runs on the very same layouts: the ceiling.

Each trial's cue carries its task standard deviation and the model's OCSVM
verdict, so success can be split by flagged/unflagged cue (the paper's
Figure 5C) and by sigma quartile.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from democheck.errors import DemocheckError

# Rollouts of trial 0 of every KEEP_EVERY-th task come back with their frames, for the recording.
KEEP_EVERY = 4


@dataclass
class Trial:
    task: str
    target: str
    distractor: str
    trial: int
    seed: int
    cues: list[int]
    z: list[float] = field(default_factory=list)
    sigma: float = float("nan")
    sigma_vec: list[float] = field(default_factory=list)
    ocsvm_margin: float = float("nan")
    flagged: bool = False
    keep_frames: bool = False


def wilson(successes: int, n: int, z: float = 1.96) -> list[float]:
    """95% Wilson score interval of a success rate."""
    if n == 0:
        return [float("nan"), float("nan")]
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return [max(0.0, float(centre - half)), min(1.0, float(centre + half))]


def rate(success: np.ndarray) -> dict[str, Any]:
    s = np.asarray(success, bool)
    return {"success_rate": float(s.mean()) if len(s) else float("nan"), "n": int(len(s)),
            "ci95": wilson(int(s.sum()), len(s))}


def plan_trials(ds, split: str, trials: int, shots: int, seed: int) -> list[Trial]:
    """Trials of every task of ``split`` that has enough clean demos with sim records."""
    eps = ds.episodes
    if "sim" not in eps:
        raise DemocheckError(f"{ds.root}: no sim records; eval rolls out in the simulator and needs a suite made by "
                             "democheck synth")
    sel = eps[eps["split"] == split] if "split" in eps else eps[:0]
    if "label" in sel:
        sel = sel[sel["label"].fillna("clean") == "clean"]
    if not len(sel):
        raise DemocheckError(f"{ds.root}: no clean demos in split {split!r}")
    out = []
    for ti, (task, idx) in enumerate(sorted(sel.groupby("task").groups.items())):
        idx = sorted(int(e) for e in idx)
        if len(idx) < shots:
            continue
        sim = json.loads(eps.loc[idx[0], "sim"])
        for k in range(trials):
            rng = np.random.default_rng([seed, ti, k])
            cues = sorted(int(e) for e in rng.choice(idx, size=shots, replace=False))
            out.append(Trial(task=str(task), target=sim["target"], distractor=sim["distractor"], trial=k,
                             seed=int(np.random.SeedSequence([seed, ti, k, 1]).generate_state(1)[0]), cues=cues,
                             keep_frames=(k == 0 and ti % KEEP_EVERY == 0)))
    if not out:
        raise DemocheckError(f"{ds.root}: no task of split {split!r} has {shots} clean demos")
    return out


def infer_tasks(ds, ckpt, trials: list[Trial], device) -> None:
    """Fill each trial's z (and for PETNet its sigma and OCSVM verdict) from its cue demos."""
    from democheck.audit.scores import ocsvm_margin
    from democheck.petnet.train import task_posteriors

    eps = sorted({e for t in trials for e in t.cues})
    pos = {e: i for i, e in enumerate(eps)}
    mu, var = task_posteriors(ckpt.model, ds.cue_frames_many(eps), device)
    ref = (ckpt.meta.get("reference") or {}).get("ocsvm")
    for t in trials:
        rows = [pos[e] for e in t.cues]
        if ckpt.config.model_type == "tecnet":
            z = mu[rows].mean(0)
            t.z = (z / max(np.linalg.norm(z), 1e-12)).tolist()
            continue
        v = 1.0 / (1.0 / var[rows]).sum(0)
        t.z = (v * (mu[rows] / var[rows]).sum(0)).tolist()
        sig = np.sqrt(v)
        t.sigma, t.sigma_vec = float(sig.mean()), sig.tolist()
        if ref:
            t.ocsvm_margin = float(ocsvm_margin(ref, sig[None])[0])
            t.flagged = t.ocsvm_margin < 0


class ControllerPolicy:
    """The model's controller acting on the env's latest observation under a fixed task variable z."""

    def __init__(self, env, model, norm, z: np.ndarray):
        import torch

        self.env, self.model, self.norm = env, model, norm
        self.z = torch.as_tensor(np.asarray(z, np.float32))[None]

    def act(self) -> np.ndarray:
        import torch

        obs = self.env.last_obs
        frame = torch.from_numpy(np.ascontiguousarray(obs["image"]))[None, None]
        state = torch.from_numpy(self.norm.state(obs["state"]).astype(np.float32))[None, None]
        with torch.no_grad():
            y = self.model.controller.act(frame, state, self.z)[0, 0].numpy()
        return np.clip(self.norm.unaction(y), -1.0, 1.0).astype(np.float32)


def _eval_init(model: str, image_size: int) -> None:
    import torch

    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.sim.suite import _W
    from democheck.sim.variants import EnvCache

    torch.set_num_threads(1)  # one core per worker process
    _W.update(ckpt=load_checkpoint(model), envs=EnvCache(image_size))


def _eval_shard(job: tuple[int, int, list[Trial]]) -> list[dict[str, Any]]:
    from democheck.sim.catalog import OBJECTS
    from democheck.sim.expert import ScriptedExpert
    from democheck.sim.suite import _W, tick
    from democheck.sim.variants import record_demo

    _, steps, trials = job
    ckpt = _W["ckpt"]
    out = []
    for t in trials:
        env = _W["envs"].get(OBJECTS[t.target], OBJECTS[t.distractor])
        rec = record_demo(env, ControllerPolicy(env, ckpt.model, ckpt.norm, np.asarray(t.z)).act, steps, seed=t.seed)
        row = {"task": t.task, "trial": t.trial, "success": rec["success"],
               "final_distance": float(env.target_to_goal()), "steps_in_goal": int(env.steps_in_goal)}
        expert = ScriptedExpert(env)
        row["expert_success"] = record_demo(env, expert.act, steps, seed=t.seed)["success"]
        if t.keep_frames:
            row["frames"], row["actions"], row["state"] = rec["frames"], rec["actions"], rec["state"]
        out.append(row)
        tick()
    return out


def sigma_quartiles(sigma: np.ndarray, success: np.ndarray) -> list[dict[str, Any]]:
    """Success per quartile of cue sigma (1 = lowest uncertainty)."""
    if not np.isfinite(sigma).all() or len(sigma) < 4:
        return []
    edges = np.quantile(sigma, [0, 0.25, 0.5, 0.75, 1.0])
    q = np.clip(np.searchsorted(edges[1:-1], sigma, side="right"), 0, 3)
    return [{"quartile": i + 1, "sigma_range": [float(edges[i]), float(edges[i + 1])], **rate(success[q == i])}
            for i in range(4)]


def fmt_rate(r: dict[str, Any]) -> str:
    """``71.4% [66.7, 75.7] (n = 384)``; ``n/a (n = 0)`` for an empty group."""
    if not r["n"] or r["success_rate"] is None:
        return "n/a (n = 0)"
    lo, hi = r["ci95"]
    return f"{100 * r['success_rate']:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] (n = {r['n']})"


def markdown(summary: dict[str, Any]) -> str:
    s = summary
    pct = fmt_rate

    lines = ["# democheck eval", "", f"model: {s['model']} ({s['model_type']})  ", f"cues from: {s['dataset']}, "
             f"split {s['split']}, {s['shots']}-shot, {s['trials']} trials per task, {s['tasks']} tasks, seed {s['seed']}",
             "", "| | success (95% CI) |", "|---|---|", f"| model | {pct(s['model_success'])} |",
             f"| scripted expert, same layouts | {pct(s['expert'])} |"]
    if s.get("flagged") is not None:
        lines += [f"| cues flagged by the OCSVM | {pct(s['flagged'])} |", f"| cues not flagged | {pct(s['unflagged'])} |"]
    if s.get("sigma_quartiles"):
        lines += ["", "| cue sigma quartile | sigma range | success |", "|---:|---|---|"]
        for q in s["sigma_quartiles"]:
            lines.append(f"| {q['quartile']} | {q['sigma_range'][0]:.4f}..{q['sigma_range'][1]:.4f} | {pct(q)} |")
    lines += ["", "## Per task", "", "| task | success | expert |", "|---|---:|---:|"]
    for task, r in s["per_task"].items():
        lines.append(f"| {task} | {r['success']}/{r['trials']} | {r['expert']}/{r['trials']} |")
    return "\n".join(lines) + "\n"


def evaluate(model: str | Path | None, dataset: str | Path, out: str | Path, split: str = "test", trials: int = 6,
             shots: int = 1, workers: int = 2, seed: int = 0, device: str = "auto", force: bool = False,
             on_progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Run the meta-test and write eval.json, eval.md, trials.parquet and eval.rrd into ``out`` (atomically)."""
    import pandas as pd

    from democheck.audit.run import to_json
    from democheck.data import open_dataset
    from democheck.fsutil import atomic_output_dir
    from democheck.petnet.checkpoint import DEFAULT_MODEL, load_checkpoint
    from democheck.petnet.train import resolve_device
    from democheck.sim.suite import run_shards
    from democheck.viz.report import write_eval_rrd

    if min(trials, shots, workers) < 1:
        raise DemocheckError("--trials, --shots and --workers must be at least 1")
    model = Path(model) if model is not None else DEFAULT_MODEL
    ckpt = load_checkpoint(model, device=resolve_device(device))
    ds = open_dataset(dataset)
    if ds.image_shape[:2] != (ckpt.config.image_size,) * 2:
        raise DemocheckError(f"{ds.root}: {ds.image_shape[0]} px cues, the model takes {ckpt.config.image_size} px")
    plan = plan_trials(ds, split, trials, shots, seed)
    infer_tasks(ds, ckpt, plan, resolve_device(device))
    steps = int(ds.episodes["length"].iloc[0])
    by_task: dict[str, list[Trial]] = {}
    for t in plan:
        by_task.setdefault(t.task, []).append(t)
    jobs = [(i, steps, ts) for i, ts in enumerate(by_task.values())]
    t0 = time.perf_counter()
    rows = run_shards(jobs, _eval_shard, _eval_init, (str(model), ckpt.config.image_size), workers, len(plan),
                      on_progress)
    wall = time.perf_counter() - t0
    res = {(r["task"], r["trial"]): r for r in rows}
    table = pd.DataFrame([{**{k: v for k, v in asdict(t).items() if k not in ("keep_frames",)},
                           **{k: v for k, v in res[(t.task, t.trial)].items() if k not in ("frames", "actions", "state")}}
                          for t in plan])
    success = table["success"].to_numpy(bool)
    summary: dict[str, Any] = {
        "model": str(model), "model_type": ckpt.config.model_type, "dataset": str(ds.root), "split": split,
        "shots": shots, "trials": trials, "seed": seed, "tasks": len(by_task), "n_trials": len(plan),
        "model_success": rate(success), "expert": rate(table["expert_success"].to_numpy(bool)),
        "per_task": {task: {"success": int(g["success"].sum()), "expert": int(g["expert_success"].sum()),
                            "trials": int(len(g)), "cue_sigma": float(g["sigma"].mean())}
                     for task, g in table.groupby("task")},
        "wall_s": round(wall, 2), "rollouts_per_s": round(len(plan) / wall, 2),
    }
    summary["success_rate"], summary["ci95"] = summary["model_success"]["success_rate"], summary["model_success"]["ci95"]
    if ckpt.config.model_type == "petnet":
        flagged = table["flagged"].to_numpy(bool)
        summary["flagged"], summary["unflagged"] = rate(success[flagged]), rate(success[~flagged])
        summary["sigma_quartiles"] = sigma_quartiles(table["sigma"].to_numpy(float), success)
    summary = to_json(summary)
    kept = [(t, res[(t.task, t.trial)]) for t in plan if "frames" in res[(t.task, t.trial)]]
    with atomic_output_dir(out, force=force) as tmp:
        table.to_parquet(tmp / "trials.parquet", index=False)
        (tmp / "eval.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
        (tmp / "eval.md").write_text(markdown(summary))
        write_eval_rrd(tmp / "eval.rrd", summary, kept, ds.fps)
    return summary
