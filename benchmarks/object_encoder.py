"""Does a task encoder made to keep the objects know when a cue has none?  The experiment behind issue 22's
third approach (the first two, densities on the shipped encoder's features and an ensemble of encoders, did
not see empty scenes or random cues: an empty scene's conv features lie *closer* to the training cues' mean).

    python benchmarks/object_encoder.py --train data/push-v1 --sets data/push-v1-dev,data/push-v1-dev-probes \
        [--object-weight 1.0] [--steps 6000] [--out runs/object-encoder]

Trains PETNet's task encoder alone (its conv stack and variance head, ``petnet.model.TaskEncoder``) on the
training split's cues with the shipped recipe's embedding terms -- the task-matching loss on batches of
look-alike tasks and the broken-cue hinge (``petnet.regularisers``) -- plus, with ``--object-weight`` above 0,
a linear read-out from the conv features of where the target and the distractor are in the cue's first and
last frames (the recorded environment state: x, y, cos and sin of yaw, each standardised).  Then fits the
novelty density on the training cues' conv features with its reference on the val split
(``petnet.novelty.fit_novelty``, as ``democheck train`` does) and prints, on each ``--sets`` dataset's cues,
the AUROC of each labelled kind against the clean demos and how many clean standard deviations its mean lies
above the clean mean (the paper's Figure 5A), for the task uncertainty (both parts), the head alone and the
novelty alone.  No probe or defect is trained on: the sets are read only to report.
"""

from __future__ import annotations

import argparse
import glob
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from sklearn.metrics import roc_auc_score

from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.petnet.batches import Batches, task_rows
from democheck.petnet.model import ModelConfig, PETNet, cue_input
from democheck.petnet.encode import encode
from democheck.petnet.novelty import fit_novelty
from democheck.petnet.regularisers import broken_cue_loss, broken_cues, task_matching_loss
from democheck.workflows import object_pair_groups


def object_targets(root: Path, episodes: pd.DataFrame) -> np.ndarray:
    """[N, 16]: per row of ``episodes`` the environment state at its first and last step, yaw as cos and sin."""
    cols = pd.concat([pd.read_parquet(f, columns=["episode_index", "frame_index", "observation.environment_state"])
                      for f in sorted(glob.glob(str(root / "data" / "*" / "*.parquet")))])
    env = np.stack(cols["observation.environment_state"].to_numpy()).astype(np.float64)
    ends = cols.assign(row=np.arange(len(cols))).groupby("episode_index")["row"].agg(["first", "last"])
    out = []
    for e in episodes["episode_index"]:
        first, last = env[ends.at[e, "first"]], env[ends.at[e, "last"]]
        parts = []
        for s in (first, last):
            for obj in (0, 3):
                parts += [s[obj], s[obj + 1], np.cos(s[obj + 2]), np.sin(s[obj + 2])]
        out.append(parts)
    return np.asarray(out, np.float32)


