"""Do the reasons say what happened?  Per planted kind, the share of its flagged demos whose reason leads with the
finding that names the cause:

    python benchmarks/reasons.py AUDIT [--labels LABELS.csv]

AUDIT is a ``democheck audit`` folder; labels come from the table's ``label`` column (synthetic sets) or from a
csv of ``episode_index,label``.  ``CAUSE`` holds, per kind, the findings (``check`` or ``check:kind``, as the
table's ``finding`` column names the lead) that name its cause: the arm standing still for an idle demo, the view
covered for an occluded one, the world left unlike the task's for a wrong object...  Also printed: the median and
largest reason length, whether any reason prints a probability under 1e-12, a negative mutual information or a
latent dimension, and how many demos the words count as clean (the reference, less the flagged) a reason calls
beyond every clean demo (none should be).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pandas as pd

STILL = ("idle", "motion:hardly", "motion:less")
FLAIL = ("motion:more", "motion:flails", "jerk:shakes", "grasps:chatters")
# a picture unlike its task's, over the demo or at its first or last frames (where a card or a moved camera shows)
VIEW = ("view:changed", "colours:changed", "start:view", "end:view", "moved:view")
WORLD = ("outcome", "moved")  # the world left: as recorded, or as the camera saw it
CAUSE = {
    "idle": STILL, "no-action": STILL, "gave-up": STILL + WORLD,
    "random": FLAIL, "jerky": FLAIL, "jittery": FLAIL,
    "occluded": VIEW, "hidden": VIEW, "no-objects": VIEW + ("moved:not moved",),  # its objects not there
    "wrong-object": WORLD, "both-objects": WORLD, "wrong-task": WORLD,
    "frozen-camera": ("frozen_video",), "frozen-state": ("frozen_state",), "dead-dim": ("frozen_state",),
    "scaled": FLAIL + ("lag:scale",), "sensor-nan": ("broken",), "lagged": ("lag:delay",),
    "dropped": ("frame_jump", "state_jump"), "nan": ("broken",),
    # done backwards, or the task undone forwards (a reset recorded as a demo): it begins where its task's demos end
    "reversed": ("backwards:done backwards", "backwards_state:done backwards", "start:where they end",
                 "end:where they begin", "path:backwards", "outcome:undone"),
    "hesitates": ("pause", "idle"),
    # on the way: a path unlike its task's (a detour; a drop, the arm back down and up again), an end unlike
    # its task's, the world left otherwise or the gripper ending open where its task's demos hold (an object
    # let go off its goal)
    "detour": ("path:state", "path:view", "motion:more"),
    "drop-regrasp": ("grasps", "path:state", "path:view", "pause"), "regrasp": ("grasps", "path:state", "path:view"),
    "failed-place": ("end:view", "grasps:ends otherwise") + WORLD,
}
CAUSE["reset"] = CAUSE["reversed"]
TINY = re.compile(r"e-(1[2-9]|[2-9]\d|\d{3,})\b")  # a probability under 1e-12, printed
LATENT = re.compile(r"(?<!state )dimension \d|widest on|furthest from its task on")  # not a recorded one


def names_cause(finding: str, cause: tuple[str, ...]) -> bool:
    """Whether a lead ('check:kind') is one of ``cause`` ('check' for any of its kinds, or 'check:kind')."""
    return any(finding == c or finding.split(":")[0] == c for c in cause)


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
        cause = CAUSE.get(kind, ())
        named = flagged["finding"].astype(str).map(lambda f: names_cause(f, cause))
        out[kind] = {"flagged": len(flagged), "lead names the cause": round(float(named.mean()), 2)
                     if len(flagged) else None}
        if len(flagged) and named.mean() < 1:
            missed = flagged.loc[~named]
            out[kind]["leads"] = missed["finding"].value_counts().head(3).to_dict()
            out[kind]["e.g."] = str(missed["reason"].iloc[0]).split("; also ")[0][:150]
    details = table["details"].astype(str)
    lengths = table["reason"].astype(str).str.len()
    out["reasons"] = {"median characters": int(lengths.median()), "largest": int(lengths.max()),
                      "probability under 1e-12": int(details.map(lambda d: bool(TINY.search(d))).sum()),
                      "negative information": int(details.str.contains(r"information -\d").sum()),
                      "latent dimension": int(details.str.contains(LATENT).sum()),
                      "clean demos called beyond every clean demo": int(
                          (table["reference"] & ~table["is_anomaly"]
                           & details.str.contains("beyond every clean demo")).sum())}
    for k, v in out.items():
        print(f"{k:14s} {v}")
    return out


if __name__ == "__main__":
    main()
