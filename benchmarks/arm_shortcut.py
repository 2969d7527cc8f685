"""Does a push controller see the objects, or read them off the arm?  In a demo the expert's arm heads for the
target, so a network trained on demo frames can place the target where the arm points; in closed loop the arm goes
where the controller sends it, and such a network reports its own intention back.  This renders the val split's
layouts of a pushing suite three ways and asks a PETNet model's controller:

    python benchmarks/arm_shortcut.py MODEL DATA [--demos 60] [--step 50]

- its read-out of the objects (``Controller.act(..., read=True)``, de-standardised as training standardises it),
  with the arm at home (where it tells nothing: the same pose in every demo), and with the arm posed as at
  ``--step`` of another demo: how far the target is read from its own place and from the other demo's target;
- the task variable: how far each demo's posterior mean lies from the first's (0: every cue gives the same z);
- how much the first action moves when the arm (in the picture alone, in the state alone), the objects or z is
  that of another demo.

MODEL is a model folder (``benchmarks/partial_model.py`` makes one from a run's saved state).  Distances are
medians over ``--demos`` clean val demos, in cm; actions in the model's standardised units.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.petnet.batches import task_rows
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.encode import encode_rows
from democheck.petnet.blocks import to_input
from democheck.petnet.train import env_standardisation
from democheck.sim.posed import render_layouts


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--demos", type=int, default=60)
    ap.add_argument("--step", type=int, default=50, help="the step of another demo whose arm pose is shown")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ds = open_dataset(args.data)
    arrays = build_cache(ds)
    ck = load_checkpoint(args.model)
    model = ck.model.eval()
    train = np.concatenate(list(task_rows(arrays, "train", 0).values()))
    env_mean, env_sd = env_standardisation(arrays, train)  # as training standardises the read-out's targets
    eps = arrays.episodes.reset_index(drop=True)
    clean = eps["label"].fillna("clean") == "clean" if "label" in eps else np.ones(len(eps), bool)
    rng = np.random.default_rng(args.seed)
    val = np.flatnonzero((eps["split"] == "val") & clean & (arrays.lengths > args.step))
    rows = np.sort(rng.choice(val, size=min(args.demos, len(val)), replace=False))
    other = rows[np.roll(np.arange(len(rows)), 1)]  # each demo's donor: another demo of the draw
    z = torch.from_numpy(encode_rows(model, arrays, rows).mu.astype(np.float32))

    def sim(row: int) -> dict:
        return json.loads(ds.episodes.loc[int(eps.loc[row, "episode_index"]), "sim"])

    sims = [sim(i) for i in rows]
    donor_arms = np.stack([np.asarray(arrays.state[arrays.offsets[j] + args.step])[:7] for j in other])
    home_arms = np.stack([s["layout"]["arm_qpos"] for s in sims])
    frames, states = {}, {}
    f, poses, st = render_layouts(sims, np.stack([home_arms, donor_arms], 1))
    frames["home"], frames["arm"], states["home"], states["arm"] = f[:, 0], f[:, 1], st[:, 0], st[:, 1]
    moved_objects = [{**s, "layout": {**sim(j)["layout"], "arm_qpos": s["layout"]["arm_qpos"]}}
                     for s, j in zip(sims, other)]  # another demo's places, this demo's objects and arm
    f, _, st = render_layouts(moved_objects, home_arms[:, None])
    frames["objects"], states["objects"] = f[:, 0], st[:, 0]
    own = poses[:, 0, :2]
    donor = np.stack([np.asarray(arrays.env_state[arrays.offsets[j] + args.step])[:2] for j in other])

    def act(key_frames: str, key_state: str, zz: torch.Tensor = z):
        f = torch.from_numpy(np.stack(frames[key_frames]))[:, None]
        st = torch.from_numpy(ck.norm.state(np.stack(states[key_state])).astype(np.float32))[:, None]
        with torch.no_grad():
            a, r = model.controller.act(f, st, zz, read=True)
        return a[:, 0].numpy(), r[:, 0].numpy() * env_sd + env_mean

    def cm(read: np.ndarray, truth: np.ndarray) -> float:
        return round(float(np.median(100 * np.hypot(*(read[:, :2] - truth).T))), 2)

    def moved(a: np.ndarray, b: np.ndarray) -> float:
        return round(float(np.median(np.linalg.norm(a - b, axis=1))), 2)

    a_home, r_home = act("home", "home")
    a_arm, r_arm = act("arm", "arm")
    a_img, _ = act("arm", "home")
    a_state, _ = act("home", "arm")
    a_obj, _ = act("objects", "home")
    a_z, _ = act("home", "home", z[torch.from_numpy(np.roll(np.arange(len(rows)), 1))])
    with torch.no_grad():
        h = {k: model.controller.features(to_input(torch.from_numpy(np.stack(frames[k]))), z).numpy()
             for k in frames}
    init = np.asarray(arrays.env_state[arrays.offsets[train]])[:, :2].mean(0)
    out = {
        "demos": len(rows),
        "read-out, arm at home: cm from the target": cm(r_home, own),
        "guessing the mean first place of the target: cm": cm(np.tile(init, (len(rows), 1)), own),
        f"read-out, arm as at step {args.step} of another demo: cm from the target": cm(r_arm, own),
        "... and from that other demo's target": cm(r_arm, donor),
        "task variable: largest |mu - mu of the first demo|": round(float(np.abs(z - z[0]).max()), 4),
        "first action moved by: the arm (picture and state)": moved(a_arm, a_home),
        "... the arm in the picture alone": moved(a_img, a_home),
        "... the arm in the state alone": moved(a_state, a_home),
        "... another layout of the objects": moved(a_obj, a_home),
        "... another demo's task variable": moved(a_z, a_home),
        "... a typical first action (its size)": round(float(np.median(np.linalg.norm(a_home, axis=1))), 2),
        "image features moved by: the arm / the objects": (moved(h["arm"], h["home"]),
                                                          moved(h["objects"], h["home"])),
    }
    for k, v in out.items():
        print(f"{k}: {v}")
    return out


if __name__ == "__main__":
    main()
