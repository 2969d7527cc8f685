"""Every registered scorer keeps the contract and ranks a planted bad demo of the kind it is meant for first.

The dataset is a slice of the pushing suite (8 tasks x 6 demos, the shipped models' camera and episode length)
with one idle, one random, one occluded and one wrong-object demo planted, and one hidden probe (squares over
most of the view) beside it; each scorer is judged, as bench judges it, on the clean demos plus its kind.
"""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from democheck.audit.run import gather_evidence
from democheck.audit.evidence import NEEDS, Evidence
from democheck.audit.scorers import SCORERS, explanation, ranking_recipe, select
from democheck.data import open_dataset
from democheck.petnet.checkpoint import load_checkpoint
from democheck.sim.suite import generate, load_recipe

PLANTS = {"idle": 1, "random": 1, "occluded": 1, "wrong-object": 1}
# The kind each scorer is for.  ``random`` is the floor, not a detector: CONTROLS holds what it must do instead.
MEANT_FOR = {
    "task_uncertainty": "occluded",  # a cue that cannot show the task
    "task_uncertainty_head": "occluded",
    "novelty": "occluded",  # images unlike the training cues
    "consistency": "wrong-object",  # a cue that clearly shows another task
    "action_error": "random",  # behaviour the controller cannot explain
    "motion": "idle",  # model-free: an arm that never moves
    "idle": "idle",  # model-free: actions that do not change
    "jerk": "random",  # model-free: actions that shake
    "saturation": "random",  # model-free: random torques hit their limits
    "model_free": "idle",
    "view": "hidden",  # model-free: squares over most of the camera's view
    "colours": "hidden",  # model-free: the squares' colours, which no clean demo shows
    "outcome": "wrong-object",  # model-free: the objects end up unlike the task's other demos
    "suspicion": "random",
    "ocsvm_flag": "occluded",
    "tecnet_knn": "occluded",  # a cue far from its task's others in the embedding
    "heuristic": "random",  # what linters see: the motion
}
CONTROLS = {"random"}
# Checked on demos made for them in tests/test_modelfree.py: nothing in the pushing suite freezes its camera,
# copies a demo, records its actions against another demo's state or out of step, drops frames, records NaN,
# freezes a sensor or lets go of the arm half-way (the coupling's kind; of an idle arm it says nothing).
ELSEWHERE = {"frozen_video", "frame_jump", "duplicate", "dynamics", "lag", "timing", "broken", "frozen_state",
             "coupling"}


@pytest.fixture(scope="module")
def evidence(tmp_path_factory) -> Evidence:
    import pandas as pd

    from democheck.sim.probes import make_probes

    root = tmp_path_factory.mktemp("planted") / "push"
    generate(load_recipe("push-mini").with_overrides(tasks=8, demos=6, defects=PLANTS, seed=4), root, workers=1)
    make_probes(root, root.with_name("hidden"), ["hidden"], per_kind=1, seed=4, workers=1)  # a covered camera
    sets = [open_dataset(root), open_dataset(root.with_name("hidden"))]
    episodes = pd.concat([d.episodes.reset_index() for d in sets], ignore_index=True)
    episodes["label"] = episodes["label"].fillna("clean")
    episodes["episode_index"] = np.arange(len(episodes))  # pooled, as bench pools
    return gather_evidence(sets, load_checkpoint(), select(audit=False), "cpu",
                           tecnet=load_checkpoint("tecnet-push-v1"), episodes=episodes)


def test_every_scorer_has_a_planted_kind_or_is_a_control():
    assert set(SCORERS) == set(MEANT_FOR) | CONTROLS | ELSEWHERE


