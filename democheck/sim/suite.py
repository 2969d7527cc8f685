"""Suite recipes (``synth/*.toml``) and generation of a suite as a LeRobot v3 dataset.

Generation runs in ``spawn`` worker processes (each holds its own GL
context); each worker writes whole data/video files for a contiguous range of
episodes, and the parent writes ``meta/`` at the end.  Every episode's seed is
derived from (recipe seed, episode index, attempt), so the result does not
depend on the number of workers.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from democheck import pool, resources
from democheck.data.demo import Demo
from democheck.data.lerobot_write import VideoOptions, write_meta, write_shard
from democheck.errors import RecipeError
from democheck.fsutil import atomic_output_dir
from democheck.sim.catalog import CATALOG_VERSION, make_tasks
from democheck.sim.env import ACTION_NAMES, ENV_STATE_NAMES, EPISODE_STEPS, STATE_NAMES
from democheck.sim.scene import FPS, SCENE_VERSION
from democheck.sim.variants import (DEFECTS, EXPERTS, PLANT_KINDS, EnvCache, action_noise_for, make_policy,
                                    record_demo, sim_record)


@dataclass(frozen=True)
class Recipe:
    """What a suite is made of; every field can be set in the TOML file."""

    name: str
    seed: int = 0
    description: str = ""
    train_tasks: int = 400
    val_tasks: int = 40
    test_tasks: int = 64
    test_object_fraction: float = 0.2
    # Seed of the train/test object split; None: ``seed``.  A fresh meta-test set for a model trained on
    # another suite keeps that suite's split seed (its held-out objects) and changes ``seed``.
    split_seed: int | None = None
    demos_per_task: int = 12
    steps: int = 100
    image_size: int = 64
    max_attempts: int = 5  # layouts the expert fails on are re-drawn, up to this many tries
    episodes_per_file: int = 50  # fixed, not tied to --workers: the encoder's output depends on the file's content
    # Demos replaced by a bad operator or a semantic defect, labelled with its kind: (("idle", 4), ("random", 4)).
    defects: tuple[tuple[str, int], ...] = ()
    # And this share of all episodes replaced by the four semantic defects in equal parts.
    defect_rate: float = 0.0
    pix_fmt: str = "yuv444p"
    crf: int = 20
    # The scripted expert (``democheck.sim.variants.EXPERTS``): "hysteresis" keeps its phase from step to step
    # (push-v1); "markovian" decides it from the current state alone, so the same state always gets one label.
    expert: str = "hysteresis"
    # DART: Gaussian noise (normalised torque SD) on the executed action of the kinds the expert drives; the
    # expert's own action is recorded.
    action_noise: float = 0.0

    @property
    def n_tasks(self) -> int:
        return self.train_tasks + self.val_tasks + self.test_tasks

    @property
    def n_episodes(self) -> int:
        return self.n_tasks * self.demos_per_task

    def tasks(self) -> list:
        """The suite's tasks (``democheck.sim.catalog.Task``), train, then val, then test."""
        return make_tasks(self.train_tasks, self.val_tasks, self.test_tasks, self.seed, self.test_object_fraction,
                          split_seed=self.split_seed)

    def defect_counts(self) -> dict[str, int]:
        """How many episodes each kind replaces: the explicit counts plus ``defect_rate`` over the semantic ones."""
        counts = dict(self.defects)
        n_rate = int(round(self.defect_rate * self.n_episodes))
        if n_rate:
            for kind, n in zip(DEFECTS, _apportion(n_rate, [1] * len(DEFECTS), keep_all=False)):
                counts[kind] = counts.get(kind, 0) + n
        return {k: n for k, n in sorted(counts.items()) if n}

    def with_overrides(self, tasks: int | None = None, demos: int | None = None, steps: int | None = None,
                       size: int | None = None, seed: int | None = None,
                       defects: dict[str, int] | None = None, defect_rate: float | None = None) -> "Recipe":
        """Command-line overrides; ``tasks`` is the total, split in the recipe's proportions."""
        r = self
        if tasks is not None:
            r = replace(r, **dict(zip(("train_tasks", "val_tasks", "test_tasks"),
                                      _apportion(tasks, [r.train_tasks, r.val_tasks, r.test_tasks]))))
        if demos is not None:
            r = replace(r, demos_per_task=demos)
        if steps is not None:
            r = replace(r, steps=steps)
        if size is not None:
            r = replace(r, image_size=size)
        if seed is not None:
            r = replace(r, seed=seed)
        if defects is not None:
            r = replace(r, defects=tuple(sorted(defects.items())))
        if defect_rate is not None:
            r = replace(r, defect_rate=float(defect_rate))
        r.validate()
        return r

    def validate(self) -> None:
        problems = []
        if self.train_tasks < 0 or self.n_tasks < 1:
            problems.append("at least one task")
        if min(self.val_tasks, self.test_tasks) < 0:
            problems.append("non-negative val/test task counts")
        if self.demos_per_task < 1:
            problems.append("at least one demo per task")
        if self.steps < 2:
            problems.append("at least 2 steps per episode")
        if not 8 <= self.image_size <= 512:
            problems.append("an image size between 8 and 512")
        unknown = [k for k, _ in self.defects if k not in PLANT_KINDS]
        if unknown:
            problems.append(f"defect kinds among {', '.join(PLANT_KINDS)} (not {', '.join(unknown)})")
        if not 0.0 <= self.defect_rate <= 1.0:
            problems.append("a defect rate between 0 and 1")
        counts = self.defect_counts() if not unknown else {}
        if sum(counts.values()) > self.n_episodes or any(n < 0 for n in counts.values()):
            problems.append("between 0 and as many defective demos as there are episodes")
        if self.episodes_per_file < 1:
            problems.append("at least one episode per file")
        if self.expert not in EXPERTS:
            problems.append(f"an expert among {', '.join(EXPERTS)} (not {self.expert!r})")
        if not 0.0 <= self.action_noise <= 1.0:
            problems.append("an action noise between 0 and 1 (normalised torque)")
        if self.pix_fmt not in ("yuv444p", "yuv420p"):
            problems.append("pix_fmt yuv444p or yuv420p")
        if self.pix_fmt == "yuv420p" and self.image_size % 2:
            problems.append("an even image size with yuv420p")
        if problems:
            raise RecipeError(f"recipe {self.name!r} needs " + "; ".join(problems))


