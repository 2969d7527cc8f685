"""Does deleting democheck's suspects make the robot better?  The same policy trained on five versions of a
dataset with bad demos mixed in, and its closed-loop success on the dataset's own tasks.

    python benchmarks/curation.py data/push-v1-fresh data/push-v1-fresh-probes --out runs/curation \
        [--per-kind 25] [--rollouts 300] [--steps 20000] [--seed 0] [--model petnet-push-v1]

SUITE is a pushing suite with semantic defects (``democheck synth push-v1-test --seed S``: 20% wrong-object,
both-objects, occluded, gave-up); PROBES its probes (``democheck probe``), of which ``--per-kind`` of each kind
a state-based learner can use are mixed in (no-action, random, hidden; no-objects probes have no object poses
to learn from).  The pool is audited as one dataset by democheck (the shipped model unless ``--model``) and
the policy -- ``privileged_bc.py``'s MLP on robot state and true object poses, target first -- is trained on:

  (i)   everything;
  (ii)  what ``democheck clean --drop fpr:X`` keeps, for each X of ``--fprs`` (``fpr:0.01`` = the audit's
        default flags);
  (iii) the ground-truth clean demos only;
  (iv)  what a rule-based linter keeps: demos whose largest robust |z| of idle fraction, action energy and
        jerk (the ``heuristic`` baseline) is at most 3.5, the usual MAD outlier rule;
  (v)   a random removal of as many demos as (ii) removed.

Each policy is rolled out on the same ``--rollouts`` (task, layout) pairs: tasks drawn from the pool's tasks,
layouts new.  Prints success with its 95% Wilson interval, the bad demos each set kept by kind, the clean ones
it threw away, and the share of the gap between (i) and (iii) that (ii) recovers; ``OUT/curation.json`` keeps it.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from privileged_bc import COLUMNS, load_frames, rollouts, train_policy  # noqa: E402

from democheck.audit.flagging import flagged_regardless, flags  # noqa: E402
from democheck.audit.run import gather_evidence, score_table  # noqa: E402
from democheck.audit.scorers import select  # noqa: E402
from democheck.data import open_dataset  # noqa: E402
from democheck.data.subset import write_subset  # noqa: E402
from democheck.evaluate.meta_test import wilson  # noqa: E402
from democheck.petnet.checkpoint import load_checkpoint  # noqa: E402

LEARNABLE_PROBES = ("no-action", "random", "hidden")
LINTER_Z = 3.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", type=Path)
    ap.add_argument("probes", type=Path)
    ap.add_argument("--out", type=Path, default=Path("runs/curation"))
    ap.add_argument("--per-kind", type=int, default=25)
    ap.add_argument("--rollouts", type=int, default=300)
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", default=None)
    ap.add_argument("--fprs", default="0.01", help="levels of democheck's flag to train (ii) at, comma-separated "
                    "(the first is the one (v) matches and the gap is measured at)")
    args = ap.parse_args()
    fprs = [float(x) for x in args.fprs.split(",")]
    rng = np.random.default_rng([args.seed, 7])
    t0 = time.perf_counter()

    # The pool: the suite, and per kind --per-kind probes a state-based learner can use, as one audited set.
    side = pd.read_parquet(args.probes / "meta/democheck/episodes.parquet")
    chosen = sorted(int(e) for kind in LEARNABLE_PROBES
                    for e in rng.permutation(side.loc[side["label"] == kind, "episode_index"].to_numpy())[:args.per_kind])
    with tempfile.TemporaryDirectory() as tmp:
        probes = Path(tmp) / "probes"
        probes.mkdir()
        write_subset(args.probes, chosen, probes)
        sets = [open_dataset(args.suite), open_dataset(probes)]
        ckpt = load_checkpoint(args.model)
        sets = [s.resized(ckpt.config.image_size) for s in sets]
        eps = pd.concat([s.episodes.reset_index().assign(dataset=i) for i, s in enumerate(sets)], ignore_index=True)
        eps["source_index"] = eps["episode_index"]
        eps["episode_index"] = np.arange(len(eps))
        eps["label"] = eps["label"].fillna("clean")
        scorers = select() + select(["heuristic"], audit=False)
        ev = gather_evidence(sets, ckpt, scorers, "cpu", episodes=eps, seed=args.seed)
        table = score_table(ev).sort_values("episode_index").reset_index(drop=True)
        frames = {i: load_frames(root, eps.loc[eps["dataset"] == i, "source_index"].tolist())
                  for i, root in enumerate([args.suite, probes])}
        for i, f in frames.items():  # pooled episode numbers
            f["episode_index"] = f["episode_index"].map(dict(zip(eps.loc[eps["dataset"] == i, "source_index"],
                                                                 eps.loc[eps["dataset"] == i, "episode_index"])))
        pool = pd.concat(frames.values(), ignore_index=True)
    audit_s = time.perf_counter() - t0
    labels = table["label"].to_numpy()
    flagged_at = {f: flags(table["p_value"].to_numpy(), f, flagged_regardless(table)) for f in fprs}
    flagged = flagged_at[fprs[0]]
    linter_drop = table["heuristic"].to_numpy() > LINTER_Z
    n_drop = int(flagged.sum())
    random_drop = np.zeros(len(table), bool)
    random_drop[rng.choice(len(table), size=n_drop, replace=False)] = True
    keeps = {"(i) everything": np.ones(len(table), bool),
             **{f"(ii) democheck clean --drop fpr:{f:g}": ~flagged_at[f] for f in fprs},
             "(iii) ground-truth clean": labels == "clean", f"(iv) linter (robust |z| <= {LINTER_Z:g})": ~linter_drop,
             f"(v) random removal of {n_drop}": ~random_drop}

    sims = [json.loads(s) for s in pd.read_parquet(args.suite / "meta/democheck/episodes.parquet")["sim"].dropna()]
    tasks_all = sorted({(sim["target"], sim["distractor"]) for sim in sims})
    picks = rng.integers(0, len(tasks_all), args.rollouts)
    tasks = [tasks_all[int(k)] for k in picks]
    results = {}
    for name, keep in keeps.items():
        t1 = time.perf_counter()
        rows = pool[pool["episode_index"].isin(table.loc[keep, "episode_index"])]
        policy, mse = train_policy(rows, COLUMNS["pose"], args.steps, np.random.default_rng([args.seed, 1]))
        wins = rollouts(policy, tasks, np.random.default_rng([args.seed, 2]))
        lo, hi = wilson(sum(wins), len(wins))
        kept_bad = pd.Series(labels[keep & (labels != "clean")]).value_counts().to_dict()
        results[name] = {"demos": int(keep.sum()), "clean_dropped": int(((labels == "clean") & ~keep).sum()),
                         "bad_kept": {k: int(v) for k, v in sorted(kept_bad.items())},
                         "success": float(np.mean(wins)), "ci95": [lo, hi], "wins": [bool(w) for w in wins],
                         "seconds": round(time.perf_counter() - t1, 1), "last_mse": mse}
        print(f"{name}: {results[name]['demos']} demos, success {np.mean(wins):.1%} [{lo:.1%}, {hi:.1%}] "
              f"({results[name]['seconds']:.0f} s)", flush=True)
    s = {k: v["success"] for k, v in results.items()}
    names = list(keeps)
    everything, truth = s[names[0]], s["(iii) ground-truth clean"]
    gap = truth - everything
    recovered = {f: (s[f"(ii) democheck clean --drop fpr:{f:g}"] - everything) / gap if abs(gap) > 1e-9
                 else float("nan") for f in fprs}
    summary = {"suite": str(args.suite), "probes": str(args.probes), "probe_kinds": list(LEARNABLE_PROBES),
               "per_kind": args.per_kind, "pool": {k: int(v) for k, v in pd.Series(labels).value_counts().items()},
               "rollouts": args.rollouts, "steps": args.steps, "seed": args.seed, "audit_s": round(audit_s, 1),
               "sets": results, "gap_recovered_by_democheck": recovered}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "curation.json").write_text(json.dumps(summary, indent=2))
    print(f"\npool: {summary['pool']}; {args.rollouts} rollouts per policy on the same tasks and layouts\n")
    print("| training set | demos | bad demos kept | clean demos dropped | success [95% CI] |")
    print("|---|---:|---|---:|---|")
    for name, r in results.items():
        bad = ", ".join(f"{k} {v}" for k, v in r["bad_kept"].items()) or "none"
        print(f"| {name} | {r['demos']} | {bad} | {r['clean_dropped']} | {r['success']:.1%} "
              f"[{r['ci95'][0]:.1%}, {r['ci95'][1]:.1%}] |")
    print("\nshare of the gap between (i) and (iii) democheck's cleaning recovers: "
          + ", ".join(f"fpr {f:g} {r:.0%}" for f, r in recovered.items()))


if __name__ == "__main__":
    main()