@pytest.mark.parametrize("name", list(SCORERS))
def test_scorer_keeps_the_contract(name, evidence):
    s = SCORERS[name]
    assert s.higher_is_more_suspect and s.description and "\n" not in s.description and s.short
    assert set(s.needs) <= set(NEEDS) and s.family in ("democheck", "baseline")
    assert ("demos" in s.needs) == (s.decode is not None)
    values = evidence.scores[name]
    assert values.shape == (len(evidence.episodes),) and not np.isinf(values).any()
    # Every task here has several demos: a scorer says nothing (NaN) only where it cannot hold -- the coupling of
    # a demo whose actions never change -- and says so.
    silent = ~np.isfinite(values)
    if name == "coupling":
        idle = evidence.episodes["label"].to_numpy() == "idle"
        assert (silent == idle).all() and all("never change" in evidence.reasons[name][i]
                                              for i in np.flatnonzero(silent))
    else:
        assert not silent.any()
    if name in evidence.reasons:
        assert len(evidence.reasons[name]) == len(values)


@pytest.mark.parametrize("name", sorted(MEANT_FOR))
def test_scorer_ranks_its_planted_demo_first(name, evidence):
    labels = evidence.episodes["label"].to_numpy()
    kind = MEANT_FOR[name]
    values = evidence.scores[name]
    planted = values[labels == kind]
    clean = values[labels == "clean"]
    assert len(planted) == 1
    if set(np.unique(values)) <= {0.0, 1.0}:  # a flag: the planted demo is flagged, most clean ones are not
        assert planted[0] == 1 and clean.mean() < 0.1
    else:
        assert planted[0] > clean.max(), (name, kind, planted[0], np.sort(clean)[-3:])


def test_the_random_scorer_is_a_uniform_draw_that_ignores_the_data(evidence):
    values = evidence.scores["random"]
    assert ((0 <= values) & (values < 1)).all()
    # The same draws for any data of the same size, dealt in ranking order.
    order = np.lexsort((evidence.episodes["episode_index"].to_numpy(), -evidence.scores["suspicion"]))
    from democheck.audit.baselines import random_score

    assert np.array_equal(values[order], random_score(len(values), evidence.seed))


def test_suspicion_reason_names_the_score_that_ranks_each_demo(evidence):
    labels = evidence.episodes["label"].to_numpy()
    reasons = np.asarray(evidence.reasons["suspicion"], dtype=object)
    flailing = reasons[labels == "random"][0]
    # What happened, then the driver and how unusual: the flailing behaviour, or the cue it left (an arm flung where
    # no training cue has it, which the task uncertainty's novelty part sees).
    first = flailing.split("; also ")[0]
    assert re.search(r"\((action_error|motion|idle|task_uncertainty), (as unusual as 1 clean demo in|beyond every "
                     r"clean demo)", first), first
    idle = reasons[labels == "idle"][0]
    assert "the arm hardly moves" in idle or "the arm stands still" in idle, idle
    drivers = set(explanation(evidence)[1])
    assert drivers <= set(ranking_recipe()["scores"])
    for r, d in zip(reasons, explanation(evidence)[1]):  # each reason's first clause ends with its driver
        assert not r or f"({d}, " in r.split("; also ")[0] or r.startswith(f"{d}: "), (d, r)


def test_a_reason_leads_with_what_the_demo_did_over_a_reading_of_it():
    """The coupling (a reading of how actions go with the state) beyond every clean demo, and the arm standing still
    clearly unusual: the reason leads with the arm.  A recording fault beyond every clean demo keeps the lead, and
    the reading leads where nothing the demo did is unusual."""
    from democheck.audit.ranking import clauses
    from democheck.audit.scorers import ranking_config

    config = ranking_config(["idle", "frozen_video", "coupling"])
    names = config.names
    row = np.log([0.01, 0.5, 1e-6])  # idle 1 in 100, the coupling far beyond 100 clean demos
    assert names[clauses(config, row, 100)[0]] == "idle"
    assert names[clauses(config, np.log([0.2, 0.5, 1e-6]), 100)[0]] == "coupling"
    assert names[clauses(config, np.log([0.01, 1e-6, 1e-6]), 100)[0]] == "frozen_video"


