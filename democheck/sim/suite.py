"""Suite recipes (``synth/*.toml``) and generation of a suite as a LeRobot v3 dataset.

Generation runs in ``spawn`` worker processes (each holds its own GL
context); each worker writes whole data/video files for a contiguous range of
episodes, and the parent writes ``meta/`` at the end.  Every episode's seed is
derived from (recipe seed, episode index, attempt), so the result does not
depend on the number of workers.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queue_mod
import time
import tomllib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from democheck.errors import RecipeError

SYNTH_DIR = Path(__file__).resolve().parents[2] / "synth"


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
    demos_per_task: int = 12
    steps: int = 100
    image_size: int = 64
    max_attempts: int = 5  # layouts the expert fails on are re-drawn, up to this many tries
    episodes_per_file: int = 50  # fixed, not tied to --workers: the encoder's output depends on the file's content
    # Demos replaced by a bad policy, labelled with its kind: (("idle", 4), ("random", 4)).
    plant: tuple[tuple[str, int], ...] = ()
    pix_fmt: str = "yuv444p"
    crf: int = 20

    @property
    def n_tasks(self) -> int:
        return self.train_tasks + self.val_tasks + self.test_tasks

    @property
    def n_episodes(self) -> int:
        return self.n_tasks * self.demos_per_task

    def with_overrides(self, tasks: int | None = None, demos: int | None = None, steps: int | None = None,
                       size: int | None = None, seed: int | None = None,
                       plant: dict[str, int] | None = None) -> "Recipe":
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
        if plant is not None:
            r = replace(r, plant=tuple(sorted(plant.items())))
        r.validate()
        return r

    def validate(self) -> None:
        problems = []
        if self.train_tasks < 1:
            problems.append("at least one training task")
        if min(self.val_tasks, self.test_tasks) < 0:
            problems.append("non-negative val/test task counts")
        if self.demos_per_task < 1:
            problems.append("at least one demo per task")
        if self.steps < 2:
            problems.append("at least 2 steps per episode")
        if not 8 <= self.image_size <= 512:
            problems.append("an image size between 8 and 512")
        unknown = [k for k, _ in self.plant if k not in PLANT_POLICIES]
        if unknown:
            problems.append(f"plant kinds among {', '.join(PLANT_POLICIES)} (not {', '.join(unknown)})")
        if sum(n for _, n in self.plant) > self.n_episodes or any(n < 0 for _, n in self.plant):
            problems.append("between 0 and as many planted demos as there are episodes")
        if self.episodes_per_file < 1:
            problems.append("at least one episode per file")
        if self.pix_fmt not in ("yuv444p", "yuv420p"):
            problems.append("pix_fmt yuv444p or yuv420p")
        if self.pix_fmt == "yuv420p" and self.image_size % 2:
            problems.append("an even image size with yuv420p")
        if problems:
            raise RecipeError(f"recipe {self.name!r} needs " + "; ".join(problems))


def _apportion(total: int, weights: list[int]) -> list[int]:
    """Split ``total`` in proportion to ``weights`` (largest remainder), each non-empty share at least 1."""
    if total < 1:
        raise RecipeError("--tasks must be at least 1")
    w = np.asarray(weights, dtype=float)
    raw = total * w / w.sum()
    out = np.floor(raw).astype(int)
    for i in np.argsort(-(raw - out))[: total - out.sum()]:
        out[i] += 1
    # Keep every split that the recipe has, when there are enough tasks to go round.
    for i in range(len(out)):
        if w[i] > 0 and out[i] == 0 and total >= int((w > 0).sum()):
            j = int(np.argmax(out))
            out[j] -= 1
            out[i] += 1
    return [int(v) for v in out]


def available_recipes() -> list[str]:
    return sorted(p.stem for p in SYNTH_DIR.glob("*.toml"))


def load_recipe(name_or_path: str) -> Recipe:
    """A recipe by name (``synth/<name>.toml``) or by path to a TOML file."""
    path = Path(name_or_path)
    if not (path.suffix == ".toml" and path.exists()):
        path = SYNTH_DIR / f"{name_or_path}.toml"
    if not path.exists():
        raise RecipeError(f"no suite recipe {name_or_path!r}; known: {', '.join(available_recipes()) or 'none'}"
                          " (or give a path to a .toml file)")
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RecipeError(f"{path}: not valid TOML ({exc})") from None
    flat: dict[str, Any] = {"name": doc.get("name", path.stem)}
    for key in ("seed", "description"):
        if key in doc:
            flat[key] = doc[key]
    sections = {"tasks": {"train": "train_tasks", "val": "val_tasks", "test": "test_tasks",
                          "test_object_fraction": "test_object_fraction"},
                "episodes": {"demos_per_task": "demos_per_task", "steps": "steps", "image_size": "image_size",
                             "max_attempts": "max_attempts"},
                "video": {"pix_fmt": "pix_fmt", "crf": "crf", "episodes_per_file": "episodes_per_file"}}
    if "plant" in doc:
        flat["plant"] = tuple(sorted((str(k), int(v)) for k, v in doc["plant"].items()))
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


class IdlePolicy:
    """A recording where the arm never moves: zero torque (the arm holds still, gravity compensated)."""

    def __init__(self, env, seed: int):
        self.action_dim = env.action_space.shape[0]

    def act(self) -> np.ndarray:
        return np.zeros(self.action_dim, np.float32)


class RandomPolicy:
    """Random torques, low-pass filtered so the arm flails like a confused operator rather than vibrating."""

    def __init__(self, env, seed: int, smoothing: float = 0.85, scale: float = 0.6):
        self.rng = np.random.default_rng(seed)
        self.a = np.zeros(env.action_space.shape[0])
        self.smoothing, self.scale = smoothing, scale

    def act(self) -> np.ndarray:
        self.a = self.smoothing * self.a + (1 - self.smoothing) * self.rng.normal(0, 3 * self.scale, self.a.shape)
        return np.clip(self.a, -1.0, 1.0).astype(np.float32)


PLANT_POLICIES = {"idle": IdlePolicy, "random": RandomPolicy}


def planted_episodes(recipe: Recipe) -> dict[int, str]:
    """Which episodes the recipe replaces by a bad policy, chosen by the recipe's seed."""
    total = sum(n for _, n in recipe.plant)
    if not total:
        return {}
    picks = np.random.default_rng([recipe.seed, 0xBAD]).choice(recipe.n_episodes, size=total, replace=False)
    kinds = [k for k, n in recipe.plant for _ in range(n)]
    return {int(e): k for e, k in zip(picks, kinds)}


