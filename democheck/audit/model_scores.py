"""PETNet's readings of a demo as scorers (``democheck.audit.scorers`` registers them): its task uncertainty (both
parts of the variance, or the head alone), the novelty of its end, the consistency of its task mean with its
task-mates', and how well the model's controller explains its actions -- each with a finding that states the value
against its task's median."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from democheck.audit import scores
from democheck.audit.action_error import ActionErrors
from democheck.audit.evidence import Evidence, Scores
from democheck.audit.findings import Vocabulary
from democheck.audit.words import factor


def _against_task(vocabulary: Vocabulary, values: np.ndarray, groups: np.ndarray) -> list:
    """Each demo's finding of a model's reading: its value as a multiple of its comparison group's median."""
    median = pd.Series(values).groupby(np.asarray(groups)).transform("median").to_numpy()
    return [vocabulary("against its task", ratio=float(v / m)) if np.isfinite(v) and m > 0 else vocabulary("read")
            for v, m in zip(values, median)]


TASK_UNCERTAINTY = Vocabulary("task_uncertainty", {
    "against its task": lambda ratio: ("the model cannot tell the task from its first and last frames "
                                       f"({factor(ratio)} x its task's median)"),
    "read": "the model cannot tell the task from its first and last frames",
})
NOVELTY = Vocabulary("novelty", {
    "against its task": lambda ratio: (f"its end looks unlike the ends the model learnt from ({factor(ratio)} x its "
                                       "task's median)"),
    "read": "its end looks unlike the ends the model learnt from",
})
CONSISTENCY = Vocabulary("consistency", {
    "against its task": "its first and last frames read as another task than its task's other demos ({ratio:.2g} "
                        "x its task's median)",
    "read": "its first and last frames read as another task than its task's other demos",
})


def task_uncertainty(ev: Evidence) -> Scores:
    values = ev.posterior.task_uncertainty()
    return values, _against_task(TASK_UNCERTAINTY, values, ev.groups)


def task_uncertainty_head(ev: Evidence) -> Scores:
    return ev.posterior.task_uncertainty(head_only=True), None


def novelty(ev: Evidence) -> Scores:
    values = scores.novelty(ev.posterior, ev.model.model.encoder.prior_var.cpu().numpy())
    return values, _against_task(NOVELTY, values, ev.groups)


def consistency(ev: Evidence) -> Scores:
    value, _ = scores.consistency_parts(ev.posterior, ev.tasks)
    return value, _against_task(CONSISTENCY, value, ev.groups)


def action_error(ev: Evidence) -> Scores:
    got = ev.behaviour["action_error"]  # (values, reasons) from ``ActionErrors``, or values given directly
    return got if isinstance(got, tuple) else (np.asarray(got), None)


def decode_action_error(ev: Evidence, rows: slice, device: Any) -> ActionErrors:
    # Each demo is judged under its task across all the evidence (a bench pools datasets).
    return ActionErrors(ev.model, ev.task_variables()[rows], device)
