"""Recovery training (``democheck dagger``): DAgger rounds that teach the controller to recover from its own mistakes.

Works on PETNet and on the TecNets baseline alike, so the two compare on the same budget.

Behaviour cloning only shows the controller the expert's own states; once the
learned controller drifts off them it has never seen what to do, and errors
compound (on push-v1 a controller trained on demos alone pushes the target
home in about 4% of rollouts, on training tasks as on new ones).  Each round
here (Ross et al. 2011, DAgger):

1. rolls the current controller out on every training task, with ``z = mu`` of
   a demo of the task as the cue, handing each step to the scripted expert with
   probability ``beta`` (so rollouts stay near the task while visiting the
   controller's own states);
2. labels *every* visited state with the action the scripted expert takes there
   (``MarkovianExpert``: its action is a function of the state alone, so a state
   reached off the expert's own path gets the one label it would always get);
3. adds those episodes to the recovery set and trains the controller for
   ``steps`` more steps, each on a batch of demo timesteps plus a batch of
   recovery timesteps.

Only the controller learns.  The task encoder -- and with it sigma,
consistency, the stored score scales and the one-class SVM -- stays exactly
as trained; the audit's action error is then the new controller's.

The rounds, rollouts and optimiser come from a recipe, as ``train``'s do
(``load_recipe``: ``democheck/recipes/dagger/<name>.toml`` or a path, with
``--set key=value``).  Needs a democheck suite (sim records): the expert must
be able to act in the same scenes.  The run's state after each round (weights,
recovery episodes, RNG) lives in a work folder beside the output; ``resume``
continues from the last complete round.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from democheck import pool, resources
from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.errors import DemocheckError, RecipeError
from democheck.evaluate.rollout import ControllerPolicy, init_worker
from democheck.fsutil import atomic_output_dir, work_dir
from democheck.petnet.batches import Batches, task_rows, uniform_steps
from democheck.petnet.card import git_commit, model_card
from democheck.petnet.checkpoint import load_checkpoint, save_checkpoint
from democheck.petnet.encode import encode_rows
from democheck.petnet.recipe import parse_set
from democheck.petnet.run_state import load_state, save_state
from democheck.petnet.train import resolve_device
from democheck.sim.catalog import OBJECTS
from democheck.sim.expert import MarkovianExpert
from democheck.sim.variants import record_demo


DEFAULT_RECIPE = "dagger"
RECIPE_KEYS = ("rounds", "episodes_per_task", "beta", "steps", "batch_tasks", "timesteps", "lr", "seed")


@dataclass
class DaggerConfig:
    """A recovery run: the recipe's keys (``RECIPE_KEYS``) and the machine's (``workers``, ``device``)."""

    rounds: int = 4
    episodes_per_task: int = 1  # rollouts per training task per round
    beta: float = 0.3  # probability that the expert acts at a step of a rollout
    steps: int = 2000  # controller training steps per round
    batch_tasks: int = 16
    timesteps: int = 8
    lr: float = 5e-4
    seed: int = 0
    workers: int = 2
    device: str = "auto"


def load_recipe(name_or_path: str | Path = DEFAULT_RECIPE, sets: list[str] | None = None,
                **machine: Any) -> tuple[DaggerConfig, dict[str, Any]]:
    """The ``DaggerConfig`` of a recovery recipe (a shipped name or a path to a .toml file) with its ``--set
    key=value`` overrides and the machine's options that are not None (``workers``, ``device``), and the resolved
    recipe as a document."""
    path, doc = resources.read_recipe("dagger", name_or_path, "recovery")
    values = {k: v for k, v in doc.items() if k not in ("name", "description")}
    values.update(parse_set(item, "steps=500") for item in sets or [])
    where = f"{path}" + (" with --set " + " ".join(sets) if sets else "")
    unknown = sorted(set(values) - set(RECIPE_KEYS))
    if unknown:
        raise RecipeError(f"{where}: unknown key {', '.join(unknown)}; keys: {', '.join(RECIPE_KEYS)}")
    default = DaggerConfig()
    for key, v in values.items():
        want = type(getattr(default, key))
        if isinstance(v, bool) or not isinstance(v, (want, int) if want is float else want):
            raise RecipeError(f"{where}: {key} must be {want.__name__}, not {v!r}")
        values[key] = want(v)
    cfg = DaggerConfig(**values, **{k: v for k, v in machine.items() if v is not None})
    resolved = {"name": doc.get("name", path.stem), "description": doc.get("description", ""),
                "source": str(path) if path.parent != resources.recipe_dir("dagger") else path.stem,
                "set": list(sets or [])}
    return cfg, resolved


class MixedPolicy:
    """The learner acts, except on a ``beta`` share of steps where the expert does; the expert labels every step."""

    def __init__(self, learner: Callable[[], np.ndarray], expert, beta: float, seed: int):
        self.learner, self.expert, self.beta = learner, expert, beta
        self.rng = np.random.default_rng(seed)
        self.labels: list[np.ndarray] = []

    def act(self) -> np.ndarray:
        label = self.expert.act()  # a function of the current state alone (MarkovianExpert)
        self.labels.append(label)
        return label if self.rng.random() < self.beta else self.learner()


def _rollout_shard(job: tuple[int, int, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    _, steps, specs = job
    ckpt = pool.state["ckpt"]
    out = []
    for s in specs:
        env = pool.state["envs"].get(OBJECTS[s["target"]], OBJECTS[s["distractor"]])
        learner = ControllerPolicy(env, ckpt.model, ckpt.norm, np.asarray(s["z"], np.float32))
        policy = MixedPolicy(learner.act, MarkovianExpert(env), s["beta"], s["seed"])
        rec = record_demo(env, policy.act, steps, seed=s["seed"])
        out.append({"row": s["row"], "frames": rec["frames"], "state": rec["state"],
                    "labels": np.stack(policy.labels).astype(np.float32), "success": rec["success"]})
        pool.tick()
    return out


class RecoverySet:
    """The recovery episodes of all rounds so far: frames, normalised state and expert labels, and their task."""

    def __init__(self) -> None:
        self.parts: list[dict[str, np.ndarray]] = []

    def add(self, part: dict[str, np.ndarray]) -> None:
        self.parts.append(part)
        self._cat = {k: np.concatenate([p[k] for p in self.parts]) for k in part}

    def __len__(self) -> int:
        return sum(len(p["task"]) for p in self.parts)

    def sample(self, rng: np.random.Generator, n: int, k: int) -> dict[str, np.ndarray]:
        c = self._cat
        ep = rng.integers(0, len(c["task"]), n)
        t = rng.integers(0, c["frames"].shape[1], (n, k))
        return {"task": c["task"][ep], "frames": c["frames"][ep[:, None], t], "state": c["state"][ep[:, None], t],
                "actions": c["actions"][ep[:, None], t]}

    def save_last(self, folder: Path) -> None:
        """Write the newest round's episodes (earlier rounds are there already)."""
        folder.mkdir(parents=True, exist_ok=True)
        for k, v in self.parts[-1].items():
            np.save(folder / f"round{len(self.parts) - 1}.{k}.npy", v)

    @classmethod
    def load(cls, folder: Path, rounds: int) -> "RecoverySet":
        rs = cls()
        for i in range(rounds):
            rs.add({k: np.load(folder / f"round{i}.{k}.npy", mmap_mode="r")
                    for k in ("task", "frames", "state", "actions")})
        return rs


