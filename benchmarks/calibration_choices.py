"""The development-set sweep behind the ranking's calibration: the robust core, the consistency form, the task
uncertainty's scale, and the rule that sets the flags.

    python benchmarks/calibration_choices.py BENCH_DIR [BENCH_DIR ...] [--only DATASET]

BENCH_DIR is a ``democheck bench`` output written with a model (its scores.parquet holds every scorer's score,
``mu`` and ``sigma``).  ``consistency`` is computed again from ``mu`` and ``sigma`` in each form below (the
bench's own column is whatever form wrote it), every ranking score is put in robust standard deviations within
its task as ``democheck audit`` does, and then:

- ``tails``: each score's exponential tail fitted on all the audited demos (``core off``: democheck before the
  robust core) or on the robust core (``scores.robust_tails``) found at ``CORE_P`` 1e-3, 1e-4 or 1e-5;
- ``consistency``: ``product`` (before: RMS of (mu - m) / sqrt(v + var) against the product of the 5 nearest)
  or ``scaled kNN`` (the shipped form, ``scores.consistency``);
- ``log unc.``: the task uncertainty on a log scale in the ranking, or not;
- the flag rule: ``model`` (the combined tail probability at most the fpr) or ``conformal`` (the share of the
  core at least as suspect at most the fpr, ``scores.conformal_p``; the shipped rule);
- ``final fit LO-HI`` (the shipped choices otherwise): once the core is found, each tail refitted through the
  core's LO and HI percentiles instead of ``TAIL_QUANTILES`` -- upper percentiles, which the core leaves to the
  clean demos, for scores whose clean tail is lighter or heavier than the quartiles say.

Printed per variant: the ranking's AUROC per kind and its mean; at each fpr the share of clean demos flagged
against the number the audit states it expects (``scores.expected_false_flags``), and each kind's share
flagged.  ``--no-model`` rows rank the model-free scores alone.  ``--only`` keeps the rows of one of the bench's
datasets (what an audit of that dataset alone would see).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from democheck.audit import scorers, scores
from democheck.audit.scorers import SCORERS, Evidence, ranking_z
from democheck.petnet.posterior import TaskPosterior
from suspicion_choices import aurocs, bench_tables

FPRS = (0.01, 0.02)
CORES = (None, 1e-3, 1e-4, 1e-5)
FINAL_FITS = ((0.5, 0.9), (0.75, 0.95), (0.5, 0.95))


def product_consistency(mu: np.ndarray, var: np.ndarray, tasks: np.ndarray) -> np.ndarray:
    """The form before: RMS over dimensions of (mu - m) / sqrt(v + var), (m, v) the product of the 5 nearest."""
    post = TaskPosterior(mu, var, np.zeros_like(var))
    m, v = post.others(tasks, scores.CONSISTENCY_K)
    return np.sqrt(((mu - m) ** 2 / (v + var)).mean(1))


def ranking(table, consistency: np.ndarray, log_uncertainty: bool, model_free: bool) -> np.ndarray:
    """[N, K] the ranking's scores in robust SD within their task, with these choices."""
    saved = SCORERS["task_uncertainty"]
    SCORERS["task_uncertainty"] = dataclasses.replace(saved, log_in_ranking=log_uncertainty)
    try:
        values = {c: table[c].to_numpy() for c in table if c in SCORERS} | {"consistency": consistency}
        ev = Evidence(episodes=table[["episode_index", "task"]], scores=values)
        return ranking_z(ev, scorers.ranked(values, table["task"].to_numpy(), model_free))
    finally:
        SCORERS["task_uncertainty"] = saved


def calibrate(z: np.ndarray, core_p: float | None, final: tuple[float, float] | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """(-log10 combined tail probability, core) with the tails fitted on all demos or on the robust core (and then,
    with ``final``, refitted on the core through those percentiles)."""
    if core_p is None:
        return -scores.combined_log10(scores.tail_probabilities(z)), np.ones(len(z), bool)
    log_p, core = scores.robust_tails(z, core_p)
    if final is not None:
        saved = scores.TAIL_QUANTILES
        scores.TAIL_QUANTILES = final
        try:
            log_p = scores.tail_probabilities(z, core)
        finally:
            scores.TAIL_QUANTILES = saved
    return -scores.combined_log10(log_p), core


def show(name: str, s: np.ndarray, core: np.ndarray, labels: np.ndarray, kinds: list[str]) -> None:
    """One variant's AUROC per kind and, at each fpr and rule, the clean demos flagged and each kind's recall."""
    clean = labels == "clean"
    au = aurocs(s, labels)
    print(f"  {name:<38} AUROC " + " ".join(f"{au[k]:.3f}" for k in kinds)
          + f" | {np.mean(list(au.values())):.3f}  core {core.mean():.2f}")
    for fpr in FPRS:
        for rule, p in (("model", 10.0 ** -s), ("conformal", scores.conformal_p(s, core))):
            flagged = p <= fpr
            expected = scores.expected_false_flags(core, fpr)
            print(f"      fpr {fpr:<5g} {rule:<9} clean {flagged[clean].sum():3d} "
                  f"({flagged[clean].mean():.2%}, expected {expected:5.1f})  recall "
                  + " ".join(f"{flagged[labels == k].mean():.2f}" for k in kinds))


def main() -> None:
    for path, only, table in bench_tables(__doc__):
        labels = table["label"].fillna("clean").to_numpy()
        clean = labels == "clean"
        kinds = sorted(set(labels) - {"clean"})
        tasks = table["task"].to_numpy()
        mu = np.stack(table["mu"].to_numpy()).astype(np.float64)
        var = np.stack(table["sigma"].to_numpy()).astype(np.float64) ** 2
        forms = {"product": product_consistency(mu, var, tasks),
                 "scaled kNN": scores.consistency(TaskPosterior(mu, var, np.zeros_like(var)), tasks)}
        print(f"\n{path}{' (' + only + ')' if only else ''}: {len(table)} demos, {table['task'].nunique()} tasks, "
              f"{np.mean(~clean):.0%} bad; kinds: {' '.join(kinds)}")
        for model_free in (False, True):
            for form, cons in forms.items():
                for log_unc in (False, True):
                    if model_free and (form != "scaled kNN" or log_unc):
                        continue  # neither choice touches the model-free scores
                    z = ranking(table, cons, log_unc, model_free)
                    for core_p in CORES:
                        name = ("no model" if model_free else f"{form}{', log unc.' if log_unc else ''}") + \
                            f", core {'off' if core_p is None else f'{core_p:g}'}"
                        show(name, *calibrate(z, core_p), labels, kinds)
                    if form == "scaled kNN" and (log_unc or model_free):  # the shipped choices
                        for final in FINAL_FITS:
                            show(f"{'no model' if model_free else 'shipped'}, final fit {final[0]:g}-{final[1]:g}",
                                 *calibrate(z, scores.CORE_P, final), labels, kinds)


if __name__ == "__main__":
    main()
