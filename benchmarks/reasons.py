"""Do the reasons say what happened?  Per planted kind, the share of its flagged demos whose reason's first clause
names the cause in a reviewer's words:

    python benchmarks/reasons.py AUDIT [--labels LABELS.csv]

AUDIT is a ``democheck audit`` folder; labels come from the table's ``label`` column (synthetic sets) or from a
csv of ``episode_index,label``.  ``CAUSE`` holds, per kind, the words that name its cause (the arm standing
still for an idle demo, the view covered for an occluded one, the world left unlike the task's for a wrong
object...).  Also printed: the median and largest reason length, and whether any reason prints a probability
under 1e-12, a negative mutual information or a latent dimension.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pandas as pd

STILL = ("stands still", "hardly moves", "moves less")
FLAIL = ("move more", "shake")
VIEW = ("view is covered", "colours changed")
WORLD = ("left the world",)
CAUSE = {
    "idle": STILL, "no-action": STILL, "gave-up": STILL + WORLD,
    "random": FLAIL, "jerky": FLAIL, "jittery": FLAIL,
    "occluded": VIEW, "hidden": VIEW, "no-objects": VIEW,
    "wrong-object": WORLD, "both-objects": WORLD, "wrong-task": WORLD,
    "frozen-camera": ("picture stays the same",), "frozen-state": ("holds one value",),
    "dead-dim": ("holds one value",), "scaled": FLAIL + ("another scale",), "sensor-nan": ("broken",),
    "lagged": ("follow its actions best",), "dropped": ("frame jumps",), "nan": ("broken",),
}
TINY = re.compile(r"e-(1[2-9]|[2-9]\d|\d{3,})\b")  # a probability under 1e-12, printed
LATENT = re.compile(r"(?<!state )dimension \d|widest on|furthest from its task on")  # not a recorded one


def first_clause(reason: str) -> str:
    return str(reason).split("; also ")[0]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("audit", type=Path)
    ap.add_argument("--labels", type=Path)
    args = ap.parse_args(argv)
    table = pd.read_parquet(args.audit / "scores.parquet")
    if args.labels is not None:
        table = table.drop(columns="label", errors="ignore").merge(pd.read_csv(args.labels), on="episode_index")
    labels = table["label"].fillna("clean").astype(str)
    out = {}
    for kind in sorted(set(labels) - {"clean"}):
        flagged = table[(labels == kind) & table["is_anomaly"]]
        words = CAUSE.get(kind, ())
        named = flagged["reason"].map(lambda r: any(w in first_clause(r) for w in words))
        out[kind] = {"flagged": len(flagged), "first clause names the cause": round(float(named.mean()), 2)
                     if len(flagged) else None}
        if len(flagged) and named.mean() < 1:
            out[kind]["e.g."] = first_clause(flagged.loc[~named, "reason"].iloc[0])[:150]
    details = table["details"].astype(str)
    lengths = table["reason"].astype(str).str.len()
    out["reasons"] = {"median characters": int(lengths.median()), "largest": int(lengths.max()),
                      "probability under 1e-12": int(details.map(lambda d: bool(TINY.search(d))).sum()),
                      "negative information": int(details.str.contains(r"information -\d").sum()),
                      "latent dimension": int(details.str.contains(LATENT).sum())}
    for k, v in out.items():
        print(f"{k:14s} {v}")
    return out


if __name__ == "__main__":
    main()
