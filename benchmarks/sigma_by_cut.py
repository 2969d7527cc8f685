"""Does a model's task uncertainty grow when a cue shows less of its task?

    python benchmarks/sigma_by_cut.py data/push-v1 petnet-push-v1 [more model folders]

For the val demos of the dataset, the cue's last frame is taken at step t instead of the end
(``EpisodeArrays.cue(rows, end=t)``); prints the mean task standard deviation for each t.  A model
whose variance carried what a cue leaves out would be most uncertain at t = 0.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.batches import task_rows
from democheck.petnet.encode import encode

CUTS = (0, 10, 25, 50, 75, 99)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("models", nargs="+")
    args = ap.parse_args()
    arrays = build_cache(open_dataset(args.dataset))
    rows = np.concatenate(list(task_rows(arrays, "val", 0).values()))
    for path in args.models:
        model = load_checkpoint(path).model
        cut = lambda t: np.minimum(t, arrays.lengths[rows] - 1)  # noqa: E731
        sig = [encode(model, arrays.cue(rows, end=cut(t)), torch.device("cpu"),
                      end_states=arrays.state[arrays.offsets[rows] + cut(t)]).sigma.mean() for t in CUTS]
        print(f"{path}: " + "  ".join(f"t={t}: {s:.3f}" for t, s in zip(CUTS, sig)))


if __name__ == "__main__":
    main()
