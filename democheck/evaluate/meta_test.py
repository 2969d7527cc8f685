"""Closed-loop meta-test (``democheck eval``): one-shot success from a cue, and whether uncertainty predicts failure.

For every task of a split, ``trials`` times: draw ``shots`` clean cue demos of
the task from the dataset, infer ``z = mu`` (product of Gaussians over the
shots; a TecNets model averages its normalised embeddings), and run the
controller in ``PushEnv`` for the episode length on a new layout; success is
the suite's rule (the target in the goal for ``SUCCESS_STEPS`` steps).  The
scripted expert runs on the very same layouts: the ceiling.

Each trial's cue carries its task standard deviation and the model's OCSVM
verdict, so success can be split by flagged/unflagged cue (the paper's
Figure 5C) and by sigma quartile.  With a run-time gate (``petnet.gate``)
each trial also says whether the gate would have acted on its cue, and a
refused trial is asked for more demonstrations of its task, one at a time,
and rolled out again on the same layout once the gate accepts.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np
import pandas as pd

from democheck import pool
from democheck.audit.ocsvm import ocsvm_margin
from democheck.data.demo import DemoSet
from democheck.errors import DemocheckError
from democheck.evaluate.rollout import ControllerPolicy, init_worker
from democheck.fsutil import to_json
from democheck.petnet.checkpoint import Checkpoint
from democheck.petnet.gate import Gate
from democheck.petnet.encode import encode_demos
from democheck.sim.catalog import OBJECTS
from democheck.sim.expert import ScriptedExpert
from democheck.sim.variants import record_demo

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
    task_uncertainty: float = float("nan")  # of the cue(s): the mean of ``sigma``
    sigma: list[float] = field(default_factory=list)  # the task standard deviation per dimension
    ocsvm_margin: float = float("nan")
    flagged: bool = False
    keep_frames: bool = False
    spare_cues: list[int] = field(default_factory=list)  # more demos of the task, asked for in turn by the gate
    refused: bool = False  # the gate would not act on the first cue(s)
    asked: int = 0  # demonstrations the gate asked for beyond the first cue(s)
    gate_uncertainty: float = float("nan")  # task uncertainty of the cues the gate last saw
    gate_acted: bool = False  # the gate acted, at once or after asking
    gate_z: list[float] = field(default_factory=list)  # the task variable the gate acted with


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


def plan_trials(ds, split: str, trials: int, shots: int, seed: int, spare: int = 0) -> list[Trial]:
    """Trials of every task of ``split`` that has enough clean demos with sim records; each with up to ``spare``
    more clean demos of its task for a gate to ask for."""
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
            rest = [e for e in idx if e not in cues]
            spares = [int(e) for e in np.random.default_rng([seed, ti, k, 2]).permutation(rest)[:spare]]
            out.append(Trial(task=str(task), target=sim["target"], distractor=sim["distractor"], trial=k,
                             seed=int(np.random.SeedSequence([seed, ti, k, 1]).generate_state(1)[0]), cues=cues,
                             keep_frames=(k == 0 and ti % KEEP_EVERY == 0), spare_cues=spares))
    if not out:
        raise DemocheckError(f"{ds.root}: no task of split {split!r} has {shots} clean demos")
    return out


def infer_tasks(ds: DemoSet, ckpt: Checkpoint, trials: list[Trial], device, gate: Gate | None = None) -> None:
    """Fill each trial's z (and for PETNet its sigma and OCSVM verdict) from its cue demos; with a ``gate``, what
    it decides on them, asking for the trial's spare cues in turn while it refuses."""
    eps = sorted({e for t in trials for e in t.cues + t.spare_cues})
    pos = {e: i for i, e in enumerate(eps)}
    post = encode_demos(ckpt.model, ds, eps, device)
    ref = (ckpt.meta.get("reference") or {}).get("ocsvm")
    for t in trials:
        if gate is not None:
            shown = list(t.cues)
            decision = gate.decide(post.take([pos[e] for e in shown]))
            t.refused = not decision.act
            for extra in t.spare_cues[:max(0, gate.max_cues - len(t.cues))]:
                if decision.act:
                    break
                shown.append(extra)
                decision = gate.decide(post.take([pos[e] for e in shown]))
            t.asked, t.gate_acted = len(shown) - len(t.cues), decision.act
            t.gate_uncertainty, t.gate_z = decision.uncertainty, decision.z.tolist()
        cues = post.take([pos[e] for e in t.cues])
        if ckpt.config.model_type == "tecnet":
            z = cues.mu.mean(0)
            t.z = (z / max(np.linalg.norm(z), 1e-12)).tolist()
            continue
        z, v = cues.combined()
        t.z = z.tolist()
        sig = np.sqrt(v)
        t.task_uncertainty, t.sigma = float(sig.mean()), sig.tolist()
        if ref:
            t.ocsvm_margin = float(ocsvm_margin(ref, sig[None])[0])
            t.flagged = t.ocsvm_margin < 0