def _apportion(total: int, weights: list[int], keep_all: bool = True) -> list[int]:
    """Split ``total`` in proportion to ``weights`` (largest remainder); with ``keep_all`` each share at least 1."""
    if total < 1:
        raise RecipeError("--tasks must be at least 1")
    w = np.asarray(weights, dtype=float)
    raw = total * w / w.sum()
    out = np.floor(raw).astype(int)
    for i in np.argsort(-(raw - out))[: total - out.sum()]:
        out[i] += 1
    # Keep every split that the recipe has, when there are enough tasks to go round.
    for i in range(len(out) if keep_all else 0):
        if w[i] > 0 and out[i] == 0 and total >= int((w > 0).sum()):
            j = int(np.argmax(out))
            out[j] -= 1
            out[i] += 1
    return [int(v) for v in out]


def available_recipes() -> list[str]:
    return resources.recipe_names("synth")


def load_recipe(name_or_path: str) -> Recipe:
    """A recipe by name (``synth/<name>.toml``) or by path to a TOML file."""
    path, doc = resources.read_recipe("synth", name_or_path, "suite")
    flat: dict[str, Any] = {"name": doc.get("name", path.stem)}
    for key in ("seed", "description"):
        if key in doc:
            flat[key] = doc[key]
    sections = {"tasks": {"train": "train_tasks", "val": "val_tasks", "test": "test_tasks",
                          "test_object_fraction": "test_object_fraction", "split_seed": "split_seed"},
                "episodes": {"demos_per_task": "demos_per_task", "steps": "steps", "image_size": "image_size",
                             "max_attempts": "max_attempts", "expert": "expert", "action_noise": "action_noise"},
                "video": {"pix_fmt": "pix_fmt", "crf": "crf", "episodes_per_file": "episodes_per_file"}}
    defects = dict(doc.get("defects", {}))
    if "rate" in defects:
        flat["defect_rate"] = float(defects.pop("rate"))
    if defects:
        flat["defects"] = tuple(sorted((str(k), int(v)) for k, v in defects.items()))
    for section, fields in sections.items():
        for key, value in doc.get(section, {}).items():
            if key not in fields:
                raise RecipeError(f"{path}: unknown key [{section}] {key}")
            flat[fields[key]] = value
    try:
        recipe = Recipe(**flat)
    except TypeError as exc:
        raise RecipeError(f"{path}: {exc}") from None
    recipe.validate()
    return recipe


def episode_seed(seed: int, episode_index: int, attempt: int) -> int:
    return int(np.random.SeedSequence([seed, episode_index, attempt]).generate_state(1)[0])


def planted_episodes(recipe: Recipe) -> dict[int, str]:
    """Which episodes the recipe replaces by a bad operator or a defect, chosen by the recipe's seed."""
    counts = recipe.defect_counts()
    total = sum(counts.values())
    if not total:
        return {}
    picks = np.random.default_rng([recipe.seed, 0xBAD]).choice(recipe.n_episodes, size=total, replace=False)
    kinds = [k for k, n in counts.items() for _ in range(n)]
    return {int(e): k for e, k in zip(picks, kinds)}


def _suite_init(recipe: Recipe, root: str) -> None:
    tasks = recipe.tasks()
    names = sorted({t.name for t in tasks})
    pool.state.update(recipe=recipe, root=Path(root), envs=EnvCache(recipe.image_size), tasks=tasks,
              task_index={n: i for i, n in enumerate(names)}, planted=planted_episodes(recipe))


