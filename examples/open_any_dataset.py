"""Open a LeRobot dataset (v3.0 or v2.1) and look at it the way democheck does: by demo.

    python examples/open_any_dataset.py path/to/dataset [--camera top]

Prints the tasks and their demo counts and saves the cue (first and last
frame, side by side) of each task's first demo as PNG files -- reading only
those two frames of each video, never whole episodes.
"""

import argparse
from pathlib import Path

import numpy as np
from PIL import Image

from democheck.data import open_dataset

ap = argparse.ArgumentParser()
ap.add_argument("dataset", type=Path)
ap.add_argument("--camera", default=None)
ap.add_argument("--out", type=Path, default=Path("cues"))
args = ap.parse_args()

ds = open_dataset(args.dataset, camera=args.camera)
print(ds)
args.out.mkdir(exist_ok=True)
for i, (task, episodes) in enumerate(ds.by_task().items()):
    print(f"{len(episodes):4d} demos  {task}")
    first, last = ds.cue_frames(episodes[0])
    Image.fromarray(np.concatenate([first, last], axis=1)).save(args.out / f"task{i:03d}_ep{episodes[0]}.png")
print(f"cues of each task's first demo written to {args.out}/")
