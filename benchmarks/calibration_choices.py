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
  core at least as suspect at most the fpr, ``flagging.conformal_p``; the shipped rule);
- ``final fit LO-HI`` (the shipped choices otherwise): once the core is found, each tail refitted through the
  core's LO and HI percentiles instead of ``TAIL_QUANTILES`` -- upper percentiles, which the core leaves to the
  clean demos, for scores whose clean tail is lighter or heavier than the quartiles say;
- the shipped choices with one part changed (``VARIANTS``): ``Cauchy`` combines the tail probabilities by the
  Cauchy combination test instead of Fisher-Brown; ``normal idle`` gives the idle share a normal tail (median
  and IQR / 1.349 of the core) instead of the exponential; ``exponential coupling`` gives the coupling the
  exponential tail instead of its own normal one (``Scorer.tail``; the shipped choice since, every row but that
  one); ``family by likelihood`` gives each score the normal
  or the exponential tail, whichever fits the core's values above its median better (half-normal against
  exponential likelihood); ``empirical`` takes, once the core is found, each score's p-value as its rank among
  the core's values, the exponential carrying on beyond the core's largest; ``core-centred`` puts the scores in
  robust SD within their task from the task's *core* demos' median (and the core's MAD), refitted with the
  core at every round, so that a task's bad demos do not move the centre its clean demos are judged from.
  ``core-centred`` is the shipped calibration since the ``colours`` check joined the ranking
  (``benchmarks/colour_choices.py``); every other row centres each task on all its demos, the choice before.

Printed per variant: the ranking's AUROC per kind and its mean; at each fpr the share of clean demos flagged
against the number the audit states it expects (``flagging.expected_false_flags``), and each kind's share
flagged.  ``--no-model`` rows rank the model-free scores alone.  ``--only`` keeps the rows of one of the bench's
datasets (what an audit of that dataset alone would see).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from democheck.audit import flagging, scores
from democheck.audit.ranking import alone_columns, look_columns, normal_tails, ranked, ranking_z
from democheck.audit.scorers import SCORERS, Evidence
from democheck.petnet.posterior import TaskPosterior
from suspicion_choices import aurocs, bench_tables

FPRS = (0.01, 0.02)
CORES = (None, 1e-3, 1e-4, 1e-5)
FINAL_FITS = ((0.5, 0.9), (0.75, 0.95), (0.5, 0.95))
VARIANTS = ("Cauchy", "normal idle", "family by likelihood", "empirical", "core-centred",
            "core-centred, exponential coupling")
CAUCHY_P_MAX = 0.9  # the Cauchy test needs p < 1: the exponential tails give p = 1 below their 25th percentile


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
        return ranking_z(ev, ranked_names(values, table, model_free))
    finally:
        SCORERS["task_uncertainty"] = saved


def ranked_names(values, table, model_free: bool) -> list[str]:
    return ranked(values, table["task"].to_numpy(), model_free)


def cauchy_log10(log_p: np.ndarray) -> np.ndarray:
    """log10 of the Cauchy combination of each row's tail probabilities (natural logs; NaN left out): the mean of
    tan((0.5 - p) pi), p at most ``CAUCHY_P_MAX``, against the standard Cauchy."""
    p = np.minimum(np.exp(log_p), CAUCHY_P_MAX)
    seen = ~np.isnan(log_p)
    with np.errstate(all="ignore"):
        t = np.where(p < 1e-15, 1.0 / (np.pi * p), np.tan((0.5 - p) * np.pi))  # far out: its leading term
        stat = np.where(seen, t, 0.0).sum(1) / np.maximum(seen.sum(1), 1)
        out = np.where(stat > 1e15, -np.log10(np.pi * stat), np.log10(0.5 - np.arctan(stat) / np.pi))
    return np.where(np.isinf(stat), -np.inf, out)


def normal_fits_better(x: np.ndarray, core: np.ndarray) -> bool:
    """Whether the core's values above their median are likelier half-normal than exponential."""
    f = x[np.isfinite(x) & core]
    e = f[f > np.median(f)] - np.median(f)
    if len(e) < 10 or not e.any():
        return False
    return 0.5 * np.log(2 / np.pi) - 0.5 * np.log((e ** 2).mean()) - 0.5 > -(np.log(e.mean()) + 1)


def empirical_tails(z: np.ndarray, core: np.ndarray) -> np.ndarray:
    """Each column's p-value as its rank among the core's values, (1 + #{core >= x}) / (1 + n); beyond the core's
    largest, the column's exponential tail (its scale as ``scores.tail_probabilities`` fits it) from 1 / (1 + n)."""
    lo, hi = scores.TAIL_QUANTILES
    out = scores.tail_probabilities(z, core)
    for k in range(z.shape[1]):
        x = z[:, k]
        f = np.sort(x[np.isfinite(x) & core])
        q_lo, q_hi = np.quantile(f, [lo, hi])
        beta = max((q_hi - q_lo) / np.log((1 - lo) / (1 - hi)), scores.TAIL_MIN_SCALE)
        with np.errstate(all="ignore"):
            rank = np.log((1 + len(f) - np.searchsorted(f, x, side="left")) / (1 + len(f)))
            beyond = -np.log(1 + len(f)) - (x - f[-1]) / beta
        out[:, k] = np.where(np.isnan(x), np.nan, np.where(x == np.inf, -np.inf, np.where(x > f[-1], beyond, rank)))
    return out


def core_centred_z(table, values: dict, names: list[str], core: np.ndarray) -> np.ndarray:
    """``ranking_z`` with each task's centre the median of its core demos (all its demos where none is in the
    core) and the scale the core's MAD about those centres: the shipped calibration (``scores.calibrated``)."""
    return ranking_z(Evidence(episodes=table[["episode_index", "task"]], scores=values), names, core)


def variant(how: str, table, cons: np.ndarray, model_free: bool) -> tuple[np.ndarray, np.ndarray]:
    """(-log10 combined tail probability, core) of the shipped choices with one part changed (``VARIANTS``)."""
    values = {c: table[c].to_numpy() for c in table if c in SCORERS} | {"consistency": cons}
    names = ranked_names(values, table, model_free)
    alone = alone_columns(names)  # the recording faults stand apart, as the audit combines them
    looks = look_columns(names)  # and the scores of one look are merged

    def combine(log_p: np.ndarray) -> np.ndarray:
        return cauchy_log10(log_p) if how == "Cauchy" else scores.combined_log10(log_p, alone, looks)

    def tails(z: np.ndarray, core: np.ndarray) -> np.ndarray:
        normal = normal_tails(names)  # the scorers' own families (``Scorer.tail``), then the variant's
        for k, n in enumerate(names):
            if f"exponential {n}" in how.split(", "):
                normal[k] = False
            by_likelihood = how == "family by likelihood" and normal_fits_better(z[:, k], core)
            if f"normal {n}" in how.split(", ") or by_likelihood:
                normal[k] = True
        return scores.tail_probabilities(z, core, normal)

    def z_for(core: np.ndarray) -> np.ndarray:
        return core_centred_z(table, values, names, core) if how.startswith("core-centred") else \
            ranking(table, cons, True, model_free)

    core = np.ones(len(table), bool)
    z = z_for(core)
    log_p = tails(z, core)
    for _ in range(scores.CORE_ROUNDS):  # as scores.robust_tails
        new = ~(10.0 ** combine(log_p) <= scores.CORE_P)
        if (new == core).all() or new.sum() < len(z) / 2:
            break
        core = new
        z = z_for(core)
        log_p = tails(z, core)
    if how == "empirical":
        log_p = empirical_tails(z, core)
    return -combine(log_p), core


def calibrate(z: np.ndarray, core_p: float | None, final: tuple[float, float] | None = None,
              normal: np.ndarray | None = None, alone: np.ndarray | None = None, looks: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """(-log10 combined tail probability, core) with the tails (``normal``: the columns with a normal one) fitted
    on all demos or on the robust core (and then, with ``final``, refitted on the core through those
    percentiles); ``alone`` and ``looks``: how the columns are combined (``scores.combined_log10``)."""
    if core_p is None:
        return (-scores.combined_log10(scores.tail_probabilities(z, normal=normal), alone, looks),
                np.ones(len(z), bool))
    log_p, core = scores.robust_tails(z, core_p, normal=normal, alone=alone, looks=looks)
    if final is not None:
        saved = scores.TAIL_QUANTILES
        scores.TAIL_QUANTILES = final
        try:
            log_p = scores.tail_probabilities(z, core, normal)
        finally:
            scores.TAIL_QUANTILES = saved
    return -scores.combined_log10(log_p, alone, looks), core


def show(name: str, s: np.ndarray, core: np.ndarray, labels: np.ndarray, kinds: list[str]) -> None:
    """One variant's AUROC per kind and, at each fpr and rule, the clean demos flagged and each kind's recall."""
    clean = labels == "clean"
    au = aurocs(s, labels)
    print(f"  {name:<38} AUROC " + " ".join(f"{au[k]:.3f}" for k in kinds)
          + f" | {np.mean(list(au.values())):.3f}  core {core.mean():.2f}")
    for fpr in FPRS:
        for rule, p in (("model", 10.0 ** -s), ("conformal", flagging.conformal_p(s, core))):
            flagged = p <= fpr
            expected = flagging.expected_false_flags(core, fpr)
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
                    values = {c: table[c].to_numpy() for c in table if c in SCORERS} | {"consistency": cons}
                    names = ranked_names(values, table, model_free)
                    normal, alone = normal_tails(names), alone_columns(names)
                    looks = look_columns(names)
                    for core_p in CORES:
                        name = ("no model" if model_free else f"{form}{', log unc.' if log_unc else ''}") + \
                            f", core {'off' if core_p is None else f'{core_p:g}'}"
                        show(name, *calibrate(z, core_p, normal=normal, alone=alone, looks=looks), labels, kinds)
                    if form == "scaled kNN" and (log_unc or model_free):  # the shipped choices
                        who = "no model" if model_free else "shipped"
                        for final in FINAL_FITS:
                            show(f"{who}, final fit {final[0]:g}-{final[1]:g}",
                                 *calibrate(z, scores.CORE_P, final, normal, alone, looks), labels, kinds)
                        for how in VARIANTS:
                            show(f"{who}, {how}", *variant(how, table, cons, model_free), labels, kinds)


if __name__ == "__main__":
    main()