def _eval_shard(job: tuple[int, int, list[Trial], bool]) -> list[dict[str, Any]]:
    """Roll out each trial with its z (with ``asked``: the z the gate acted with after asking), and the expert."""
    _, steps, trials, asked = job
    ckpt = pool.state["ckpt"]
    out = []
    for t in trials:
        env = pool.state["envs"].get(OBJECTS[t.target], OBJECTS[t.distractor])
        z = np.asarray(t.gate_z if asked else t.z)
        rec = record_demo(env, ControllerPolicy(env, ckpt.model, ckpt.norm, z).act, steps, seed=t.seed)
        if asked:
            out.append({"task": t.task, "trial": t.trial, "success_after_asking": rec["success"]})
            pool.tick()
            continue
        row = {"task": t.task, "trial": t.trial, "success": rec["success"],
               "final_distance": float(env.target_to_goal()), "steps_in_goal": int(env.steps_in_goal)}
        expert = ScriptedExpert(env)
        row["expert_success"] = record_demo(env, expert.act, steps, seed=t.seed)["success"]
        if t.keep_frames:
            row["frames"], row["actions"], row["state"] = rec["frames"], rec["actions"], rec["state"]
        out.append(row)
        pool.tick()
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
    if s.get("gate"):
        g = s["gate"]
        at = (f"threshold {g['threshold']:.4g}: refuses {100 * g['false_refusal']:.0f}% of real cues by construction"
              if g["threshold"] is not None else f"no threshold: too few to promise {100 * g['false_refusal']:.0f}%")
        lines += ["", f"## The run-time gate ({at}, read from {g['reference_cues']} held-out cues)", "",
                  "| | success (95% CI) |", "|---|---|", f"| no gate: every cue | {pct(s['model_success'])} |",
                  f"| cues the gate acted on at once | {pct(g['executed'])} |",
                  f"| cues it refused, had they been run ({100 * g['refused_share']:.1f}% of cues) | "
                  f"{pct(g['refused_would_have'])} |",
                  f"| refused cues, after asking for more demonstrations (up to {g['max_cues']} cues) | "
                  f"{pct(g['after_asking'])} |",
                  f"| with the gate: every trial it acted on | {pct(g['gated'])} |",
                  f"| still refused at {g['max_cues']} cues | {g['still_refused']} trials |"]
    lines += ["", "## Per task", "", "| task | success | expert |", "|---|---:|---:|"]
    for task, r in s["per_task"].items():
        lines.append(f"| {task} | {r['success']}/{r['trials']} | {r['expert']}/{r['trials']} |")
    return "\n".join(lines) + "\n"


def gate_summary(gate: Gate, table: pd.DataFrame) -> dict[str, Any]:
    """What the gate did: success of the cues it acted on at once, the share it refused and what those cues
    scored when run anyway, and success once it acted after asking for more demonstrations (and how many it
    still refused at ``max_cues``)."""
    success = table["success"].to_numpy(bool)
    refused = table["refused"].to_numpy(bool)
    acted = table["gate_acted"].to_numpy(bool)
    after = table.get("success_after_asking", pd.Series(np.nan, index=table.index))
    asked_ok = refused & acted
    # Success under the gate: each trial it acted on, with the cues it acted on.
    gated = np.where(asked_ok, after.fillna(False).to_numpy(bool), success)[acted]
    return {"threshold": gate.threshold, "false_refusal": gate.false_refusal, "reference_cues": gate.reference_cues,
            "max_cues": gate.max_cues, "refused_share": float(refused.mean()) if len(refused) else float("nan"),
            "executed": rate(success[~refused]), "refused_would_have": rate(success[refused]),
            "after_asking": rate(after[asked_ok].to_numpy(bool)), "gated": rate(gated),
            "still_refused": int((~acted).sum()),
            "asked_mean": float(table.loc[refused, "asked"].mean()) if refused.any() else 0.0}


