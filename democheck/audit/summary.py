"""What an audit's summary says beside its table: how the flags were set and what they should cost
(``flag_summary``), and what makes the scores less trustworthy, a sentence each (``warnings``: files that could
not be read, a reference too small for the rate asked for, small tasks, the model's scores left out)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from democheck.audit import scorers as registry, trust
from democheck.audit.evidence import GROUP_MIN_DEMOS, small_tasks
from democheck.audit.flagging import DEFAULT_FPR, broken_recordings, exact_copies, expected_false_flags, flag_level
from democheck.petnet.checkpoint import Checkpoint


def unreadable_files(episodes: np.ndarray, findings: list | None) -> list[str]:
    """One line per file whose frames cannot be read, with the episodes it takes down (``findings``: the broken
    check's, in ``episodes``' order, naming the files): a truncated video is one fault, not one suspect per episode
    it holds."""
    files: dict[str, tuple[list[int], str]] = {}
    for episode, finding in zip(episodes, findings or []):
        for path, why in finding.params.get("files", []):
            files.setdefault(path, ([], why))[0].append(int(episode))
    return [f"{path} cannot be read ({why}): {len(eps)} episode{'s' * (len(eps) > 1)} ({spans(eps)}) flagged as "
            "broken recordings" for path, (eps, why) in files.items()]


def spans(values: list[int]) -> str:
    """Sorted integers as runs, e.g. '3, 7-9, 12'."""
    runs: list[list[int]] = []
    for v in sorted(values):
        if runs and runs[-1][1] == v - 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def flag_summary(table: pd.DataFrame, fpr: float, untrusted=()) -> dict[str, Any]:
    """How the flags were set and what they should cost: the level, the number of false flags to expect were the
    unflagged demos clean, and, with labels, the observed recall per kind and share of clean demos flagged;
    ``untrusted``: the model's scores left out of the ranking (``trust.untrusted``)."""
    flagged = table["is_anomaly"].to_numpy(bool)
    copies, broken = exact_copies(table), broken_recordings(table)
    reference = table["reference"].to_numpy(bool)
    recipe = registry.ranking_recipe()
    out: dict[str, Any] = {
        "fpr": fpr, "rule": f"at most {fpr:g} of the reference demos at least as suspect (p_reference), an exact "
                            "copy of another demo, or a broken recording (frames that cannot be decoded, NaN or "
                            "infinite states or actions)",
        # If the reference demos are clean and the others like them, about fpr of them are flagged.
        "expected_false_flags": round(expected_false_flags(reference, fpr), 2),
        "too_small": small_reference(int(reference.sum()), fpr) if 1 / (reference.sum() + 1) > fpr else None,
        "p_value_at_level": flag_level(table, fpr),
        "exact_copies": 0 if copies is None else int(copies.sum()),
        "broken_recordings": 0 if broken is None else int(broken.sum()),
        "reference": f"the audited demos' robust core ({int(reference.sum())} of {len(table)}): the demos whose "
                     f"combined tail probability is above {recipe['core_p']:g} once each score's tail is fitted "
                     "on them, refitted until it no longer changes -- believed clean while the bad demos are a "
                     "minority",
        "scores": registry.ranked(table, table["task"].to_numpy(), untrusted=untrusted),
    }
    left_out = [n for n, keys in recipe["scores"].items() if not keys.get("single_task", True)
                and n in table] if table["task"].nunique() == 1 else []
    if left_out:
        verb = "is" if len(left_out) == 1 else "are"
        out["one_task"] = (f"one task: {' and '.join(n.replace('_', ' ') for n in left_out)} {verb} reported but "
                           "not ranked (with no other task to tell apart, a demo far from its neighbours is mostly "
                           "one on an unusual layout)")
    if "label" in table:
        labels = table["label"].fillna("clean").astype(str).to_numpy()
        clean = labels == "clean"
        if clean.any():
            out["observed"] = {"clean_flagged": int(flagged[clean].sum()),
                               "clean_share_flagged": round(float(flagged[clean].mean()), 4),
                               "recall": {k: round(float(flagged[labels == k].mean()), 3)
                                          for k in sorted(set(labels) - {"clean"})}}
    return out


def small_reference(reference: int, fpr: float) -> str:
    """What a reference of ``reference`` demos lets ``fpr`` flag, where it is too small for a share of it to be as
    small as ``fpr``."""
    beyond = np.log10(1 / ((reference + 1) * fpr))
    return (f"the reference holds {reference} demos, too few for --fpr {fpr:g}: a demo is flagged only where its "
            f"suspicion is {beyond:.2g} or more above the most suspect of them (beyond it the fitted tails, not a "
            f"count, set the level); --fpr {1 / (reference + 1):.2g} flags every demo more suspect than all of them, "
            f"and a reference of {int(np.ceil(1 / fpr)) - 1} demos or more lets --fpr {fpr:g} count")


def warnings(table: pd.DataFrame, ckpt: Checkpoint | None, untrusted: dict[str, str] | None = None,
             fpr: float = DEFAULT_FPR) -> list[str]:
    """What makes this audit's scores less trustworthy, in a sentence each: a reference too small to calibrate
    ``fpr`` on, tasks too small to judge a demo by, the model's scores left out of the ranking (``untrusted``,
    default: by its training record alone), tasks the model never learnt, and images unlike any it was trained
    on."""
    out = []
    small, tasks = small_tasks(table["task"]), table["task"].nunique()
    if len(small):
        n = int(small.sum())
        out.append(f"{len(small)} of {tasks} tasks have fewer than {GROUP_MIN_DEMOS} demos ({n} demos, e.g. "
                   f"{str(small.index[0])!r}): "
                   + ("every demo is compared with all the others, as if the dataset were one task"
                      if len(small) == tasks else "their demos are compared with each other, not with their "
                      "own task's") + "; if they hold several tasks, expect clean demos of the rarer ones among the "
                   "suspects, and a demo of the wrong task cannot be told apart")
    reference = int(table["reference"].sum()) if "reference" in table else 0
    if reference and 1 / (reference + 1) > fpr:
        out.append(small_reference(reference, fpr))
    if ckpt is None:
        return out
    left_out = trust.untrusted(ckpt.meta) if untrusted is None else untrusted
    out += [why for name, why in left_out.items() if name in table]
    trained = (ckpt.meta.get("data", {}).get("task_split") or {}).get("trained")
    if trained is not None:
        new = sorted(set(table["task"]) - set(trained))
        if new:
            n = int(table["task"].isin(new).sum())
            out.append(f"{len(new)} of {table['task'].nunique()} tasks ({n} demos) are not among the "
                       f"{len(trained)} the model was trained on (e.g. {new[0]!r}): their demos are read by an "
                       "encoder that never learnt them; compare their scores with care")
    if "novelty" in table and len(table) and float(np.median(table["novelty"])) > 1:
        out.append(f"most demos' ends are unfamiliar to the model (median novelty "
                   f"{float(np.median(table['novelty'])):.3g}; 1 = the 90th percentile of its own held-out cues): "
                   "another camera, scene or robot than it was trained on; train a model on this data")
    return out