def test_a_behaviour_barely_named_does_not_lead_one_that_would_flag_the_demo_alone():
    """A covered camera seen weakly (the view as unusual as 1 clean demo in 500) beside the actions 1 in 21: the
    view leads where the reading (the coupling, beyond every clean demo) gives the lead to a behaviour; where both
    would flag the demo alone, the arm leads (the order of equally clear evidence)."""
    from democheck.audit.ranking import clauses
    from democheck.audit.scorers import ranking_config

    config = ranking_config(["jerk", "view", "coupling"])
    names = config.names
    assert names[clauses(config, np.log([0.048, 0.002, 1e-5]), 600)[0]] == "view"
    assert names[clauses(config, np.log([0.008, 0.002, 1e-5]), 600)[0]] == "jerk"
    assert names[clauses(config, np.log([0.048, 0.03, 1e-5]), 600)[0]] == "view"  # neither clear: the rarer


def test_a_reason_leads_with_the_cause_the_other_clauses_follow_from():
    """A frozen state leads over the end state read from it; an arm moving somewhat less than its task's, or
    actions that jump once (demoted), lead only where nothing else is beyond every clean demo."""
    from democheck.audit.ranking import clauses
    from democheck.audit.scorers import ranking_config

    config = ranking_config(["idle", "motion", "jerk", "outcome", "frozen_state", "coupling"])
    names = config.names

    def lead(p, demoted=(), refs=160):
        weak = np.isin(names, list(demoted))
        return names[clauses(config, np.log(p), refs, weak)[0]]

    assert lead([0.75, 1.0, 0.5, 1.4e-7, 1.2e-6, 3.5e-20]) == "frozen_state"
    assert lead([1e-30, 1.0, 0.5, 1e-40, 0.5, 0.5]) == "idle"  # the stillness explains the world left as it was
    # Another task's demo: its arm moves a quarter less, the world ends elsewhere.
    assert lead([1.0, 2e-15, 0.5, 1e-300, 0.5, 2e-110], demoted=["motion"]) == "outcome"
    assert lead([1.0, 2e-15, 0.5, 1e-300, 0.5, 2e-110]) == "motion"
    # An arm stopped at once: one jump of the actions, then it stands still.
    assert lead([6e-4, 0.002, 1e-9, 0.001, 0.5, 0.001], demoted=["jerk"]) == "idle"
    assert lead([0.5, 0.5, 1e-9, 0.5, 0.5, 0.5], demoted=["jerk"]) == "jerk"  # nothing else beyond
    # A frozen state yields to the outcome where the world already differed at the first step (another scene whose
    # parts hold still because the demo never moves them), where both are beyond every clean demo, and only then.
    f, o = names.index("frozen_state"), names.index("outcome")
    p = np.log([0.75, 1.0, 0.5, 1e-46, 1e-17, 0.5])
    assert names[clauses(config, p, 160, None, [(f, o)])[0]] == "outcome"
    assert names[clauses(config, p, 160)[0]] == "frozen_state"
    assert names[clauses(config, np.log([0.75, 1.0, 0.5, 0.02, 1e-17, 0.5]), 160, None, [(f, o)])[0]] \
        == "frozen_state"


def test_a_late_start_or_a_pause_says_how_the_demo_differs_and_a_stop_what_went_wrong():
    """The arm still for the first fifth of a demo (it began late) or for a fifth in the middle (it paused) is
    demoted; still from the middle to the end (it stopped), or throughout, is not."""
    from democheck.audit.modelfree import ActionTraces, paused

    rng = np.random.default_rng(0)
    traces = ActionTraces()
    moving = np.cumsum(rng.normal(0, 1, (100, 4)), 0)
    late, pause, stopped, never = moving.copy(), moving.copy(), moving.copy(), np.zeros((100, 4))
    late[:20] = late[20]
    pause[40:60] = pause[40]
    stopped[50:] = stopped[50]
    for a in (moving, late, pause, stopped, never):
        traces.actions.append(a)
    assert paused(traces).tolist() == [False, True, True, False, False]