def dagger(model_dir: str | Path, dataset: str | Path, out: str | Path, cfg: DaggerConfig, resume: bool = False,
           force: bool = False, command: str | None = None, cache_dir: Path | None = None,
           on_stage: Callable[[str], None] | None = None,
           on_progress: Callable[[int, int], None] | None = None,
           recipe: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run ``cfg.rounds`` recovery rounds on ``model_dir`` with the training tasks of ``dataset``; write ``out``
    (its card records ``recipe``, ``load_recipe``'s document, where given)."""
    if min(cfg.rounds, cfg.episodes_per_task, cfg.steps, cfg.batch_tasks, cfg.timesteps, cfg.workers) < 1:
        raise DemocheckError("rounds, episodes_per_task, steps, batch_tasks, timesteps and --workers must be at "
                             "least 1")
    if not 0.0 <= cfg.beta <= 1.0:
        raise DemocheckError(f"beta is a probability, not {cfg.beta}")
    out, model_dir = Path(out), Path(model_dir)
    work = work_dir(out, resume, force)
    device = resolve_device(cfg.device)
    ckpt = load_checkpoint(model_dir, device=device)
    ds = open_dataset(dataset).require_camera("recovery training")
    if "sim" not in ds.episodes:
        raise DemocheckError(f"{ds.root}: no sim records; recovery training needs the scripted expert to act in the "
                             "dataset's scenes, i.e. a suite made by democheck synth")
    arrays = build_cache(ds, cache_dir)
    if arrays.fingerprint != ckpt.meta.get("data", {}).get("fingerprint"):
        raise DemocheckError(f"{model_dir}: trained on other data than {ds.root}; recovery training continues a "
                             "model on its own training data")
    model, norm = ckpt.model, ckpt.norm
    meta = {k: v for k, v in ckpt.meta.items() if k not in ("format", "format_version", "model", "normalisation")}
    rows = task_rows(arrays, "train", int(ckpt.meta.get("training", {}).get("seed", 0)))
    batches = Batches(arrays, rows, norm)
    sims = {t: json.loads(ds.episodes.loc[int(arrays.episodes.loc[r[0], "episode_index"]), "sim"])
            for t, r in zip(batches.tasks, batches.rows)}
    steps_per_ep = int(arrays.lengths[batches.rows[0][0]])

    for p in model.encoder.parameters():  # the audit's half of the model stays as trained
        p.requires_grad_(False)
    model.encoder.eval()
    opt = torch.optim.Adam(model.controller.parameters(), lr=cfg.lr)
    rng = np.random.default_rng([cfg.seed, 17])
    torch.manual_seed(cfg.seed)
    recovery, history, done, wall_before = RecoverySet(), [], 0, 0.0
    if resume and any((work / d / "state.json").exists() for d in ("state", "state.old")):
        # Weights, Adam moments and both RNGs as after the last complete round (saved like train's state).
        done, rng, doc = load_state(work, model, opt)
        if doc["config"] != {**asdict(cfg), "rounds": doc["config"]["rounds"], "workers": doc["config"]["workers"]}:
            raise DemocheckError(f"{work}: saved with other options; resume with the same options")
        history, wall_before = doc["history"], doc["wall_s"]
        recovery = RecoverySet.load(work / "recovery", done)
    work.mkdir(parents=True, exist_ok=True)

    # z of every training demo once: the encoder does not change.
    all_rows = np.concatenate(batches.rows)
    post = encode_rows(model, arrays, all_rows, device)
    mu_all, var_all = post.mu, post.var
    row_of = {int(r): i for i, r in enumerate(all_rows)}
    t0 = time.perf_counter()
    for rd in range(done, cfg.rounds):
        save_checkpoint(work / "current", model, ckpt.config, norm, meta)  # what the workers roll out
        specs = []
        for ti, t in enumerate(batches.tasks):
            for _ in range(cfg.episodes_per_task):
                cue = int(rng.choice(batches.rows[ti]))
                specs.append({"row": ti, "target": sims[t]["target"], "distractor": sims[t]["distractor"],
                              "z": mu_all[row_of[cue]].tolist(), "beta": cfg.beta, "seed": int(rng.integers(1 << 31))})
        if on_stage:
            on_stage(f"round {rd + 1}/{cfg.rounds}: rollouts")
        jobs = [(i, steps_per_ep, specs[i::cfg.workers * 4]) for i in range(min(len(specs), cfg.workers * 4))]
        res = sorted(pool.run_shards(jobs, _rollout_shard, init_worker, (str(work / "current"), ckpt.config.image_size),
                                     cfg.workers, len(specs), on_progress), key=lambda r: r["row"])
        recovery.add({"task": np.array([r["row"] for r in res], np.int64),
                      "frames": np.stack([r["frames"] for r in res]),
                      "state": norm.state(np.stack([r["state"] for r in res])).astype(np.float32),
                      "actions": norm.action(np.stack([r["labels"] for r in res])).astype(np.float32)})
        mixed = float(np.mean([r["success"] for r in res]))
        if on_stage:
            on_stage(f"round {rd + 1}/{cfg.rounds}: training the controller ({len(recovery)} recovery episodes)")
        model.controller.train()
        run_demo = run_rec = None
        for step in range(cfg.steps):
            cue_rows, traj_rows = batches.pick_rows(rng, cfg.batch_tasks)
            demo = batches.gather(cue_rows, traj_rows, uniform_steps(rng, arrays.lengths[traj_rows], cfg.timesteps))
            rec = recovery.sample(rng, cfg.batch_tasks, cfg.timesteps)
            # z ~ N(mu, var) as in training: from each demo's cue, and from a demo of each recovery episode's task,
            # both looked up (the encoder is frozen).  A TecNets model's embedding is deterministic: "var" is zero.
            rec_cues = [rng.choice(batches.rows[ti]) for ti in rec["task"]]
            at = np.array([row_of[int(r)] for r in [*cue_rows, *rec_cues]])
            mu, sd = torch.from_numpy(mu_all[at]).to(device), torch.from_numpy(np.sqrt(var_all[at])).to(device)
            z = mu + sd * torch.randn_like(sd)
            n = cfg.batch_tasks
            frames = torch.from_numpy(np.concatenate([demo["frames"], rec["frames"]])).to(device)
            state = torch.from_numpy(np.concatenate([demo["state"], rec["state"]]).astype(np.float32)).to(device)
            target = torch.from_numpy(np.concatenate([demo["actions"], rec["actions"]]).astype(np.float32)).to(device)
            err = ((model.controller.act(frames, state, z) - target) ** 2).mean(dim=(1, 2))
            loss = err.mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            d, r = float(err[:n].mean().detach()), float(err[n:].mean().detach())
            run_demo = d if run_demo is None else 0.98 * run_demo + 0.02 * d
            run_rec = r if run_rec is None else 0.98 * run_rec + 0.02 * r
            if on_progress:
                on_progress(step + 1, cfg.steps)
        history.append({"round": rd + 1, "rollouts": len(res), "mixed_success": round(mixed, 4),
                        "demo_mse": round(run_demo, 4), "recovery_mse": round(run_rec, 4)})
        done = rd + 1
        recovery.save_last(work / "recovery")  # before the state that counts the round: a kill redoes the round
        save_state(work, model, opt, done, rng, {"config": asdict(cfg), "history": history,
                                                 "wall_s": wall_before + time.perf_counter() - t0})
    wall = wall_before + time.perf_counter() - t0
    summary = {"base_model": str(model_dir), "dataset": str(ds.root), "recipe": recipe, "config": asdict(cfg),
               "history": history,
               "wall_s": round(wall, 1), "command": command, "commit": git_commit(Path(__file__).parent)}
    meta["recovery"] = summary
    meta["extra_sections"] = [recovery_section(summary)] + [
        s for s in meta.get("extra_sections", []) if not s.startswith("## Recovery training")]
    with atomic_output_dir(out, force=True) as tmp:
        save_checkpoint(tmp, model, ckpt.config, norm, meta, model_card(out.name, meta))
    shutil.rmtree(work, ignore_errors=True)
    return summary


def recovery_section(summary: dict[str, Any]) -> str:
    """The model card's account of the recovery rounds."""
    c = summary["config"]
    lines = ["## Recovery training", "",
             f"The controller was then trained further by {c['rounds']} DAgger rounds on the training tasks "
             f"(`democheck dagger`; the task encoder, hence sigma, consistency and the one-class SVM, unchanged):", "",
             f"    {summary.get('command') or '?'}", "",
             f"- from `{summary['base_model']}`, commit `{summary['commit']}`; per round {c['episodes_per_task']} "
             f"rollout(s) per task with the expert acting on {c['beta']:.0%} of steps, then {c['steps']} steps of "
             f"{c['batch_tasks']} demo + {c['batch_tasks']} recovery trajectories x {c['timesteps']} timesteps, "
             f"Adam lr {c['lr']}, seed {c['seed']}; wall time {summary['wall_s'] / 60:.1f} min", "",
             "| round | rollouts | mixed-rollout success | demo mse | recovery mse |", "|---:|---:|---:|---:|---:|"]
    lines += [f"| {h['round']} | {h['rollouts']} | {h['mixed_success']:.1%} | {h['demo_mse']:.4f} | "
              f"{h['recovery_mse']:.4f} |" for h in summary["history"]]
    return "\n".join(lines)
