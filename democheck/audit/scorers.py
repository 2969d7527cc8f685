"""The registry of scorers: every way democheck (and the baselines it is measured against) scores a demo.

One contract, in the spirit of cleanlab's issue managers: a scorer has a
``name`` (its column in every table), a one-line ``description``, what it
``needs``, and a ``score`` function that returns one number per demo --
higher is more suspect, always -- and, where it can, a reason per demo
(which timestep, which dimension, which score).  ``democheck audit``,
``democheck bench``, the audit's summary, the terminal table and the Rerun
report all read ``SCORERS``; adding a scorer is one entry here plus its test
(``tests/test_scorers.py`` runs every entry on a planted bad demo).

Scorers that need every frame (``needs`` has ``demos``) also give a
``decode`` function: it returns a consumer fed each decoded demo of one
dataset once, in order, so all of them share one decoding pass per dataset;
what the consumers return lands in ``Evidence.behaviour``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np
import pandas as pd

from democheck.audit.baselines import MotionFeatures, score_heuristic, score_random, score_tecnet_knn
from democheck.audit import colours, coupling, dynamics, frames, modelfree, outcome, ranking, sensors, trust
from democheck.audit.action_error import ACTION_STEPS, ActionErrors, controller_z
from democheck.audit.flagging import is_broken
from democheck.audit.ocsvm import ocsvm_margin
from democheck.audit.scores import CONSISTENCY_K, consistency_parts
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
    reasons: dict[str, list[str]] = field(default_factory=dict)
    seed: int = 0
    frames: bool = True  # the demos have camera frames (False: a dataset that records no camera, ``NO_CAMERA``)
    # Task uncertainty of cut cues and of the same demos' real ones (``trust``), or how to measure it when needed.
    still: tuple[np.ndarray, np.ndarray] | Callable[[], tuple[np.ndarray, np.ndarray]] | None = None
    _z: np.ndarray | None = field(default=None, repr=False)
    _combinations: dict[tuple, ranking.Ranking] = field(default_factory=dict, repr=False)
    _explained: dict[bool, tuple[list[str], list[str]]] = field(default_factory=dict, repr=False)

    def task_variables(self) -> np.ndarray:
        """``controller_z`` of every demo (what its actions are judged under), computed once."""
        if self._z is None:
            self._z = controller_z(self.posterior, self.tasks)
        return self._z

    def combination(self, model_free: bool = False) -> ranking.Ranking:
        """The ranking of the scores ``ranked`` picks (``ranking.rank`` under ``ranking_config``): their tail
        probabilities, the robust core they were fitted on (the reference the flags are calibrated on) and the
        suspicion.  Computed once for each set of scores (the ranking and the audit's flags both read it)."""
        names = ranked(self.scores, self.tasks, model_free, self.untrusted)
        key = tuple(names)
        if key not in self._combinations:
            self._combinations[key] = ranking.rank(self.scores, self.groups, ranking_config(names),
                                                   broken_rows(self))
        return self._combinations[key]

    def explanation(self, model_free: bool = False) -> tuple[list[str], list[str]]:
        """Each demo's reason (every clause) and the check it names first (``ranking.explain``), once."""
        if model_free not in self._explained:
            self._explained[model_free] = ranking.explain(self.combination(model_free), self.reasons,
                                                          self.reasons.get("broken"))
        return self._explained[model_free]

    @property
    def untrusted(self) -> dict[str, str]:
        """The model's scores that stay out of the ranking, and why (``trust.untrusted``: on the demos whose arm
        the motion check finds hardly moving, else on the cut cues where the audit encoded them)."""
        if self.model is None:
            return {}
        idle = None
        if self.posterior is not None and "motion" in self.behaviour:
            still = np.asarray(self.behaviour["motion"])[:, 0] < modelfree.HARDLY_MOVES  # mean |action|
            sigma = self.posterior.task_uncertainty()
            idle = (sigma[still], sigma[~still])
        return trust.untrusted(self.model.meta, self.still, idle)

    @property
    def tasks(self) -> np.ndarray:
        return self.episodes["task"].to_numpy()

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


Scores = tuple[np.ndarray, list[str] | None]  # one number per demo, and a reason per demo (or None)


class DemoConsumer(Protocol):
    def add(self, demo: Demo) -> None: ...

    def finish(self) -> Any: ...


@dataclass(frozen=True)
class Scorer:
    name: str
    description: str
    needs: tuple[str, ...]
    score: Callable[[Evidence], Scores]
    family: str = "democheck"  # "democheck" or "baseline" (what users would pick instead)
    in_audit: bool = True  # computed by ``democheck audit`` (False: ``bench`` only)
    in_suspicion: bool = False  # one of the scores the ranking combines
    # In the ranking of a dataset with a single task too.  The task embedding's scores are not: with no other
    # task to tell apart, a demo far from its neighbours is mostly one on an unusual layout.  On two one-task
    # development sets (Meta-World drawer-open seed 1 and push seed 2, 40 clean + 15 bad each, their your-data
    # models) task uncertainty and consistency put 1 and 2 of 40 clean demos over the --fpr 0.01 flag; without
    # them none, recall 0.93 and 0.93 (with them 0.93 and 1.00), AUROC >= 0.99 on every kind either way.
    in_single_task_ranking: bool = True
    # In the ranking on a log scale: a score whose clean demos' right tail is long (a squared error) would
    # otherwise put clean demos many robust standard deviations up.
    log_in_ranking: bool = False
    in_robust_sd: bool = False  # its score is already a robust z within the task: the ranking takes it as it is
    # Scorers of one look ask one question of a demo (whether its actions are explained: by the model's controller,
    # or by its state): where the ranking has more than one of them they are one piece of evidence, the Sidak
    # minimum of their tail probabilities (``scores.merge_looks``); see ``democheck.audit.coupling``.
    look: str = ""
    # The least spread a robust standard deviation of this score stands for in the ranking, in its units.
    ranking_min_scale: float = 0.0
    # The family of its clean right tail in the ranking (``scores.tail_probabilities``): "exponential", or
    # "normal" for a score that is a mean over many steps (the central limit theorem makes its clean spread normal,
    # and an exponential through its quartiles would call a demo six robust SD out one clean demo in a few hundred).
    tail: str = "exponential"
    # A recording fault (a frozen camera, dropped frames, actions recorded out of step, a shaking command stream,
    # a frozen sensor): the faults' tail probabilities stand apart, beside the combination of the others
    # (``scores.combined_log10``), instead of adding up with them in Fisher's sum, where one small probability is
    # diluted by every ordinary one beside it.
    alone: bool = False
    # Where its decoding pass's result lands in ``Evidence.behaviour`` (default: its name); scorers that give
    # the same key share one consumer.
    behaviour: str = ""
    # For "demos": (evidence, its rows of one dataset, device) -> a consumer of that dataset's decoded demos.
    decode: Callable[[Evidence, slice, Any], DemoConsumer] | None = None
    short: str = ""  # header in narrow terminal tables
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


# ---------------------------------------------------------------------------
# PETNet's scores
# ---------------------------------------------------------------------------

def _against_task(values: np.ndarray, groups: np.ndarray, words: str) -> list[str]:
    """'<words> (k x its task's median)' for each demo, in the terms of its comparison group."""
    median = pd.Series(values).groupby(np.asarray(groups)).transform("median").to_numpy()
    return [f"{words} ({v / m:.2g} x its task's median)" if np.isfinite(v) and m > 0 else words
            for v, m in zip(values, median)]


def _task_uncertainty(ev: Evidence) -> Scores:
    values = ev.posterior.task_uncertainty()
    return values, _against_task(values, ev.groups, "the model cannot tell the task from its first and last frames")


def _task_uncertainty_head(ev: Evidence) -> Scores:
    return ev.posterior.task_uncertainty(head_only=True), None


def _novelty(ev: Evidence) -> Scores:
    # d2 / d2_ref of each cue: the novelty part of the variance is the prior's variance times this.
    return (ev.posterior.var_novel / ev.model.model.encoder.prior_var.cpu().numpy()).mean(1), None


def _consistency(ev: Evidence) -> Scores:
    value, _ = consistency_parts(ev.posterior, ev.tasks)
    return value, _against_task(value, ev.groups, "its first and last frames read as another task than its "
                                                  "task's other demos")


def _action_error(ev: Evidence) -> Scores:
    got = ev.behaviour["action_error"]  # (values, reasons) from ``ActionErrors``, or values given directly
    return got if isinstance(got, tuple) else (np.asarray(got), None)


def _decode_action_error(ev: Evidence, rows: slice, device: Any) -> ActionErrors:
    # Each demo is judged under its task across all the evidence (a bench pools datasets).
    return ActionErrors(ev.model, ev.task_variables()[rows], device)


ACTIONS_EXPLAINED = "actions explained"  # the look of the action error and the coupling (``Scorer.look``)

# The least spread a robust standard deviation of a recording fault's score stands for in the ranking (a share of
# the steps for the frozen video, a log ratio for the frame jump, the lag and the timing): a camera whose frames
# never repeat, actions that no shift explains better or a clock that never slips leave a MAD of zero, which
# would call a single repeated frame many standard deviations (chosen on the development sets: docs/decisions.md,
# "Recording faults beside the sum, not in it").
FAULT_MIN_SCALE = 0.02


def _suspicion(ev: Evidence, model_free: bool = False) -> Scores:
    r = ev.combination(model_free)
    return (r.suspicion, ev.explanation(model_free)[0]) if r.config.specs else (r.suspicion, None)


def _model_free(ev: Evidence) -> Scores:
    return _suspicion(ev, model_free=True)


def _motion(ev: Evidence) -> Scores:
    return modelfree.motion(ev.behaviour["motion"], ev.groups)


def _view(ev: Evidence) -> Scores:
    return modelfree.view(ev.behaviour["view"], ev.groups)


def _colours(ev: Evidence) -> Scores:
    return colours.colours(ev.behaviour["colours"], ev.groups)


def _idle(ev: Evidence) -> Scores:
    return modelfree.idle(ev.behaviour["actions"])


def _broken(ev: Evidence) -> Scores:
    return modelfree.broken(ev.behaviour["actions"])


def _jerk(ev: Evidence) -> Scores:
    return modelfree.jerk(ev.behaviour["actions"])


def _saturation(ev: Evidence) -> Scores:
    return modelfree.saturation(ev.behaviour["actions"])


def _duplicate(ev: Evidence) -> Scores:
    return modelfree.duplicate(ev.behaviour["actions"], ev.episodes["episode_index"].to_numpy())


def _dynamics(ev: Evidence) -> Scores:
    return dynamics.dynamics(ev.behaviour["dynamics"])


def _timing(ev: Evidence) -> Scores:
    return modelfree.timing(ev.behaviour["actions"])


def _frozen_video(ev: Evidence) -> Scores:
    return frames.frozen_video(ev.behaviour["frozen_video"])


def _frame_jump(ev: Evidence) -> Scores:
    return frames.frame_jump(ev.behaviour["frozen_video"])


def _lag(ev: Evidence) -> Scores:
    return dynamics.lag(ev.behaviour["dynamics"])


def _frozen_state(ev: Evidence) -> Scores:
    return sensors.frozen_state(ev.behaviour["frozen_state"], ev.groups)


def _outcome(ev: Evidence) -> Scores:
    return outcome.outcome(ev.behaviour["outcome"], ev.groups)


def _coupling(ev: Evidence) -> Scores:
    return coupling.coupling(ev.behaviour["coupling"], ev.groups)


def _ocsvm_flag(ev: Evidence) -> Scores:
    margin = ocsvm_margin(ev.model.meta["reference"]["ocsvm"], ev.posterior.sigma)
    return (margin < 0).astype(float), None


def _traces(ev: Evidence, rows: slice, device: Any) -> modelfree.ActionTraces:
    return modelfree.ActionTraces()


SCORERS: dict[str, Scorer] = {s.name: s for s in (
    Scorer("task_uncertainty", "PETNet's task uncertainty (the paper's score): mean task standard deviation of the "
           "demo's cue, both parts of the variance", ("cues",), _task_uncertainty, in_suspicion=True,
           in_single_task_ranking=False, log_in_ranking=True, short="unc."),
    Scorer("task_uncertainty_head", "the paper's variance head alone, without the novelty part",
           ("cues",), _task_uncertainty_head, in_audit=False, short="head"),
    Scorer("novelty", "how unfamiliar the demo's end is (its last frame, and where the arm ended where the model "
           "reads that too): squared feature distance from the training demos' over the model's reference (above 1: "
           "less familiar than 9 in 10 of the real demos it was referenced on, held out or, where the model learnt "
           "every demo, its own)",
           ("cues", "novelty"), _novelty, short="novel."),
    Scorer("consistency", f"mean distance of the demo's task mean from those of its {CONSISTENCY_K} nearest other "
           "demos of its task, each dimension in units of its median task standard deviation", ("cues",), _consistency,
           in_suspicion=True, in_single_task_ranking=False, short="cons."),
    Scorer("action_error", f"how badly PETNet's controller, told the task by the other demos of the task, explains "
           f"the demo's normalised actions (MSE at {ACTION_STEPS} evenly spaced timesteps)", ("demos", "model"),
           _action_error, in_suspicion=True, log_in_ranking=True, look=ACTIONS_EXPLAINED, decode=_decode_action_error,
           short="act."),
    Scorer("motion", "model-free: how unusually much or little the demo's actions move (mean |action| and mean "
           "|change of action|, the larger robust |z| within its task)", ("demos",), _motion, in_suspicion=True,
           in_robust_sd=True, decode=lambda ev, rows, device: modelfree.MotionStats(), short="mot."),
    Scorer("idle", "model-free: share of steps at which the actions hardly change (under "
           f"{modelfree.STILL:g} x each dimension's median change), and the longest still stretch", ("demos",),
           _idle, in_suspicion=True, ranking_min_scale=modelfree.IDLE_MIN_SCALE, behaviour="actions",
           decode=_traces, short="idle"),
    Scorer("broken", "model-free: the share of the demo's frames that could not be decoded, or whose states or "
           "actions held NaN or infinite values (repaired to be read; any: the demo ranks first and is flagged)",
           ("demos",), _broken, behaviour="actions", decode=_traces, short="broken"),
    Scorer("jerk", "model-free: log mean |third difference of actions| in median-change units (shaking, "
           "chatter)", ("demos",), _jerk, in_suspicion=True, alone=True, ranking_min_scale=modelfree.JERK_MIN_SCALE,
           behaviour="actions", decode=_traces, short="jerk"),
    Scorer("saturation", "model-free: share of steps at which some action dimension sits at its limit over all "
           "the demos", ("demos",), _saturation, behaviour="actions", decode=_traces, short="sat."),
    Scorer("duplicate", "model-free: how much nearer than usual the nearest other demo's actions are (log "
           "ratio; inf = an exact copy of another demo: actions, state and frames)", ("demos", "many"), _duplicate,
           behaviour="actions", decode=_traces, short="dup."),
    Scorer("dynamics", "model-free: action-state disagreement -- log of how badly a linear model of its block of "
           f"{dynamics.DYNAMICS_BLOCK} demos predicts the demo's change of state from its state and actions, "
           "over the median demo's", ("demos",), _dynamics,
           decode=lambda ev, rows, device: dynamics.DynamicsFit(), short="dyn."),
    Scorer("lag", f"model-free: how much better the demo's states follow its actions moved in time (log of the "
           f"dynamics check's error as recorded over the least with the actions moved up to {dynamics.LAG_MAX} "
           "steps either way): actions recorded late or early", ("demos",), _lag, in_suspicion=True, alone=True,
           ranking_min_scale=FAULT_MIN_SCALE, behaviour="dynamics",
           decode=lambda ev, rows, device: dynamics.DynamicsFit(), short="lag"),
    Scorer("timing", "model-free: how far the worst time step is off the frame period 1/fps, log(1 + |step - "
           "period| / period), 0 when every step is within half a period (dropped, repeated or reordered frames; "
           "NaN without timestamps)", ("demos",), _timing, in_suspicion=True, alone=True,
           ranking_min_scale=FAULT_MIN_SCALE, behaviour="actions", decode=_traces, short="time"),
    Scorer("frozen_video", "model-free: the longest stretch of steps at which the camera frame repeats while the "
           "actions change, as a share of the demo's steps (a camera that stopped delivering)", ("demos", "frames"),
           _frozen_video, in_suspicion=True, alone=True, ranking_min_scale=FAULT_MIN_SCALE,
           decode=lambda ev, rows, device: frames.FrameChanges(), short="frozen"),
    Scorer("frame_jump", "model-free: how much more the camera frame changes at one step than at the "
           f"{frames.JUMP_NEIGHBOURS} steps either side (log of the largest ratio): frames dropped from the "
           "recording, or recordings spliced", ("demos", "frames"), _frame_jump, in_suspicion=True, alone=True,
           ranking_min_scale=FAULT_MIN_SCALE, behaviour="frozen_video",
           decode=lambda ev, rows, device: frames.FrameChanges(), short="jump"),
    Scorer("frozen_state", "model-free: the longest stretch of steps at which a state dimension repeats its "
           "value exactly while the actions change, as a share of the demo (the largest over the dimensions still "
           "in hardly any of its task's demos): a sensor that stopped updating", ("demos",), _frozen_state,
           in_suspicion=True, alone=True, ranking_min_scale=sensors.FROZEN_STATE_MIN_SCALE,
           decode=lambda ev, rows, device: sensors.StateRepeats(), short="frz.st"),
    Scorer("view", "model-free: share of the demo's average picture (16x16) unlike its task's other demos' there "
           f"(over {modelfree.VIEW_K:g} robust SD from their median): a covered or moved camera, another scene; "
           "robust z within its task", ("demos", "frames"), _view, in_suspicion=True, in_robust_sd=True,
           decode=lambda ev, rows, device: modelfree.ViewStats(), short="view"),
    Scorer("colours", "model-free: how differently from its task's other demos the frames are coloured, wherever "
           f"the colours are in the view (every {modelfree.VIEW_EVERY}th frame's pixels in "
           f"{colours.COLOUR_LEVELS ** 3} colour bins, each bin's log share in robust SD within its task, RMS "
           "over the colours shown): an object missing or another one, a covered camera; robust z within its "
           "task", ("demos", "frames"), _colours, in_suspicion=True, in_robust_sd=True,
           decode=lambda ev, rows, device: colours.ColourStats(), short="colour"),
    Scorer("outcome", "model-free: how differently from its task's other demos the demo left the world (the "
           "environment state where recorded, else the state: last value and change from the first, RMS of robust "
           "z within its task)", ("demos",), _outcome, in_suspicion=True,
           decode=lambda ev, rows, device: outcome.OutcomeStats(), short="outc."),
    Scorer("coupling", "model-free: how little the demo's actions go with its state (minus their mutual "
           "information over its steps, KSG estimate, nats); one look with the action error in the ranking",
           ("demos",), _coupling, in_suspicion=True, look=ACTIONS_EXPLAINED, tail="normal",
           ranking_min_scale=coupling.COUPLING_MIN_SCALE,
           decode=lambda ev, rows, device: coupling.CouplingStats(), short="coupl."),
    Scorer("suspicion", "democheck's ranking: -log10 of the combined tail probability of task uncertainty (log), "
           "consistency, motion, idle, view, colours, outcome and whether the actions are explained (the action "
           "error (log) and the coupling, one look: the Sidak minimum of the two) (one task: without the first "
           "two), each in robust standard deviations within its task, the "
           "tails fitted on the robust core; beside that, the smallest of the recording faults' (timing, frozen "
           "video, frame jump, frozen state, lag, jerk) (2 = as unusual as 1 clean demo in 100)", ("scores",),
           _suspicion, short="susp."),
    Scorer("model_free", "the same combination of the model-free scores of the ranking alone (motion, idle, "
           "view, colours, outcome, coupling, and the recording faults): what democheck says with no model",
           ("scores",), _model_free,
           in_audit=False, short="no-model"),
    Scorer("ocsvm_flag", "the paper's linear one-class SVM on 1/sigma^2, fitted on the model's training demos "
           "(1 = flagged; one operating point)", ("cues", "reference"), _ocsvm_flag, in_audit=False, short="ocsvm"),
    Scorer("tecnet_knn", "TecNets embedding: mean distance to the 5 nearest other demos of the task", ("tecnet",),
           score_tecnet_knn, family="baseline", in_audit=False, short="tecnet"),
    Scorer("heuristic", "linter rules: max |robust z| of idle fraction, action energy and jerk", ("demos",),
           score_heuristic, family="baseline", in_audit=False, decode=lambda ev, rows, device: MotionFeatures(),
           short="heurist."),
    Scorer("random", "a uniform random score, the floor every detector must clear", ("scores",), score_random,
           family="baseline", in_audit=False, short="random"),
)}

# The checks whose words say what the demo did, in the order a reason prefers them: the arm, then the world it left,
# then what the camera saw.  The recording faults come after them, then the other model-free checks (the coupling:
# a frozen sensor and an operator who let go both loosen it), the model's readings last (``ScoreSpec.lead``).
WHAT_HAPPENED = ("idle", "motion", "jerk", "outcome", "view", "colours")


def ranked(available, tasks: np.ndarray, model_free: bool = False, untrusted=()) -> list[str]:
    """The scores the ranking combines, of those ``available`` (names, or columns by name): every
    ``in_suspicion`` scorer's, less the task embedding's on a dataset of one task (``in_single_task_ranking``),
    less the model's with ``model_free`` and those it did not earn (``untrusted``, ``trust.untrusted``), less a
    column with no score at all (the outcome of a dataset whose tasks are all too small to compare): a look that
    cannot see anything must not cost the others' correction."""
    one_task = len(np.unique(tasks)) == 1
    columns = isinstance(available, (dict, pd.DataFrame))

    def scored(n: str) -> bool:
        return not columns or bool(np.isfinite(np.asarray(available[n], np.float64)).any())

    return [n for n, s in SCORERS.items() if s.in_suspicion and n in available and n not in untrusted
            and (s.model_free or not model_free) and (s.in_single_task_ranking or not one_task) and scored(n)]


def ranking_config(names: list[str]) -> ranking.RankingConfig:
    """How the scores ``names`` enter the ranking, from their scorers: ``ranking.ScoreSpec`` each."""
    def lead(s: Scorer) -> int:
        if s.name in WHAT_HAPPENED:
            return WHAT_HAPPENED.index(s.name)
        return len(WHAT_HAPPENED) + (0 if s.alone else 1 if s.model_free else 2)

    return ranking.RankingConfig(tuple(
        ranking.ScoreSpec(n, log=s.log_in_ranking, in_robust_sd=s.in_robust_sd, floor=s.ranking_min_scale,
                          tail=s.tail, alone=s.alone, look=s.look, lead=lead(s), behaviour=n in WHAT_HAPPENED)
        for n, s in ((n, SCORERS[n]) for n in names)))


def broken_rows(ev: Evidence) -> np.ndarray:
    """Which demos are broken recordings (``flagging.is_broken``; ``flagging.broken_recordings`` on a table): bool
    [N], all False without that check."""
    return is_broken(ev.scores["broken"]) if "broken" in ev.scores else np.zeros(len(ev.episodes), bool)


def select(names: list[str] | None = None, audit: bool = True) -> list[Scorer]:
    """Scorers by name, in the registry's order; default: those ``democheck audit`` computes."""
    if names is None:
        return [s for s in SCORERS.values() if s.in_audit or not audit]
    unknown = [n for n in names if n not in SCORERS]
    if unknown:
        raise KeyError(f"unknown scorer {', '.join(unknown)}; scorers: {', '.join(SCORERS)}")
    return [s for s in SCORERS.values() if s.name in names]


def compute(ev: Evidence, scorers: list[Scorer]) -> Evidence:
    """Run ``scorers`` (whose decoding pass, if any, has filled ``ev.behaviour``) in the registry's order, each
    that the evidence can feed; fills ``ev.scores`` and ``ev.reasons``."""
    for s in scorers:
        if not s.can_run(ev):
            continue
        values, reasons = s.score(ev)
        ev.scores[s.name] = values  # as computed: float32 where the network's output is, float64 elsewhere
        if reasons is not None:
            ev.reasons[s.name] = reasons
    return ev
