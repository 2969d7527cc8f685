"""Does the novelty density see where a demo ended?  Its last state beside its last frame, read four ways.

    python benchmarks/end_state_choices.py --train data/push-v1 --sets data/push-v1-dev,data/push-v1-dev-probes \
        [--model MODEL]

The novelty part of the task variance (``democheck/petnet/novelty.py``) is a Gaussian over a cue autoencoder's
features of each demo's last frame.  A random probe whose arm was flung out of view ends in a frame with *less*
in it than a real one -- the objects where they started, no arm -- and a density over what a picture holds finds
that about as unusual as the most unusual clean ends of new tasks.  The demo's state at its last step says where
the arm is, in view or not.  On the model's own autoencoder (no training), this fits, on the training split's
demos, and scores each labelled demo of ``--sets`` by:

- ``image d2``: one Gaussian over the last frame's features (the density before end states);
- ``state d2``: one Gaussian over the last state, each dimension in the units ``novelty.end_state_units`` gives;
- ``image + state``: those two, each over its held-out reference, summed (two independent densities);
- ``joint d2``: one Gaussian over both, the standardised state after the features (``fit_novelty`` with end
  states): the state's surprise *given* what the frame shows, plus the frame's own;

and the whole task uncertainty with each (the head's variance plus prior_var * d2 / its held-out reference, as
``TaskEncoder`` adds it).  Prints the AUROC of each against the clean demos for every labelled kind; no kind is
used to fit anything.

``--time DATA``: what reading the end states costs the audit's cue pass on DATA -- the pass (first and last
frames, the model; ``model.encode_demos``) and the end states' read alone, interleaved over ``--repeats`` runs,
the median of each and their ratio.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from sklearn.covariance import LedoitWolf
from sklearn.metrics import roc_auc_score

from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.novelty import QUANTILE, conv_features, end_state_units, stack_features


def read(model, path: str, split: str | None = None, limit: int | None = None) -> dict[str, np.ndarray]:
    """Of a dataset's demos (one split, at most ``limit`` drawn with seed 0): the autoencoder's features of the
    last frame, the last state, the head's task variances, the labels."""
    ds = open_dataset(path, image_size=model.cfg.image_size)
    eps = ds.episodes.reset_index()
    if split is not None:
        eps = eps[eps["split"] == split]
    if limit and len(eps) > limit:
        eps = eps.sample(limit, random_state=0).sort_values("episode_index")
    idx = eps["episode_index"].tolist()
    cues, cpu = ds.cue_frames_many(idx), torch.device("cpu")
    return {"image": stack_features(model.encoder.novelty_conv, cues, cpu, view="last").astype(np.float64),
            "state": ds.end_states(idx).astype(np.float64),
            "var_task": conv_features(model.encoder, cues, cpu)[2].astype(np.float64),
            "label": np.asarray(eps["label"].fillna("clean") if "label" in eps else np.full(len(eps), "clean"))}


def time_cue_pass(model, path: str, repeats: int) -> None:
    """Median seconds of the cue pass over DATA and of its end-state read alone (see the module docstring)."""
    import time

    from democheck.petnet.encode import encode_demos

    ds = open_dataset(path, image_size=model.cfg.image_size)
    eps = ds.episode_indices
    whole, ends = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for s in range(0, len(eps), 256):
            encode_demos(model, ds, eps[s:s + 256])
        t1 = time.perf_counter()
        ds.end_states(eps)
        whole.append(t1 - t0)
        ends.append(time.perf_counter() - t1)
    w, e = float(np.median(whole)), float(np.median(ends))
    print(f"{len(eps)} demos: cue pass {w:.2f} s ({len(eps) / w:.0f} demos/s), of which the end states {e:.2f} s "
          f"({e / w:.1%}); median of {repeats}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None, help="a PETNet model with a cue autoencoder (default: the shipped one)")
    ap.add_argument("--train", help="the model's training dataset (its train and val splits)")
    ap.add_argument("--sets", help="comma-separated labelled datasets (a development set and probes)")
    ap.add_argument("--train-cues", type=int, default=3000, help="training demos the densities are fitted on")
    ap.add_argument("--time", metavar="DATA", help="time the cue pass and its end-state read on DATA instead")
    ap.add_argument("--repeats", type=int, default=5, help="runs of --time")
    args = ap.parse_args()
    torch.set_num_threads(2)
    model = load_checkpoint(args.model).model.eval()
    if args.time:
        return time_cue_pass(model, args.time, args.repeats)
    if not (args.train and args.sets):
        ap.error("--train and --sets are needed (or --time)")
    if not model.cfg.novelty_autoencoder:
        raise SystemExit("the model has no cue autoencoder (democheck fit-novelty gives it one)")
    train, held = read(model, args.train, "train", args.train_cues), read(model, args.train, "val")
    parts = [read(model, p) for p in args.sets.split(",")]
    scored = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    centre, unit = end_state_units(train["state"])
    views = {"image": lambda d: d["image"], "state": lambda d: (d["state"] - centre) / unit,
             "joint": lambda d: np.concatenate([d["image"], (d["state"] - centre) / unit], 1)}
    d2 = {}
    for name, view in views.items():
        fit = LedoitWolf().fit(view(train))
        d2[f"{name} d2"] = fit.mahalanobis(view(scored)) / np.quantile(fit.mahalanobis(view(held)), QUANTILE)
    d2["image + state"] = d2["image d2"] + d2["state d2"]
    prior_var = model.encoder.prior_var.cpu().numpy().astype(np.float64)
    rows = dict(d2)
    for name, value in d2.items():
        rows[f"task uncertainty, {name}"] = np.sqrt(scored["var_task"] + prior_var * value[:, None]).mean(1)
    labels = scored["label"]
    kinds = sorted(set(labels) - {"clean"})
    print(f"{len(train['label'])} training demos, {len(held['label'])} held-out, {len(labels)} scored "
          f"({(labels == 'clean').sum()} clean)")
    print(f"{'score':<36}" + "".join(f"{k[:12]:>13}" for k in kinds))
    for name, s in rows.items():
        au = [roc_auc_score(labels[np.isin(labels, ["clean", k])] == k, s[np.isin(labels, ["clean", k])])
              for k in kinds]
        print(f"{name:<36}" + "".join(f"{a:13.4f}" for a in au))


if __name__ == "__main__":
    main()
