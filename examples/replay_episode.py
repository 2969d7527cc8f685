"""Re-simulate one episode of a democheck suite from its sim record and compare it with the dataset.

    python examples/replay_episode.py data/push-mini 5

Every synthetic demo carries the objects, the initial layout and arm pose,
and the seed; replaying its recorded actions from that state reproduces the
episode exactly (state bit for bit; frames up to video compression). Probes
and injected defects are made the same way, with other actions or scenes.
"""

import argparse

import numpy as np

from democheck.data import open_dataset
from democheck.sim.catalog import OBJECTS
from democheck.sim.env import PushEnv
from democheck.sim.variants import record_demo

ap = argparse.ArgumentParser()
ap.add_argument("dataset")
ap.add_argument("episode", type=int)
args = ap.parse_args()

demo = open_dataset(args.dataset)[args.episode]
if demo.sim is None:
    raise SystemExit(f"episode {args.episode} has no sim record: it was not made by democheck synth")
env = PushEnv((OBJECTS[demo.sim["target"]], OBJECTS[demo.sim["distractor"]]), image_size=demo.frames.shape[1])
actions = iter(demo.actions)
rec = record_demo(env, lambda: next(actions), len(demo), layout=demo.sim["layout"])
mse = np.mean((rec["frames"].astype(float) - demo.frames.astype(float)) ** 2)
print(f"task: {demo.task}")
print(f"state identical: {np.array_equal(rec['state'], demo.state)}; success: {rec['success']} (recorded {demo.success})")
print(f"frames PSNR vs video: {10 * np.log10(255**2 / mse):.1f} dB")