def auroc_table(name: str, values: dict[str, np.ndarray], labels: np.ndarray) -> None:
    kinds = sorted(set(labels) - {"clean"})
    clean = labels == "clean"
    print(f"  {name}: {' '.join(kinds)}")
    for what, v in values.items():
        au, sep = [], []
        for k in kinds:
            sel = clean | (labels == k)
            au.append(roc_auc_score(labels[sel] == k, v[sel]))
            sep.append((v[labels == k].mean() - v[clean].mean()) / v[clean].std())
        print(f"    {what:<18} AUROC " + " ".join(f"{a:.3f}" for a in au)
              + " | clean SDs above " + " ".join(f"{s:5.1f}" for s in sep))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", type=Path, required=True)
    ap.add_argument("--sets", required=True, help="comma-separated labelled datasets to report on")
    ap.add_argument("--object-weight", type=float, default=1.0)
    ap.add_argument("--broken-cue-weight", type=float, default=1.0)
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--batch-tasks", type=int, default=32)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("runs/object-encoder"))
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    ds = open_dataset(args.train, image_size=64)
    arrays = build_cache(ds)
    targets = object_targets(args.train, arrays.episodes)
    mean, sd = targets.mean(0), targets.std(0) + 1e-6
    targets = torch.from_numpy((targets - mean) / sd)
    train, val = task_rows(arrays, "train", args.seed), task_rows(arrays, "val", args.seed)
    batches = Batches(arrays, train, None, object_pair_groups(ds))  # rows only: no trajectories are gathered
    cfg = ModelConfig(state_dim=ds.state_dim, action_dim=ds.action_dim, novelty=False)
    model = PETNet(cfg)
    encoder = model.encoder
    readout = torch.nn.Linear(encoder.head[0].in_features, targets.shape[1])
    opt = torch.optim.Adam(list(encoder.parameters()) + list(readout.parameters()), lr=args.lr)
    t0 = time.perf_counter()
    for step in range(1, args.steps + 1):
        cue_rows, traj_rows = batches.pick_rows(rng, args.batch_tasks)
        cue = torch.from_numpy(arrays.cue(cue_rows))
        traj = torch.from_numpy(arrays.cue(traj_rows))
        h = encoder.conv(cue_input(torch.cat([cue, traj])))  # no shift: the shipped recipe has none
        mu, var = encoder.head_posterior(h)
        n = len(cue_rows)
        loss = task_matching_loss(mu[:n], var[:n], mu[n:], var[n:], torch.from_numpy(batches.task_ids[cue_rows]))
        terms = {"task_matching": float(loss)}
        if args.broken_cue_weight > 0:
            _, var_b = encoder.head_posterior(encoder.conv(cue_input(broken_cues(cue))))
            hinge = broken_cue_loss(var[:n].sqrt().mean(1), var_b.sqrt().mean(1))
            loss = loss + args.broken_cue_weight * hinge
            terms["broken_cue"] = float(hinge)
        if args.object_weight > 0:
            rows = torch.from_numpy(np.concatenate([cue_rows, traj_rows]))
            obj = F.mse_loss(readout(h), targets[rows])
            loss = loss + args.object_weight * obj
            terms["objects"] = float(obj)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 500 == 0 or step == args.steps:
            print(f"step {step}/{args.steps} " + " ".join(f"{k} {v:.4f}" for k, v in terms.items())
                  + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    train_cues = arrays.cue(np.concatenate(list(train.values())))
    val_cues = arrays.cue(np.concatenate(list(val.values())))
    encoder.eval()
    # Over the trained encoder's own conv features: what this experiment asks about (not a cue autoencoder's).
    report = fit_novelty(model, train_cues, val_cues, torch.device("cpu"), autoencoder=0)
    print("novelty:", json.dumps({k: report[k] for k in ("d2_ref", "shrinkage", "held_out_d2")}))
    args.out.mkdir(parents=True, exist_ok=True)
    torch.save({"encoder": encoder.state_dict(), "readout": readout.state_dict(), "args": vars(args)},
               args.out / f"encoder-objects{args.object_weight:g}.pt")
    values: dict[str, list[np.ndarray]] = {"task uncertainty": [], "head alone": [], "novelty alone": []}
    labels = []
    for k, path in enumerate(args.sets.split(",")):
        s = open_dataset(path, image_size=64)
        eps = s.episode_indices
        lab = s.episodes["label"].fillna("clean").to_numpy() if "label" in s.episodes else np.full(len(eps), "clean")
        labels.append(lab)
        post = encode(model, s.cue_frames_many(eps))
        values["task uncertainty"].append(post.task_uncertainty())
        values["head alone"].append(post.task_uncertainty(head_only=True))
        values["novelty alone"].append((post.var_novel / encoder.prior_var.numpy()).mean(1))
        if k == 0:  # how well the read-out finds the objects in cues it was not trained on
            clean = np.flatnonzero(lab == "clean")[:200]
            with torch.no_grad():
                got = readout(encoder.conv(cue_input(torch.from_numpy(s.cue_frames_many([eps[i] for i in clean])))))
            want = (object_targets(Path(path), s.episodes.reset_index().iloc[clean]) - mean) / sd
            print(f"object read-out on {path}'s clean cues: RMS error "
                  f"{np.sqrt(((got.numpy() - want) ** 2).mean()):.3f} standard deviations")
    auroc_table(args.sets, {k: np.concatenate(v) for k, v in values.items()}, np.concatenate(labels))

if __name__ == "__main__":
    main()
