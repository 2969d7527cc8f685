"""The flags over several development draws, and two ways of setting them that were measured and not kept.

    python benchmarks/flag_choices.py TABLE_DIR [TABLE_DIR ...]

TABLE_DIR is a ``democheck bench`` or a labelled ``democheck audit`` output (its scores.parquet holds every
scorer's score, each demo's task and label).  The ranking is combined as ``democheck audit`` combines it
(``Evidence.combination``: each score in robust SD within its task from the robust core, exponential tails,
Fisher-Brown) and printed per variant: the ranking's AUROC per kind, the clean demos flagged at --fpr 0.01 against
the number the audit expects (``flagging.expected_false_flags``), how many bad demos the robust core holds, and each
kind's share flagged; the ``nm`` rows rank the model-free scores alone.  The variants:

- ``shipped``: the conformal flags (``flagging.conformal_p``: the share of the core at least as suspect).
- ``bulk LO-HI``: the flag level extrapolated from the bulk of the core instead of read off its top: log10 of the
  core's survival function fitted as a line in the suspicion between its LO and HI quantiles, the level where it
  reaches the fpr.  The idea: bad demos left in the core sit at its top and raise the conformal level; the bulk
  is clean.  (Only the flags change.)
- ``tail POT Q``: each score's tail above the core's Q quantile u refitted by peaks over threshold -- an
  exponential whose scale is the core's mean excess over u (its maximum-likelihood fit), spliced to the shipped
  tail at u -- so that a score whose clean tail is light (the idle share of a scripted expert) is not valued by
  the heavy tail its quartiles imply.  (The ranking, the core and the flags change.)
- ``empirical``: the core found as shipped, then each score's tail probability its rank among the core's values,
  and beyond the core's largest the shipped exponential's fall (``calibration_choices.empirical_tails``): every
  score valued by what the core's demos actually show, as far as they reach.  (The ranking and the flags change;
  the core does not.)
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
import pandas as pd

from democheck.audit import flagging, ranking, scores
from democheck.audit.ranking import ranking_z
from democheck.audit.scorers import SCORERS, Evidence
from calibration_choices import empirical_tails
from suspicion_choices import aurocs

FPR = 0.01
BULKS = ((0.5, 0.9), (0.5, 0.95), (0.75, 0.95), (0.9, 0.98))
POT_QUANTILES = (0.8, 0.9, 0.95)
SHIPPED_TAILS = scores.tail_probabilities


def pot_tails(q: float):
    """``scores.tail_probabilities`` with each column's tail above its core's ``q`` quantile refitted (see above)."""

    def tails(z: np.ndarray, core: np.ndarray | None = None, normal: np.ndarray | None = None) -> np.ndarray:
        out = SHIPPED_TAILS(z, core, normal)
        core = np.ones(len(z), bool) if core is None else np.asarray(core, bool)
        for k in range(z.shape[1]):
            x = z[:, k]
            f = x[np.isfinite(x) & core]
            if len(f) < 20:
                continue
            u = np.quantile(f, q)
            excess = f[f > u] - u
            beta = max(float(excess.mean()) if len(excess) else 0.0, scores.TAIL_MIN_SCALE)
            # The shipped tail's value at u: u as one more row, outside the core it is fitted on.
            at_u = SHIPPED_TAILS(np.append(x, u)[:, None], np.append(core, False),
                                 None if normal is None else normal[k:k + 1])[-1, 0]
            with np.errstate(invalid="ignore"):
                out[:, k] = np.where(x > u, np.minimum(at_u - (x - u) / beta, 0.0), out[:, k])
        return out
    return tails


def combined(table: pd.DataFrame, model_free: bool, tails=SHIPPED_TAILS, empirical: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
    """(suspicion, robust core) of a score table, as the audit computes them, with ``tails`` for the tails; with
    ``empirical``, the core found so, then the tails taken again from it by ``calibration_choices.empirical_tails``."""
    values = {c: table[c].to_numpy(float) for c in table if c in SCORERS}
    names = ranking.ranked(values, table["task"].to_numpy(), model_free)
    ev = Evidence(episodes=table[["episode_index", "task"]], scores=values)
    scores.tail_probabilities = tails
    try:
        log_p, core = ranking.ranking_tails(ev, names)
    finally:
        scores.tail_probabilities = SHIPPED_TAILS
    if empirical:
        log_p = empirical_tails(ranking_z(ev, names, core), core)
    return ranking.combine(names, log_p), core


def bulk_flags(s: np.ndarray, core: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, float]:
    """Flags at the level where the core's survival function, fitted between its ``lo`` and ``hi`` quantiles as
    log10 S(x) = a + b x, reaches ``FPR``; and that level."""
    ref = s[core & np.isfinite(s)]
    qs = np.linspace(lo, hi, 20)
    b, a = np.polyfit(np.quantile(ref, qs), np.log10(1 - qs), 1)
    level = (np.log10(FPR) - a) / b
    return np.nan_to_num(s, nan=-np.inf) >= level, float(level)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tables", nargs="+")
    args = ap.parse_args()
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    for path in args.tables:
        table = pd.read_parquet(f"{path}/scores.parquet").reset_index(drop=True)
        labels = table["label"].fillna("clean").to_numpy()
        clean = labels == "clean"
        kinds = sorted(set(labels) - {"clean"})
        print(f"\n{path}: {len(table)} demos, {np.mean(~clean):.0%} bad; AUROC {' '.join(kinds)} | flagged at --fpr {FPR}")

        def show(name: str, s: np.ndarray, core: np.ndarray, flagged: np.ndarray, extra: str = "") -> None:
            au = aurocs(s, labels)
            print(f"  {name:<20} " + " ".join(f"{au[k]:.3f}" for k in kinds)
                  + f" | clean {flagged[clean].sum():3d} ({flagged[clean].mean():.1%}, expected "
                  f"{flagging.expected_false_flags(core, FPR):4.1f}), bad in core {(core & ~clean).sum():3d} | "
                  + " ".join(f"{flagged[labels == k].mean():.2f}" for k in kinds) + extra, flush=True)

        for model_free in (False, True):
            who = "nm " if model_free else ""
            s, core = combined(table, model_free)
            show(f"{who}shipped", s, core, flagging.conformal_p(s, core) <= FPR)
            for lo, hi in BULKS:
                flagged, level = bulk_flags(s, core, lo, hi)
                show(f"{who}bulk {lo:g}-{hi:g}", s, core, flagged, f"  (level {level:.2f})")
            for q in POT_QUANTILES:
                s_q, core_q = combined(table, model_free, pot_tails(q))
                show(f"{who}tail POT {q:g}", s_q, core_q, flagging.conformal_p(s_q, core_q) <= FPR)
            s_e, core_e = combined(table, model_free, empirical=True)
            show(f"{who}empirical", s_e, core_e, flagging.conformal_p(s_e, core_e) <= FPR)


if __name__ == "__main__":
    main()
