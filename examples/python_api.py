"""democheck from Python: score demonstrations one by one, and gate a cue at run time.

    python examples/python_api.py data/push-mini

Loads the shipped PETNet, computes the task posterior of a few cues, combines
several cues of one task by the product of Gaussians, and refuses a cue whose
task uncertainty the model's one-class SVM calls anomalous -- what a robot
should do before acting on a demonstration it was just shown.
"""

import argparse

import numpy as np
import torch

from democheck.audit.scores import ocsvm_margin, task_score
from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.train import task_posteriors

ap = argparse.ArgumentParser()
ap.add_argument("dataset")
ap.add_argument("--model", default=None)
args = ap.parse_args()

ds = open_dataset(args.dataset)
ckpt = load_checkpoint(args.model)
task, episodes = next(iter(ds.by_task().items()))
cues = ds.cue_frames_many(episodes)  # [N, 2, H, W, 3]: first and last frame of each demo
mu, var = task_posteriors(ckpt.model, cues, torch.device("cpu"))
sigma = np.sqrt(var)
print(f"task: {task}")
for e, s in zip(episodes, task_score(sigma)):
    print(f"  episode {e}: task uncertainty (mean sigma) {s:.4f}")

# Several cues of one task: the posterior narrows.
with torch.no_grad():
    mu_all, var_all = ckpt.model.task_posterior(torch.from_numpy(cues[None]))
print(f"all {len(episodes)} cues together: mean sigma {var_all.sqrt().mean():.4f}")

# Gate: would the model's one-class SVM accept these cues?
ocsvm = ckpt.meta["reference"]["ocsvm"]
for name, cue_sigma in (("real cue", sigma[:1]), ("black cue", np.sqrt(task_posteriors(
        ckpt.model, np.zeros_like(cues[:1]), torch.device("cpu"))[1]))):
    ok = ocsvm_margin(ocsvm, cue_sigma)[0] >= 0
    print(f"{name}: {'accept' if ok else 'refuse: ask for another demonstration'}")
