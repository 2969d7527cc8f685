"""The development-set sweep behind the ``colours`` check (``democheck.audit.colours``) and the ranking's
core-centred calibration (``scores.calibrated`` with ``core``).

    python benchmarks/colour_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output (scores.parquet: each demo's dataset, source episode, task, label and
every scorer's score).  Every dataset the bench read is decoded once more for each demo's colour shares at 4
and 8 ranges per channel (``ColourStats``); then for each floor (log units) and form (RMS or largest z over the
colours shown) the colour score joins the bench's columns in one of three ways -- ``add`` (its own score in the
ranking), ``max`` (folded into ``view``: the larger of the two robust z), ``replace`` (in view's place) -- and
the ranking is combined as ``democheck audit`` combines it, each task centred on all its demos (``all``, the
calibration before) or on its robust core's (``core``, the shipped one).  Printed per variant: the ranking's
AUROC per kind, the clean demos flagged at ``--fpr 0.01`` against the number the audit expects, and each kind's
share flagged; the first rows are the ranking without the colour check; ``--no-model`` rows rank the model-free
scores alone.  A bench written before the colour check existed has no ``colours`` column; one written after
has, and it is left out of the rows without the check.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from suspicion_choices import aurocs, bench_tables

from democheck.audit import colours, flagging, ranking, scores
from democheck.audit.ranking import ranking_z
from democheck.audit.scorers import SCORERS, Evidence
from democheck.data import open_dataset

LEVELS = (4, 8)
FLOORS = (0.25, 0.5, 1.0)
FORMS = ("rms", "max")
MODES = ("add", "max", "replace")


def colour_shares(table: pd.DataFrame, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """([N, levels ** 3] colour shares, [N] one pixel's share) of every row, as ``ColourStats`` makes them."""
    old, colours.COLOUR_LEVELS = colours.COLOUR_LEVELS, levels
    try:
        shares, pixel = np.zeros((len(table), levels ** 3)), np.zeros(len(table))
        for path, rows in table.groupby("dataset").groups.items():
            ds, stats = open_dataset(path), colours.ColourStats()
            for i in rows:
                stats.add(ds[int(table.at[i, "source_index"])])
            shares[np.asarray(rows)], pixel[np.asarray(rows)] = stats.arrays()
        return shares, pixel
    finally:
        colours.COLOUR_LEVELS = old


def colour_score(shares: np.ndarray, pixel: np.ndarray, tasks: np.ndarray, floor: float, form: str) -> np.ndarray:
    """The colour score with this floor and form, in robust SD within the task (as ``colours.colours``)."""
    old, colours.COLOUR_FLOOR = colours.COLOUR_FLOOR, floor
    try:
        z = colours.colour_z(shares, pixel, tasks)[0]
    finally:
        colours.COLOUR_FLOOR = old
    with np.errstate(all="ignore"):
        raw = np.sqrt(np.nanmean(z ** 2, axis=1)) if form == "rms" else np.nanmax(z, axis=1)
    return scores.calibrated(raw, tasks, min_scale=colours.COLOUR_MIN_SCALE)


def judged(table: pd.DataFrame, colour: np.ndarray | None, mode: str, centring: str, model_free: bool) -> str:
    labels = table["label"].fillna("clean").to_numpy()
    tasks = table["task"].to_numpy()
    values = {c: table[c].to_numpy(float) for c in table if c in SCORERS and c != "colours"}
    names = ranking.ranked(values, tasks, model_free)
    if colour is not None:
        if mode == "add":
            values["colours"] = colour
            names.append("colours")
        elif mode == "max":
            values["view"] = np.fmax(values["view"], colour)
        else:
            values["view"] = colour
    ev = Evidence(episodes=table[["episode_index", "task"]], scores=values)
    z = (lambda core: ranking_z(ev, names, core)) if centring == "core" else ranking_z(ev, names)
    log_p, core = scores.robust_tails(z, normal=ranking.normal_tails(names), alone=ranking.alone_columns(names),
                                      looks=ranking.look_columns(names))
    s = ranking.combine(names, log_p)
    au = aurocs(s, labels)
    kinds = sorted(set(labels) - {"clean"})
    flagged = flagging.conformal_p(s, core) <= flagging.DEFAULT_FPR
    clean = labels == "clean"
    return (" ".join(f"{au[k]:.3f}" for k in kinds) + f" | clean {flagged[clean].sum():3d} (expected "
            f"{flagging.expected_false_flags(core, flagging.DEFAULT_FPR):4.1f}) "
            + " ".join(f"{flagged[labels == k].mean():.2f}" for k in kinds))


def main() -> None:
    if "colours" not in SCORERS:
        raise SystemExit("this democheck has no colours check")
    for path, only, table in bench_tables(__doc__):
        kinds = sorted(set(table["label"].fillna("clean")) - {"clean"})
        tasks = table["task"].to_numpy()
        print(f"\n{path}{' (' + only + ')' if only else ''}: {len(table)} demos; AUROC {' '.join(kinds)} | "
              "clean flagged | kinds flagged")
        for model_free in (False, True):
            who = "no model, " if model_free else ""
            for centring in ("all", "core"):
                print(f"  {who}without colours, {centring:<4}            {judged(table, None, '', centring, model_free)}")
        for levels in LEVELS:
            shares, pixel = colour_shares(table, levels)
            for floor in FLOORS:
                for form in FORMS:
                    c = colour_score(shares, pixel, tasks, floor, form)
                    for model_free in (False, True):
                        for mode in MODES:
                            for centring in ("all", "core"):
                                who = "no model, " if model_free else ""
                                print(f"  {who}{levels} levels, floor {floor:g}, {form}, {mode:<7} {centring:<4} "
                                      f"{judged(table, c, mode, centring, model_free)}", flush=True)


if __name__ == "__main__":
    main()
