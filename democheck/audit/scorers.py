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
what the consumers return lands in ``Evidence.behaviour``.  What a check found
in each demo is a ``findings.Finding`` (a kind of the check's vocabulary and
its parameters); ``democheck.audit.reasons`` builds the reasons from them.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pandas as pd

from democheck import resources
from democheck.audit import (colours, coupling, dynamics, frames, grasps, model_scores, modelfree, moved, outcome,
                             ranking, reasons, sensors, timeline, view, way)
from democheck.audit.action_error import ACTION_STEPS
from democheck.audit.baselines import MotionFeatures, score_heuristic, score_random, score_tecnet_knn
from democheck.audit.evidence import Evidence, Scorer, Scores
from democheck.audit.findings import VOCABULARIES, camera_column, check_of, known
from democheck.audit.flagging import DEFAULT_FPR, is_broken
from democheck.audit.ocsvm import ocsvm_margin
from democheck.audit.scores import CONSISTENCY_K
from democheck.errors import RecipeError


def _suspicion(ev: Evidence, model_free: bool = False) -> Scores:
    return combination(ev, model_free).suspicion, None


def _model_free(ev: Evidence) -> Scores:
    return _suspicion(ev, model_free=True)


def _motion(ev: Evidence) -> Scores:
    return modelfree.motion(ev.behaviour["motion"], ev.groups)


def _view(ev: Evidence) -> Scores:
    return view.view(ev.behaviour["view"], ev.groups)


def _colours(ev: Evidence) -> Scores:
    return colours.colours(ev.behaviour["colours"], ev.groups)


def _idle(ev: Evidence) -> Scores:
    return modelfree.idle(ev.behaviour["actions"])


def _pause(ev: Evidence) -> Scores:
    return modelfree.pause(ev.behaviour["actions"])


def _grasps(ev: Evidence) -> Scores:
    return grasps.grasps(ev.behaviour["actions"], ev.groups)


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
    return frames.frozen_video(ev.behaviour["frozen_video"], ev.groups)


def _frame_jump(ev: Evidence) -> Scores:
    return frames.frame_jump(ev.behaviour["frozen_video"])


def _lag(ev: Evidence) -> Scores:
    return dynamics.lag(ev.behaviour["dynamics"], ev.groups)


def _state_jump(ev: Evidence) -> Scores:
    return dynamics.state_jump(ev.behaviour["dynamics"])


def _frozen_state(ev: Evidence) -> Scores:
    # The arm's longest still stretch (the idle check's finding) tells a sensor that stopped from a state held
    # while the arm rested.
    still = None
    if "idle" in ev.findings:
        still = np.array([f.params.get("longest", 0.0) for f in ev.findings["idle"]], np.float64)
    return sensors.frozen_state(ev.behaviour["frozen_state"], ev.groups, still=still)


def _outcome(ev: Evidence) -> Scores:
    return outcome.outcome(ev.behaviour["outcome"], ev.groups)


def _moved(ev: Evidence) -> Scores:
    return moved.moved(ev.behaviour["moved"], ev.groups)


def _start(ev: Evidence) -> Scores:
    return timeline.start(ev.behaviour["timeline"], ev.groups)


def _end(ev: Evidence) -> Scores:
    return timeline.end(ev.behaviour["timeline"], ev.groups)


def _path(ev: Evidence) -> Scores:
    return timeline.path(ev.behaviour["timeline"], ev.groups)


def _backwards(ev: Evidence) -> Scores:
    return timeline.backwards(ev.behaviour["timeline"], ev.groups)


def _backwards_state(ev: Evidence) -> Scores:
    return way.backwards_state(ev.behaviour["timeline"], ev.groups)


def _timeline(ev: Evidence, rows: slice, device: Any) -> timeline.Timeline:
    return timeline.Timeline()


def _coupling(ev: Evidence) -> Scores:
    return coupling.coupling(ev.behaviour["coupling"], ev.groups)


