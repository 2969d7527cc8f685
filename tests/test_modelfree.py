"""The model-free checks rank the defect each is for first, say where it is, and the combination's flags
keep the false-positive rate they state."""

import re

import numpy as np
import pytest
import pandas as pd
from scipy import stats

from democheck.audit import dynamics, modelfree
from democheck.audit.evidence import Evidence
from democheck.audit.scorers import SCORERS, compute, explanation, select
from democheck.audit.flagging import conformal_p, flags
from democheck.audit.scores import combined_log10, robust_tails, sidak_log10, tail_probabilities
from democheck.data.demo import Demo

T, A, S = 100, 6, 9


def _demo(i: int, rng: np.random.Generator, frames: np.ndarray | None = None) -> Demo:
    """A busy arm: smooth random actions, a state that follows them, a camera that sees it move."""
    phase = rng.uniform(0, 2 * np.pi, A)
    t = np.arange(T)[:, None]
    actions = (np.sin(0.08 * t + phase) + rng.normal(0, 0.02, (T, A))).astype(np.float32)
    state = np.concatenate([np.cumsum(actions, 0) * 0.05, rng.normal(0, 0.01, (T, S - A))], 1).astype(np.float32)
    if frames is None:
        frames = rng.integers(0, 255, (T, 8, 8, 3), dtype=np.uint8)
    return Demo(episode_index=i, task="push", frames=frames, state=state, actions=actions,
                extra={"timestamp": np.arange(T) / 20.0, "fps": 20.0})


def _planted(kind: str, n: int = 30, seed: int = 0) -> tuple[list[Demo], int]:
    rng = np.random.default_rng(seed)
    demos = [_demo(i, rng) for i in range(n)]
    bad = 17
    d = demos[bad]
    if kind == "idle":  # the arm stops at step 40 and never moves again
        d.actions[40:] = d.actions[40]
    elif kind == "pause":  # the arm stops at step 40 for 30 steps, then goes on as before
        d.actions[:] = np.concatenate([d.actions[:40], np.repeat(d.actions[40:41], 30, 0), d.actions[40:70]])
    elif kind == "jerk":
        d.actions += rng.normal(0, 0.5, d.actions.shape).astype(np.float32)
    elif kind == "saturation":  # commands clipped at their limit half the time
        d.actions[::2, 0] = 5.0
    elif kind == "frozen_state":  # the state stream stops updating at frame 30 while the actions go on
        d.state[30:] = d.state[30]
    elif kind == "frozen_video":  # the camera stops delivering at frame 30 while the arm goes on
        d.frames[30:] = d.frames[30]
    elif kind == "dynamics":  # actions recorded against another demo's state
        d.actions[:] = demos[3].actions
    elif kind == "lag":  # actions recorded 10 steps late against the states (the first action held until then)
        d.actions[:] = np.concatenate([np.repeat(d.actions[:1], 10, 0), d.actions[:-10]])
    elif kind == "timing":  # frames 60-69 dropped: the clock jumps from frame 59 to 60
        d.extra["timestamp"][60:] += 0.5
    elif kind == "outcome":  # every demo pushes object a to the goal at (1, 1); the planted one pushes object b there
        for i, demo in enumerate(demos):
            start = rng.uniform(-1, 0, (1, 4))
            end = start.copy()
            end[0, 2 * (i == bad):2 * (i == bad) + 2] = 1.0 + rng.normal(0, 0.02, 2)
            demo.env_state = np.repeat(start, T, 0) + np.linspace(0, 1, T)[:, None] * (end - start)
            demo.extra["env_state_names"] = ["a.x", "a.y", "b.x", "b.y"]
    elif kind == "grasps":  # every demo closes its gripper at step 30; the planted one opens it at 50, closes it at 60
        for demo in demos:
            demo.actions[:, -1] = np.where(np.arange(T) < 30, 1.0, -1.0) + rng.normal(0, 0.05, T)
            demo.extra["action_names"] = [f"joint{k}" for k in range(A - 1)] + ["gripper"]
        d.actions[50:60, -1] = 1.0
    elif kind == "duplicate":  # a bit-exact copy of demo 3
        demos[bad] = Demo(episode_index=bad, task="push", frames=demos[3].frames.copy(),
                          state=demos[3].state.copy(), actions=demos[3].actions.copy())
    return demos, bad


def _evidence(demos: list[Demo], names: list[str]) -> Evidence:
    eps = pd.DataFrame({"episode_index": [d.episode_index for d in demos], "task": [d.task for d in demos]})
    ev = Evidence(episodes=eps)
    chosen = select(names)
    consumers = {}
    for s in chosen:
        if s.decode is not None:
            consumers.setdefault(s.source, s.decode(ev, slice(0, len(demos)), "cpu"))
    for d in demos:
        for c in consumers.values():
            c.add(d)
    ev.behaviour = {k: c.finish() for k, c in consumers.items()}
    return compute(ev, chosen)


def _ranks_first(kind: str) -> Evidence:
    demos, bad = _planted(kind)
    ev = _evidence(demos, [kind])
    values = ev.scores[kind]
    others = np.delete(values, bad)
    assert values[bad] > np.nanmax(others), (kind, values[bad], np.sort(others)[-3:])
    return ev


def test_idle_ranks_first_and_names_the_frames_it_is_still():
    ev = _ranks_first("idle")
    reason = ev.reasons["idle"][17]
    assert "frames 40-99" in reason and "60% of the demo" in reason, reason
    assert ev.scores["idle"][17] > 0.55 and np.median(ev.scores["idle"]) < 0.1


def test_pause_ranks_a_hesitation_first_and_a_still_end_is_none():
    ev = _ranks_first("pause")
    finding = ev.findings["pause"][17]
    assert finding.kind == "paused" and (finding.params["start"], finding.params["stop"]) == (40, 70), finding
    demos, _ = _planted("idle")  # still from step 40 to the end: no pause
    assert _evidence(demos, ["pause"]).findings["pause"][17].kind == "no pause"


def test_grasps_counts_a_grasp_tried_again_and_names_its_frames():
    ev = _ranks_first("grasps")
    found = ev.findings["grasps"]
    assert found[17].kind == "again" and found[17].params["frames"] == [30, 50, 60], found[17]
    assert "3 times (at frames 30, 50 and 60) where its task's demos do so once:" in found[17].words
    assert {f.kind for i, f in enumerate(found) if i != 17} == {"as its task's"}
    # Through the ranking: the one look that sees it is not diluted, and the reason leads with it.
    ev = _evidence(_planted("grasps")[0], ["grasps", "motion", "idle", "jerk", "suspicion"])
    assert np.argmax(ev.scores["suspicion"]) == 17 and explanation(ev).lead[17] == "grasps:again"
    # One change more (let go and never closed again) ends the other way: not called a grasp tried again.
    demos, _ = _planted("grasps")
    demos[17].actions[60:, -1] = 1.0
    assert _evidence(demos, ["grasps"]).findings["grasps"][17].kind == "ends otherwise"


def test_a_gripper_command_that_flickers_is_told_from_a_grasp_tried_again_and_leads_no_reason_of_its_own():
    """The planted demo's gripper command flips between open and closed at every step over frames 30-40 before it
    stays closed: eleven changes, ten of them a step after the last.  No gripper follows that; the words say the command flickers, and
    the kind is demoted, so that the actions' shaking the jerk reads leads its reason."""
    demos, _ = _planted("grasps")
    demos[17].actions[:, -1] = np.where(np.arange(len(demos[17].actions)) < 30, 1.0, -1.0)
    demos[17].actions[30:41:2, -1] = 1.0
    ev = _evidence(demos, ["grasps", "motion", "idle", "jerk", "suspicion"])
    found = ev.findings["grasps"][17]
    assert found.kind == "chatters" and found.params["flickers"] == 10, found
    assert found.words.startswith("the gripper command flickers: opens or closes 11 times")
    assert explanation(ev).lead[17] != "grasps:chatters"


def test_grasps_reads_a_named_gripper_only_and_a_command_that_crosses_its_range():
    from democheck.audit.grasps import changes

    demos, _ = _planted("grasps")
    for d in demos:  # no dimension named for the gripper: the check says nothing
        d.extra["action_names"] = [f"joint{k}" for k in range(A)]
    ev = _evidence(demos, ["grasps"])
    assert np.isnan(ev.scores["grasps"]).all() and ev.findings["grasps"][0].kind == "no gripper"
    # A command changes where it crosses from one third of its range to the other: not where it wavers between.
    assert changes(np.array([0.0, 0.4, 0.6, 0.5, 0.9, 0.6, 0.1]), 0.0, 1.0) == [4, 6]


def test_a_broken_recording_is_repaired_to_be_read_ranks_first_and_is_flagged_whatever_its_scores():
    """NaN states at frames 40-44 of one demo (a sensor that dropped out) and an infinite action in another: the
    reader carries each column's last finite value on, the check names the frames, and the combination puts the
    demos first and flags them although every other score of theirs is ordinary."""
    from democheck.audit.run import score_table
    from democheck.data.demo import repair_non_finite

    demos, _ = _planted("none")
    episode = np.concatenate([np.full(T, d.episode_index) for d in demos])
    state = np.concatenate([d.state for d in demos])
    actions = np.concatenate([d.actions for d in demos])
    clean_state = state.copy()
    state[17 * T + 40:17 * T + 45, 2] = np.nan
    actions[5 * T, 0] = np.inf  # the first frame: nothing before it, the first finite value after it
    state, bad_state = repair_non_finite(state, "observation.state", episode)
    actions, bad_actions = repair_non_finite(actions, "action", episode)
    assert np.isfinite(state).all() and np.isfinite(actions).all() and set(bad_state) == {17} and set(bad_actions) == {5}
    assert (state[17 * T + 40:17 * T + 45, 2] == clean_state[17 * T + 39, 2]).all()
    assert actions[5 * T, 0] == actions[5 * T + 1, 0]
    assert bad_state[17][:2] == (5, "NaN or infinite values in 'observation.state' at 5 of 100 frames, 40-44")
    assert bad_actions[5][:2] == (1, "NaN or infinite values in 'action' at 1 of 100 frames, 0")
    for i, d in enumerate(demos):
        d.state, d.actions = state[i * T:(i + 1) * T], actions[i * T:(i + 1) * T]
        d.damaged = [found[i] for found in (bad_state, bad_actions) if i in found]
    ev = _evidence(demos, ["broken", "motion", "idle", "suspicion"])
    assert ev.scores["broken"][17] == 0.05 and ev.scores["broken"][5] == 0.01
    assert (np.delete(ev.scores["broken"], [5, 17]) == 0).all()
    table = score_table(ev)
    assert set(table["episode_index"][:2]) == {5, 17} and table["is_anomaly"][:2].all()
    assert table["reason"][table["episode_index"] == 17].item() == f"broken: {bad_state[17][1]}"
    assert not table["reference"][:2].any()  # no reference for the others' flags