def test_a_part_of_the_state_at_rest_for_a_while_is_no_sensor_that_died():
    """One dimension holding still over a stretch and moving again while the others change (an object left alone
    for a time), or two holding together to the end, is at rest; one dimension held to the end (an encoder that
    died), or the whole state held over the stretch (a stream that stalled), is not."""
    from democheck.audit.sensors import StateRepeats, at_rest, frozen_state
    from democheck.data.demo import Demo, no_frames

    rng = np.random.default_rng(0)
    stats = StateRepeats()
    kinds = ["clean"] * 20 + ["rest", "object", "dead", "stall"]
    for kind in kinds:
        state = np.cumsum(rng.normal(0, 1, (100, 3)), 0)
        if kind == "rest":
            state[40:60, 1] = state[40, 1]
        elif kind == "object":  # two dimensions of one object at rest to the end
            state[40:, 1:] = state[40, 1:]
        elif kind == "dead":
            state[40:, 1] = state[40, 1]
        elif kind == "stall":
            state[40:60] = state[40]
        stats.add(Demo(0, "t", no_frames(100), state, rng.normal(0, 1, (100, 2))))
    named = frozen_state(stats, np.zeros(len(kinds), int))[2]
    assert at_rest(stats, named).tolist() == [False] * 20 + [True, True, False, False]


def test_an_arm_that_rests_gives_the_lead_to_a_state_held_for_longer_while_it_moved():
    """A demo that finished and rested for its last tenth, whose one state dimension read its first value all
    along (an encoder that died), names the encoder first; an arm that stopped half-way (its state holds because
    nothing moves it) keeps the lead, and so does a rest longer than the hold."""
    from democheck.audit.evidence import Evidence
    from democheck.audit.modelfree import ActionTraces
    from democheck.audit.scorers import yields
    from democheck.audit.sensors import StateRepeats, frozen_state
    from democheck.data.demo import Demo, no_frames

    rng = np.random.default_rng(0)
    traces, stats = ActionTraces(), StateRepeats()
    kinds = ["clean"] * 20 + ["dead, rests at the end", "stopped", "dead for a while, rests longer"]
    for kind in kinds:
        actions = np.cumsum(rng.normal(0, 1, (100, 2)), 0)
        state = np.cumsum(rng.normal(0, 1, (100, 3)), 0)
        if kind == "dead, rests at the end":
            actions[90:] = actions[90]
            state[:, 1] = state[0, 1]
        elif kind == "stopped":
            actions[50:] = actions[50]
            state[50:] = state[50]
        elif kind == "dead for a while, rests longer":
            actions[60:] = actions[60]
            state[:20, 1] = state[0, 1]
        traces.actions.append(actions)
        stats.add(Demo(0, "t", no_frames(100), state, actions))
    ev = Evidence(episodes=pd.DataFrame({"episode_index": np.arange(len(kinds)), "task": ["t"] * len(kinds)}),
                  behaviour={"actions": traces, "frozen_state": stats})
    ev.scores["frozen_state"], _, ev.named["frozen_state"] = frozen_state(stats, np.zeros(len(kinds), int))
    to_sensor = [mask for name, other, mask in yields(ev) if (name, other) == ("idle", "frozen_state")]
    assert len(to_sensor) == 1 and to_sensor[0][20:].tolist() == [True, False, False]


