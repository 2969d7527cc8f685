"""The ``coupling`` check (model-free): how little a demo's actions depend on the state they were taken in.

The mutual information between the demo's states and its actions, over its own steps, by the Kraskov-Stoegbauer-
Grassberger estimator (KSG, Kraskov et al. 2004, their first form: the ``COUPLING_K``-th nearest neighbour in
the joint space, max-norm, and the neighbours within that distance in each space alone), each dimension first
standardised over the demo's steps (a dimension that never moves is left out); the score is minus that, in
nats, so that higher is more suspect.  An operator who drives the arm leaves actions that go with where it is;
one who let go half-way -- zero torque, the arm at rest -- or never drove leaves a long stretch in which the
state says nothing about the actions.  A demo of more than ``COUPLING_MAX_STEPS`` steps is read at that many
evenly spaced steps: the estimate costs 2.5 ms for push-v1's 100 steps of 17 + 7 dimensions, 18 ms for 300 (53
ms for 300 steps of 64 + 14), 95 ms for 1,000 -- beside the action pass's ~19 ms a demo.  NaN for a demo of
fewer than ``COUPLING_K + 2`` steps.  What dataset-quality tools measure as a demo's predictability
(democlean's mutual information); a consumer of the audit's decoding pass like the other model-free checks
(``democheck.audit.modelfree``).

In the ranking one look with the model's action error where there is one (``scorers.Scorer.look``): both ask
whether the actions are explained -- by the model's controller, or by the state -- so the two are one piece of
evidence, the Sidak minimum of their tail probabilities (``scores.merge_looks``); beside the action error in
Fisher's sum the coupling would count the same resting arm twice.  Without a model it is the look alone.

First it stood in for the action error only where there was none, chosen on the development sets (benches of
push-v1-dev, -dev3 and -dev4 with their probes, each set's rows alone, Meta-World mw2-dev and mw2-one-dev;
``benchmarks/coupling_choices.py``: the KSG score in the ranking as the audit combines it): without a model, gave-up
AUROC 0.993 / 0.998 / 0.997 -> 0.997 / 1.000 / 0.999 with the probes pooled and its flags at --fpr 0.01 0.58 / 0.47
/ 0.82 -> 0.92 / 0.92 / 1.00 (each set alone 0.58 / 0.42 / 0.74 -> 0.92 / 0.87 / 1.00), no more clean demos flagged
(0-4 of 614), no-objects 0.964 / 0.947 / 0.941 -> 0.956 / 0.936 / 0.918; Meta-World the same. With the model's
scores it was a wash on the ranking (gave-up +0.0002 to +0.0011) but flagged more clean demos (push-v1-dev pooled 6
-> 12 of 614). Alone it reads gave-up and no-action 1.000 on every push draw, random 0.32-0.37: a flailing arm's
state follows its torques closely.

Its tail in the ranking is normal (``Scorer.tail``), not the exponential through the quartiles the other scores
get: an estimate averaged over a demo's steps spreads normally over clean demos, and the exponential called a
demo that let go, 5.7 robust SD below its task's median, one clean demo in 400 -- fewer than a clean demo that
pushed its object 13 robust SD past the others' (``outcome``), which then ranked above two gave-up demos.  On the
same development benches (``benchmarks/calibration_choices.py``, "no model" rows), without a model: gave-up
AUROC 0.996 / 1.000 / 0.999 -> 1.000 on all three, its flags 0.92 / 0.92 / 1.00 -> 1.00 / 0.97 / 1.00, clean
demos flagged 3 / 0 / 4 -> 4 / 0 / 4 of 614, no-objects 0.956 / 0.936 / 0.918 -> 0.942 / 0.929 / 0.902 and
occluded 0.983 / 0.996 / 0.990 -> 0.977 / 0.995 / 0.985; Meta-World mw2-dev gave-up 0.997 -> 0.999, its clean
demos flagged 5 of 200 either way; mw2-one-dev the same.  (The idle share's normal tail was measured and not
kept: Meta-World's resting demos give it a long clean tail.)  With the model's scores, and this tail, measured
again on the three draws pooled and not kept (``coupling_choices.py``): forced in beside the action error,
gave-up 0.999 -> 1.000 on all three but 7 / 9 / 12 -> 14 / 9 / 13 of 614 clean demos flagged; merged with it into
one piece of evidence (the Sidak minimum of the two tail probabilities, both asking whether the actions are
explained), gave-up 1.000 on all three and 12 / 9 / 11 clean flagged.  The flags are what a user deletes by.

Measured again once the recording faults, the jerk and the frozen state had joined the ranking (``democheck audit``
of each development set with the shipped model, the alternatives recombined from its table): merged, the push-v1
draws' gave-up AUROC 0.9997 / 0.9982 / 0.9994 -> 1.0000 / 0.9997 / 1.0000 audited alone (clean demos flagged 8 / 9 /
7 -> 8 / 10 / 8 of 614), seed 2 with its probes pooled 0.9997 -> 1.0000 (6 -> 7 clean flagged; wrong-object 0.9988
-> 0.9985, both-objects 0.9995 -> 0.9996), every other kind the same; beside the action error 9 / 10 / 9 clean
flagged for the same gave-up ranking. Meta-World, each set with its your-data model: mw2-dev and mw2-one-dev
unchanged; mw3-dev dropped 0.9989 -> 0.9978; its copy with sensor faults planted frozen-state 0.9987 -> 1.0000,
dropped 0.9975 -> 0.9962, scaled 0.981 -> 0.979; mw4-dev wrong-task 0.974 -> 0.964 (two demos of pushing the puck
named picking it up, which barely differ); no set's flags otherwise changed. Kept merged: an arm that rests half-way
is explained by the model's controller, which has seen arms rest, and not by its state.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree
from scipy.special import digamma

from democheck.audit.modelfree import PerDemo
from democheck.data.demo import Demo

COUPLING_K = 3  # KSG's neighbour count (the estimator's authors' and most tools' choice)
COUPLING_MAX_STEPS = 300  # see the module docstring; every development set's demos are shorter
# The least spread a robust standard deviation of the coupling stands for in the ranking, in nats: a tenth of a nat
# is no real change in how the actions go with the state (a gave-up push demo reads a nat or more below its task's
# median).  Clean demos spread 0.16 nats within a push-v1 task, 0.09-0.10 within a Meta-World one, and no
# development set's ranking or flags changed with the floor; a set of smooth scripted demos (the peers' harness's
# generator, seed 5, 26 clean demos) spread 0.04, and a clean demo 0.15 nats below its task's median read as
# unusual as one clean demo in 10 million and was flagged (not with the floor; a fresh draw, seed 8: none either way).
# (The ranking's normal tail is at least half a robust SD wide, ``scores.TAIL_MIN_SCALE``: with the floor a demo
# 0.1 nats out reads about 1 in 50, 0.2 nats 1 in 40,000.)
COUPLING_MIN_SCALE = 0.1


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


def _nats(value: float) -> str:
    """An estimate of mutual information as a reader takes it: never below 0 (the estimator's bias can be)."""
    return f"{value:.2g} nats" if value > 0.005 else "about 0 nats"


def coupling(stats: CouplingStats, tasks: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Minus each demo's state-action mutual information (see the module docstring), and a reason that compares it
    with its task's median."""
    info = np.asarray(stats.information, np.float64)
    medians = pd.Series(info).groupby(np.asarray(tasks)).transform("median").to_numpy()
    reasons = [f"its actions go with its state less than its task's others': state-action mutual information "
               f"{_nats(value)} (its task's median {_nats(median)})" if np.isfinite(value)
               else "too short, no state, or actions that never change: nothing to relate"
               for value, median in zip(info, medians)]
    return -info, reasons