# ---------------------------------------------------------------------------
# workers
# ---------------------------------------------------------------------------

_W: dict[str, Any] = {}


def _worker_init(recipe: Recipe, root: str, progress: Any) -> None:
    from democheck.sim.catalog import make_tasks

    tasks = make_tasks(recipe.train_tasks, recipe.val_tasks, recipe.test_tasks, recipe.seed,
                       recipe.test_object_fraction)
    names = sorted({t.name for t in tasks})
    _W.update(recipe=recipe, root=Path(root), progress=progress, env=None, tasks=tasks,
              task_index={n: i for i, n in enumerate(names)}, planted=planted_episodes(recipe))


def record_demo(env, policy: Callable[[], np.ndarray], steps: int, seed: int | None = None,
                layout: Any = None) -> dict[str, Any]:
    """Roll one episode out: observation t, then action t, for ``steps`` steps."""
    obs, info = env.reset(seed=seed, options={"layout": layout} if layout is not None else None)
    frames = np.empty((steps, env.image_size, env.image_size, 3), np.uint8)
    state = np.empty((steps, obs["state"].shape[0]), np.float32)
    env_state = np.empty((steps, 6), np.float32)
    actions = np.empty((steps, env.action_space.shape[0]), np.float32)
    for t in range(steps):
        frames[t], state[t], env_state[t] = obs["image"], obs["state"], env.object_state()
        actions[t] = policy()
        obs, _, _, _, info = env.step(actions[t])
    return {"frames": frames, "state": state, "env_state": env_state, "actions": actions,
            "success": bool(info["success"]), "layout": env.layout}


