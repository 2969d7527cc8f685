"""What a scorer reads and what it is: ``Evidence`` (the demos being scored, what the passes over them found, the
scores so far), the ``Scorer`` contract, and the comparison groups the within-task checks judge a demo in.  The
registry of scorers (``democheck.audit.scorers``) builds on it; the checks' modules need nothing above it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Protocol

import numpy as np
import pandas as pd

from democheck.audit import modelfree, scores as arithmetic, trust
from democheck.audit.action_error import controller_z
from democheck.audit.findings import Finding, camera_column
from democheck.data.demo import Demo
from democheck.petnet.checkpoint import Checkpoint
from democheck.petnet.posterior import TaskPosterior

NEEDS = {
    "cues": "the task posterior of each demo's cue, its first and last frame (the fast pass of a PETNet model)",
    "demos": "every frame, state and action of each demo (one decoding pass)",
    "model": "a PETNet model",
    "novelty": "a PETNet model with a novelty density (democheck train fits one)",
    "reference": "the model's reference of its training demos (the one-class SVM)",
    "tecnet": "a TecNets model trained on the same data (democheck bench --tecnet)",
    "scores": "other scorers' scores",
    "many": "more than one demo",
    "frames": "camera frames (a dataset that records no camera has none: ``NO_CAMERA``)",
}


# A task of fewer demos than this is no reference for its demos: the checks that compare a demo with its task's
# others compare those of such tasks with each other instead (``comparison_groups``).  Where every demo names a
# task of its own -- a free-text instruction per episode -- a robust median and MAD within each task leave every
# demo at 0: the Meta-World set LeRobot's writer made, each episode's task string made its own, ranked every kind
# at 0.50 and flagged nothing.  Every development set's tasks hold 12 or more demos, so none is changed.
GROUP_MIN_DEMOS = 5
SMALL_TASKS = "\0tasks of fewer demos"  # the group of the small tasks' demos (never shown)


def small_tasks(tasks: np.ndarray) -> pd.Series:
    """The tasks of fewer than ``GROUP_MIN_DEMOS`` demos, and how many each has (most first)."""
    counts = pd.Series(np.asarray(tasks, dtype=object)).value_counts()
    return counts[counts < GROUP_MIN_DEMOS]


def comparison_groups(tasks: np.ndarray) -> np.ndarray:
    """Each demo's task where the task has at least ``GROUP_MIN_DEMOS`` demos, else one group of every demo of the
    smaller tasks (the whole set where all its tasks are small: ``small_tasks``)."""
    tasks = np.asarray(tasks, dtype=object)
    small = np.isin(tasks, small_tasks(tasks).index.to_numpy())
    return np.where(small, SMALL_TASKS, tasks) if small.any() else tasks


@dataclass
class Evidence:
    """What scorers read about the demos being scored, one row of ``episodes`` per demo, in one order."""

    episodes: pd.DataFrame  # episode_index, task (+ label, split, ...)
    posterior: TaskPosterior | None = None  # each demo's cue under the PETNet model
    model: Checkpoint | None = None
    embedding: np.ndarray | None = None  # each demo's cue under the TecNets model
    behaviour: dict[str, Any] = field(default_factory=dict)  # results of the decoding pass, by scorer name
    scores: dict[str, np.ndarray] = field(default_factory=dict)  # computed so far, by scorer name
    findings: dict[str, list[Finding]] = field(default_factory=dict)  # what each check found, by scorer name
    reasons: dict[str, list[str]] = field(default_factory=dict)  # the findings' words
    seed: int = 0
    frames: bool = True  # the demos have camera frames (False: a dataset that records no camera, ``NO_CAMERA``)
    # The camera read first (its short name, ``data.demo.camera_name``) and the dataset's others, whose pictures
    # the ``per_camera`` checks read too (``behaviour`` keys "<source>@<camera>": ``findings.camera_column``).
    camera: str = ""
    cameras: tuple[str, ...] = ()
    unread_cameras: dict[str, str] = field(default_factory=dict)  # other cameras left unread, and why
    # Task uncertainty of cut cues and of the same demos' real ones (``trust``), or how to measure it when needed.
    still: tuple[np.ndarray, np.ndarray] | Callable[[], tuple[np.ndarray, np.ndarray]] | None = None
    # Some demos' rows and their cues played backwards (``trust``), or how to encode them when needed.
    backwards: tuple[np.ndarray, TaskPosterior] | Callable[[], tuple[np.ndarray, TaskPosterior]] | None = None
    _z: np.ndarray | None = field(default=None, repr=False)
    # The ranking of each set of ranked scores, and the reasons, computed once (``scorers.combination``,
    # ``scorers.explanation``).
    rankings: dict[tuple, Any] = field(default_factory=dict, repr=False)
    explained: dict[tuple, Any] = field(default_factory=dict, repr=False)

    def task_variables(self) -> np.ndarray:
        """``controller_z`` of every demo (what its actions are judged under), computed once."""
        if self._z is None:
            self._z = controller_z(self.posterior, self.tasks)
        return self._z

    @property
    def untrusted(self) -> dict[str, str]:
        """The model's scores that stay out of the ranking, and why (``trust.untrusted``: task uncertainty on the
        demos whose arm the motion check finds hardly moving, else on the cut cues where the audit encoded them;
        the novelty and the consistency on cues played backwards)."""
        if self.model is None:
            return {}
        idle = None
        if self.posterior is not None and "motion" in self.behaviour:
            still = np.asarray(self.behaviour["motion"])[:, 0] < modelfree.HARDLY_MOVES  # mean |action|
            sigma = self.posterior.task_uncertainty()
            idle = (sigma[still], sigma[~still])
        return trust.untrusted(self.model.meta, self.still, idle, self.read_backwards())

    def read_backwards(self) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
        """The novelty and the consistency of the demos' cues played backwards and of the same demos' real cues
        (``trust.untrusted``'s ``backwards``); None where they were not encoded."""
        if self.backwards is None or self.posterior is None:
            return None
        rows, back = self.backwards() if callable(self.backwards) else self.backwards
        if not len(rows):
            return None
        own = self.scores.get("consistency")
        own = arithmetic.consistency(self.posterior, self.tasks) if own is None else np.asarray(own)
        out = {"consistency": (arithmetic.consistency_of(back, rows, self.posterior, self.tasks), own[rows])}
        if self.has("novelty"):
            prior_var = self.model.model.encoder.prior_var.cpu().numpy()
            out["novelty"] = (arithmetic.novelty(back, prior_var), arithmetic.novelty(self.posterior, prior_var)[rows])
        return out

    @property
    def tasks(self) -> np.ndarray:
        return self.episodes["task"].to_numpy()

    def on_camera(self, camera: str, source: str) -> "Evidence | None":
        """This evidence as a ``per_camera`` check reads another camera: its decoding pass's result ``source`` that
        camera's (None where that camera was not decoded)."""
        key = camera_column(source, camera)
        if key not in self.behaviour:
            return None
        return replace(self, behaviour={**self.behaviour, source: self.behaviour[key]})

    @property
    def groups(self) -> np.ndarray:
        """What each demo is compared with by the checks that judge a demo against its task's others
        (``comparison_groups``)."""
        return comparison_groups(self.tasks)

    def has(self, need: str) -> bool:
        """Whether this evidence can feed a scorer that needs ``need``."""
        return {"cues": self.posterior is not None, "model": self.model is not None,
                "novelty": self.model is not None and bool(self.model.config.novelty),
                "reference": self.model is not None and bool((self.model.meta.get("reference") or {}).get("ocsvm")),
                "tecnet": self.embedding is not None, "demos": True, "scores": True,
                "many": len(self.episodes) > 1, "frames": self.frames}[need]


Scores = tuple[np.ndarray, list[Finding] | None]  # one number per demo, and what the check found in it (or None)


class DemoConsumer(Protocol):
    def add(self, demo: Demo) -> None: ...

    def finish(self) -> Any: ...


@dataclass(frozen=True)
class Scorer:
    """A check: its column, what it needs, how it scores (higher = more suspect) and decodes.  Whether and how its
    score enters the ranking is the ranking recipe's (``democheck/recipes/ranking/default.toml``)."""

    name: str
    description: str
    needs: tuple[str, ...]
    score: Callable[[Evidence], Scores]
    family: str = "democheck"  # "democheck" or "baseline" (what users would pick instead)
    in_audit: bool = True  # computed by ``democheck audit`` (False: ``bench`` only)
    # Where its decoding pass's result lands in ``Evidence.behaviour`` (default: its name); scorers that give
    # the same key share one consumer.
    behaviour: str = ""
    # For "demos": (evidence, its rows of one dataset, device) -> a consumer of that dataset's decoded demos.
    decode: Callable[[Evidence, slice, Any], DemoConsumer] | None = None
    short: str = ""  # header in narrow terminal tables
    # It reads the pictures alone, so it reads every camera of a dataset of several: its column on each other
    # camera is "<name>@<camera>" (``Evidence.cameras``).
    per_camera: bool = False
    higher_is_more_suspect: bool = True  # the contract: every scorer's direction

    @property
    def source(self) -> str:
        """Its key in ``Evidence.behaviour``."""
        return self.behaviour or self.name

    @property
    def model_free(self) -> bool:
        return not {"cues", "model", "novelty", "reference", "tecnet"} & set(self.needs)

    def can_run(self, ev: Evidence) -> bool:
        """Whether ``ev`` has what this scorer needs: for one that needs every frame, its decoding pass's result
        (``ev.behaviour``); for the others, every need."""
        if "demos" in self.needs:  # what it needs besides the decoded demos was needed by the decoding pass
            return self.source in ev.behaviour and all(ev.has(n) for n in self.needs if n in ("many", "frames"))
        return all(ev.has(n) for n in self.needs)

    def can_decode(self, ev: Evidence) -> bool:
        """Whether this scorer's decoding pass can run on ``ev`` (it needs every frame, and has the rest)."""
        return self.decode is not None and all(ev.has(n) for n in self.needs if n != "demos")
