"""democheck from Python: score demonstrations one by one, and gate a cue at run time.

    python examples/python_api.py data/push-mini

Loads the shipped PETNet, computes the task posterior of a few cues, combines
several cues of one task by the product of Gaussians, and refuses a cue whose
task uncertainty the model's one-class SVM calls anomalous -- what a robot
should do before acting on a demonstration it was just shown.
"""

import argparse

import numpy as np

from democheck.audit.scores import ocsvm_margin
from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.model import encode

ap = argparse.ArgumentParser()
ap.add_argument("dataset")
ap.add_argument("--model", default=None)
args = ap.parse_args()

ds = open_dataset(args.dataset)
ckpt = load_checkpoint(args.model)
task, episodes = next(iter(ds.by_task().items()))
cues = ds.cue_frames_many(episodes)  # [N, 2, H, W, 3]: first and last frame of each demo
ends = ds.end_states(episodes)  # [N, S]: where each demo ended (the novelty density reads it too)
post = encode(ckpt.model, cues, end_states=ends)  # a TaskPosterior: mu, and the variance's two parts
sigma = post.sigma
print(f"task: {task}")
for e, s in zip(episodes, post.task_uncertainty()):
    print(f"  episode {e}: task uncertainty (mean sigma) {s:.4f}")

# Several cues of one task: the product of Gaussians, and the posterior narrows.
_, var_all = post.combined()
print(f"all {len(episodes)} cues together: mean sigma {np.sqrt(var_all).mean():.4f}")

# Gate: would the model's one-class SVM accept these cues?
ocsvm = ckpt.meta["reference"]["ocsvm"]
for name, cue_sigma in (("real cue", sigma[:1]), ("black cue", encode(ckpt.model, np.zeros_like(cues[:1]), end_states=ends[:1]).sigma)):
    ok = ocsvm_margin(ocsvm, cue_sigma)[0] >= 0
    print(f"{name}: {'accept' if ok else 'refuse: ask for another demonstration'}")
