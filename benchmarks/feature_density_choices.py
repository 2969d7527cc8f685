"""Which density over the features the novelty part is fitted on tells an empty or flailing cue from a real one?

    python benchmarks/feature_density_choices.py --train data/push-v1 --sets data/push-v1-dev,data/push-v1-dev-probes

The novelty part of the task variance (``democheck/petnet/novelty.py``) is one Gaussian over a model's novelty
features (``TaskEncoder.novelty_features``: its cue autoencoder's, or the task encoder's own conv features for a
model fitted before the autoencoder): a cue far from the training cues' mean is unfamiliar.  This measures, on the
same features and with no training, the other densities out-of-distribution work proposes, each a score higher =
less familiar:

- ``global d2``: the shipped one, squared Mahalanobis distance from the model's fitted Gaussian;
- ``typicality``: |log d2 - its median over the held-out (val) cues| in their MADs -- a cue *closer* to the
  mean than real cues are is atypical too (the typical set of a high-dimensional Gaussian is a shell);
- ``task min d2`` and ``task -logsumexp``: class-conditional Gaussians (deep deterministic uncertainty's GDA),
  one mean per training task with a shared within-task covariance (Ledoit-Wolf): the distance to the nearest
  task, or minus the mixture's log density -- an input between the tasks' clusters is far from all of them;
- ``kNN10 whitened``, ``kNN10 cosine``: the mean distance to the 10 nearest training cues, in the whitened
  feature space or by cosine similarity of the raw features (deep nearest neighbours);
- ``location max d2``: one Gaussian per position of the feature map (PaDiM), the largest of the positions' d2;
- ``task uncertainty with D``: the whole task uncertainty (the head's variance plus the novelty part) with the
  density D's score in place of the shipped d2, each referenced to the held-out cues' ``QUANTILE`` as d2 is;
- ``view V d2``: the Gaussian refitted on the features (the autoencoder's, or the task encoder's) of what view V
  reads of each training cue -- ``cue`` (first, last), ``last`` (the last frame in both places: the shipped
  ``NOVELTY_VIEW``), ``first`` (first, first), ``swapped`` (last, first) -- and ``last | first d2``, the last
  frame's given the first's: one Gaussian over both views' features, less the first view's own d2 under it (a
  likelihood ratio against the start, which a held-out object makes as unfamiliar as the end);
- ``shift spread``, ``brightness spread``: not a density -- how far the task mean mu moves when the cue is
  shifted by one or two pixels or made brighter or darker (the mean variance of mu over those versions, in
  units of the cue's own variance for shifts): a cue the encoder reads no task from might be read unsteadily.

Prints the AUROC of each against the sets' clean demos for every labelled kind.  No kind is used to fit anything.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from sklearn.covariance import LedoitWolf
from sklearn.metrics import roc_auc_score

from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.novelty import QUANTILE, conv_features, stack_features


def features(encoder, path: str, split: str | None = None, limit: int | None = None, seed: int = 0,
             with_cues: bool = False):
    """(novelty features [N, D] float64, tasks [N], labels [N], the head's variances [N, z]) of a dataset's cues
    (one split, at most ``limit``), and the cues themselves with ``with_cues``."""
    ds = open_dataset(path)
    episodes = ds.episodes.reset_index()
    if split is not None:
        episodes = episodes[episodes["split"] == split]
    if limit and len(episodes) > limit:
        episodes = episodes.sample(limit, random_state=seed).sort_values("episode_index")
    cues = ds.cue_frames_many(episodes["episode_index"].to_numpy())
    cpu = torch.device("cpu")
    f = stack_features(encoder.image_features, cues, cpu)
    var_task = conv_features(encoder, cues, cpu)[2]
    labels = episodes["label"].fillna("clean") if "label" in episodes else np.full(len(episodes), "clean")
    out = (f.astype(np.float64), episodes["task"].to_numpy(), np.asarray(labels), var_task)
    return (*out, cues) if with_cues else out


def test_time_spread(model, cues: np.ndarray) -> dict[str, np.ndarray]:
    """How far mu moves over shifted and over brightened or darkened versions of each cue [N, 2, H, W, 3]."""
    from democheck.petnet.encode import encode

    base = encode(model, cues)
    shifted = np.stack([encode(model, np.roll(cues, (dy, dx), axis=(2, 3))).mu
                        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0), (2, 2), (-2, -2))])
    lit = np.stack([encode(model, np.clip(cues.astype(np.int16) + d, 0, 255).astype(np.uint8)).mu
                    for d in (-20, -10, 10, 20)])
    return {"shift spread": (shifted.var(0) / base.var).mean(1), "brightness spread": lit.var(0).mean(1)}


def mahalanobis(x: np.ndarray, mean: np.ndarray, precision: np.ndarray) -> np.ndarray:
    d = x - mean
    return np.einsum("ij,jk,ik->i", d, precision, d)


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a ** 2).sum(1)[:, None] - 2.0 * a @ b.T + (b ** 2).sum(1)[None]


def densities(encoder, train: np.ndarray, train_tasks: np.ndarray, val: np.ndarray, channels: int,
              *sets: np.ndarray) -> list[dict[str, np.ndarray]]:
    """Each density's score (see the module docstring) of the features [N, D] of each of ``sets``, every density
    fitted once, on the ``train`` features (the typicality's centre and the PaDiM references on ``val``)."""
    if encoder.cfg.novelty_state:  # the model's Gaussian reads end states too: the image features' own, as it fits
        fit = LedoitWolf().fit(train)
        mean, precision = fit.location_, fit.precision_
    else:
        mean = encoder.feature_mean.cpu().numpy().astype(np.float64)
        precision = encoder.feature_precision.cpu().numpy().astype(np.float64)
    log_val = np.log(mahalanobis(val, mean, precision))
    centre = np.median(log_val)
    spread = np.median(np.abs(log_val - centre))
    names = np.unique(train_tasks)
    means = np.stack([train[train_tasks == t].mean(0) for t in names])
    within = LedoitWolf().fit(train - means[np.searchsorted(names, train_tasks)]).precision_
    w = np.linalg.cholesky(within)
    g = np.linalg.cholesky(precision)
    unit = lambda v: v / np.linalg.norm(v, axis=1, keepdims=True)  # noqa: E731
    means_w, train_g, train_unit = means @ w, train @ g, unit(train)
    out = []
    for x, location in zip(sets, location_d2(train, val, channels, *sets)):
        global_d2 = mahalanobis(x, mean, precision)
        d = squared_distances(x @ w, means_w)
        near = np.sort(squared_distances(x @ g, train_g), 1)
        out.append({"global d2": global_d2, "typicality": np.abs(np.log(global_d2) - centre) / spread,
                    "task min d2": d.min(1), "task -logsumexp": -np.logaddexp.reduce(-d / 2.0, axis=1),
                    **{f"kNN{k} whitened": near[:, :k].mean(1) for k in (1, 10, 50)},
                    "kNN10 cosine": 1.0 - np.sort(unit(x) @ train_unit.T, 1)[:, -10:].mean(1),
                    "location max d2": location})
    return out


def location_d2(train: np.ndarray, val: np.ndarray, channels: int, *sets: np.ndarray) -> list[np.ndarray]:
    """PaDiM's image score (Defard et al. 2020) of each of ``sets``: one Gaussian per position of the [channels, s,
    s] feature map, fitted on the training cues; each position's d2 in units of its held-out cues' ``QUANTILE``;
    the largest over the positions -- a small thing missing or added somewhere is not averaged away over the
    whole map."""
    train_map, val_map, *maps = [f.reshape(len(f), channels, -1) for f in (train, val, *sets)]
    per_position: list[list[np.ndarray]] = [[] for _ in sets]
    for pos in range(train_map.shape[2]):
        fit = LedoitWolf().fit(train_map[:, :, pos])
        ref = np.quantile(fit.mahalanobis(val_map[:, :, pos]), QUANTILE)
        for scored, m in zip(per_position, maps):
            scored.append(fit.mahalanobis(m[:, :, pos]) / ref)
    return [np.max(scored, axis=0) for scored in per_position]


VIEWS = {"cue": [0, 1], "last": [1, 1], "first": [0, 0], "swapped": [1, 0]}


def view_densities(conv, train_cues: np.ndarray, *sets: np.ndarray) -> list[dict[str, np.ndarray]]:
    """d2 of the cues [N, 2, H, W, 3] of each of ``sets`` under a Gaussian fitted, once, on each view (``VIEWS``)
    of ``train_cues``, as ``fit_novelty`` fits it, and the last view's given the first's (see the module
    docstring)."""
    cpu = torch.device("cpu")
    feats = lambda c: {view: stack_features(conv, c[:, pick], cpu).astype(np.float64)  # noqa: E731
                       for view, pick in VIEWS.items()}
    train = feats(train_cues)
    fits = {view: LedoitWolf().fit(f) for view, f in train.items()}
    both = LedoitWolf().fit(np.concatenate([train["first"], train["last"]], 1))
    d = train["first"].shape[1]
    first_precision = np.linalg.inv(both.covariance_[:d, :d])
    out = []
    for cues in sets:
        f = feats(cues)
        scored = {f"view {view} d2": fits[view].mahalanobis(f[view]) for view in VIEWS}
        marginal = mahalanobis(f["first"], both.location_[:d], first_precision)
        scored["last | first d2"] = both.mahalanobis(np.concatenate([f["first"], f["last"]], 1)) - marginal
        out.append(scored)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None, help="a PETNet model with a novelty density (default: the shipped one)")
    ap.add_argument("--train", required=True, help="the model's training dataset (its train and val splits)")
    ap.add_argument("--sets", required=True, help="comma-separated labelled datasets (a development set and probes)")
    ap.add_argument("--train-cues", type=int, default=3000, help="training cues to fit the task Gaussians on")
    args = ap.parse_args()

    torch.set_num_threads(2)
    model = load_checkpoint(args.model).model
    encoder = model.encoder
    if not hasattr(encoder, "feature_mean"):
        raise SystemExit("the model has no novelty density (democheck fit-novelty gives it one)")
    train, train_tasks, _, _, train_cues = features(encoder, args.train, "train", args.train_cues, with_cues=True)
    val, _, _, _, val_cues = features(encoder, args.train, "val", with_cues=True)
    parts = [features(encoder, p, with_cues=True) for p in args.sets.split(",")]
    x, labels = np.concatenate([p[0] for p in parts]), np.concatenate([p[2] for p in parts])
    var_task, cues = np.concatenate([p[3] for p in parts]), np.concatenate([p[4] for p in parts])
    prior_var = encoder.prior_var.cpu().numpy().astype(np.float64)
    kinds = sorted(set(labels) - {"clean"})
    print(f"{len(train)} training cues of {len(np.unique(train_tasks))} tasks, {len(val)} held-out, {len(x)} scored")
    print(f"{'score':<40}" + "".join(f"{k[:12]:>13}" for k in kinds))
    channels = model.cfg.conv_channels
    scored, held = densities(encoder, train, train_tasks, val, channels, x, val)
    conv = encoder.novelty_conv if model.cfg.novelty_autoencoder else encoder.conv
    viewed, viewed_held = view_densities(conv, train_cues, cues, val_cues)
    scored |= viewed
    held |= viewed_held
    for name in list(scored):
        ref = np.quantile(held[name], QUANTILE)  # as the novelty part is referenced (``fit_novelty``)
        scored[f"task uncertainty with {name}"] = np.sqrt(var_task + prior_var * (scored[name] / ref)[:, None]).mean(1)
    for name, s in (scored | test_time_spread(model, cues)).items():
        row = [roc_auc_score(labels[np.isin(labels, ["clean", k])] == k, s[np.isin(labels, ["clean", k])])
               for k in kinds]
        print(f"{name:<40}" + "".join(f"{r:13.3f}" for r in row))


if __name__ == "__main__":
    main()