def test_jerk_and_saturation_rank_first():
    ev = _ranks_first("jerk")
    # In the ranking, the jerk stands beside the recording faults with its own floor, as the frozen state does.
    from democheck.audit.scorers import ranking_config

    specs = {s.name: s for s in ranking_config(["jerk", "frozen_state", "motion"]).specs}
    assert specs["jerk"].alone and specs["frozen_state"].alone and not specs["motion"].alone
    assert specs["jerk"].floor == 0.25 and specs["frozen_state"].floor == 0.05
    ev = _evidence(_planted("jerk")[0], ["jerk", "motion", "idle", "suspicion"])
    told = explanation(ev)
    assert np.argmax(ev.scores["suspicion"]) == 17 and told.lead[17] in ("jerk:shakes", "motion:flails")
    assert "(jerk, beyond every clean demo)" in told.details[17]
    ev = _ranks_first("saturation")
    assert "dimension 0" in ev.reasons["saturation"][17]


def test_dynamics_ranks_actions_recorded_against_another_demos_state_first():
    ev = _ranks_first("dynamics")
    assert "x worse than usual" in ev.reasons["dynamics"][17]
    assert abs(np.median(ev.scores["dynamics"])) < 0.05  # the usual demo is the unit


def test_dynamics_is_the_same_fed_whole_or_in_shards_and_a_short_last_block_is_judged_by_the_one_before(
        monkeypatch):
    """Shards merged in order give every demo the error one consumer fed every demo gives it (shards smaller
    than a block, a block each, several blocks each); a last block too small to fit on its own is scored by
    the fit of the block before, so a bad demo there still stands out."""
    monkeypatch.setattr(dynamics, "DYNAMICS_BLOCK", 8)
    monkeypatch.setattr(dynamics, "DYNAMICS_MIN_BLOCK", 4)
    rng = np.random.default_rng(3)
    demos = [_demo(i, rng) for i in range(26)]  # three blocks of 8, and a last block of 2
    demos[25].actions[:] = demos[3].actions  # recorded against another demo's state
    whole = dynamics.DynamicsFit()
    for d in demos:
        whole.add(d)
    whole = whole.finish()
    for size in (4, 8, 16):
        parts = []
        for s in range(0, len(demos), size):
            part = dynamics.DynamicsFit()
            for d in demos[s:s + size]:
                part.add(d)
            parts.append(part)
        merged = dynamics.DynamicsFit.merged(parts).finish()
        assert np.array_equal(np.asarray(merged.errors), np.asarray(whole.errors)), size
    values, _ = dynamics.dynamics(whole)
    assert values[25] > np.nanmax(values[:25])
    bad = [dynamics.DynamicsFit(), dynamics.DynamicsFit()]  # shards of 12 do not line up with blocks of 8
    for i, d in enumerate(demos[:24]):
        bad[i // 12].add(d)
    import pytest

    with pytest.raises(ValueError, match="line up"):
        dynamics.DynamicsFit.merged(bad)


def test_outcome_ranks_the_other_object_pushed_first_and_names_what_differs():
    ev = _ranks_first("outcome")
    reason = ev.reasons["outcome"][17]
    assert reason.startswith("left the world unlike its task's other demos") and ("a." in reason or "b." in reason)
    assert np.median(ev.scores["outcome"]) < 1.5 < 10 < ev.scores["outcome"][17]


def test_outcome_reads_the_state_without_an_environment_state_and_skips_tasks_too_small_to_compare():
    demos, bad = _planted("outcome")  # the objects' positions recorded as part of the state (as Meta-World does)
    for i, d in enumerate(demos):
        d.state, d.env_state = np.concatenate([d.state, d.env_state], 1).astype(np.float32), None
        d.task = "push" if i < 27 else "rare"
    ev = _evidence(demos, ["outcome"])
    values = ev.scores["outcome"]
    assert values[bad] == np.nanmax(values) and np.isnan(values[27:]).all()
    assert "state[" in ev.reasons["outcome"][bad] and "enough demos" in ev.reasons["outcome"][28]


def test_timing_ranks_the_dropped_frames_first_and_names_the_frame():
    ev = _ranks_first("timing")
    assert "first at frame 60" in ev.reasons["timing"][17], ev.reasons["timing"][17]
    assert np.nanmax(np.delete(ev.scores["timing"], 17)) == 0.0
    # Ten frames dropped read as one step eleven periods long (log 11), not as one step in a hundred.
    np.testing.assert_allclose(ev.scores["timing"][17], np.log(11.0))
    assert "the worst at frame 60: 0.55 s" in ev.reasons["timing"][17], ev.reasons["timing"][17]
    demos, _ = _planted("timing")
    demos[5].extra["timestamp"][[30, 31]] = demos[5].extra["timestamp"][[31, 30]]  # two frames swapped
    ev = _evidence(demos, ["timing"])
    assert "goes back at frame 31" in ev.reasons["timing"][5], ev.reasons["timing"][5]
    demos[7].extra["timestamp"][5] = np.nan  # a null in the column: not "regular"
    ev = _evidence(demos, ["timing"])
    assert np.isnan(ev.scores["timing"][7]) and "missing" in ev.reasons["timing"][7]
    for d in demos:
        d.extra.clear()
    assert np.isnan(_evidence(demos, ["timing"]).scores["timing"]).all()  # a format without timestamps


def test_frozen_video_ranks_first_and_says_where():
    ev = _ranks_first("frozen_video")
    assert "frames 30-99" in ev.reasons["frozen_video"][17], ev.reasons["frozen_video"][17]
    assert (np.delete(ev.scores["frozen_video"], 17) == 0).all()
    # Scattered repeated frames (a codec's) are not a camera that stopped: every third frame repeated scores one
    # step's share, where the stretch from frame 30 on scores 70% of the demo.
    demos, bad = _planted("frozen_video")
    demos[5].frames[1::3] = demos[5].frames[0::3][:len(demos[5].frames[1::3])]
    ev = _evidence(demos, ["frozen_video"])
    assert ev.scores["frozen_video"][5] <= 1.5 / T and ev.scores["frozen_video"][bad] > 0.65


def test_frozen_state_ranks_a_stopped_sensor_first_and_says_where():
    ev = _ranks_first("frozen_state")
    assert "frames 30-99 (70% of the demo)" in ev.reasons["frozen_state"][17], ev.reasons["frozen_state"][17]
    assert (np.delete(ev.scores["frozen_state"], 17) == 0).all()
    # One joint's encoder dead for the whole demo reads as frozen as it gets; a dimension that holds still in
    # most of its task's demos (a goal, an object no demo touches) is not live there and reads nothing.
    demos, _ = _planted("none")
    demos[4].state[:, 1] = demos[4].state[0, 1]
    for d in demos:
        d.state[:, -1] = 0.5
    ev = _evidence(demos, ["frozen_state"])
    assert ev.scores["frozen_state"][4] == 1.0 and "state[1] holds" in ev.reasons["frozen_state"][4]
    assert (np.delete(ev.scores["frozen_state"], 4) == 0).all()
    # Named as the dataset names it, where it does.
    for d in demos:
        d.extra["state_names"] = [f"joint{k}.pos" for k in range(d.state.shape[1])]
    ev = _evidence(demos, ["frozen_state"])
    assert ev.reasons["frozen_state"][4].startswith("joint1.pos holds one value while the arm is driven")


def test_lag_ranks_actions_recorded_late_first_and_says_by_how_much():
    ev = _ranks_first("lag")
    assert "10 steps earlier" in ev.reasons["lag"][17] and "recorded 10 steps late" in ev.reasons["lag"][17], \
        ev.reasons["lag"][17]
    assert np.median(ev.scores["lag"]) < 0.05 and ev.scores["lag"][17] > 1.0  # clean: as recorded is best
    # The shifts are read off one prediction's parts; each is what the dynamics error of the moved actions is.
    demos, bad = _planted("lag")
    states, actions = [d.state for d in demos], [d.actions for d in demos]
    fit = dynamics._dynamics_fit(states, actions)
    errors = {k: dynamics._dynamics_errors([states[bad]], [dynamics._shifted(actions[bad], k)], fit)[0].mean()
              for k in range(-dynamics.LAG_MAX, dynamics.LAG_MAX + 1)}
    read = dynamics._lag(states[bad], actions[bad], fit)
    assert read.best == min(errors, key=errors.get) == 10
    np.testing.assert_allclose(read.gain, np.log(errors[0] / errors[10]), rtol=1e-9)
    shifts = range(-dynamics.LAG_MAX, dynamics.LAG_MAX + 1)
    np.testing.assert_allclose(read.curve, [errors[k] for k in shifts], rtol=1e-9)


def test_a_lag_is_read_against_the_shift_its_tasks_demos_share():
    """A recorder that pairs every action with the state five steps on shifts every demo alike: no demo is late
    against its task, and the words say the task's demos go so.  One demo recorded 10 steps late on top of that
    is read as 10 steps off its task's, ranked first and named."""
    demos, bad = _planted("lag")
    for d in demos:  # every demo: the actions five steps early; the planted one 10 late on top of it
        d.actions[:] = np.concatenate([d.actions[5:], np.repeat(d.actions[-1:], 5, 0)])
    ev = _evidence(demos, ["lag"])
    values = ev.scores["lag"]
    assert values[bad] > np.nanmax(np.delete(values, bad)) and np.median(values) < 0.05
    found = ev.findings["lag"]
    assert found[bad].kind == "delay" and 9 <= found[bad].params["steps"] <= 11, found[bad]
    assert "earlier than its task's demos' do" in found[bad].words and "recorded" in found[bad].words
    usual = [f for i, f in enumerate(found) if i != bad and f.kind == "as recorded"]
    assert len(usual) > len(demos) // 2
    assert usual[0].params["task_shift"] < 0 and usual[0].words.startswith(
        "its actions go with its states as its task's demos' do (best with the actions ")


def _integrating(n: int, seed: int) -> list[Demo]:
    """Arms whose position integrates their commands (smooth ones, with noise), one task: every demo's states follow
    its actions best at one shift, with one factor."""
    rng = np.random.default_rng(seed)
    demos = []
    for i in range(n):
        actions = rng.normal(0, 1, (T, A)) * 0.5 + np.sin(np.arange(T) / 8.0 + rng.uniform(0, 6))[:, None]
        state = np.concatenate([np.cumsum(actions, 0) * 0.05, rng.normal(0, 0.01, (T, S - A))], 1)
        demos.append(Demo(episode_index=i, task="reach", frames=np.zeros((T, 8, 8, 3), np.uint8),
                          state=state.astype(np.float32), actions=actions.astype(np.float32)))
    return demos


def test_a_pairing_one_step_off_is_no_delay():
    """Arms whose position integrates their commands, every demo's states following its actions best at one shift;
    one demo paired a step off (an action sampled just after its state's tick), one four steps off.  A step is the
    pairing's own resolution: no demo reads a delay but the one four steps off."""
    demos = _integrating(30, seed=6)
    one, four = 4, 11
    demos[one].actions[:] = dynamics._shifted(demos[one].actions, -1)
    demos[four].actions[:] = dynamics._shifted(demos[four].actions, -4)
    ev = _evidence(demos, ["lag"])
    found, values = ev.findings["lag"], ev.scores["lag"]
    shifts = [lag.best for i, lag in enumerate(ev.behaviour["dynamics"].lags) if i not in (one, four)]
    assert len(set(shifts)) == 1, shifts  # the clean demos agree: no scatter to read a step against
    assert found[four].kind == "delay" and abs(found[four].params["steps"]) == 4 and values[four] > 0.1, found[four]
    assert [i for i, f in enumerate(found) if f.kind == "delay"] == [four], found
    assert found[one].kind == "as recorded" and values[one] == 0.0, found[one]


def test_an_error_still_falling_past_the_shift_window_is_no_delay_located():
    """Actions recorded further out of step than the check looks (30 steps): the error still falls one step past
    the window's edge, so no delay is located there (shift and gain 0); a delay of the window's own size is."""
    demos, _ = _planted("none")
    states, actions = [d.state for d in demos], [d.actions for d in demos]
    fit = dynamics._dynamics_fit(states, actions)
    read = {k: dynamics._lag(states[3], dynamics._shifted(actions[3], k), fit)
            for k in (0, 5, dynamics.LAG_MAX, 30)}
    # ... nor read against its task's shift
    assert (read[30].gain, read[30].best) == (0.0, 0) and read[30].curve is None, read[30][:2]
    read = {k: r[:2] for k, r in read.items()}
    assert abs(read[5][1]) in (4, 5, 6) and read[5][0] > 0.1, read
    assert abs(read[dynamics.LAG_MAX][1]) >= dynamics.LAG_MAX - 1 and read[dynamics.LAG_MAX][0] > 0.1, read


def _moving_square(t: int, size: int = 24) -> np.ndarray:
    """A camera that sees a bright square move one pixel a step (and back), over a dim textured floor."""
    rng = np.random.default_rng(t % 7)
    frame = np.full((size, size, 3), 40, np.uint8) + rng.integers(0, 3, (size, size, 3), dtype=np.uint8)
    x = t % (2 * (size - 6))
    x = x if x < size - 6 else 2 * (size - 6) - x
    frame[9:15, x:x + 6] = 220
    return frame


def test_frame_jump_ranks_a_dropped_stretch_first_and_says_where():
    """Frames 40-59 dropped from one demo and the steps re-indexed (no timestamp shows it): the camera jumps
    between frames 39 and 40 of what was kept; every other demo's square moves a pixel a step."""
    rng = np.random.default_rng(1)
    demos = []
    for i in range(20):
        start = int(rng.integers(0, 30))
        frames = np.stack([_moving_square(start + t) for t in range(T)])
        demos.append(_demo(i, rng, frames))
    d = demos[17]
    keep = np.r_[0:40, 60:T]
    demos[17] = Demo(episode_index=17, task="push", frames=d.frames[keep], state=d.state[keep], actions=d.actions[keep])
    ev = _evidence(demos, ["frame_jump"])
    values = ev.scores["frame_jump"]
    assert values[17] > np.delete(values, 17).max() + 1.0, (values[17], np.sort(np.delete(values, 17))[-3:])
    assert "between frames 39 and 40" in ev.reasons["frame_jump"][17], ev.reasons["frame_jump"][17]


def test_state_jump_ranks_steps_lost_from_the_recording_first_and_a_commanded_fast_move_is_none():
    """Steps 40-59 lost from one demo's record (state and actions; the steps re-indexed): its state moves at step 39
    as far as over the 20 steps lost while the action there asks for one step's move.  Another demo's arm moves
    four times as fast for three steps because its actions say so: explained, no jump; a third's first states lie
    off its path, as an arm settling after its reset: no jump either."""
    demos, _ = _planted("none")
    demos[5].actions[50:53] *= 4
    for d in demos:  # each step's action moves the arm to the next step's state
        d.state[:, :A] = 0.05 * np.vstack([np.zeros((1, A)), np.cumsum(d.actions, 0)[:-1]])
    demos[9].state[:2, :A] += 0.5  # an arm that settles after its reset: a start's own jolt, no steps lost
    keep = np.r_[0:40, 60:T]
    d = demos[17]
    demos[17] = Demo(episode_index=17, task="push", frames=d.frames[keep], state=d.state[keep], actions=d.actions[keep])
    ev = _evidence(demos, ["state_jump"])
    values = ev.scores["state_jump"]
    others = np.delete(values, 17)
    assert values[17] > others.max() + 1.0, (values[17], np.sort(others)[-3:])
    assert max(values[5], values[9]) < np.quantile(others, 0.9), (values[5], values[9], np.sort(others))
    finding = ev.findings["state_jump"][17]
    assert finding.kind == "jump" and finding.params["frame"] == 39, finding
    assert "between frames 39 and 40" in ev.reasons["state_jump"][17], ev.reasons["state_jump"][17]


def test_the_frame_checks_read_the_same_numbers_at_any_decoded_size():
    """A camera decoded at 128 px reads as the same frames area-shrunk to 64 px (what a model's decoding gives):
    the frame checks shrink every frame to ``FRAME_CHECK_SIZE`` first."""
    import cv2

    from democheck.audit import frames

    rng = np.random.default_rng(4)
    big = np.stack([cv2.resize(_moving_square(t), (128, 128), interpolation=cv2.INTER_NEAREST) for t in range(T)])
    big = np.clip(big.astype(np.int16) + rng.integers(-3, 4, big.shape), 0, 255).astype(np.uint8)  # codec noise
    small = np.stack([cv2.resize(f, (64, 64), interpolation=cv2.INTER_AREA) for f in big])
    demo = _demo(0, rng)
    fed = []
    for video in (big, small):
        fc = frames.FrameChanges()
        fc.add(Demo(episode_index=0, task="push", frames=video, state=demo.state, actions=demo.actions))
        fed.append(fc.deltas[0])
    np.testing.assert_allclose(fed[0], fed[1], atol=0.05)


def test_a_score_beside_the_sum_is_in_it_and_apart_from_it():
    """A column marked ``beside`` counts in Fisher's sum and by its own Sidak minimum too: one extreme probability
    there is not diluted by the ordinary ones, evidence it shares with the others still adds up, and on clean demos
    the share flagged stays within the rate asked for."""
    rng = np.random.default_rng(3)
    n, k = 20000, 8
    log_p = np.log(rng.uniform(size=(n, k)))
    beside = np.zeros(k, bool)
    beside[0] = True
    log_p[0] = np.log(0.5)
    log_p[0, 0] = np.log(1e-5)  # extreme on the marked column alone
    log_p[1] = np.log(0.02)  # a little surprising on every column
    combined, fisher = combined_log10(log_p, beside=beside), combined_log10(log_p)
    assert fisher[0] > np.log10(1e-3) and combined[0] < np.log10(1e-4)
    assert combined[1] < np.log10(1e-4) and combined[1] <= fisher[1] + np.log10(2)  # the sum still counts
    for fpr in (0.01, 0.05):
        assert int((combined[2:] <= np.log10(fpr)).sum()) <= stats.binom.interval(0.999, n - 2, fpr)[1]


def test_a_recording_fault_stands_apart_in_the_combination():
    """The columns marked ``alone`` are combined by their Sidak minimum, and that with the others' Fisher-Brown
    probability by theirs: a demo extreme on one fault alone is not diluted by its ordinary scores (in Fisher's
    sum over eight scores, a tail probability of 1e-5 reads about 1e-2; here at most 4e-5), and on clean demos
    the combination still flags the share asked for."""
    rng = np.random.default_rng(2)
    n, k = 20000, 8
    log_p = np.log(rng.uniform(size=(n, k)))  # clean demos: every tail probability uniform
    alone = np.zeros(k, bool)
    alone[-2:] = True
    log_p[0] = np.log(0.5)
    log_p[0, -1] = np.log(1e-5)
    with_alone, fisher = combined_log10(log_p, alone), combined_log10(log_p)
    assert with_alone[0] < np.log10(5e-5) and fisher[0] > np.log10(1e-3)
    np.testing.assert_allclose(combined_log10(log_p[:, :1], np.ones(1, bool)), log_p[:, 0] / np.log(10))
    # A group that saw nothing in a row is no look there: with no fault scored, the rest's probability as it is.
    no_faults = log_p.copy()
    no_faults[:, alone] = np.nan
    np.testing.assert_allclose(combined_log10(no_faults, alone), combined_log10(log_p[:, ~alone]))
    for fpr in (0.01, 0.05):
        flagged = int((with_alone[1:] <= np.log10(fpr)).sum())
        lo, hi = stats.binom.interval(0.999, n - 1, fpr)
        assert flagged <= hi, (fpr, flagged, hi)
        assert flagged >= 0.8 * lo  # Sidak is conservative only under dependence; these are independent


def test_an_exact_copy_is_named_and_flagged():
    demos, bad = _planted("duplicate")
    ev = _evidence(demos, ["duplicate"])
    assert np.isinf(ev.scores["duplicate"][bad]) and np.isfinite(np.delete(ev.scores["duplicate"], bad)).all()
    assert ev.reasons["duplicate"][bad] == "an exact copy of episode 3 (actions, state and frames)"
    p = np.ones(len(demos))
    assert flags(p, 0.01, np.isinf(ev.scores["duplicate"])).tolist() == [i == bad for i in range(len(demos))]
    # The same actions with other frames (a probe that covers the camera) is near, not a copy.
    demos[bad].frames = demos[bad].frames[::-1].copy()
    ev = _evidence(demos, ["duplicate"])
    assert np.isfinite(ev.scores["duplicate"][bad]) and ev.scores["duplicate"][bad] == ev.scores["duplicate"].max()


def test_model_free_suspicion_without_a_model_ranks_the_still_arm_first():
    demos, bad = _planted("idle")
    ev = _evidence(demos, [n for n, s in SCORERS.items() if s.model_free and s.in_audit])
    assert int(np.argmax(ev.scores["suspicion"])) == bad
    # What happened first, in the check's words; which check and how rare after.
    told = explanation(ev)
    assert told.lead[bad] in ("idle:still", "motion:hardly", "coupling:less"), told.details[bad]
    assert re.search(r"\((idle|motion|coupling), beyond every clean demo\)", told.details[bad])


def test_a_normal_tail_keeps_the_rate_on_normal_scores_and_sees_how_far_out_a_demo_is():
    """A score whose clean spread is normal (a mean over many steps: ``ScoreSpec.tail`` "normal") gets a normal tail
    through the core's median and interquartile range: the flags at a level flag that share of clean demos, and a
    demo six robust SD out is as rare as a normal says, where the exponential through the quartiles calls it one
    clean demo in a few hundred."""
    rng = np.random.default_rng(1)
    n = 20000
    z = rng.normal(0.0, 1.0, (n, 1))
    normal = np.array([True])
    for fpr in (0.01, 0.05):
        flagged = int((np.exp(tail_probabilities(z, normal=normal)[:, 0]) <= fpr).sum())
        lo, hi = stats.binom.interval(0.999, n, fpr)
        assert lo <= flagged <= hi, (fpr, flagged, lo, hi)
    far = np.append(z[:, 0], 6.0)[:, None]
    core = np.append(np.ones(n, bool), False)
    as_normal = tail_probabilities(far, core, normal)[-1, 0]
    assert as_normal == pytest.approx(stats.norm.logsf(6.0), abs=0.5)  # about 1e-9
    assert np.exp(tail_probabilities(far, core)[-1, 0]) > 1e-3  # the exponential: more common than 1 in 1,000
    # The audit's ranking gives the coupling (a mean over a demo's steps) this tail, the other scores theirs.
    tasks = np.repeat(["a", "b"], 200)
    values = {"idle": rng.normal(0.2, 0.05, 400), "motion": rng.normal(0.0, 1.0, 400),
              "coupling": rng.normal(-1.5, 0.1, 400)}
    values["coupling"][7] = -0.9  # six of its SDs less coupled than its task's others
    ev = Evidence(episodes=pd.DataFrame({"episode_index": np.arange(400), "task": tasks}), scores=values)
    from democheck.audit.scorers import combination

    r = combination(ev, model_free=True)
    names, log_p = r.config.names, r.log_p
    assert sorted(names) == ["coupling", "idle", "motion"]
    assert [s.tail for s in r.config.specs] == ["normal" if n == "coupling" else "exponential" for n in names]
    assert log_p[7, names.index("coupling")] < np.log(1e-6)  # the exponential through its quartiles: about 1e-3
    assert np.isnan(tail_probabilities(np.array([[np.nan], [0.0]]), normal=normal)[0, 0])  # no score: none


def test_the_combined_tail_probability_keeps_its_false_alarm_rate():
    """On scores whose tail really is exponential, the flags at a level flag that share of clean demos: within
    the binomial interval for independent scores; for a score looked at twice (a copy) and for scores that move
    together (correlation 0.5) within 1.35x of it -- Brown's correction measures their dependence on the demos
    themselves; its scaled chi-square is a two-moment match, a little light in the far tail -- where Fisher's
    sum alone, which takes them as independent, flags 2.6x and 4.9x the rate asked for at 1%."""
    rng = np.random.default_rng(0)
    n, k = 20000, 4
    z = rng.exponential(1.0, (n, k))  # clean demos' scores in robust SD: an exponential tail
    copied = np.column_stack([z[:, 0], z[:, 0], z[:, 1], z[:, 2]])
    together = -np.log(stats.norm.sf(rng.multivariate_normal(np.zeros(k), 0.5 * np.eye(k) + 0.5, n)))
    for scores_, slack in ((z, 1.0), (copied, 1.35), (together, 1.35)):
        log_p = tail_probabilities(scores_)
        p = 10.0 ** combined_log10(log_p)
        for fpr in (0.01, 0.05):
            flagged = int(flags(p, fpr).sum())
            lo, hi = stats.binom.interval(0.999, n, fpr)
            assert lo <= flagged <= hi * slack, (fpr, flagged, lo, hi)
        if scores_ is not z:
            fisher = stats.chi2.sf(-2 * log_p.sum(1), 2 * k)
            assert (fisher <= 0.01).sum() > 2 * stats.binom.interval(0.999, n, 0.01)[1]
    # Too few demos to measure the dependence on: the Sidak minimum, valid whatever it is.
    few = tail_probabilities(z[:20])
    np.testing.assert_allclose(combined_log10(few), sidak_log10(few))
    # A bad demo far out on one score is far more surprising than any clean one.
    z[0, 2] = 40.0
    p = 10.0 ** combined_log10(tail_probabilities(z))
    assert p[0] < 1e-12 and p[0] == p.min()
    # Beyond what a float holds, the most surprising demos keep their order (no tie at p = 0).
    z[1, 1], z[2, 1] = 4000.0, 2000.0
    log10_p = combined_log10(tail_probabilities(z))
    assert np.isfinite(log10_p[:3]).all() and log10_p[1] < log10_p[2] < -300


def test_a_minority_of_bad_demos_makes_the_tail_probabilities_conservative_and_missing_scores_count_nothing():
    rng = np.random.default_rng(1)
    clean = rng.exponential(1.0, (900, 1))
    with_bad = np.concatenate([clean, np.full((100, 1), 30.0)])
    a = np.exp(tail_probabilities(clean)[:, 0])
    b = np.exp(tail_probabilities(with_bad)[:, 0])
    # 10% bad demos shift the fitted tail outwards: the clean demos' flags grow fewer, never more (the rate a
    # user is told is an upper bound then), and the bad ones stay beyond every clean demo.
    for fpr in (0.01, 0.05):
        assert (b[:900] <= fpr).sum() <= (a <= fpr).sum()
    assert b[900:].max() < 1e-6 < b[:900].min()
    z = np.array([[np.nan], [1.0], [2.0], [np.inf]])
    lp = tail_probabilities(z)[:, 0]
    assert np.isnan(lp[0]) and lp[3] == -np.inf
    # A missing score is left out of the combination with its degrees of freedom: the demo is judged on the scores
    # it has, neither more nor less typical for the one it lacks.
    rng = np.random.default_rng(2)
    z = rng.exponential(1.0, (3000, 4))
    log_p = tail_probabilities(z)
    row = log_p[7].copy()
    without = log_p.copy()
    without[7, 3] = np.nan
    three = combined_log10(np.vstack([log_p[:, :3], row[None, :3]]))[-1]  # the same row with three scores
    assert combined_log10(without)[7] < combined_log10(np.where(np.isnan(without), 0.0, without))[7]
    assert abs(combined_log10(without)[7] - three) < 0.15
    assert combined_log10(np.full((40, 3), np.nan)).tolist() == [0.0] * 40
    assert np.isclose(sidak_log10(np.array([[np.nan, np.log(0.01)]]))[0], -2.0)  # one score seen: its own p


def test_the_robust_core_leaves_the_bad_demos_out_and_the_conformal_flags_keep_their_rate():
    """A fifth of the demos far out on one score of four: fitted on every demo, that score's tail is wider than
    the clean demos' and fewer bad demos are flagged; fitted on the robust core it is the clean demos' own, the core
    holds the clean demos but the few extreme ones, and the conformal flags take no more than the share of clean
    demos asked for (the binomial interval's upper end; fewer where the bad demos left in the core take the top of
    it) and most bad demos -- also where the clean tails are heavier than exponential (log-normal), where the combined
    probability's own level flags several times the rate asked for.  (A quarter or more, all on one score, hides
    itself: the core then keeps them all.)"""
    rng = np.random.default_rng(4)
    n_clean, n_bad, k = 6000, 1500, 4
    for clean in (rng.exponential(1.0, (n_clean, k)), np.exp(rng.normal(0.0, 0.8, (n_clean, k)))):
        bad = clean[:n_bad].copy()
        bad[:, 1] += rng.uniform(10.0, 30.0, n_bad) * clean[:, 1].std()  # unusual on one score, the rest as clean
        z = np.concatenate([clean, bad])
        everything = 10.0 ** combined_log10(tail_probabilities(z))
        log_p, core = robust_tails(z, core_p=1e-4)
        assert core[:n_clean].mean() > 0.99 and core[n_clean:].mean() < 0.25
        p = conformal_p(-combined_log10(log_p), core)
        for fpr in (0.01, 0.05):
            assert (p[:n_clean] <= fpr).sum() <= stats.binom.interval(0.999, n_clean, fpr)[1], fpr
            assert (p[n_clean:] <= fpr).mean() > max(0.85, (everything[n_clean:] <= fpr).mean())
    model = 10.0 ** combined_log10(log_p)  # the log-normal set
    assert (model[:n_clean] <= 0.01).sum() > 2 * stats.binom.interval(0.999, n_clean, 0.01)[1]


def test_the_core_sets_each_tasks_centre_and_unit_and_the_tails_refit_them_each_round():
    from democheck.audit.scores import calibrated

    rng = np.random.default_rng(4)
    tasks = np.repeat(["a", "b"], 30)
    x = np.concatenate([rng.normal(0, 1, 30), rng.normal(5, 1, 30)])
    bad = np.zeros(60, bool)
    bad[[3, 7, 11, 15, 19, 23, 27, 33, 37, 41, 45, 49, 53, 57]] = True  # 7 of each task's 30, far up
    x[bad] += 30
    core = ~bad
    z = calibrated(x, tasks, core=core)
    # Each task's centre is its core demos' median, the unit the core's MAD about those centres.
    centre = np.where(tasks == "a", np.median(x[core & (tasks == "a")]), np.median(x[core & (tasks == "b")]))
    resid = x - centre
    unit = 1.4826 * np.median(np.abs(resid[core] - np.median(resid[core])))
    np.testing.assert_allclose(z, resid / unit)
    # A task's own bad demos no longer shift its centre and widen the unit: they stand further out.
    assert z[bad].min() > calibrated(x, tasks)[bad].max() + 2
    # The tails refit the z at every round: called first with None (every demo), then with the core found.
    seen = []

    def z_of(c):
        seen.append(None if c is None else c.copy())
        return calibrated(x, tasks, core=c)[:, None]

    log_p, found = robust_tails(z_of, core_p=1e-4)
    assert seen[0] is None and len(seen) >= 2 and not found[bad].any() and found[core].mean() > 0.9
    np.testing.assert_array_equal(seen[-1], found)  # the last z were those of the core returned
    assert np.isfinite(log_p).all() and log_p[bad].max() < log_p[found].min()


def test_a_task_whose_clean_demos_surely_spread_more_is_judged_in_its_own_unit():
    from democheck.audit.scores import MAD_RELATIVE_SE, calibrated

    rng = np.random.default_rng(5)
    # Three tasks of 40 demos spread 1, 1 and 3 (a task with contact); a task of 6 demos spread 1.5.
    tasks = np.repeat(["a", "b", "wide", "small"], [40, 40, 40, 6])
    x = np.concatenate([rng.normal(0, 1, 40), rng.normal(4, 1, 40), rng.normal(-3, 3, 40), rng.normal(2, 1.5, 6)])
    pooled = calibrated(x, tasks)
    own = calibrated(x, tasks, task_units=True)
    wide, small = tasks == "wide", tasks == "small"
    # The wide task is measured in (nearly) its own robust SD, so its clean demos stand where a clean demo does.
    resid = x[wide] - np.median(x[wide])
    mad = 1.4826 * np.median(np.abs(resid))
    np.testing.assert_allclose(own[wide], resid / (mad * (1 - 1.96 * MAD_RELATIVE_SE / np.sqrt(40))))
    assert np.abs(own[wide]).max() < np.abs(pooled[wide]).max()
    # Where a task's spread is not surely larger (a narrower task; a task of 6, whose MAD chance moves), the
    # pooled unit stands.
    np.testing.assert_allclose(own[~wide & ~small], pooled[~wide & ~small])
    np.testing.assert_allclose(own[small], pooled[small])
    # The unit is never smaller than the pooled one.
    assert (np.abs(own) <= np.abs(pooled) + 1e-12).all()


def test_conformal_p_counts_the_other_core_demos_and_carries_on_beyond_them():
    s = np.array([0.1, 0.5, 1.0, 2.0, 5.0, 3.0])
    core = np.array([True, True, True, True, False, False])
    p = conformal_p(s, core)
    # A core demo leaves itself out: of the 3 others, 2 are at least as suspect as 0.5 -> (1 + 2) / 4.
    assert np.isclose(p[1], 3 / 4) and np.isclose(p[3], 1 / 4)
    # Beyond the most suspect core demo (2.0): 1 / 5, a tenth of it per unit of suspicion further.
    assert np.isclose(p[5], 0.1 / 5) and np.isclose(p[4], 0.001 / 5)
    assert conformal_p(np.array([np.inf]), np.array([False]))[0] == 0.0
    np.testing.assert_allclose(conformal_p(s, np.zeros(6, bool)), 10.0 ** -s)  # no core: the probability itself


def test_audit_without_a_model_on_data_the_shipped_model_cannot_read(tmp_path):
    """A Meta-World dataset LeRobot's writer made (4-d actions, 39-d state): the audit falls back to the model-free
    checks, says why, and still flags every planted demo (a still, random and stopped arm, a covered camera,
    another task's recording); --no-model does the same on purpose; --drop-list holds what suspects.txt holds."""
    import json
    from pathlib import Path

    from typer.testing import CliRunner

    from democheck.cli import app

    data = Path(__file__).resolve().parents[1] / "tests/data/mw-tiny"
    labels = pd.read_csv(data.with_name("mw-tiny.labels.csv")).set_index("episode_index")["label"]
    runner = CliRunner()
    for extra in ([], ["--no-model"]):
        out = tmp_path / ("auto" if not extra else "none")
        res = runner.invoke(app, ["audit", str(data), "--out", str(out), "--drop-list", str(out) + ".json", *extra])
        assert res.exit_code == 0, res.output
        summary = json.loads((out / "summary.json").read_text())
        assert summary["model"] is None and summary["no_model"]
        assert any("cannot read this data" in w for w in summary["warnings"]) == (not extra)
        table = pd.read_parquet(out / "scores.parquet")
        assert "task_uncertainty" not in table and {"motion", "idle", "duplicate", "suspicion"} <= set(table)
        assert (table["timing"] == 0).all()  # LeRobot's writer's timestamps, read through: every step regular
        assert np.isfinite(table["dynamics"]).all()
        flagged = table.loc[table["is_anomaly"], "episode_index"].tolist()
        assert set(labels[flagged]) - {"clean"} == {"idle", "random", "gave-up", "occluded", "wrong-task"}
        assert (labels[flagged] == "clean").sum() <= 1
        assert json.loads(Path(str(out) + ".json").read_text()) == sorted(flagged)
        assert (out / "report.rrd").stat().st_size > 0
    res = runner.invoke(app, ["audit", str(data), "--out", str(tmp_path / "x"), "--no-model", "--no-actions"])
    assert res.exit_code == 2 and "nothing to score" in res.output


def test_sensor_faults_planted_in_a_dataset_lerobot_wrote_are_found(tmp_path):
    """benchmarks/foreign/plant_faults.py on the Meta-World set LeRobot's writer made: a NaN stretch ranks first
    as a broken recording, a state stream frozen from a step on reads frozen longer than any clean demo, and both
    are flagged (the model-free audit).  The dead encoder lands on a dimension (state[21]) that rests bit for bit in
    its task's clean demos while they are still, so the frozen-state check cannot tell it from a joint the demo did
    not use; but the task's demos move it from 1 to 0.29 and it holds 1: its outcome names it, and it is flagged
    (three of the task's twelve demos end near 1 -- it, an idle and a wrong-task demo --, a fault they share, not
    an outcome of the task)."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from typer.testing import CliRunner

    from democheck.cli import app

    root = Path(__file__).resolve().parents[1]
    data = root / "tests/data/mw-tiny"
    out = tmp_path / "planted"
    subprocess.run([sys.executable, str(root / "benchmarks/foreign/plant_faults.py"), str(data),
                    str(data.with_name("mw-tiny.labels.csv")), str(out), "--seed", "3", "--per-kind", "1",
                    "--kinds", "dead-dim,frozen-state,sensor-nan"], check=True, capture_output=True)
    labels = pd.read_csv(tmp_path / "planted.labels.csv").set_index("episode_index")["label"]
    res = CliRunner().invoke(app, ["audit", str(out), "--out", str(tmp_path / "r"), "--no-model"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet").set_index("episode_index")
    kind = labels[table.index].to_numpy()
    first = table.index[0]
    assert labels[first] == "sensor-nan" and table.loc[first, "reason"].startswith("broken: NaN or infinite values")
    frozen = table.index[kind == "frozen-state"][0]
    assert table.loc[frozen, "frozen_state"] > table["frozen_state"][kind == "clean"].max()
    assert "holds one value while the arm is driven" in table.loc[frozen, "details"]
    assert table["is_anomaly"][np.isin(kind, ["frozen-state", "sensor-nan"])].all()
    dead = table.index[kind == "dead-dim"][0]
    assert table.loc[dead, "is_anomaly"] and table.loc[dead, "frozen_state"] == 0
    assert table.loc[dead, "finding"] == "outcome:held" and "state[21] holds one value" in table.loc[dead, "reason"]
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["flag"]["broken_recordings"] == 1


def test_the_decoding_pass_in_two_worker_processes_gives_the_same_scores(tmp_path, monkeypatch):
    """Shards decoded in spawned workers, merged before the checks finish: every score as in one process."""
    from democheck.audit import shards
    from democheck.audit.run import audit
    from democheck.data import open_dataset
    from democheck.sim.suite import generate
    from tests.conftest import TINY
    from dataclasses import replace

    root = tmp_path / "d"
    generate(replace(TINY, seed=6, demos_per_task=6, steps=16, defects=(("idle", 1),)), root, workers=1)
    ds = open_dataset(root)
    monkeypatch.setattr(shards, "SHARD", 4)  # 24 demos: six shards, three per worker
    monkeypatch.setattr(shards, "PARALLEL_MIN_PIXELS", 0)  # spread however little they decode
    one, _ = audit(ds, None, workers=1)
    two, _ = audit(ds, None, workers=2)
    for col in one.columns:
        assert one[col].equals(two[col]), col


def test_both_passes_in_two_worker_processes_give_the_same_scores_with_a_model(tmp_path, monkeypatch, tiny_model):
    """With a model, the cue pass too runs in the workers (whole batches of cues per shard), and the decoding pass
    in the same workers: every column -- task uncertainty, consistency, action error, mu, sigma -- as in one
    process."""
    from dataclasses import replace

    from democheck.audit import shards
    from democheck.audit.run import audit
    from democheck.data import open_dataset
    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    root = tmp_path / "d"
    generate(replace(TINY, seed=7, demos_per_task=6, steps=12, defects=(("idle", 1),)), root, workers=1)
    ds, ckpt = open_dataset(root), load_checkpoint(tiny_model)
    monkeypatch.setattr(shards, "SHARD", 4)  # 24 demos: six decoding shards
    monkeypatch.setattr(shards, "CUE_SHARD", 8)  # and three cue shards of two batches (the jobs carry the size)
    monkeypatch.setattr(shards, "CUE_BATCH", 4)
    monkeypatch.setattr(shards, "PARALLEL_MIN_PIXELS", 0)
    passes = []
    from democheck import pool

    monkeypatch.setattr(pool.Workers, "run", lambda self, jobs, shard, total, on_progress=None, on_result=None,
                        real=pool.Workers.run: (self.workers > 1 and passes.extend(job[1]["pass"] for job in jobs))
                        or real(self, jobs, shard, total, on_progress, on_result))
    one, _ = audit(ds, ckpt, workers=1)
    assert not passes  # one process: its shards run here, not by workers
    two, _ = audit(ds, ckpt, workers=2)
    assert passes.count("cues") == 3 and passes.count("decode") == 6
    assert {"task_uncertainty", "consistency", "action_error", "mu", "sigma"} <= set(two)
    for col in one.columns:
        assert one[col].equals(two[col]), col


def _scene(rng: np.random.Generator, card: bool = False) -> np.ndarray:
    """A fixed camera on a textured table, an arm (a bright square) sweeping across it, sensor noise; ``card``
    covers the top left 45% of the view with a grey card all episode."""
    h = w = 48
    yy, xx = np.mgrid[:h, :w]
    table = np.stack([80 + 60 * np.sin(xx / 5.0), 90 + 50 * np.cos(yy / 7.0), 70 + 0.8 * xx], -1)
    frames = np.repeat(table[None], T, 0) + rng.normal(0, 3, (T, h, w, 3))
    start = rng.integers(0, w - 8)
    for t in range(T):
        c = int(start + 8 * np.sin(t / 15.0)) % (w - 8)
        frames[t, 20:28, c:c + 8] = 230
    if card:
        frames[:, :32, :32] = 128
    return np.clip(frames, 0, 255).astype(np.uint8)


def test_view_ranks_the_covered_camera_first_and_says_where():
    rng = np.random.default_rng(3)
    demos = [_demo(i, rng, frames=_scene(rng, card=i == 17)) for i in range(30)]
    ev = _evidence(demos, ["view"])
    z = ev.scores["view"]
    assert z[17] > 10 and np.abs(np.delete(z, 17)).max() < 3, np.sort(z)[-3:]
    assert "unlike its task's other demos'" in ev.reasons["view"][17] and "top left" in ev.reasons["view"][17]
    # Tasks are compared with themselves: another task's own scene is not unusual for it.
    for d in demos[:10]:
        d.task = "other"
        d.frames = 255 - d.frames
    ev = _evidence(demos, ["view"])
    assert int(np.argmax(ev.scores["view"])) == 17 and np.abs(np.delete(ev.scores["view"], 17)).max() < 3


def test_colours_rank_the_demo_whose_object_is_missing_first_wherever_the_objects_lie():
    rng = np.random.default_rng(5)
    demos = []
    for i in range(30):
        frames = _scene(rng)
        if i != 17:  # every other demo has a cyan block on the table, somewhere else each time
            r, c = rng.integers(30, 42), rng.integers(0, 42)
            frames[:, r:r + 5, c:c + 5] = (20, 220, 220)
        demos.append(_demo(i, rng, frames=frames))
    ev = _evidence(demos, ["colours", "view"])
    z = ev.scores["colours"]
    assert z[17] > 5 and np.abs(np.delete(z, 17)).max() < 2, np.sort(z)[-3:]
    assert ev.reasons["colours"][17].startswith("the view's colours changed: less cyan (#20e0e0) than its task's other "
                                                "demos: 0% of")
    # The block moves from demo to demo, so where the picture differs says little: view does not see it.
    assert ev.scores["view"][17] < 3


def test_moved_ranks_the_demo_that_moved_the_other_object_first_and_names_its_colour():
    """Every demo's cyan and magenta blocks lie somewhere else; every demo moves the cyan one but episode 17, which
    moves the magenta one.  Where the blocks lie says nothing; which colour changed place does."""
    rng = np.random.default_rng(6)
    demos = []
    for i in range(30):
        frames = _scene(rng)
        blocks = {colour: (rng.integers(30, 42), rng.integers(0, 20)) for colour in ((20, 220, 220), (220, 20, 220))}
        moving = (220, 20, 220) if i == 17 else (20, 220, 220)
        goal = rng.integers(2, 12), rng.integers(26, 42)
        for colour, (r, c) in blocks.items():
            frames[:, r:r + 5, c:c + 5] = colour
            if colour == moving:  # carried to its goal half-way through
                frames[T // 2:, r:r + 5, c:c + 5] = frames[0, 0, 0]
                frames[T // 2:, goal[0]:goal[0] + 5, goal[1]:goal[1] + 5] = colour
        demos.append(_demo(i, rng, frames=frames))
    ev = _evidence(demos, ["moved"])
    z = ev.scores["moved"]
    assert int(np.argmax(z)) == 17 and z[17] > 2 * np.delete(z, 17).max(), np.sort(z)[-3:]
    found = ev.findings["moved"][17]
    assert found.kind == "another object"
    assert "more purple" in found.words and "less cyan" in found.words, found.words
    assert {f.kind for i, f in enumerate(ev.findings["moved"]) if i != 17} <= {"like", "another object", "not moved"}


def test_the_ray_engine_gives_the_local_engines_scores(tmp_path, monkeypatch, tiny_model):
    """``--engine ray`` on a local 2-CPU Ray instance: the same cue and decoding shards run by Ray Data actors,
    every score as the local engine's in one process."""
    import pytest

    pytest.importorskip("ray.data")
    from dataclasses import replace

    from democheck.audit import shards
    from democheck.audit.run import audit
    from democheck.data import open_dataset
    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    root = tmp_path / "d"
    generate(replace(TINY, seed=6, demos_per_task=6, steps=16, defects=(("idle", 1),)), root, workers=1)
    ds, ckpt = open_dataset(root), load_checkpoint(tiny_model)
    monkeypatch.setattr(shards, "SHARD", 8)  # 24 demos: three decoding shards
    monkeypatch.setattr(shards, "CUE_SHARD", 8)  # three cue shards of two whole batches
    monkeypatch.setattr(shards, "CUE_BATCH", 4)
    local, _ = audit(ds, ckpt, workers=1)
    on_ray, _ = audit(ds, ckpt, workers=2, engine="ray")
    assert {"task_uncertainty", "action_error", "idle"} <= set(on_ray)
    for col in local.columns:
        assert local[col].equals(on_ray[col]), col


def test_the_ray_engine_without_ray_says_how_to_get_it(monkeypatch):
    import sys

    import pytest

    from democheck import pool
    from democheck.errors import DemocheckError

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now fails, as where it is not installed
    with pytest.raises(DemocheckError, match=r"pip install 'democheck\[ray\]'"):
        with pool.RayWorkers(2, print, ()):
            pass


def test_on_one_task_task_uncertainty_stays_out_and_the_cue_scores_rank_where_they_earn_it():
    """A dataset of one task: task uncertainty is scored and reported, not ranked -- a clean demo far from its
    neighbours there is mostly one on an unusual layout.  The novelty and the consistency rank on one task as on
    many, where the model reads demos played backwards as unlike them (``trust.untrusted``), and not elsewhere."""
    from democheck.audit.scorers import ranked
    from democheck.audit.trust import untrusted

    available = ["task_uncertainty", "novelty", "consistency", "action_error", "motion", "idle", "view"]
    one_task, two = np.array(["push"] * 9), np.array(["push", "pull"] * 5)
    assert ranked(available, one_task) == available[1:]
    assert ranked(available, two) == available
    real = np.linspace(1.0, 2.0, 20)
    failed = untrusted({}, backwards={"novelty": (1.5 * real, real), "consistency": (3 * real, real)})
    assert set(failed) == {"novelty"}
    assert ranked(available, one_task, untrusted=failed) == ["consistency", "action_error", "motion", "idle", "view"]
    assert ranked(available, two, untrusted=failed) == ["task_uncertainty",
                                                        *ranked(available, one_task, untrusted=failed)]
    rng = np.random.default_rng(2)
    n = 60
    scores = {name: rng.normal(0, 1, n) for name in ("motion", "idle", "view")}
    scores.update(task_uncertainty=rng.exponential(1.0, n), consistency=rng.exponential(1.0, n))
    scores["consistency"][7] = 1e6  # far from its neighbours: where consistency ranks, it leads
    scores["task_uncertainty"][11] = 1e6  # on one task, task uncertainty alone says nothing
    one = Evidence(episodes=pd.DataFrame({"episode_index": range(n), "task": ["push"] * n}), scores=dict(scores))
    values, _ = SCORERS["suspicion"].score(one)
    assert values[7] == values.max() and values[7] > 5 and values[11] < 2
    from democheck.audit.summary import flag_summary

    table = pd.DataFrame({"task": ["push"] * n, "is_anomaly": False, "reference": True, "p_reference": 0.5,
                          "suspicion": values, "driven_by": "", **scores})
    assert flag_summary(table, 0.01)["one_task"].startswith("one task: task uncertainty is reported but not ranked")


def _failing_init() -> None:
    raise RuntimeError("no model here")


def _echo_shard(job: tuple) -> list[dict]:
    return [{"shard": job[0]}]


def test_a_worker_whose_setup_fails_reports_it_instead_of_hanging():
    """A spawned pool restarts a worker whose initializer raises, forever; the setup's error comes back from the
    first shard instead (in one process and in two)."""
    import pytest

    from democheck import pool

    for workers in (1, 2):
        with pytest.raises(RuntimeError, match="no model here"):
            pool.run_shards([(0, None, [0]), (1, None, [1])], _echo_shard, _failing_init, (), workers, 2)
    assert pool.run_shards([(0, None, [0]), (1, None, [1])], _echo_shard, lambda: None, (), 1, 2) == [
        {"shard": 0}, {"shard": 1}]


def test_ksg_mutual_information_matches_the_gaussian_formula():
    """KSG's estimate on samples with a known mutual information: independent (0) and correlated Gaussians
    (-log(1 - rho^2) / 2 per pair), and a copy that never moves counts as no information at all."""
    from democheck.audit.coupling import ksg_mutual_information

    rng = np.random.default_rng(0)
    x = rng.normal(size=(1000, 2))
    assert abs(ksg_mutual_information(x, rng.normal(size=(1000, 3)))) < 0.05
    for rho in (0.6, 0.9):
        y = rho * x + np.sqrt(1 - rho ** 2) * rng.normal(size=x.shape)
        want = -np.log(1 - rho ** 2)  # two independent pairs, each -log(1 - rho^2) / 2
        assert abs(ksg_mutual_information(x, y) - want) < 0.1 * want, (rho, ksg_mutual_information(x, y), want)
    assert np.isnan(ksg_mutual_information(x[:4], x[:4]))
    # A long demo is read at COUPLING_MAX_STEPS evenly spaced steps, its first and last among them.
    from democheck.audit.coupling import COUPLING_MAX_STEPS, CouplingStats

    long = _demo(0, rng)
    long.state, long.actions = np.repeat(long.state, 25, 0), np.repeat(long.actions, 25, 0)
    stats = CouplingStats()
    stats.add(long)
    steps = np.linspace(0, len(long.state) - 1, COUPLING_MAX_STEPS).round().astype(int)
    assert stats.information[0] == ksg_mutual_information(long.state[steps], long.actions[steps])


def test_coupling_ranks_the_arm_let_go_of_first_and_is_one_look_with_the_action_error():
    from democheck.audit.ranking import Ranking
    from democheck.audit.reasons import look_columns
    from democheck.audit.scorers import ranked, ranking_config

    demos, bad = _planted("idle")
    d = demos[bad]
    d.actions[40:] = 0.0  # nobody drives from step 40: zero torque, the arm at rest
    d.state[40:] = d.state[40]
    ev = _evidence(demos, ["coupling"])
    values = ev.scores["coupling"]
    assert values[bad] > np.nanmax(np.delete(values, bad))
    assert "mutual information" in ev.reasons["coupling"][bad]
    # In the ranking with the model's action error or without it, one look with it: the Sidak minimum of the two.
    available = {"motion": values, "idle": values, "coupling": values}
    tasks = np.array(["push"] * len(values))
    names = ranked(available | {"action_error": values}, tasks)
    assert "coupling" in ranked(available, tasks) and {"coupling", "action_error"} <= set(names)
    config = ranking_config(names)
    looks = config.looks()
    assert len(set(looks)) == len(names) - 1 and looks[names.index("coupling")] == looks[names.index("action_error")]
    log_p = np.log(np.array([[0.5, 0.5, 1e-6, 0.5], [0.5, 0.5, 0.5, 0.5]]))  # one row surprising on one of the two
    order = [names.index(n) for n in ("motion", "idle", "action_error", "coupling")]
    log_p = log_p[:, np.argsort(order)]
    from democheck.audit.scores import combined_log10, sidak_log10

    def combine(cfg, lp):
        return -combined_log10(lp, np.array([s.alone for s in cfg.specs]), cfg.looks())

    merged = combine(config, log_p)
    alone = combine(config.without("coupling"), np.delete(log_p, names.index("coupling"), axis=1))
    np.testing.assert_allclose(merged[0], alone[0] - np.log10(2), rtol=1e-3)  # 1 - (1 - p)^2 is about 2p
    # With enough demos for Brown's correction too: the pair is one column, its Sidak minimum, NaN where neither saw.
    log_p = np.log(np.random.default_rng(1).uniform(size=(60, len(names))))
    log_p[3, [names.index("action_error"), names.index("coupling")]] = np.nan
    pair = [names.index("action_error"), names.index("coupling")]
    one = np.where(np.isnan(log_p[:, pair]).all(1), np.nan, sidak_log10(log_p[:, pair]) * np.log(10))
    by_hand = np.column_stack([log_p[:, [j for j in range(len(names)) if j not in pair]], one])
    np.testing.assert_allclose(combine(config, log_p), -combined_log10(by_hand), rtol=1e-9)
    # A reason names the look once, by the score that drove it, at the odds the ranking counted.
    three = ranking_config(["motion", "action_error", "coupling"])
    _, shown = look_columns(Ranking(three, np.log([[0.3, 1e-6, 0.5], [0.3, 0.4, 0.01]]), np.ones(2, bool), np.zeros(2)))
    np.testing.assert_allclose(np.exp(shown[:, 0]), [0.3, 0.3])
    np.testing.assert_allclose(np.exp([shown[0, 1], shown[1, 2]]), [2e-6, 1 - 0.99 ** 2], rtol=1e-5)
    assert np.isnan(shown[0, 2]) and np.isnan(shown[1, 1])


def test_a_tenth_of_a_nat_of_coupling_is_no_evidence_however_alike_the_demos():
    # Smooth scripted demos whose state-action information hardly varies (0.02 nats): one 0.15 nats below the rest
    # stays in the robust core (its floor in the ranking recipe), one that let go (a nat and a half below) is far out.
    from democheck.audit.ranking import rank
    from democheck.audit.scorers import ranking_config

    rng = np.random.default_rng(0)
    values = -3.4 + rng.normal(0, 0.02, 40)
    values[[5, 9]] = -3.4 + 0.15, -3.4 + 1.5  # minus the information: higher is less coupled
    config, tasks = ranking_config(["coupling"]), np.array(["reach"] * 40)
    p = np.exp(rank({"coupling": values}, tasks, config).log_p[:, 0])
    assert p[5] > config.core_p and p[9] < 1e-6
    # Without the floor (a variant of the config, as a sweep makes one) the near-identical demos' spread calls the
    # first one far out.
    assert np.exp(rank({"coupling": values}, tasks, config.with_spec("coupling", floor=0.0)).log_p[5, 0]) < 1e-8


def test_an_arm_every_demo_takes_back_to_one_home_pose_ends_no_demo_far_out():
    """Where each demo ends with the arm back at one home pose, the outcome reads most demos exactly at their task's
    median and a few one float32 step of the recorded pose away (about 5e-6 of a feature's unit): the outcome's
    floor in the ranking recipe keeps those in the robust core, and a demo that ended 5 units off is far out."""
    from democheck.audit.ranking import rank
    from democheck.audit.scorers import ranking_config

    values = np.zeros(80)
    values[10:22] = 5.4e-6
    values[7] = 5.0
    config, tasks = ranking_config(["outcome"]), np.array(["pick"] * 80)
    p = np.exp(rank({"outcome": values}, tasks, config).log_p[:, 0])
    assert (np.delete(p, 7) > 1e-2).all() and p[7] < 1e-6, (np.delete(p, 7).min(), p[7])
    # Without the floor (a variant, as a sweep makes one) the noise's own spread calls some demo far out.
    bare = np.exp(rank({"outcome": values}, tasks, config.with_spec("outcome", floor=0.0)).log_p[:, 0])
    assert np.delete(bare, 7).min() < 1e-4


def test_a_clock_that_drops_a_frame_in_most_demos_makes_two_dropped_no_fault():
    """A recorder that drops a frame in most demos (the worst step two periods long) and two or three in a few: its
    timing's floor in the ranking recipe, the half period at which the check calls a step irregular, keeps those in
    the robust core; a recording that stopped for two seconds is far out.  The floor is the check's own tolerance."""
    from democheck.audit.modelfree import TIMING_TOLERANCE
    from democheck.audit.ranking import rank
    from democheck.audit.scorers import ranking_config

    rng = np.random.default_rng(1)
    values = np.log1p(1.0 + rng.normal(0, 0.02, 60))  # a frame dropped: the worst step two periods long
    values[:8] = 0.0  # no frame dropped
    values[[20, 21, 22]] = np.log1p([2.0, 2.5, 3.0])  # two, two and a half, three
    values[40] = np.log1p(20.0)  # the recording stopped for 2 s at 10 fps
    config, tasks = ranking_config(["timing"]), np.array(["pick"] * 60)
    assert config.specs[0].floor == pytest.approx(np.log1p(TIMING_TOLERANCE), abs=1e-3)
    p = np.exp(rank({"timing": values}, tasks, config).log_p[:, 0])
    assert (p[[20, 21, 22]] > 1e-3).all() and p[40] < 1e-4, p[[20, 21, 22, 40]]
    # With the floor of a clock that never slips (a variant, as a sweep makes one) the pile's own jitter calls
    # two dropped frames far out.
    assert np.exp(rank({"timing": values}, tasks, config.with_spec("timing", floor=0.02)).log_p[20, 0]) < 1e-6


def test_outcome_compares_an_end_with_the_demos_that_started_on_its_side():
    # A push that stops 9 mm short of its goal's line on the side it came from: 10 demos start above the line,
    # 3 below.  Those 3 end below it -- as they should -- and a demo that started below but ended above is the
    # one that differs.  Two demos of another scene, whose target sits 20 cm off from the first step and never
    # moves, are no side of their own: each is far from its task's.
    from democheck.audit import outcome

    rng = np.random.default_rng(0)
    stats = outcome.OutcomeStats()
    # The push runs along x; y starts 1-3 cm off the goal's line, so that 18 mm across it is far past the task's
    # own spread and its job on y (outcome.TASK_FLOOR of how far its demos move y).
    starts = np.r_[rng.uniform(0.012, 0.03, 10), rng.uniform(-0.03, -0.012, 4)]
    starts = np.r_[starts, np.full(12, -0.02), 0.2, 0.2]  # a second task: every demo starts below the line
    for i, y0 in enumerate(starts):
        y1 = (0.009 if y0 > 0 else -0.009) + rng.normal(0, 2e-4)
        if i == 13:
            y1 = 0.009  # started below, ended above: pushed past
        if i >= len(starts) - 2:
            y1 = y0  # another scene: the target is elsewhere and stays there
        stats.ends.append(np.array([[0.5, y0], [0.7 + rng.normal(0, 1e-3), y1]]))
        stats.moves.append(np.array([[0.2, abs(y1 - y0)], [0.002, abs(y1 - y0) / 100]]))  # range, jitter
        stats.sources.append("environment state")
        stats.names.append(["target.x", "target.y"])
    tasks = np.r_[np.zeros(14, int), np.ones(14, int)]
    by_side, found = outcome.outcome(stats, tasks)
    assert by_side[10:13].max() < 3 < 5 < by_side[13] and by_side[:13].max() < by_side[13]
    assert found[13].kind == "another job" and (found[13].params["name"], found[13].params["part"]) == \
        ("target.y", "at the end")
    assert by_side[14:26].max() < 3 < 5 < by_side[26:].min()


def _camera_less_copies(data, tmp_path):
    """The Meta-World set LeRobot's writer made, as a state-only LeRobot dataset (its video feature and files
    removed), as a robomimic low-dimensional file (robot0_eef_pos, robot0_gripper_qpos and the objects under
    obs/object, no images; each demo naming its task) and as a robomimic raw file (no obs group: its ``states``)."""
    import json
    import shutil

    import h5py

    lerobot = tmp_path / "no-camera"
    shutil.copytree(data, lerobot, ignore=shutil.ignore_patterns("videos"))
    info = json.loads((lerobot / "meta/info.json").read_text())
    info["features"] = {k: f for k, f in info["features"].items() if f["dtype"] not in ("video", "image")}
    (lerobot / "meta/info.json").write_text(json.dumps(info))
    frame = pd.read_parquet(data / "data/chunk-000/file-000.parquet")
    tasks = pd.read_parquet(data / "meta/tasks.parquet")
    names = dict(zip(tasks["task_index"], tasks.index))
    low, raw = tmp_path / "low_dim.hdf5", tmp_path / "demo.hdf5"
    for path in (low, raw):
        with h5py.File(path, "w") as f:
            for e, rows in frame.groupby("episode_index"):
                g = f.create_group(f"data/demo_{e}")
                g.attrs["task"] = names[int(rows["task_index"].iloc[0])]
                g.create_dataset("actions", data=np.stack(rows["action"].to_numpy()))
                state = np.stack(rows["observation.state"].to_numpy())
                if path == raw:
                    g.create_dataset("states", data=state)
                    continue
                g.create_dataset("obs/robot0_eef_pos", data=state[:, :3])
                g.create_dataset("obs/robot0_gripper_qpos", data=state[:, 3:4])
                g.create_dataset("obs/object", data=state[:, 4:])
    return lerobot, low, raw


def test_a_dataset_without_a_camera_is_audited_on_its_states_and_actions(tmp_path):
    """A dataset that records no camera -- a state-only LeRobot dataset, robomimic's low-dimensional and raw
    files -- is audited with the model-free checks of its states and actions (automatically, saying why): every
    planted demo the frames are not needed for (a still, random and stopped arm, another task's recording) is
    flagged, the checks of the frames are left out, and what needs frames (the model, training, probes) refuses
    in one line."""
    import json
    from pathlib import Path

    from typer.testing import CliRunner

    from democheck.cli import app
    from democheck.data import open_dataset

    data = Path(__file__).resolve().parents[1] / "tests/data/mw-tiny"
    labels = pd.read_csv(data.with_name("mw-tiny.labels.csv")).set_index("episode_index")["label"]
    runner = CliRunner()
    for source in _camera_less_copies(data, tmp_path):
        ds = open_dataset(source)
        assert ds.camera is None and not ds.has_camera and ds[3].frames.shape == (len(ds[3]), 0, 0, 3)
        out = tmp_path / f"audit-{source.name}"
        res = runner.invoke(app, ["audit", str(source), "--out", str(out)])
        assert res.exit_code == 0, res.output
        summary = json.loads((out / "summary.json").read_text())
        assert summary["model"] is None and "records no camera" in summary["warnings"][0]
        table = pd.read_parquet(out / "scores.parquet")
        assert not {"view", "colours", "frozen_video", "frame_jump"} & set(table)
        assert {"motion", "idle", "outcome", "lag", "coupling"} <= set(table)
        flagged = table.loc[table["is_anomaly"], "episode_index"].tolist()
        assert set(labels[flagged]) - {"clean"} == {"idle", "random", "gave-up", "wrong-task"}, source
        assert (labels[flagged] == "clean").sum() <= 1
        assert (out / "report.rrd").stat().st_size > 0
        if source.is_dir():  # democheck clean writes it without the flagged demos, still without a camera
            res = runner.invoke(app, ["clean", str(source), "--report", str(out), "--out", str(tmp_path / "clean")])
            assert res.exit_code == 0, res.output
            kept = open_dataset(tmp_path / "clean")
            assert len(kept) == len(ds) - len(flagged) and not kept.has_camera
        shipped = Path(__file__).resolve().parents[1] / "models/petnet-push-v1"
        for command in (["audit", str(source), "--out", str(tmp_path / "m"), "--model", str(shipped)],
                        ["train", str(source), "--out", str(tmp_path / "t")],
                        ["probe", str(source), "--out", str(tmp_path / "p")]):
            res = runner.invoke(app, command)
            assert res.exit_code != 0 and "records no camera" in res.output, (command, res.output)


def test_a_dataset_whose_every_demo_names_its_own_task_is_compared_as_one(tmp_path):
    """Free-text instructions, one per episode: every task holds one demo.  Within-task medians would leave every
    demo at 0 (before: every kind ranked at 0.50); compared with all the demos instead, the still, random and
    stopped arms and the covered camera rank above every clean demo, and the summary says how they were judged."""
    import json
    import shutil
    from pathlib import Path

    from typer.testing import CliRunner

    from democheck.cli import app

    data = Path(__file__).resolve().parents[1] / "tests/data/mw-tiny"
    labels = pd.read_csv(data.with_name("mw-tiny.labels.csv")).set_index("episode_index")["label"]
    copy = tmp_path / "one-task-each"
    shutil.copytree(data, copy)
    table = copy / "meta/episodes/chunk-000/file-000.parquet"
    episodes = pd.read_parquet(table)
    episodes["tasks"] = [np.array([f"{t[0]}, take {e}"], dtype=object)
                         for e, t in zip(episodes["episode_index"], episodes["tasks"])]
    episodes.to_parquet(table, index=False)
    res = CliRunner().invoke(app, ["audit", str(copy), "--out", str(tmp_path / "r"), "--no-model"])
    assert res.exit_code == 0, res.output
    scores = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    kinds = scores["episode_index"].map(labels).fillna("clean").to_numpy()
    top = set(kinds[:4])
    assert top == {"idle", "random", "gave-up", "occluded"}, kinds[:6]
    warning = json.loads((tmp_path / "r" / "summary.json").read_text())["warnings"][0]
    assert warning.startswith("21 of 21 tasks have fewer than 5 demos") and "as if the dataset were one task" in warning
    assert "wrong task cannot be told apart" in warning


def test_coupling_says_nothing_of_actions_that_never_change_and_never_prints_a_negative_information():
    from democheck.audit import coupling

    demos, bad = _planted("idle")
    demos[bad].actions[:] = demos[bad].actions[0]  # an arm never driven: the same command throughout
    ev = _evidence(demos, ["coupling"])
    assert np.isnan(ev.scores["coupling"][bad]) and "actions that never change" in ev.reasons["coupling"][bad]
    assert np.isfinite(np.delete(ev.scores["coupling"], bad)).all()
    assert coupling._nats(-0.33, 1.234) == "about 0 nats (its task's median 1.2 nats)"
    # Both about 0: the estimates the check compared, not "about 0" twice.
    assert coupling._nats(-0.72, -0.04) == "about 0 nats, as its task's median, but the estimate 0.68 nats lower"
    assert coupling._nats(1.891, 1.912) == "1.89 nats (its task's median 1.91 nats)"


def test_a_motion_dimension_one_task_uses_weighs_as_much_as_the_others():
    """A gripper one task closes and the other never touches: each action dimension is measured in units of its
    typical motion over the demos, so a demo of the first task that leaves its gripper alone moves about a quarter
    less than its task's demos, not hundreds of times less."""
    from types import SimpleNamespace

    rng = np.random.default_rng(0)
    stats_, tasks = modelfree.MotionStats(), []
    for i in range(30):
        grip = 1.0 if i < 10 and i != 3 else 0.0  # task 0 closes the gripper; its demo 3 does not
        a = np.column_stack([rng.uniform(0.4, 0.6, (50, 3)), np.full(50, grip)])
        stats_.add(SimpleNamespace(actions=a, task="closes" if i < 10 else "opens"))
        tasks.append(0 if i < 10 else 1)
    ratio = np.array([f.params["ratio"] for f in modelfree.motion(stats_.finish(), np.array(tasks))[1]])
    assert 0.5 < ratio[3] < 0.9, ratio[3]
    assert np.all(np.abs(np.delete(ratio, 3) - 1) < 0.15)


def test_numbers_compared_in_a_reason_never_read_the_same():
    from democheck.audit.colours import colour_name
    from democheck.audit.words import pair

    assert pair(0.9999998, 0.99999994) == ("0.9999998", "0.9999999")
    assert pair(1.891, 1.912) == ("1.89", "1.91")
    assert pair(0.25, 0.5) == ("0.25", "0.5")
    assert pair(2.0, 2.0) == ("2", "2")
    assert pair(-1.0, 7.42e-17) == ("-1", "0") and pair(3e-9, 1e-9) == ("3e-09", "1e-09")  # noise beside, reads 0
    assert colour_name(0) == "black (#202020)" and colour_name(21).startswith("grey")


def test_actions_recorded_at_another_scale_are_named_a_scale_not_a_delay():
    """Arms that reach (commands large at first, then small) and whose position integrates them; one demo's actions
    recorded x3 (another unit or gain), one recorded 10 steps late.  Moved later the x3 actions fit better (where
    they are smaller), but one factor, far off the other demos', fits better still: its reason names the scale
    and no delay.  The late demo keeps its delay."""
    rng = np.random.default_rng(3)
    demos = []
    for i in range(40):
        drift = np.cumsum(rng.normal(0, 0.05, (T, A)), 0)
        actions = rng.normal(0, 1, A) * np.exp(-np.arange(T) / 20.0)[:, None] + drift
        state = np.concatenate([np.cumsum(actions, 0) * 0.05, rng.normal(0, 0.01, (T, S - A))], 1)
        demos.append(Demo(episode_index=i, task="reach", frames=np.zeros((T, 8, 8, 3), np.uint8),
                          state=state.astype(np.float32), actions=actions.astype(np.float32)))
    demos[3].actions[:] *= 3.0
    demos[17].actions[:] = np.concatenate([np.repeat(demos[17].actions[:1], 10, 0), demos[17].actions[:-10]])
    ev = _evidence(demos, ["lag"])
    scaled, late = ev.findings["lag"][3], ev.findings["lag"][17]
    assert scaled.kind == "scale" and scaled.params["size"] > 2, scaled
    assert late.kind == "delay" and 9 <= late.params["steps"] <= 11 and late.params["named"], late


def test_an_arm_held_against_something_is_no_scale():
    """Arms whose position integrates their commands; one arm held still from a third of its demo on while its
    commands go on (a button pressed, a table met), and one demo's actions recorded x3.  Over the whole demo one
    factor of about a third explains the held arm best, but a unit or a gain holds throughout the recording: the
    held arm's first third follows its actions as its task's do, so it reads no scale; the x3 demo does."""
    demos = _integrating(40, seed=5)
    rng = np.random.default_rng(5)
    held = T // 3
    demos[7].state[held:, :A] = demos[7].state[held, :A] + rng.normal(0, 1e-3, (T - held, A))
    demos[21].actions[:] *= 3.0
    ev = _evidence(demos, ["lag"])
    whole = ev.behaviour["dynamics"].lags[7]
    assert whole.factor < np.median([lag.factor for lag in ev.behaviour["dynamics"].lags]) / dynamics.SCALE_NAMED
    assert ev.findings["lag"][7].kind != "scale" and ev.scores["lag"][7] < 0.1, ev.findings["lag"][7]
    assert ev.findings["lag"][21].kind == "scale" and ev.findings["lag"][21].params["size"] > 2, ev.findings["lag"][21]


def test_a_camera_that_stopped_delivers_frames_like_its_tasks_and_a_card_does_not():
    """Three pictures that stay the same while the arm moves: one camera stopped at frame 40, one still scene whose
    moving square a grey card covers all along, one whose card was put down at frame 33.  The frames each delivered (but for the repeats) are like the
    task's at the same steps for the stopped camera, and unlike them for the card; so the view gives the stopped
    camera's reason to the frozen picture and keeps the covered one's."""
    from democheck.audit import frames, view
    from democheck.audit.ranking import Ranking
    from democheck.audit.reasons import explain
    from democheck.audit.scorers import ranking_config

    rng = np.random.default_rng(2)
    demos = [_demo(i, rng, np.stack([_moving_square(int(rng.integers(0, 30)) + t) for t in range(T)]))
             for i in range(20)]
    demos[5].frames[40:] = demos[5].frames[40]
    demos[9].frames[:] = demos[9].frames[0]  # a still scene but for the arm, which moves under the card
    demos[9].frames[:, 6:18] = 128
    demos[13].frames[33:, 6:18] = 128  # a card put down at frame 33, after which the scene stands still
    demos[13].frames[34:] = demos[13].frames[33]
    ev = _evidence(demos, ["frozen_video", "view"])
    assert min(ev.scores["frozen_video"][[5, 9, 13]]) > 0.5
    z = frames.delivered_unlike(ev.behaviour["frozen_video"], ev.groups)
    assert z[5] < view.VIEW_K < min(z[9], z[13]), z[[5, 9, 13]]
    kinds = [f.kind for f in ev.findings["frozen_video"]]
    assert (kinds[5], kinds[9], kinds[13]) == ("stopped camera", "still picture", "still picture")
    config = ranking_config(["frozen_video", "view"])
    log_p = np.zeros((20, 2))
    log_p[[5, 9]] = np.log([1e-20, 1e-3])  # both beyond every clean demo
    core = np.ones(20, bool)
    core[[5, 9]] = False
    told = explain(Ranking(config, log_p, core, np.zeros(20)), ev.findings, 0.01)
    assert (told.driven_by[5], told.driven_by[9]) == ("frozen_video", "view")