def _suite_shard(job: tuple[int, int, list[tuple[int, int]]]) -> list[dict[str, Any]]:
    file_index, first_index, episodes = job
    w = pool.state
    r: Recipe = w["recipe"]
    tasks, task_index, planted = w["tasks"], w["task_index"], w["planted"]
    demos, attempts_log = [], []
    for episode_index, task_id in episodes:
        task = tasks[task_id]
        kind = planted.get(episode_index, "expert")
        env = w["envs"].get(task.target, task.distractor, kind)
        # Re-draw layouts the expert fails on (only when episodes are long enough to succeed).
        tries = r.max_attempts if kind in ("expert", "occluded") and r.steps >= EPISODE_STEPS else 1
        for attempt in range(tries):
            seed = episode_seed(r.seed, episode_index, attempt)
            noise = action_noise_for(kind, r.action_noise)
            rec = record_demo(env, make_policy(kind, env, seed, expert=r.expert).act, r.steps, seed=seed,
                              action_noise=noise)
            if rec["success"]:
                break
        attempts_log.append(attempt + 1)
        sim = sim_record(r.name, task, kind, seed, rec["layout"], r.image_size, r.steps, attempt=attempt,
                         expert=r.expert, action_noise=noise)
        label = "clean" if kind == "expert" else kind
        demos.append(Demo(episode_index=episode_index, task=task.name, frames=rec["frames"], state=rec["state"],
                          actions=rec["actions"], success=rec["success"], label=label, split=task.split,
                          sim=sim, env_state=rec["env_state"]))
        pool.tick()
    rows = write_shard(w["root"], file_index, demos, task_index, first_index, FPS, VideoOptions(r.pix_fmt, r.crf))
    for row, n in zip(rows, attempts_log):
        row["attempts"] = n
    return rows


def plan_shards(recipe: Recipe) -> list[tuple[int, int, list[tuple[int, int]]]]:
    """Contiguous episode ranges, one data/video file each: (file_index, first frame index, [(episode, task)]).

    The partition depends on the recipe alone, so the files are identical whatever the number of workers.
    """
    n = recipe.n_episodes
    per = recipe.episodes_per_file
    episodes = [(e, e // recipe.demos_per_task) for e in range(n)]
    return [(f, s * recipe.steps, episodes[s:s + per]) for f, s in enumerate(range(0, n, per))]


def generate(recipe: Recipe, out: str | Path, workers: int = 2, force: bool = False,
             on_progress: Callable[[int, int], None] | None = None, engine: str = "local",
             ray_address: str | None = None) -> dict[str, Any]:
    """Write the suite as a LeRobot v3 dataset under ``out`` (atomically); returns the summary.  ``engine``
    "ray" runs the same shards in ``workers`` Ray actors (``pool.RayWorkers``) on the cluster at
    ``ray_address`` (default: a local instance): the same files."""
    recipe.validate()
    tasks = recipe.tasks()
    jobs = plan_shards(recipe)
    t0 = time.perf_counter()
    with atomic_output_dir(out, force=force) as tmp:
        rows = pool.run_on(engine, jobs, _suite_shard, _suite_init, (recipe, str(tmp)), workers, recipe.n_episodes,
                           on_progress, ray_address)
        wall = time.perf_counter() - t0
        expert_rows = [r for r in rows if r["label"] == "clean"]
        first_try = np.array([r["attempts"] == 1 for r in expert_rows])
        kept = np.array([bool(r["success"]) for r in expert_rows])
        splits = np.array([r["split"] for r in expert_rows])
        n_frames = int(sum(r["length"] for r in rows))
        summary = {
            "recipe": asdict(recipe),
            "catalog_version": CATALOG_VERSION,
            "scene_version": SCENE_VERSION,
            "tasks": {s: sum(t.split == s for t in tasks) for s in ("train", "val", "test")},
            "episodes": len(rows),
            "defects": recipe.defect_counts(),
            "frames": n_frames,
            "expert": {
                "first_attempt_success": float(first_try.mean()),
                "first_attempt_success_by_split": {s: float(first_try[splits == s].mean())
                                                   for s in ("train", "val", "test") if (splits == s).any()},
                "kept_success": float(kept.mean()),
                "attempts": int(sum(r["attempts"] for r in rows)),
            },
            "workers": workers,
            "wall_s": round(wall, 3),
            "frames_per_s": round(n_frames / wall, 1),
        }
        write_meta(tmp, rows, sorted({t.name for t in tasks}), FPS, recipe.image_size, STATE_NAMES, ACTION_NAMES,
                   ENV_STATE_NAMES, VideoOptions(recipe.pix_fmt, recipe.crf), suite=summary)
    return summary
