"""What the flags were calibrated on: how many of each labelled kind an audit kept in its reference (the robust core
that the tails are fitted on and the conformal flags count against), and whether those demos, rather than the
clean ones, set the flag level.

    python benchmarks/reference_purity.py REPORT [REPORT ...] [--labels L.csv ...]

Per audit: each label's demos, how many the reference holds and how many were flagged; the suspicion at the
reference's ``1 - fpr`` quantile beside the clean demos' largest; the clean demos flagged beside the number
``--fpr`` expects of them and its binomial 95% interval; and the labels of the reference's most suspect demos.
Where bad demos the checks see only weakly stay in the reference, they are its most suspect and the level rises
above every clean demo: fewer clean demos are flagged than the rate promises, and bad demos just above the clean
ones go unflagged.  Labels come from ``--labels`` (``episode_index,label``; one per report, in order) or the
table's ``label`` column.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import binom


def labelled(report: Path, labels: Path | None) -> pd.DataFrame:
    table = pd.read_parquet(report / "scores.parquet")
    if labels is not None:
        table = table.drop(columns="label", errors="ignore").merge(pd.read_csv(labels), on="episode_index",
                                                                   how="left")
    if "label" not in table:
        raise SystemExit(f"{report}: no labels (give --labels)")
    return table.assign(label=table["label"].fillna("clean").astype(str))


def purity(table: pd.DataFrame, fpr: float, top: int = 10) -> dict:
    ref = table[table["reference"]]
    clean = table[table["label"] == "clean"]
    per_label = table.groupby("label").agg(demos=("suspicion", "size"), in_reference=("reference", "sum"),
                                           flagged=("is_anomaly", "sum"))
    low, high = binom.ppf([0.025, 0.975], len(clean), fpr)
    most = ref.nlargest(top, "suspicion")
    return {
        "per_label": {k: {c: int(v) for c, v in row.items()} for k, row in per_label.iterrows()},
        "reference": int(len(ref)),
        "bad_in_reference": int((ref["label"] != "clean").sum()),
        "reference_level": float(ref["suspicion"].quantile(1 - fpr)),
        "clean_largest": float(clean["suspicion"].max()),
        "clean_flagged": int(clean["is_anomaly"].sum()),
        "clean_expected": round(fpr * len(clean), 1),
        "clean_interval": [int(low), int(high)],
        "reference_most_suspect": most["label"].tolist(),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="+", type=Path)
    parser.add_argument("--labels", nargs="*", type=Path, default=[])
    args = parser.parse_args(argv)
    if args.labels and len(args.labels) != len(args.reports):
        parser.error("give one --labels file per report, or none")
    for i, report in enumerate(args.reports):
        fpr = json.loads((report / "summary.json").read_text())["flag"]["fpr"]
        out = purity(labelled(report, args.labels[i] if args.labels else None), fpr)
        print(f"== {report} (--fpr {fpr})")
        for label, row in out.pop("per_label").items():
            print(f"  {label:16s} {row['demos']:4d} demos, {row['in_reference']:4d} in the reference, "
                  f"{row['flagged']:4d} flagged")
        for key, value in out.items():
            print(f"  {key}: {np.round(value, 2) if isinstance(value, float) else value}")


if __name__ == "__main__":
    main()
