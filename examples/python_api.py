"""democheck from Python: score demonstrations one by one, and gate a cue at run time.

    python examples/python_api.py data/push-mini

Loads the shipped PETNet, computes the task posterior of a few cues, combines
several cues of one task by the product of Gaussians, and refuses a cue whose
task uncertainty the model's one-class SVM calls anomalous -- what a robot
should do before acting on a demonstration it was just shown.
"""

import argparse

import numpy as np

from democheck.audit.ocsvm import ocsvm_margin
from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.encode import encode, encode_demos

ap = argparse.ArgumentParser()
ap.add_argument("dataset")
ap.add_argument("--model", default=None)
args = ap.parse_args()

ds = open_dataset(args.dataset)
ckpt = load_checkpoint(args.model)
task, episodes = next(iter(ds.by_task().items()))
post = encode_demos(ckpt.model, ds, episodes)  # a TaskPosterior of each demo: mu, and the variance's two parts
sigma = post.sigma
print(f"task: {task}")
for e, s in zip(episodes, post.task_uncertainty()):
    print(f"  episode {e}: task uncertainty (mean sigma) {s:.4f}")

# Several cues of one task: the product of Gaussians, and the posterior narrows.
_, var_all = post.combined()
print(f"all {len(episodes)} cues together: mean sigma {np.sqrt(var_all).mean():.4f}")

# Gate: would the model's one-class SVM accept these cues?
ocsvm = ckpt.meta["reference"]["ocsvm"]
black = np.zeros_like(ds.cue_frames_many(episodes[:1]))  # a covered camera, the arm where the first demo ended
black_sigma = encode(ckpt.model, black, end_states=ds.end_states(episodes[:1])).sigma
for name, cue_sigma in (("real cue", sigma[:1]), ("black cue", black_sigma)):
    ok = ocsvm_margin(ocsvm, cue_sigma)[0] >= 0
    print(f"{name}: {'accept' if ok else 'refuse: ask for another demonstration'}")
