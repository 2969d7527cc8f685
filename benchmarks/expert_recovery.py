"""How well each scripted expert pushes, and recovers: from its own start, and from states it never chose.

    python benchmarks/expert_recovery.py [--episodes 200] [--seed 0] [--action-noise 0.1] [--out FILE.json]

For every expert (``ScriptedExpert``, which keeps its phase with hysteresis, and ``MarkovianExpert``, which
decides it from the current state alone) and every condition, on the same tasks and layouts:

- ``plain``: an episode from the layout's start (``EPISODE_STEPS`` steps);
- ``arm``: after 0-60 expert steps, the arm is thrown to a random pose it can be in (home + 0.35 rad SD per
  joint, at rest; poses that penetrate the table or an object, or put the fingertip under 3 cm, are drawn again);
- ``object``: after 0-60 expert steps, the target is moved 2-6 cm in a random direction (kept in the
  workspace, clear of the distractor);
- ``both``: the two at once.

After a perturbation the expert gets a fresh ``EPISODE_STEPS`` and success is counted from there (the target in
the goal for ``SUCCESS_STEPS`` steps, as the suite counts it).  Printed: success with its 95% Wilson interval,
and for ``plain`` how often the expert's labels depend on more than the state: the share of steps at which a
fresh expert, handed a copy of the simulator's state, would act differently (by more than 1e-6).
``--action-noise`` adds a recipe's DART noise to every executed action (the expert's own action is what it would
record).  Tasks are the suite's training tasks (``make_tasks`` with push-v1's seed); no images are rendered.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import mujoco
import numpy as np

from democheck.evaluate.meta_test import wilson
from democheck.sim import scene
from democheck.sim.catalog import make_tasks
from democheck.sim.env import EPISODE_STEPS, PushEnv
from democheck.sim.variants import EXPERTS
CONDITIONS = ("plain", "arm", "object", "both")
ARM_SD = 0.35
SHIFT = (0.02, 0.06)


def perturb(env: PushEnv, rng: np.random.Generator, arm: bool, obj: bool) -> None:
    d = env.data
    if arm:
        # A pose the arm can be in: nothing penetrates anything, the fingertip above the table.
        before = d.qpos[env._arm_qadr].copy()
        for _ in range(1000):
            d.qpos[env._arm_qadr] = scene.ARM_HOME + rng.normal(0.0, ARM_SD, 7)
            mujoco.mj_forward(env.model, d)
            if env.tip_pos[2] > 0.03 and all(d.contact[i].dist > -1e-3 for i in range(d.ncon)):
                break
        else:
            d.qpos[env._arm_qadr] = before
        d.qvel[env.arm_dofs] = 0.0
    if obj:
        q = env._obj_qadr["target"]
        other = d.qpos[env._obj_qadr["distractor"][:2]]
        lo, hi = scene.WORKSPACE[:, 0] - 0.04, scene.WORKSPACE[:, 1] + 0.04
        for _ in range(100):
            angle, step = rng.uniform(0, 2 * np.pi), rng.uniform(*SHIFT)
            xy = d.qpos[q[:2]] + step * np.array([np.cos(angle), np.sin(angle)])
            clear = env.target.radius + env.distractor.radius + 0.02
            if (lo <= xy).all() and (xy <= hi).all() and np.linalg.norm(xy - other) > clear:
                d.qpos[q[:2]] = xy
                break
    mujoco.mj_forward(env.model, d)
    env.steps_in_goal = 0


def fresh_action(twin: PushEnv, env: PushEnv, kind: type) -> np.ndarray:
    """What a new expert of ``kind`` does in a copy of ``env``'s current simulator state."""
    mujoco.mj_copyData(twin.data, env.model, env.data)
    return kind(twin).act()


def episode(env: PushEnv, expert, layout_seed: int, condition: str, rng: np.random.Generator,
            twin: PushEnv | None = None, action_noise: float = 0.0) -> tuple[bool, int, int]:
    """(success, steps at which a fresh expert on the same state acts differently, steps checked)."""
    noise = np.random.default_rng([layout_seed, 0xDA27])
    env.reset(seed=layout_seed)
    expert.reset()
    if condition != "plain":
        for _ in range(int(rng.integers(0, 61))):
            env.step(expert.act())
        perturb(env, rng, condition in ("arm", "both"), condition in ("object", "both"))
    differ = checked = 0
    for _ in range(EPISODE_STEPS):
        a = expert.act()
        if twin is not None:
            differ += int(np.abs(fresh_action(twin, env, type(expert)) - a).max() > 1e-6)
            checked += 1
        _, _, _, _, info = env.step(a + noise.normal(0.0, action_noise, a.shape) if action_noise else a)
        if info["success"]:
            return True, differ, checked
    return bool(info["success"]), differ, checked


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=200, help="per expert and condition")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--experts", default=",".join(EXPERTS))
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--action-noise", type=float, default=0.0, help="DART noise on every executed action")
    ap.add_argument("--out", type=Path, default=None, help="also write the numbers as JSON")
    args = ap.parse_args()
    tasks = [t for t in make_tasks(400, 40, 64, seed=0) if t.split == "train"]
    pick = np.random.default_rng([args.seed, 1]).choice(len(tasks), args.episodes)
    results = {}
    env = None
    for name in args.experts.split(","):
        for condition in args.conditions.split(","):
            rng = np.random.default_rng([args.seed, 2, CONDITIONS.index(condition)])  # same draws per expert
            wins, differ, checked, t0 = [], 0, 0, time.perf_counter()
            for k in pick:
                task = tasks[int(k)]
                if env is None:
                    env, twin = PushEnv(task, render_images=False), PushEnv(task, render_images=False)
                else:
                    env.set_task(task)
                    twin.set_task(task)
                won, d, c = episode(env, EXPERTS[name](env), int(rng.integers(1 << 31)), condition, rng,
                                    twin if condition == "plain" else None, args.action_noise)
                wins.append(won)
                differ, checked = differ + d, checked + c
            lo, hi = wilson(sum(wins), len(wins))
            row = {"success": float(np.mean(wins)), "ci95": [lo, hi], "n": len(wins)}
            if checked:
                row["state_dependent_labels"] = 1.0 - differ / checked
            results[f"{name}/{condition}"] = row
            extra = f"; a fresh expert on the same state acts differently at {differ / checked:.1%} of steps" \
                if checked else ""
            print(f"{name:<11} {condition:<7} {np.mean(wins):6.1%} [{lo:.1%}, {hi:.1%}] of {len(wins)} "
                  f"({time.perf_counter() - t0:.0f} s){extra}", flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