def test_an_arm_that_moved_with_a_purpose_gives_the_lead_to_the_world_it_left():
    """Another task's demo: its arm moves far more than its task's, smoothly but for one jump, and it left the
    world unlike theirs: the world it left leads.  A flailing arm, whose actions shake, leads with its motion."""
    from democheck.audit.evidence import Evidence
    from democheck.audit.modelfree import ActionTraces
    from democheck.audit.outcome import Differs
    from democheck.audit.ranking import Ranking, explain
    from democheck.audit.scorers import ranking_config, yields

    rng = np.random.default_rng(0)
    traces = ActionTraces()
    smooth = np.column_stack([np.sin(np.linspace(0, 3, 100)), np.cos(np.linspace(0, 3, 100))])
    smooth[50:] += 1.0  # one jump
    traces.actions += [smooth, rng.uniform(-1, 1, (100, 2))]
    config = ranking_config(["motion", "jerk", "outcome", "coupling"])
    log_p = np.log([[1e-9, 1e-29, 1e-35, 1.0],  # another task's job
                    [1e-60, 1e-25, 1e-8, 0.9]])  # flailing
    combined = Ranking(config, log_p, np.ones(2, bool), np.zeros(2))
    ev = Evidence(episodes=pd.DataFrame({"episode_index": [0, 1], "task": ["reach", "reach"]}),
                  behaviour={"actions": traces}, named={"outcome": [Differs("state", [21], False)] * 2})
    words = {name: [f"{name} words"] * 2 for name in config.names}
    _, first = explain(combined, words, yields=yields(ev, combined))
    assert first == ["outcome", "motion"]
    assert explain(combined, words)[1] == ["motion", "motion"]


def test_a_shaking_arm_in_another_picture_gives_the_lead_to_the_world_it_left():
    """Another task's policy chatters where its task's demos glide: its arm moves twice as much as theirs, its
    actions shake, and the camera saw another picture and the world ended elsewhere: the world leads.  An operator
    who shakes at the demo's own task (the picture as its task's) leads with the shaking; a flailing arm with its
    motion."""
    from democheck.audit.evidence import Evidence
    from democheck.audit.ranking import Ranking, explain
    from democheck.audit.scorers import demoted, ranking_config, yields

    n = 40
    level = np.ones(n)
    level[:3] = 2.0, 2.0, 10.0  # another task's policy, a shaking operator, a flailing arm
    ev = Evidence(episodes=pd.DataFrame({"episode_index": np.arange(n), "task": ["press"] * n}),
                  behaviour={"motion": np.column_stack([level, level])})
    config = ranking_config(["motion", "jerk", "view", "outcome"])
    log_p = np.zeros((n, 4))
    log_p[:3] = np.log([[1e-3, 1e-6, 1e-10, 1e-200],
                        [1e-3, 1e-6, 0.3, 1e-9],
                        [1e-40, 1e-20, 1e-10, 1e-30]])
    combined = Ranking(config, log_p, np.ones(n, bool), np.zeros(n))
    words = {name: [f"{name} words"] * n for name in config.names}
    weak = demoted(ev)
    _, first = explain(combined, words, None, weak, yields(ev, combined, weak))
    assert first[:3] == ["outcome", "jerk", "motion"]
    assert explain(combined, words, None, weak)[1][:3] == ["jerk", "jerk", "motion"]


def test_an_arm_moving_somewhat_more_or_less_says_how_it_differs_not_what_went_wrong():
    from democheck.audit.evidence import Evidence
    from democheck.audit.scorers import demoted

    level = np.ones(40)
    level[:4] = 0.5, 3.0, 0.1, 10.0  # a quarter less, three times more, hardly moving, flailing
    ev = Evidence(episodes=pd.DataFrame({"episode_index": np.arange(40), "task": ["push"] * 40}),
                  behaviour={"motion": np.column_stack([level, level])})
    assert demoted(ev)["motion"][:4].tolist() == [True, True, False, False]


def test_a_ranking_recipe_with_an_unknown_score_key_or_tail_is_one_clear_error(tmp_path):
    from democheck.audit.scorers import ranking_recipe
    from democheck.errors import RecipeError

    shipped = (Path(__file__).resolve().parents[1] / "democheck/recipes/ranking/default.toml").read_text()
    for bad, words in (('tail = "normal"', 'tail = "Normal"'), ("[scores.outcome]", "[scores.outcom]"),
                       ("floor = 0.05  # a share", "flor = 0.05  # a share")):
        path = tmp_path / "r.toml"
        path.write_text(shipped.replace(bad, words, 1))
        with pytest.raises(RecipeError, match="unknown or ill-typed"):
            ranking_recipe(str(path))