@dataclass
class MetaTest:
    """A meta-test's results: the summary (eval.json), one row per trial, and the rollouts kept with frames."""

    summary: dict[str, Any]
    trials: pd.DataFrame
    kept: list[tuple[Trial, dict[str, Any]]]


def meta_test(ckpt: Checkpoint, ds: DemoSet, split: str = "test", trials: int = 6, shots: int = 1, workers: int = 2,
              seed: int = 0, device: Any = "cpu", on_progress: Callable[[int, int], None] | None = None,
              gate: Gate | None = None) -> MetaTest:
    """Roll ``ckpt``'s controller out ``trials`` times on every task of ``split``, cued by ``shots`` clean demos
    of the task, with the scripted expert on the same layouts.  With a ``gate``, every trial is rolled out as
    well (what a refused cue would have scored), and a trial refused at first is rolled out again on its layout
    with the cues the gate acted on after asking for more."""
    if min(trials, shots, workers) < 1:
        raise DemocheckError("--trials, --shots and --workers must be at least 1")
    if ds.image_shape[:2] != (ckpt.config.image_size,) * 2:
        raise DemocheckError(f"{ds.root}: {ds.image_shape[0]} px cues, the model takes {ckpt.config.image_size} px")
    if gate is not None and ckpt.config.model_type != "petnet":
        raise DemocheckError(f"{ckpt.path}: a {ckpt.config.model_type} model has no task uncertainty to gate on")
    plan = plan_trials(ds, split, trials, shots, seed, spare=gate.max_cues - shots if gate is not None else 0)
    infer_tasks(ds, ckpt, plan, device, gate)
    steps = int(ds.episodes["length"].iloc[0])
    by_task: dict[str, list[Trial]] = {}
    for t in plan:
        by_task.setdefault(t.task, []).append(t)
    asked = [t for t in plan if t.asked and t.gate_acted]
    jobs = [(i, steps, ts, False) for i, ts in enumerate(by_task.values())]
    jobs += [(len(jobs) + i, steps, asked[i::workers], True) for i in range(min(workers, len(asked)))]
    t0 = time.perf_counter()
    rows = pool.run_shards(jobs, _eval_shard, init_worker, (str(ckpt.path), ckpt.config.image_size), workers,
                           len(plan) + len(asked), on_progress)
    wall = time.perf_counter() - t0
    res: dict[tuple[str, int], dict[str, Any]] = {}
    for r in rows:  # a trial's first rollout, and where the gate asked and acted, its second
        res.setdefault((r["task"], r["trial"]), {}).update(r)
    table = pd.DataFrame([{**{k: v for k, v in asdict(t).items() if k not in ("keep_frames",)},
                           **{k: v for k, v in res[(t.task, t.trial)].items() if k not in ("frames", "actions", "state")}}
                          for t in plan])
    if gate is not None and "success_after_asking" not in table:
        table["success_after_asking"] = None  # no refused trial was acted on after asking
    success = table["success"].to_numpy(bool)
    summary: dict[str, Any] = {
        "model": str(ckpt.path), "model_type": ckpt.config.model_type, "dataset": str(ds.root), "split": split,
        "shots": shots, "trials": trials, "seed": seed, "tasks": len(by_task), "n_trials": len(plan),
        "model_success": rate(success), "expert": rate(table["expert_success"].to_numpy(bool)),
        "per_task": {task: {"success": int(g["success"].sum()), "expert": int(g["expert_success"].sum()),
                            "trials": int(len(g)), "cue_sigma": float(g["task_uncertainty"].mean())}
                     for task, g in table.groupby("task")},
        "wall_s": round(wall, 2), "rollouts_per_s": round(len(plan) / wall, 2),
    }
    summary["success_rate"], summary["ci95"] = summary["model_success"]["success_rate"], summary["model_success"]["ci95"]
    if ckpt.config.model_type == "petnet":
        flagged = table["flagged"].to_numpy(bool)
        summary["flagged"], summary["unflagged"] = rate(success[flagged]), rate(success[~flagged])
        summary["sigma_quartiles"] = sigma_quartiles(table["task_uncertainty"].to_numpy(float), success)
    if gate is not None:
        summary["gate"] = gate_summary(gate, table)
    kept = [(t, res[(t.task, t.trial)]) for t in plan if "frames" in res[(t.task, t.trial)]]
    return MetaTest(to_json(summary), table, kept)
