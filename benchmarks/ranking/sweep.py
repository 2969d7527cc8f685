"""Vary the ranking over saved audits: one ``RankingConfig`` per variant, the audit's own ``ranking.rank``.

    python benchmarks/ranking/sweep.py AUDIT [AUDIT ...] [--labels A.labels.csv ...] [--variants shipped,no-looks]

Each AUDIT is a ``democheck audit`` folder (its ``scores.parquet``; labels from a ``label`` column there or from
``--labels``, one csv of ``episode_index,label`` per audit in order).  Each variant is a change to the config the
audit recorded in ``summary.json`` (``ranking``): the table is ranked again with it and scored per planted kind
(AUROC of the suspicion against the clean demos, and how many of the kind it flags) and by the clean demos it
flags at the audit's ``--fpr``.  The ``shipped`` variant reproduces the audit's own suspicion (checked).  ``VARIANTS`` lists the others; add one there.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from democheck.audit.flagging import broken_recordings, conformal_p, flagged_regardless, flags
from democheck.audit.metrics import detection
from democheck.audit.ranking import RankingConfig, rank
from democheck.audit.evidence import comparison_groups

RECORDING_FAULTS = ("jerk", "lag", "timing", "frozen_video", "frame_jump", "state_jump", "frozen_state")
TIME_ALIGNED = ("start", "end", "path")

def _set(config: RankingConfig, names: tuple[str, ...], **changes) -> RankingConfig:
    """``config`` with ``changes`` made to the specs of the scores ``names``."""
    return replace(config, specs=tuple(replace(s, **changes) if s.name in names else s for s in config.specs))


# Each: a config -> a config.  The questions the ranking's choices answered (see README.md here).
VARIANTS: dict[str, Callable[[RankingConfig], RankingConfig]] = {
    "shipped": lambda c: c,
    "no-looks": lambda c: replace(c, specs=tuple(replace(s, look="") for s in c.specs)),
    "no-faults-apart": lambda c: replace(c, specs=tuple(replace(s, alone=False) for s in c.specs)),
    "exponential-tails": lambda c: replace(c, specs=tuple(replace(s, tail="exponential") for s in c.specs)),
    "no-floors": lambda c: replace(c, specs=tuple(replace(s, floor=0.0) for s in c.specs)),
    "pooled-units": lambda c: replace(c, task_units=False),
    "core-1e-3": lambda c: replace(c, core_p=1e-3),
    "core-1e-6": lambda c: replace(c, core_p=1e-6),
    "without-outcome": lambda c: c.without("outcome"),
    "without-grasps": lambda c: c.without("grasps"),
    "without-faults": lambda c: c.without(*RECORDING_FAULTS),
    "without-time": lambda c: c.without(*TIME_ALIGNED),
    "without-backwards": lambda c: c.without("backwards", "backwards_state"),
    "without-time-and-pause": lambda c: c.without(*TIME_ALIGNED, "pause"),
    "time-apart": lambda c: replace(c, specs=tuple(replace(s, alone=True) if s.name in TIME_ALIGNED + ("pause",)
                                                   else s for s in c.specs)),
    "time-look-apart": lambda c: replace(c, specs=tuple(replace(s, alone=True) if s.name in TIME_ALIGNED else s
                                                        for s in c.specs)),
    "outcome-apart": lambda c: replace(c, specs=tuple(replace(s, alone=True) if s.name == "outcome" else s
                                                      for s in c.specs)),
    "outcome-in-sum": lambda c: replace(c, specs=tuple(replace(s, beside=False) if s.name == "outcome" else s
                                                       for s in c.specs)),
    "without-moved": lambda c: c.without("moved"),
    "moved-in-sum": lambda c: _set(c, ("moved",), beside=False),
    "moved-apart": lambda c: _set(c, ("moved",), alone=True),
    "moved-with-outcome": lambda c: _set(c, ("moved", "outcome"), look="the world left", beside=True),
    "coupling-exponential": lambda c: _set(c, ("coupling",), tail="exponential"),
    "path-beside": lambda c: _set(c, ("path",), beside=True),
    "time-beside": lambda c: _set(c, TIME_ALIGNED, beside=True),
    "time-normal": lambda c: _set(c, TIME_ALIGNED, tail="normal"),
    "start-end-normal": lambda c: _set(c, ("start", "end"), tail="normal"),
    "path-own-look": lambda c: _set(c, ("path",), look=""),
    "path-beside": lambda c: _set(c, ("path",), beside=True),
    "path-own-beside": lambda c: _set(c, ("path",), look="", beside=True),
    "time-one-look": lambda c: replace(c, specs=tuple(replace(s, look="in time") if s.name in TIME_ALIGNED else s
                                                      for s in c.specs)),
    "outcome-normal": lambda c: _set(c, ("outcome",), tail="normal"),
}


def rerank(table: pd.DataFrame, config: RankingConfig, fpr: float) -> tuple[np.ndarray, np.ndarray]:
    """The suspicion and the flags of ``table``'s demos under ``config``."""
    values = {n: table[n].to_numpy(np.float64) for n in config.names}
    r = rank(values, comparison_groups(table["task"].to_numpy()), config, broken_recordings(table))
    return r.suspicion, flags(conformal_p(r.suspicion, r.core), fpr, flagged_regardless(table))


def evaluate(table: pd.DataFrame, suspicion: np.ndarray, flagged: np.ndarray) -> dict:
    labels = table["label"].fillna("clean").astype(str).to_numpy()  # a synthetic set labels only its defects
    clean = labels == "clean"
    out = {}
    for kind in sorted(set(labels) - {"clean"}):
        bad = labels == kind
        y = np.r_[np.ones(bad.sum(), bool), np.zeros(clean.sum(), bool)]
        out[kind] = round(detection(y, np.r_[suspicion[bad], suspicion[clean]])["auroc"], 4)
        out[f"{kind} flagged"] = f"{int(flagged[bad].sum())} of {int(bad.sum())}"
    out["clean flagged"] = f"{int(flagged[clean].sum())} of {int(clean.sum())}"
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("audits", nargs="+", type=Path)
    ap.add_argument("--labels", nargs="*", type=Path, default=[])
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated names from VARIANTS")
    args = ap.parse_args(argv)
    results = {}
    for i, audit in enumerate(args.audits):
        table = pd.read_parquet(audit / "scores.parquet")
        if i < len(args.labels):
            table = table.drop(columns="label", errors="ignore").merge(pd.read_csv(args.labels[i]), on="episode_index")
        if "label" not in table:
            sys.exit(f"{audit}: no labels (a label column, or --labels)")
        summary = json.loads((audit / "summary.json").read_text())
        config = RankingConfig.from_dict(summary["ranking"])
        fpr = summary["flag"]["fpr"]
        for name in args.variants.split(","):
            suspicion, flagged = rerank(table, VARIANTS[name](config), fpr)
            if name == "shipped":  # the sweep ranks and flags as the audit did
                np.testing.assert_allclose(suspicion, table["suspicion"].to_numpy(np.float64), rtol=1e-6)
                np.testing.assert_array_equal(flagged, table["is_anomaly"].to_numpy(bool))
            results[(audit.name, name)] = evaluate(table, suspicion, flagged)
            print(f"{audit.name:24s} {name:18s} {results[(audit.name, name)]}", flush=True)
    return results


if __name__ == "__main__":
    main()