def _shard(job: tuple[int, int, list[tuple[int, int]]]) -> list[dict[str, Any]]:
    from democheck.data.demo import Demo
    from democheck.data.lerobot import VideoOptions, write_shard
    from democheck.sim.catalog import CATALOG_VERSION
    from democheck.sim.env import EPISODE_STEPS, PushEnv
    from democheck.sim.expert import ScriptedExpert
    from democheck.sim.scene import FPS, SCENE_VERSION

    file_index, first_index, episodes = job
    r: Recipe = _W["recipe"]
    tasks, task_index, planted = _W["tasks"], _W["task_index"], _W["planted"]
    demos, attempts_log = [], []
    for episode_index, task_id in episodes:
        task = tasks[task_id]
        env = _W["env"]
        if env is None:
            env = _W["env"] = PushEnv(task, image_size=r.image_size)
        elif (env.target, env.distractor) != (task.target, task.distractor):
            env.set_task(task)
        kind = planted.get(episode_index)
        if kind is None:
            expert = ScriptedExpert(env)
            # Re-draw layouts the expert fails on (only when episodes are long enough to succeed).
            tries = r.max_attempts if r.steps >= EPISODE_STEPS else 1
            for attempt in range(tries):
                seed = episode_seed(r.seed, episode_index, attempt)
                expert.reset()
                rec = record_demo(env, expert.act, r.steps, seed=seed)
                if rec["success"]:
                    break
        else:
            attempt, seed = 0, episode_seed(r.seed, episode_index, 0)
            rec = record_demo(env, PLANT_POLICIES[kind](env, seed).act, r.steps, seed=seed)
        attempts_log.append(attempt + 1)
        sim = {"suite": r.name, "catalog_version": CATALOG_VERSION, "scene_version": SCENE_VERSION,
               "target": task.target.key, "distractor": task.distractor.key, "seed": seed, "attempt": attempt,
               "image_size": r.image_size, "steps": r.steps, "policy": kind or "expert",
               "layout": rec["layout"].to_dict()}
        demos.append(Demo(episode_index=episode_index, task=task.name, frames=rec["frames"], state=rec["state"],
                          actions=rec["actions"], success=rec["success"], label=kind or "clean", split=task.split,
                          sim=sim, env_state=rec["env_state"]))
        if _W["progress"] is not None:
            _W["progress"].put(1)
    rows = write_shard(_W["root"], file_index, demos, task_index, first_index, FPS, VideoOptions(r.pix_fmt, r.crf))
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
             on_progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Write the suite as a LeRobot v3 dataset under ``out`` (atomically); returns the summary."""
    from democheck.data.lerobot import VideoOptions, write_meta
    from democheck.fsutil import atomic_output_dir
    from democheck.sim.catalog import CATALOG_VERSION, make_tasks
    from democheck.sim.env import ACTION_NAMES, ENV_STATE_NAMES, STATE_NAMES
    from democheck.sim.scene import FPS, SCENE_VERSION

    recipe.validate()
    tasks = make_tasks(recipe.train_tasks, recipe.val_tasks, recipe.test_tasks, recipe.seed,
                       recipe.test_object_fraction)
    jobs = plan_shards(recipe)
    t0 = time.perf_counter()
    with atomic_output_dir(out, force=force) as tmp:
        rows: list[dict[str, Any]] = []
        ctx = mp.get_context("spawn")  # never fork a process that may hold a GL context
        progress_q = ctx.Queue() if on_progress else None
        done = 0
        if workers <= 1:
            _worker_init(recipe, str(tmp), None)
            for job in jobs:
                rows += _shard(job)
                done += len(job[2])
                if on_progress:
                    on_progress(done, recipe.n_episodes)
        else:
            with ctx.Pool(workers, initializer=_worker_init, initargs=(recipe, str(tmp), progress_q)) as pool:
                pending = pool.map_async(_shard, jobs, chunksize=1)
                while not pending.ready() or (progress_q is not None and not progress_q.empty()):
                    try:
                        done += progress_q.get(timeout=0.2) if progress_q is not None else 0
                        if on_progress:
                            on_progress(done, recipe.n_episodes)
                    except queue_mod.Empty:
                        pass
                    if progress_q is None:
                        pending.wait(0.2)
                for part in pending.get():
                    rows += part
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
            "planted": {k: n for k, n in recipe.plant},
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
