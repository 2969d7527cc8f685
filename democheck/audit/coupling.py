"""The ``coupling`` check (model-free): how little a demo's actions depend on the state they were taken in.

The mutual information between the demo's states and its actions, over its own steps, by the Kraskov-Stoegbauer-
Grassberger estimator (KSG, Kraskov et al. 2004, their first form: the ``COUPLING_K``-th nearest neighbour in
the joint space, max-norm, and the neighbours within that distance in each space alone), each dimension first
standardised over the demo's steps (a dimension that never moves is left out); the score is minus that, in
nats, so that higher is more suspect.  An operator who drives the arm leaves actions that go with where it is;
one who let go half-way -- zero torque, the arm at rest -- or never drove leaves a long stretch in which the
state says nothing about the actions.  A demo of more than ``COUPLING_MAX_STEPS`` steps is read at that many
evenly spaced steps, so that the estimate's cost stays bounded.  NaN for a demo of fewer than ``COUPLING_K + 2``
steps.  What dataset-quality checkers measure as a demo's predictability (democlean's mutual information); a
consumer of the audit's decoding pass like the other model-free checks (``democheck.audit.modelfree``).

In the ranking it is one look with the model's action error where there is one (``ScoreSpec.look``): both
ask whether the actions are explained -- by the model's controller, or by the state -- so the two are one piece
of evidence, the Sidak minimum of their tail probabilities (``scores.merge_looks``); beside the action error in
Fisher's sum the coupling would count the same resting arm twice.  Without a model it is the look alone.  Its
tail is normal (``ScoreSpec.tail``), not the exponential through the quartiles the other scores get: an estimate
averaged over a demo's steps spreads normally over clean demos.

(Chosen on the development sets: docs/decisions.md, "The coupling and the action error: one look" and the two
entries after it.)
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree
from scipy.special import digamma

from democheck.audit import words
from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.data.demo import Demo

COUPLING_K = 3  # KSG's neighbour count (the estimator's authors' and most tools' choice)
COUPLING_MAX_STEPS = 300  # a longer demo is read at this many evenly spaced steps


def ksg_mutual_information(x: np.ndarray, y: np.ndarray, k: int = COUPLING_K) -> float:
    """KSG's estimate (its first form) of the mutual information in nats between the rows of ``x`` [n, dx] and
    ``y`` [n, dy], each column standardised first (constant ones dropped); NaN for fewer than k + 2 rows."""
    n = len(x)
    if n < k + 2:
        return float("nan")
    x, y = _standardised(x), _standardised(y)
    joint = np.hstack([x, y])
    # The distance to the k-th nearest other row in the joint space, max-norm (the row itself is its 0th).
    eps = cKDTree(joint).query(joint, k + 1, p=np.inf)[0][:, k]
    # Rows within that distance in each space alone, itself not counted (ties counted: rows that repeat).
    n_x = cKDTree(x).query_ball_point(x, eps, p=np.inf, return_length=True) - 1
    n_y = cKDTree(y).query_ball_point(y, eps, p=np.inf, return_length=True) - 1
    return float(digamma(k) + digamma(n) - np.mean(digamma(n_x + 1) + digamma(n_y + 1)))


def _standardised(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float64).reshape(len(a), -1)
    sd = a.std(0)
    moves = sd > 1e-9 * np.maximum(np.abs(a).max(0), 1.0)
    a = (a[:, moves] - a[:, moves].mean(0)) / sd[moves]
    return a if a.shape[1] else np.zeros((len(a), 1))


class CouplingStats(PerDemo):
    """Consumer of decoded demos: each demo's state-action mutual information (``ksg_mutual_information``)."""

    fields = ("information",)
    information: list[float]

    def add(self, demo: Demo) -> None:
        state, actions = np.asarray(demo.state), np.asarray(demo.actions)
        n = min(len(state), len(actions))
        steps = np.unique(np.linspace(0, n - 1, min(n, COUPLING_MAX_STEPS)).round().astype(int))
        x, y = state[steps], actions[steps]
        ok = x.size and y.size and np.isfinite(x).all() and np.isfinite(y).all()
        # Actions that never change share no information with anything: the estimate would be noise (negative);
        # the check says nothing, and the motion checks say the arm does not move.
        still = ok and not _standardised(y).any()
        self.information.append(ksg_mutual_information(x, y) if ok and not still else float("nan"))


def _nats(value: float, median: float) -> str:
    """An estimate of mutual information and its task's median as a reader takes them: never below 0 (the
    estimator's bias can be), and never rounded to the same number -- where both are about 0, by how much the
    estimates the check compared differ."""
    if value <= 0.005 and median <= 0.005:
        side = "lower" if value < median else "higher"
        return f"about 0 nats, as its task's median, but the estimate {abs(median - value):.2g} nats {side}"
    shown = [f"{t} nats" if v > 0.005 else "about 0 nats" for v, t in zip((value, median), words.pair(value, median))]
    return f"{shown[0]} (its task's median {shown[1]})"


COUPLING = Vocabulary("coupling", {
    "less": lambda value, median: f"its actions go with its state less than its task's others': state-action "
                                  f"mutual information {_nats(value, median)}",
    "as much": lambda value, median: f"its actions go with its state as much as its task's others': state-action "
                                     f"mutual information {_nats(value, median)}",
    "nothing to relate": "too short, no state, or actions that never change: nothing to relate",
})


def coupling(stats: CouplingStats, tasks: np.ndarray) -> tuple[np.ndarray, list[Finding]]:
    """Minus each demo's state-action mutual information (see the module docstring), and a reason that compares it
    with its task's median."""
    info = np.asarray(stats.information, np.float64)
    medians = pd.Series(info).groupby(np.asarray(tasks)).transform("median").to_numpy()
    reasons = [COUPLING("less" if value < median else "as much", value=float(value), median=float(median))
               if np.isfinite(value) else COUPLING("nothing to relate") for value, median in zip(info, medians)]
    return -info, reasons