def _ocsvm_flag(ev: Evidence) -> Scores:
    margin = ocsvm_margin(ev.model.meta["reference"]["ocsvm"], ev.posterior.sigma)
    return (margin < 0).astype(float), None


def _traces(ev: Evidence, rows: slice, device: Any) -> modelfree.ActionTraces:
    return modelfree.ActionTraces()


SCORERS: dict[str, Scorer] = {s.name: s for s in (
    Scorer("task_uncertainty", "PETNet's task uncertainty (the paper's score): mean task standard deviation of the "
           "demo's cue, both parts of the variance", ("cues",), model_scores.task_uncertainty, short="unc."),
    Scorer("task_uncertainty_head", "the paper's variance head alone, without the novelty part",
           ("cues",), model_scores.task_uncertainty_head, in_audit=False, short="head"),
    Scorer("novelty", "how unfamiliar the demo's end is (its last frame, and where the arm ended where the model "
           "reads that too): squared feature distance from the training demos' over the model's reference (above 1: "
           "less familiar than 9 in 10 of the real demos it was referenced on, held out or, where the model learnt "
           "every demo, its own)",
           ("cues", "novelty"), model_scores.novelty, short="novel."),
    Scorer("consistency", f"mean distance of the demo's task mean from those of its {CONSISTENCY_K} nearest other "
           "demos of its task, each dimension in units of its median task standard deviation", ("cues",),
           model_scores.consistency, short="cons."),
    Scorer("action_error", f"how badly PETNet's controller, told the task by the other demos of the task, explains "
           f"the demo's normalised actions (MSE at {ACTION_STEPS} evenly spaced timesteps)", ("demos", "model"),
           model_scores.action_error, decode=model_scores.decode_action_error, short="act."),
    Scorer("motion", "model-free: how unusually much or little the demo's actions move (mean |action| and mean "
           "|change of action|, the larger robust |z| within its task)", ("demos",), _motion,
           decode=lambda ev, rows, device: modelfree.MotionStats(), short="mot."),
    Scorer("idle", "model-free: share of steps at which the actions hardly change (under "
           f"{modelfree.STILL:g} x each dimension's median change), and the longest still stretch", ("demos",),
           _idle, behaviour="actions", decode=_traces, short="idle"),
    Scorer("pause", "model-free: the longest stretch of steps at which the actions hardly change between the "
           "demo's first and last move, as a share of its steps (an operator who hesitated mid-task)", ("demos",),
           _pause, behaviour="actions", decode=_traces, short="pause"),
    Scorer("grasps", "model-free: how many times the gripper's command changes between open and closed (the action "
           "dimensions named for the gripper; none: NaN), judged against its task's demos: a grasp tried again, an "
           "object dropped and picked up", ("demos",), _grasps, behaviour="actions", decode=_traces, short="grasps"),
    Scorer("broken", "model-free: the share of the demo's frames that could not be decoded, or whose states or "
           "actions held NaN or infinite values (repaired to be read; any: the demo ranks first and is flagged)",
           ("demos",), _broken, behaviour="actions", decode=_traces, short="broken"),
    Scorer("jerk", "model-free: log mean |third difference of actions| in median-change units (shaking, "
           "chatter)", ("demos",), _jerk, behaviour="actions", decode=_traces, short="jerk"),
    Scorer("saturation", "model-free: share of steps at which some action dimension sits at its limit over all "
           "the demos", ("demos",), _saturation, behaviour="actions", decode=_traces, short="sat."),
    Scorer("duplicate", "model-free: how much nearer than usual the nearest other demo's actions are (log "
           "ratio; inf = an exact copy of another demo: actions, state and frames)", ("demos", "many"), _duplicate,
           behaviour="actions", decode=_traces, short="dup."),
    Scorer("dynamics", "model-free: action-state disagreement -- log of how badly a linear model of its block of "
           f"{dynamics.DYNAMICS_BLOCK} demos predicts the demo's change of state from its state and actions, "
           "over the median demo's", ("demos",), _dynamics,
           decode=lambda ev, rows, device: dynamics.DynamicsFit(), short="dyn."),
    Scorer("lag", f"model-free: how much better the demo's states follow its actions moved in time than its task's "
           "demos' do (log of the dynamics check's error at its task's usual shift over the least with the actions "
           f"moved up to {dynamics.LAG_MAX} steps either way; 0 within its task's scatter of shifts or a step of its "
           "usual one, none where it still falls past that): actions recorded late or early", ("demos",),
           _lag, behaviour="dynamics",
           decode=lambda ev, rows, device: dynamics.DynamicsFit(), short="lag"),
    Scorer("timing", "model-free: how far the worst time step is off the frame period 1/fps, log(1 + |step - "
           "period| / period), 0 when every step is within half a period (dropped, repeated or reordered frames; "
           "NaN without timestamps)", ("demos",), _timing, behaviour="actions", decode=_traces, short="time"),
    Scorer("frozen_video", "model-free: the longest stretch of steps at which the camera frame repeats while the "
           "actions change, as a share of the demo's steps (a camera that stopped delivering)", ("demos", "frames"),
           _frozen_video, decode=lambda ev, rows, device: frames.FrameChanges(), short="frozen", per_camera=True),
    Scorer("frame_jump", "model-free: how much more the camera frame changes at one step than at the "
           f"{modelfree.JUMP_NEIGHBOURS} steps either side (log of the largest ratio): frames dropped from the "
           "recording, or recordings spliced", ("demos", "frames"), _frame_jump, behaviour="frozen_video",
           decode=lambda ev, rows, device: frames.FrameChanges(), short="jump", per_camera=True),
    Scorer("state_jump", "model-free: how much worse the dynamics check's fit explains the demo's change of state "
           f"at one step than at the {modelfree.JUMP_NEIGHBOURS} steps either side (log of the largest ratio of the "
           "step's error): steps dropped from the recording, or recordings spliced", ("demos",), _state_jump,
           behaviour="dynamics", decode=lambda ev, rows, device: dynamics.DynamicsFit(), short="st.jump"),
    Scorer("frozen_state", "model-free: the longest stretch of steps at which a state dimension repeats its "
           "value exactly while the actions change, as a share of the demo (the largest over the dimensions still "
           "in hardly any of its task's demos): a sensor that stopped updating", ("demos",), _frozen_state,
           decode=lambda ev, rows, device: sensors.StateRepeats(), short="frz.st"),
    Scorer("view", "model-free: share of the demo's average picture (16x16) unlike its task's other demos' there "
           f"(over {view.VIEW_K:g} robust SD from their median): a covered or moved camera, another scene; "
           "robust z within its task", ("demos", "frames"), _view,
           decode=lambda ev, rows, device: view.ViewStats(), short="view", per_camera=True),
    Scorer("colours", "model-free: how differently from its task's other demos the frames are coloured, wherever "
           f"the colours are in the view (every {view.VIEW_EVERY}th frame's pixels in "
           f"{colours.COLOUR_LEVELS ** 3} colour bins, each bin's log share in robust SD within its task, RMS "
           "over the colours shown): an object missing or another one, a covered camera; robust z within its "
           "task", ("demos", "frames"), _colours,
           decode=lambda ev, rows, device: colours.ColourStats(), short="colour", per_camera=True),
    Scorer("outcome", "model-free: how differently from its task's other demos the demo left the world (the "
           "environment state where recorded, else the state: last value and change from the first, RMS of robust "
           "z within its task)", ("demos",), _outcome,
           decode=lambda ev, rows, device: outcome.OutcomeStats(), short="outc."),
    Scorer("moved", "model-free: how unlike its task's demos the colours are of what changed between the demo's "
           f"first and last picture ({moved.MOVED_SIZE} px; each colour's root count, robust z within its task, "
           "RMS): another object moved, or none -- the outcome seen by the camera", ("demos", "frames"), _moved,
           decode=lambda ev, rows, device: moved.MovedStats(), short="moved", per_camera=True),
    Scorer("start", "model-free: how unlike its nearest task-mates' the demo's first picture is (share of it "
           f"over {timeline.UNLIKE:g} robust SD from theirs), and how much nearer their last pictures than their "
           "first its colours side by side lie (wherever they lie), the larger robust z within its task: a demo that "
           "begins elsewhere, or where its task's demos end (done backwards)",
           ("demos",), _start, behaviour="timeline", decode=_timeline, short="start"),
    Scorer("end", "model-free: how unlike its nearest task-mates' the demo's last picture is, and how much nearer "
           "their first, as the start's: a failed place, a knocked-over object, a demo that ends where its task's "
           "demos begin",
           ("demos",), _end, behaviour="timeline", decode=_timeline, short="end"),
    Scorer("path", f"model-free: how far the demo's path ({timeline.PATH_POINTS} points in normalised time, of its "
           "state and of its camera's grey thumbnail) lies from its nearest task-mates' (RMS distance over the path "
           "and at its furthest point, log, the largest robust z within its task): a detour, a regrasp, a path run "
           "backwards",
           ("demos",), _path, behaviour="timeline", decode=_timeline, short="path"),
    Scorer("backwards", "model-free: how much nearer its nearest task-mates' last pictures than their first the "
           "demo's first picture lies, and its last nearer their first, by which colours lie beside which (the lesser "
           "of its two ends, robust z within its task): a reset recorded as a demo",
           ("demos",), _backwards, behaviour="timeline", decode=_timeline, short="backw."),
    Scorer("backwards_state", "model-free: how near its task's demos' last value the demo's first lies, and its last "
           "near their first, in the state dimension that ran most backwards along its task's way (the lesser of "
           "the two, robust z within its task): a reset recorded as a demo, read from the state",
           ("demos",), _backwards_state, behaviour="timeline", decode=_timeline, short="bkw.st"),
    Scorer("coupling", "model-free: how little the demo's actions go with its state (minus their mutual "
           "information over its steps, KSG estimate, nats); one look with the action error in the ranking",
           ("demos",), _coupling,
           decode=lambda ev, rows, device: coupling.CouplingStats(), short="coupl."),
    Scorer("suspicion", "democheck's ranking: -log10 of the combined tail probability of task uncertainty (log), "
           "novelty (log) and consistency (those of the model's scores that pass their tests on the data), "
           "motion, idle, pause, view, colours, outcome, how the demo began, ended and went (start, end and path, "
           "one look) and whether the actions are explained (the action error (log) and the coupling, one look: "
           "the Sidak minimum of the two) (one task: without the task uncertainty), each in robust standard "
           "deviations within its task, the tails fitted on the robust core; beside that, the smallest of the "
           "recording faults' and single looks' (timing, frozen video, a jump of the frame or the state (one look), "
           "frozen state, lag, jerk, grasps) "
           "(2 = as unusual as 1 clean demo in 100)", ("scores",),
           _suspicion, short="susp."),
    Scorer("model_free", "the same combination of the model-free scores of the ranking alone (motion, idle, pause, "
           "grasps, view, colours, outcome, start, end, path, coupling, and the recording faults): what democheck "
           "says with no model",
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

TAILS = ("exponential", "normal")  # the families a score's clean right tail may be given (``scores.tail_probabilities``)
RANKING_KEYS = {"log": bool, "in_robust_sd": bool, "floor": float, "tail": str, "alone": bool, "beside": bool,
                "look": str, "single_task": bool}
REASON_KEYS = {"order", "demoted", "behaviour", "rules"}
RULE_KEYS = {"first", "over", "when", "unless", "same_camera", "says_again"}


def _precedence_errors(section: dict, scores: dict) -> list[str]:
    """What is wrong with a ranking recipe's ``[reasons]`` ``section``: unknown keys, names that are no ranked
    check, kinds that no check's vocabulary declares."""
    bad = [f"reasons.{k}" for k in sorted(set(section) - REASON_KEYS)]
    names = [*section.get("order", []), *section.get("demoted", []), *section.get("behaviour", [])]
    for r in section.get("rules", []):
        bad += [f"reasons.rules.{k}" for k in sorted(set(r) - RULE_KEYS)]
        names += [r.get("first", "")] + [n for k in ("over", "when", "unless", "says_again") for n in r.get(k, [])]
        if not isinstance(r.get("same_camera", False), bool):
            bad.append(f"reasons.rules.same_camera: {r['same_camera']!r}")
    bad += [f"reasons: {n!r}" for n in names if not known(n) or n.partition(":")[0] not in scores]
    return bad


@functools.lru_cache(maxsize=None)
def ranking_recipe(name_or_path: str = "default") -> dict[str, Any]:
    """How the scores enter the ranking and which finding leads a reason, as data:
    ``democheck/recipes/ranking/<name>.toml`` (or a path) read and checked -- the ranked scores in order with
    their keys (``RANKING_KEYS``), ``core_p``, ``reason_p``, ``task_units`` and ``[reasons]``
    (``ranking.Precedence``: every name a ranked check, every kind one its vocabulary declares)."""
    path, doc = resources.read_recipe("ranking", name_or_path, "ranking")
    unknown = sorted(set(doc) - {"name", "core_p", "reason_p", "task_units", "reasons", "scores"})
    scores = doc.get("scores", {})
    bad = sorted(set(scores) - set(SCORERS)) + sorted(
        f"{n}.{k}" for n, keys in scores.items() for k, v in keys.items()
        if k not in RANKING_KEYS or not isinstance(v, (RANKING_KEYS[k], int) if RANKING_KEYS[k] is float
                                                   else RANKING_KEYS[k]))
    bad += _precedence_errors(doc.get("reasons", {}), scores)
    bad += sorted(f"{n}.tail" for n, keys in scores.items() if keys.get("tail", "exponential") not in TAILS)
    if not isinstance(doc.get("task_units", False), bool):
        bad.append("task_units")
    if unknown or bad or not isinstance(doc.get("core_p"), float) or not isinstance(doc.get("reason_p"), float):
        kinds = "; ".join(f"{check}: {', '.join(v.kinds)}" for check, v in VOCABULARIES.items())
        raise RecipeError(f"{path}: unknown or ill-typed {', '.join(unknown + bad) or 'core_p or reason_p'} (a "
                          f"ranked score takes {', '.join(RANKING_KEYS)}; scores: {', '.join(SCORERS)}; kinds: "
                          f"{kinds})")
    return {**doc, "scores": {n: dict(keys) for n, keys in scores.items()}}


def ranked(available, tasks: np.ndarray, model_free: bool = False, untrusted=()) -> list[str]:
    """The scores the ranking combines, of those ``available`` (names, or columns by name): those of the ranking
    recipe, each followed by its columns on the dataset's other cameras (``findings.camera_column``), less the task
    embedding's on a dataset of one task (``single_task``), less the model's with ``model_free`` and those it did
    not earn (``untrusted``, ``trust.untrusted``), less a column with no score at all (the outcome of a dataset
    whose tasks are all too small to compare): a look that cannot see anything must not cost the others'
    correction."""
    one_task = len(np.unique(tasks)) == 1
    columns = isinstance(available, (dict, pd.DataFrame))

    def scored(n: str) -> bool:
        return not columns or bool(np.isfinite(np.asarray(available[n], np.float64)).any())

    out = []
    for n, keys in ranking_recipe()["scores"].items():
        if n in available and n not in untrusted and (SCORERS[n].model_free or not model_free) \
                and (keys.get("single_task", True) or not one_task):
            out += [c for c in [n, *(c for c in available if c != n and check_of(c) == n)] if scored(c)]
    return out


def ranking_config(names: list[str]) -> ranking.RankingConfig:
    """How the scores ``names`` enter the ranking (``ranking.ScoreSpec`` each) and the reasons' precedence, from
    the ranking recipe; of evidence equally strong, a reason names the recipe's ``order`` first, then the other
    recording faults, the other model-free checks, the model's readings."""
    recipe = ranking_recipe()
    precedence = ranking.Precedence.from_dict(recipe.get("reasons", {}))
    order = precedence.order

    checks = [check_of(n) for n in names]

    def spec(n: str) -> ranking.ScoreSpec:
        check = check_of(n)
        keys = recipe["scores"][check]
        alone = keys.get("alone", False)
        lead = order.index(check) if check in order else len(order) + (0 if alone else 1 if SCORERS[check].model_free
                                                                       else 2)
        # One check on several cameras asks one question of a demo: its columns are one look.
        look = keys.get("look", "") or (check if checks.count(check) > 1 else "")
        return ranking.ScoreSpec(n, log=keys.get("log", False), in_robust_sd=keys.get("in_robust_sd", False),
                                 floor=float(keys.get("floor", 0.0)), tail=keys.get("tail", "exponential"),
                                 alone=alone, beside=keys.get("beside", False), look=look, lead=lead)

    return ranking.RankingConfig(tuple(spec(n) for n in names), core_p=recipe["core_p"],
                                 reason_p=recipe["reason_p"], precedence=precedence,
                                 task_units=recipe.get("task_units", False))


def combination(ev: Evidence, model_free: bool = False) -> ranking.Ranking:
    """The ranking of the scores ``ranked`` picks (``ranking.rank`` under ``ranking_config``): their tail
    probabilities, the robust core they were fitted on (the reference the flags are calibrated on) and the
    suspicion.  Computed once for each set of scores (the ranking and the audit's flags both read it)."""
    names = ranked(ev.scores, ev.tasks, model_free, ev.untrusted)
    key = tuple(names)
    if key not in ev.rankings:
        ev.rankings[key] = ranking.rank(ev.scores, ev.groups, ranking_config(names), broken_rows(ev))
    return ev.rankings[key]


def explanation(ev: Evidence, fpr: float = DEFAULT_FPR, model_free: bool = False) -> reasons.Explained:
    """Each demo's reason (``reasons.explain`` of the ranking and the checks' findings at ``fpr``), once."""
    key = (model_free, fpr)
    if key not in ev.explained:
        copies = None
        if "duplicate" in ev.findings:
            copies = np.array([f.kind == "exact copy" for f in ev.findings["duplicate"]], bool)
        ev.explained[key] = reasons.explain(combination(ev, model_free), ev.findings, fpr,
                                            broken_rows(ev), copies)
    return ev.explained[key]


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
    that the evidence can feed; fills ``ev.scores``, ``ev.findings`` and their words, ``ev.reasons``."""
    def keep(column: str, values: np.ndarray, found: list | None, camera: str = "") -> None:
        ev.scores[column] = values  # as computed: float32 where the network's output is, float64 elsewhere
        if found is not None:
            ev.findings[column] = [f.on_camera(camera) for f in found] if camera else found
            ev.reasons[column] = [f.words for f in ev.findings[column]]

    for s in scorers:
        if not s.can_run(ev):
            continue
        several = s.per_camera and bool(ev.cameras)
        keep(s.name, *s.score(ev), camera=ev.camera if several else "")
        for camera in ev.cameras if s.per_camera else ():
            other = ev.on_camera(camera, s.source)
            if other is not None:
                keep(camera_column(s.name, camera), *s.score(other), camera=camera)
    return ev
