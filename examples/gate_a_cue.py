"""Gate a cue at run time, as the paper proposes: act only on a demonstration the model is sure of, else ask for
another one, then push.

    democheck synth push-mini --out data/push-mini
    python examples/gate_a_cue.py data/push-mini

For one task of the dataset: shows the robot a cue (a demonstration's first and last frame), asks the gate
whether to act, asks for more demonstrations of the task while it refuses (several cues combine by the product of
Gaussians), and rolls the controller out in the simulator once it acts.  A covered camera's cue is refused.
"""

import argparse
import json

import numpy as np

from democheck.data import open_dataset
from democheck.evaluate.rollout import ControllerPolicy
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.gate import Gate
from democheck.petnet.encode import encode, encode_demos
from democheck.sim.catalog import OBJECTS
from democheck.sim.env import PushEnv
from democheck.sim.variants import record_demo

ap = argparse.ArgumentParser()
ap.add_argument("dataset")
ap.add_argument("--model", default="petnet-push-v2", help="a PETNet that stores its gate's reference cues")
ap.add_argument("--false-refusal", type=float, default=0.05, help="share of real cues the gate refuses")
args = ap.parse_args()

ds = open_dataset(args.dataset)
ckpt = load_checkpoint(args.model)
gate = Gate.of(ckpt, false_refusal=args.false_refusal)
print(f"gate: act when the task uncertainty is at most {gate.threshold:.3f} "
      f"(refuses {args.false_refusal:.0%} of real cues, read from {gate.reference_cues} held-out cues)")

task, episodes = next(iter(ds.by_task().items()))
post = encode_demos(ckpt.model, ds, episodes)  # every demo's task posterior; the robot sees them one at a time
print(f"task: {task}")

covered = np.zeros_like(ds.cue_frames_many(episodes[:1]))  # a camera covered for the whole demonstration
d = gate.decide(encode(ckpt.model, covered, end_states=ds.end_states(episodes[:1])))
print(f"a covered camera's cue: uncertainty {d.uncertainty:.3f} -> {'act' if d.act else 'ask for another'}")

for shown in range(1, min(gate.max_cues, len(episodes)) + 1):
    d = gate.decide(post.take(list(range(shown))))
    print(f"{shown} cue(s): uncertainty {d.uncertainty:.3f} -> {'act' if d.act else 'ask for another'}")
    if d.act:
        break
if not d.act:
    raise SystemExit(f"still unsure after {gate.max_cues} demonstrations: the robot does not act")

spec = json.loads(ds.episodes.loc[episodes[0], "sim"])  # the objects of the task, from democheck's sim record
env = PushEnv((OBJECTS[spec["target"]], OBJECTS[spec["distractor"]]), image_size=ckpt.config.image_size)
steps = int(ds.episodes.loc[episodes[0], "length"])
run = record_demo(env, ControllerPolicy(env, ckpt.model, ckpt.norm, d.z).act, steps=steps, seed=12345)
print(f"pushed on a new layout: {'success' if run['success'] else 'failure'} "
      f"(target {env.target_to_goal():.3f} m from the goal)")
