"""How faithful is a synthetic dataset on disk to its simulation?

For a random sample of episodes, re-simulate each from its sim record with
its recorded actions and compare: the state arrays must be identical, the
expert's success must match, and the decoded video frames are compared with
the re-rendered ones by PSNR.

    python benchmarks/fidelity.py data/push-v1 --episodes 100
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from democheck.data import open_dataset
    from democheck.sim.catalog import OBJECTS
    from democheck.sim.env import PushEnv
    from democheck.sim.variants import record_demo

    ds = open_dataset(args.dataset)
    rng = np.random.default_rng(args.seed)
    picks = sorted(rng.choice(ds.episode_indices, size=min(args.episodes, len(ds)), replace=False))
    env = None
    psnrs, frame_min, same_state, same_success = [], [], 0, 0
    for e in picks:
        demo = ds[int(e)]
        pair = (OBJECTS[demo.sim["target"]], OBJECTS[demo.sim["distractor"]])
        if env is None:
            env = PushEnv(pair, image_size=demo.frames.shape[1])
        else:
            env.set_task(pair)
        actions = iter(demo.actions)
        rec = record_demo(env, lambda: next(actions), len(demo), layout=demo.sim["layout"])
        err = (rec["frames"].astype(np.float64) - demo.frames.astype(np.float64)) ** 2
        psnrs.append(10 * np.log10(255.0**2 / err.mean()))
        frame_min.append(min(10 * np.log10(255.0**2 / max(f.mean(), 1e-12)) for f in err))
        same_state += np.array_equal(rec["state"], demo.state)
        same_success += rec["success"] == demo.success
    n = len(picks)
    print(f"{n} episodes of {args.dataset}: state identical {same_state}/{n}, success identical {same_success}/{n}")
    print(f"PSNR decoded vs re-rendered: mean {np.mean(psnrs):.2f} dB, worst episode {np.min(psnrs):.2f} dB, "
          f"worst single frame {np.min(frame_min):.2f} dB")


if __name__ == "__main__":
    main()
