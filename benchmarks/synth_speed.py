"""Generation speed of ``democheck synth`` against a bare step-and-render loop, same run, same machine.

The bare loop runs the same scenes (same tasks, same episodes, same image size,
same number of spawn workers) but only steps the physics with random torques
and renders each frame: no expert, no recording, no encoding, no files.  The
ratio says how much of the machine generation leaves to its own overhead.

    python benchmarks/synth_speed.py --tasks 28 --demos 6 --workers 2 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import statistics
import tempfile
import time
from pathlib import Path


def _bare(job):
    """Step and render ``episodes`` episodes of the given tasks; returns frames rendered."""
    import numpy as np

    from democheck.sim.env import PushEnv

    recipe, episodes = job
    tasks = recipe.tasks()
    env, frames = None, 0
    rng = np.random.default_rng(0)
    for e, t in episodes:
        if env is None:
            env = PushEnv(tasks[t], image_size=recipe.image_size)
        elif (env.target, env.distractor) != (tasks[t].target, tasks[t].distractor):
            env.set_task(tasks[t])
        env.reset(seed=e)
        frames += 1
        for _ in range(recipe.steps - 1):
            env.step(rng.uniform(-1, 1, 7))
            frames += 1
    return frames


def bare_loop(recipe, workers: int) -> float:
    from democheck.sim.suite import plan_shards

    jobs = [(recipe, eps) for _, _, eps in plan_shards(recipe)]
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(workers) as pool:
        frames = sum(pool.map(_bare, jobs, chunksize=1))
    return frames / (time.perf_counter() - t0)


def synth(recipe, workers: int) -> float:
    from democheck.sim.suite import generate

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = generate(recipe, Path(tmp) / "ds", workers=workers)
        return summary["frames"] / (time.perf_counter() - t0)


def measure(recipe, workers: int = 2, repeats: int = 3, verbose: bool = False) -> dict:
    """Median frames/s of the bare step+render loop and of ``generate``, interleaved, and their ratio."""
    bare, gen, ratio = [], [], []
    for i in range(repeats):
        # Interleave the two so that machine noise hits both alike.
        b = bare_loop(recipe, workers)
        g = synth(recipe, workers)
        bare.append(b)
        gen.append(g)
        ratio.append(g / b)
        if verbose:
            print(f"run {i + 1}: bare {b:7.0f} frames/s   synth {g:7.0f} frames/s   ratio {g / b:.2f}", flush=True)
    return {"suite": recipe.name, "episodes": recipe.n_episodes, "steps": recipe.steps, "size": recipe.image_size,
            "workers": workers, "bare_fps": statistics.median(bare), "synth_fps": statistics.median(gen),
            "ratio": statistics.median(ratio), "repeats": repeats}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="push-mini")
    ap.add_argument("--tasks", type=int, default=None)
    ap.add_argument("--demos", type=int, default=None)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args()

    from democheck.sim.suite import load_recipe

    recipe = load_recipe(args.suite).with_overrides(tasks=args.tasks, demos=args.demos, size=args.size)
    res = measure(recipe, args.workers, args.repeats, verbose=True)
    print(f"median of {args.repeats}: bare loop {res['bare_fps']:.0f} frames/s, synth {res['synth_fps']:.0f} frames/s, "
          f"ratio {res['ratio']:.2f} ({recipe.n_episodes} episodes x {recipe.steps} steps, {recipe.image_size}px, "
          f"{args.workers} workers)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
