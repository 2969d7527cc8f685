"""Can a reactive policy clone the scripted expert at all?  The ceiling of `democheck eval`.

    python benchmarks/privileged_bc.py data/push-v1 [--inputs pose|xy] [--noise 0.1] [--tasks 60]

Trains a 3x256 MLP by behaviour cloning on the train split: robot state plus the *true* object
poses from ``observation.environment_state`` (``pose``: x, y, yaw of target and distractor;
``xy``: positions only), target first, so the task is given, not inferred.  ``--noise`` adds
Gaussian noise (in normalised units) to the object inputs while training, the robustness a
policy fed estimated positions would need.  Then rolls the policy out for 100 steps on
``--tasks`` random train tasks, each on a new layout, and prints the success rate with its
95% interval.  No images: what is left between this number and a PETNet controller is
perception and task inference.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from torch import nn

from democheck.evaluate.meta_test import wilson
from democheck.sim.catalog import OBJECTS
from democheck.sim.env import EPISODE_STEPS, PushEnv

COLUMNS = {"pose": [0, 1, 2, 3, 4, 5], "xy": [0, 1, 3, 4]}


def load_frames(suite: Path, episodes: list[int]) -> pd.DataFrame:
    """The state, object poses and actions of ``episodes`` of a LeRobot suite folder, one row per frame."""
    frames = pd.concat(pd.read_parquet(f, columns=["episode_index", "observation.state",
                                                   "observation.environment_state", "action"])
                       for f in sorted((suite / "data").glob("*/*.parquet")))
    return frames[frames["episode_index"].isin(episodes)]


class Policy:
    """A 3x256 MLP from robot state + object poses (``cols`` of the environment state) to normalised actions."""

    def __init__(self, x: np.ndarray, y: np.ndarray, cols: list[int]):
        self.cols = cols
        self.xm, self.xs, self.ym, self.ys = x.mean(0), x.std(0) + 1e-6, y.mean(0), y.std(0) + 1e-6
        self.net = nn.Sequential(nn.Linear(x.shape[1], 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                                 nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, y.shape[1]))

    def act(self, obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            a = self.net(torch.from_numpy(((obs - self.xm) / self.xs).astype(np.float32))[None])[0].numpy()
        return np.clip(a * self.ys + self.ym, -1.0, 1.0)


def train_policy(frames: pd.DataFrame, cols: list[int], steps: int, rng: np.random.Generator, noise: float = 0.0
                 ) -> tuple[Policy, float]:
    """Behaviour cloning on ``frames`` (``load_frames``), batches drawn from ``rng``; returns the policy and the
    last batch's mse."""
    x = np.concatenate([np.stack(frames["observation.state"].to_numpy()),
                        np.stack(frames["observation.environment_state"].to_numpy())[:, cols]], 1).astype(np.float32)
    y = np.stack(frames["action"].to_numpy()).astype(np.float32)
    policy = Policy(x, y, cols)
    xn = torch.from_numpy((x - policy.xm) / policy.xs)
    yn = torch.from_numpy((y - policy.ym) / policy.ys)
    n_state = x.shape[1] - len(cols)
    opt = torch.optim.Adam(policy.net.parameters(), 1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    loss = torch.zeros(())
    for _ in range(steps):
        i = torch.from_numpy(rng.integers(0, len(xn), 512))
        xb = xn[i].clone()
        xb[:, n_state:] += noise * torch.randn(len(i), len(cols))
        loss = ((policy.net(xb) - yn[i]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return policy, float(loss.item())


def rollouts(policy: Policy, tasks: list[tuple[str, str]], rng: np.random.Generator) -> list[bool]:
    """Success of ``policy`` on each (target, distractor) task of ``tasks``, each on a new layout drawn from
    ``rng`` (the same layouts for every policy given generators in the same state)."""
    env, wins = None, []
    for target, distractor in tasks:
        pair = (OBJECTS[target], OBJECTS[distractor])
        if env is None:
            env = PushEnv(pair, render_images=False)
        else:
            env.set_task(pair)
        env.reset(seed=int(rng.integers(1 << 31)))
        info = {}
        for _ in range(EPISODE_STEPS):
            obs = np.concatenate([env.state(), env.object_state()[policy.cols]])
            _, _, _, _, info = env.step(policy.act(obs))
        wins.append(bool(info["success"]))
    return wins


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", type=Path)
    ap.add_argument("--inputs", choices=sorted(COLUMNS), default="pose")
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--tasks", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    eps = pd.read_parquet(args.suite / "meta/democheck/episodes.parquet")
    eps = eps[(eps["split"] == "train") & (eps["label"].fillna("clean") == "clean")]
    frames = load_frames(args.suite, eps["episode_index"].tolist())
    t0 = time.perf_counter()
    policy, mse = train_policy(frames, COLUMNS[args.inputs], args.steps, rng, args.noise)
    print(f"trained {args.steps} steps on {len(frames)} frames in {time.perf_counter() - t0:.0f} s; "
          f"last batch mse {mse:.4f} (normalised actions)")
    picks = rng.choice(len(eps), size=min(args.tasks, len(eps)), replace=False)
    tasks = [(json.loads(eps.iloc[k]["sim"])["target"], json.loads(eps.iloc[k]["sim"])["distractor"]) for k in picks]
    wins = rollouts(policy, tasks, rng)
    lo, hi = wilson(sum(wins), len(wins))
    print(f"inputs {args.inputs}, noise {args.noise}: success {np.mean(wins):.1%} [{lo:.1%}, {hi:.1%}] "
          f"over {len(wins)} rollouts")


if __name__ == "__main__":
    main()
