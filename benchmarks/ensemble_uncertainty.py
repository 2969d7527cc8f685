"""Does a deep ensemble of PETNets give a task uncertainty that knows what it has not seen?

    python benchmarks/ensemble_uncertainty.py MODEL MODEL [MODEL ...] --sets DATA[,DATA...] [--train data/push-v1]

Each MODEL is a PETNet trained on the same data with its own seed (``democheck train ... --seed S``).  Every
member encodes the cues of the ``--sets`` (a development set and its probes) and the training split's cues of
``--train``.  The members' embedding spaces are put onto the first member's by a similarity transform
(orthogonal Procrustes with scale and translation) fitted on the training tasks' mean embeddings, the
variances carried through it; the ensemble's posterior is the members' mixture moment-matched to one
Gaussian: the mean of their variances plus the variance of their means (law of total variance).  Also
measured without any alignment: in task-identity space, each member's posterior over the sets' tasks (each
task the product of its other demos, as ``consistency`` uses them), its entropy, the entropy of the members'
mean posterior, and their mutual information.

Prints the AUROC of each against the clean demos for every labelled kind, how well the alignment fits (the
share of the prototypes' spread it leaves), and Figure 5A's separation (each kind's mean score minus the clean
mean, in clean standard deviations) for the ensemble's task uncertainty.
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from sklearn.metrics import roc_auc_score

from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.encode import encode


def similarity(src: np.ndarray, dst: np.ndarray):
    """The similarity transform taking ``src`` points onto ``dst`` (least squares), for means and diagonal
    variances, and the share of ``dst``'s spread it leaves unexplained."""
    cs, cd = src.mean(0), dst.mean(0)
    a, b = src - cs, dst - cd
    u, s, vt = np.linalg.svd(a.T @ b)
    rot = u @ vt
    scale = s.sum() / (a ** 2).sum()
    residual = np.sqrt(((scale * a @ rot - b) ** 2).sum(1).mean() / (b ** 2).sum(1).mean())
    return (lambda x: scale * (x - cs) @ rot + cd), (lambda v: scale ** 2 * v @ (rot ** 2)), float(residual)


def task_identity(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray) -> np.ndarray:
    """[N, tasks]: each cue's posterior over the tasks, each task the product of its demos other than the cue."""
    names = np.unique(tasks)
    logp = np.zeros((len(mu), len(names)))
    prec = 1.0 / var
    for j, t in enumerate(names):
        own = tasks == t
        p_sum, m_sum = prec[own].sum(0), (prec[own] * mu[own]).sum(0)
        p = np.where(own[:, None], p_sum[None] - prec, p_sum[None])
        m = np.where(own[:, None], m_sum[None] - prec * mu, m_sum[None]) / np.maximum(p, 1e-12)
        v = 1.0 / np.maximum(p, 1e-12) + var
        logp[:, j] = -0.5 * ((mu - m) ** 2 / v + np.log(v)).sum(1)
    logp -= logp.max(1, keepdims=True)
    post = np.exp(logp)
    return post / post.sum(1, keepdims=True)


def entropy(p: np.ndarray) -> np.ndarray:
    return -(p * np.log(np.maximum(p, 1e-300))).sum(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+")
    ap.add_argument("--sets", required=True, help="comma-separated datasets with labels (a set and its probes)")
    ap.add_argument("--train", default="data/push-v1", help="the members' training data (its train split)")
    args = ap.parse_args()
    train = open_dataset(args.train)
    split = train.episodes["split"] if "split" in train.episodes else pd.Series("train", train.episodes.index)
    train_eps = [int(e) for e in train.episodes.index[split == "train"]]
    train_cues, train_tasks = train.cue_frames_many(train_eps), train.episodes.loc[train_eps, "task"].to_numpy()
    train_ends = train.end_states(train_eps)
    sets = [open_dataset(p) for p in args.sets.split(",")]
    cues = np.concatenate([d.cue_frames_many(d.episode_indices) for d in sets])
    ends = np.concatenate([d.end_states(d.episode_indices) for d in sets])
    labels = np.concatenate([d.episodes["label"].fillna("clean").to_numpy() if "label" in d.episodes
                             else np.full(len(d), "clean") for d in sets])
    tasks = np.concatenate([d.episodes["task"].to_numpy() for d in sets])
    kinds = sorted(set(labels) - {"clean"})
    clean = labels == "clean"

    def row(name: str, score: np.ndarray) -> None:
        au = [roc_auc_score(labels[(labels == k) | clean] == k, score[(labels == k) | clean]) for k in kinds]
        print(f"  {name:<34}" + "".join(f"{a:>9.3f}" for a in au))

    members, prototypes = [], []
    for path in args.models:
        model = load_checkpoint(path).model.eval()
        post = encode(model, cues, end_states=ends)
        members.append((post.mu.astype(np.float64), post.var.astype(np.float64)))
        train_mu = encode(model, train_cues, end_states=train_ends).mu
        prototypes.append(pd.DataFrame(train_mu).groupby(train_tasks).mean().to_numpy())
    aligned = []
    print(f"{len(cues)} cues of {', '.join(args.sets.split(','))}; {len(members)} members")
    for (mu, var), proto, path in zip(members, prototypes, args.models):
        f, g, residual = similarity(proto, prototypes[0])
        aligned.append((f(mu), g(var)))
        print(f"  alignment of {path} onto the first: {residual:.1%} of the prototypes' spread left")
    means, variances = np.stack([a[0] for a in aligned]), np.stack([a[1] for a in aligned])
    within, between = variances.mean(0), means.var(0)
    print(f"  {'AUROC against clean':<34}" + "".join(f"{k[:8]:>9}" for k in kinds))
    for (mu, var), path in zip(members, args.models):
        row(f"task uncertainty: {path.rsplit('/', 1)[-1]}", np.sqrt(var).mean(1))
    total = np.sqrt(within + between).mean(1)
    row("ensemble task uncertainty", total)
    row("members' disagreement alone", np.sqrt(between).mean(1))
    posts = [task_identity(mu, var, tasks) for mu, var in members]
    for p, path in zip(posts, args.models):
        row(f"task-identity entropy: {path.rsplit('/', 1)[-1]}", entropy(p))
    mean_post = np.mean(posts, 0)
    row("entropy of the members' mean", entropy(mean_post))
    row("mutual information", entropy(mean_post) - np.mean([entropy(p) for p in posts], 0))
    print("  Figure 5A, ensemble task uncertainty: (kind mean - clean mean) / clean SD")
    for k in kinds:
        print(f"    {k:<14} {(total[labels == k].mean() - total[clean].mean()) / total[clean].std():7.2f}")


if __name__ == "__main__":
    main()
