"""Which features should the novelty density be over?  The measurement behind the cue autoencoder
(``democheck/petnet/novelty.py``).

    python benchmarks/novelty_features.py --train data/push-v1 --sets data/push-v1-dev,data/push-v1-dev-probes \
        [--steps 3000] [--model petnet-push-v1] [--seed 0] [--ensemble 1,2] [--frames 20000] [--partial 0.5,3]

Trains the cue autoencoder on the training split's cues (``novelty.train_cue_autoencoder``, ``--steps``), fits one
Gaussian (Ledoit-Wolf) over its encoder's features of those cues and one over the model's own conv features, each
referenced to the val split's cues at ``novelty.QUANTILE``, and prints, on the ``--sets`` datasets pooled (their
cues; no kind is fitted on), the AUROC of each labelled kind against the clean demos and how many clean standard
deviations its mean lies above the clean mean, for: the autoencoder's d2, the model's own conv features' d2, and the
autoencoder's reconstruction error.  ``--ensemble SEEDS``: autoencoders trained from those seeds too, each with
its own Gaussian, and the mean of all the members' d2 / d2_ref (an ensemble of densities: does averaging out one
autoencoder's accidents see more?).  ``--frames N``: a *frame* autoencoder too, trained on N frames drawn from every
step of the training split's demos (each fed as a cue of that frame twice, so the same code trains it), its
Gaussian over their features; a cue scored by the d2 of its first frame, of its last, their larger, and that
added to or maxed with the cue autoencoder's d2 -- the arm in every pose a demo passes through is familiar, an
arm-less or empty picture is not.  ``--partial FROM,PER``: a cue autoencoder trained on the training cues and PER
partial cues of each training demo (its first frame and a frame drawn from the last 1 - FROM of it), its Gaussian
fitted on the true cues: the arm stretched mid-push becomes familiar in the last frame's place.  ``--ends``: an
autoencoder trained on the training cues' last frames alone (each as a cue of that frame twice), its Gaussian over
their features: familiar with how demos end and nothing else.  Every autoencoder's row reads the cue as it is
(``view`` "cue"); ``autoencoder d2, last frame`` reads the first one's features of the last frame in both places,
as ``democheck train`` now fits the density (``novelty.NOVELTY_VIEW``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from sklearn.covariance import LedoitWolf

from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.petnet.batches import task_rows
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.model import cue_input
from democheck.petnet.novelty import QUANTILE, conv_features, cue_decoder, stack_features, train_cue_autoencoder
from object_encoder import auroc_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", required=True)
    ap.add_argument("--sets", required=True, help="comma-separated labelled datasets to report on, pooled")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--model", default="petnet-push-v1")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ensemble", default="", help="comma-separated seeds of more autoencoders, averaged with --seed's")
    ap.add_argument("--frames", type=int, default=0, help="also a frame autoencoder on this many training frames")
    ap.add_argument("--partial", default="", help="FROM,PER: also a cue autoencoder trained with partial cues too")
    ap.add_argument("--ends", action="store_true", help="also an autoencoder trained on the cues' last frames alone")
    args = ap.parse_args()
    cpu = torch.device("cpu")
    ckpt = load_checkpoint(args.model)
    arrays = build_cache(open_dataset(args.train, image_size=ckpt.config.image_size))
    seed = int(ckpt.meta.get("training", {}).get("seed", 0))
    train = arrays.cue(np.concatenate(list(task_rows(arrays, "train", seed).values())))
    val = arrays.cue(np.concatenate(list(task_rows(arrays, "val", seed).values())))
    t0 = time.perf_counter()
    torch.manual_seed(args.seed)
    decoder = cue_decoder(ckpt.config)  # trained beside the encoder; kept here for the reconstruction error
    conv, loss = train_cue_autoencoder(train, ckpt.config, cpu, args.steps, args.seed, decoder=decoder)
    print(f"cue autoencoder: {args.steps} steps, final loss {loss:.4f}, {time.perf_counter() - t0:.0f} s")
    own = lambda cues: conv_features(ckpt.model.encoder, cues, cpu)[0]  # noqa: E731
    ae = lambda cues: stack_features(conv, cues, cpu)  # noqa: E731
    members = [("autoencoder d2, last frame", lambda cues: stack_features(conv, cues, cpu, view="last"))]
    if args.ends:
        conv_e = train_cue_autoencoder(train[:, [1, 1]], ckpt.config, cpu, args.steps, args.seed)[0]
        members.append(("end autoencoder d2", lambda cues: stack_features(conv_e, cues, cpu, view="last")))
    if args.partial:
        start, per = float(args.partial.split(",")[0]), int(args.partial.split(",")[1])
        rows = np.repeat(np.concatenate(list(task_rows(arrays, "train", seed).values())), per)
        rng = np.random.default_rng(args.seed)
        end = ((start + (1 - start) * rng.random(len(rows))) * (arrays.lengths[rows] - 1)).astype(np.int64)
        conv_p = train_cue_autoencoder(np.concatenate([train, arrays.cue(rows, end)]), ckpt.config, cpu, args.steps,
                                       args.seed)[0]
        members.append((f"autoencoder d2, partial cues {args.partial}", lambda cues: stack_features(conv_p, cues, cpu)))
    for seed_m in [int(v) for v in args.ensemble.split(",") if v]:
        conv_m = train_cue_autoencoder(train, ckpt.config, cpu, args.steps, seed_m)[0]
        members.append((f"autoencoder d2, seed {seed_m}", lambda cues, c=conv_m: stack_features(c, cues, cpu)))
    fits = {}
    for name, feats in (("autoencoder d2", ae), ("own conv d2", own), *members):
        density = LedoitWolf().fit(feats(train).astype(np.float64))
        ref = float(np.quantile(density.mahalanobis(feats(val).astype(np.float64)), QUANTILE))
        fits[name] = (feats, density, ref)
    cues, labels = [], []
    for path in args.sets.split(","):
        ds = open_dataset(path, image_size=ckpt.config.image_size)
        cues.append(ds.cue_frames_many(ds.episode_indices))
        eps = ds.episodes
        labels.append(eps["label"].fillna("clean").to_numpy() if "label" in eps else np.full(len(eps), "clean"))
    x, lab = np.concatenate(cues), np.concatenate(labels)
    values = {name: density.mahalanobis(feats(x).astype(np.float64)) / ref for name, (feats, density, ref) in fits.items()}
    seeds = [n for n, _ in members if ", seed " in n]
    if seeds:
        values["ensemble mean d2"] = np.mean([values["autoencoder d2"]] + [values[n] for n in seeds], axis=0)
    with torch.no_grad():
        err = []
        for s in range(0, len(x), 256):
            inp = cue_input(torch.from_numpy(x[s:s + 256]))
            err.append(((decoder(conv(inp)) - inp) ** 2).mean((1, 2, 3)).numpy())
    values["reconstruction error"] = np.concatenate(err)
    if args.frames:
        values |= frame_density(arrays, seed, args, ckpt.config, x, values["autoencoder d2"])
    auroc_table(args.sets, values, lab)


def frame_density(arrays, split_seed: int, args, cfg, cues: np.ndarray, cue_d2: np.ndarray) -> dict[str, np.ndarray]:
    """The ``--frames`` rows: a frame autoencoder's Gaussian (see above), each d2 over the val split's frames'
    ``QUANTILE``."""
    cpu, rng = torch.device("cpu"), np.random.default_rng(args.seed)

    def frames(split: str, n: int) -> np.ndarray:
        rows = rng.choice(np.concatenate(list(task_rows(arrays, split, split_seed).values())), n)
        steps = (rng.random(n) * arrays.lengths[rows]).astype(np.int64)
        return arrays.frames[np.sort(arrays.offsets[rows] + steps)]

    twice = lambda f: np.stack([f, f], axis=1)  # noqa: E731
    train, val = frames("train", args.frames), frames("val", max(args.frames // 10, 1))
    t0 = time.perf_counter()
    conv, loss = train_cue_autoencoder(twice(train), cfg, cpu, args.steps, args.seed)
    print(f"frame autoencoder: {args.steps} steps, final loss {loss:.4f}, {time.perf_counter() - t0:.0f} s")
    feats = lambda f: stack_features(conv, twice(f), cpu).astype(np.float64)  # noqa: E731
    density = LedoitWolf().fit(feats(train))
    ref = float(np.quantile(density.mahalanobis(feats(val)), QUANTILE))
    first, last = (density.mahalanobis(feats(cues[:, i])) / ref for i in (0, 1))
    both = np.maximum(first, last)
    return {"frame d2, first": first, "frame d2, last": last, "frame d2, larger": both,
            "cue + frame d2": cue_d2 + both, "max(cue, frame d2)": np.maximum(cue_d2, both)}


if __name__ == "__main__":
    main()
