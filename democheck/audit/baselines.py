"""Scorers people would use instead of PETNet, for ``democheck bench``; higher = more suspect, like ours.

- ``heuristic``: what rule-based dataset linters check, from actions and
  state alone: the share of idle steps, the action energy and the jerk, each
  as a robust z-score against the benchmarked demos' median (both tails: a
  demo that never moves and one that flails are both odd); the score is the
  largest absolute z.
- ``tecnet_knn``: distance in a TecNets embedding (deterministic, unit norm)
  to the demo's nearest other demos of the same task: the mean of the k
  smallest Euclidean distances.  It is the deterministic counterpart of our
  task consistency.
- ``random``: a uniform draw, the floor every detector must clear.
"""

from __future__ import annotations

import numpy as np

from democheck.audit.findings import Finding, Vocabulary
from democheck.audit.modelfree import PerDemo
from democheck.audit.scores import rank_order, robust_stats, standardise, task_neighbours
from democheck.data.demo import Demo

# An arm that moves less than this share of its median per-step motion is idle at that step.
IDLE_FRACTION_OF_MEDIAN = 0.05
HEURISTIC_FEATURES = ("idle_fraction", "action_energy", "jerk")


def motion_features(state: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """(per-step state motion [T-1], action energy, jerk) of one demo; motion is returned for the idle rule."""
    motion = np.linalg.norm(np.diff(state.astype(np.float64), axis=0), axis=1)
    energy = float(np.mean(np.sum(actions.astype(np.float64) ** 2, axis=1)))
    third = np.diff(state.astype(np.float64), n=3, axis=0)
    jerk = float(np.mean(np.sum(third**2, axis=1))) if len(third) else 0.0
    return motion, energy, jerk


def heuristic_table(demos) -> np.ndarray:
    """[N, 3] idle fraction, action energy and jerk of each demo (an iterable of Demos)."""
    return summarise_motion([motion_features(d.state, d.actions) for d in demos])


def summarise_motion(parts: list[tuple[np.ndarray, float, float]]) -> np.ndarray:
    """[N, 3] idle fraction, action energy and jerk from each demo's ``motion_features``; a step is idle when the
    arm moves less than ``IDLE_FRACTION_OF_MEDIAN`` of the median step of all these demos."""
    motions = [m for m, _, _ in parts]
    rest = [(e, j) for _, e, j in parts]
    typical = float(np.median(np.concatenate(motions))) if motions else 0.0
    idle = [float(np.mean(m < IDLE_FRACTION_OF_MEDIAN * typical)) if len(m) else 1.0 for m in motions]
    return np.column_stack([idle, np.asarray(rest).reshape(-1, 2)]) if motions else np.zeros((0, 3))


class MotionFeatures(PerDemo):
    """Consumer of decoded demos: the linter heuristics' features (``summarise_motion``)."""

    fields = ("parts",)
    parts: list[tuple[np.ndarray, float, float]]

    def add(self, demo: Demo) -> None:
        self.parts.append(motion_features(demo.state, demo.actions))

    def finish(self) -> np.ndarray:
        return summarise_motion(self.parts)


def heuristic_z(features: np.ndarray) -> np.ndarray:
    """Absolute robust z-score of each feature [N, 3], standardised against all demos given."""
    return np.column_stack([np.abs(standardise(features[:, i], robust_stats(features[:, i])))
                            for i in range(features.shape[1])])


def heuristic_score(features: np.ndarray) -> np.ndarray:
    """Largest absolute robust z-score over the features."""
    return heuristic_z(features).max(axis=1)


def knn_same_task(emb: np.ndarray, tasks: np.ndarray, k: int = 5) -> np.ndarray:
    """Mean distance to the k nearest other demos of the same task (NaN for a task's only demo)."""
    return task_neighbours(emb, tasks, k)[0]


def random_score(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng([seed, 0x4A4D]).uniform(size=n)


# The registry's score functions (``democheck.audit.scorers``): each reads the audit's evidence and returns one
# number per demo and a finding per demo (or None).

HEURISTIC = Vocabulary("heuristic", {"largest": "{feature} |z| {z:.3g}"})


def score_tecnet_knn(ev) -> tuple[np.ndarray, list[Finding] | None]:
    return knn_same_task(ev.embedding, ev.tasks), None


def score_heuristic(ev) -> tuple[np.ndarray, list[Finding] | None]:
    z = heuristic_z(ev.behaviour["heuristic"])
    return z.max(axis=1), [HEURISTIC("largest", feature=HEURISTIC_FEATURES[int(np.argmax(r))], z=float(r.max()))
                           for r in z]


def score_random(ev) -> tuple[np.ndarray, list[Finding] | None]:
    # Dealt in ranking order (by suspicion), as benches have always done, so their random rows stay comparable.
    draws = random_score(len(ev.episodes), ev.seed)
    out = np.empty(len(draws))
    out[rank_order(ev.scores["suspicion"], ev.episodes["episode_index"].to_numpy())] = draws
    return out, None
