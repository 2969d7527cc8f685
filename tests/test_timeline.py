"""The time-aligned checks (``start``, ``end``, ``path``, ``backwards``, ``backwards_state``) and the probes that plant
what they are for.

A task of 30 demos in which the arm carries a bright block from the left of the view to the right: one demo is
the recording played backwards (a reset recorded as a demo), one ends with the block knocked down to the bottom
of the view, one takes a detour with its elbow half-way.  The summaries over time see none of the first: it has
its task's frames and joint values, in the other order.
"""

import numpy as np
import pandas as pd
import pytest

from democheck.audit.evidence import Evidence
from democheck.audit.scorers import compute, select
from democheck.data import open_dataset
from democheck.data.demo import Demo

T, S, N = 80, 4, 30
REVERSED, KNOCKED, DETOUR = 3, 7, 11
NAMES = ["shoulder", "elbow", "wrist", "gripper"]


def _frame(x: int, y: int, noise: np.ndarray | None = None) -> np.ndarray:
    frame = np.full((24, 24, 3), 40, np.uint8) + (0 if noise is None else noise)
    frame[y:y + 5, x:x + 5] = 220
    return frame


def _carry(i: int, rng: np.random.Generator, frames: bool = True) -> Demo:
    xs = np.rint(np.linspace(rng.integers(0, 7), rng.integers(13, 19), T)).astype(int)
    noise = rng.integers(0, 3, (T, 24, 24, 3), dtype=np.uint8)
    pictures = np.stack([_frame(x, 9, noise[t]) for t, x in enumerate(xs)]) if frames else np.zeros((T, 0, 0, 3),
                                                                                                     np.uint8)
    state = np.linspace(0, 1, T)[:, None] * np.array([1.0, -0.5, 0.3, 0.0]) + rng.normal(0, 0.01, (T, S))
    state[:, 0] += rng.normal(0, 0.03)
    actions = np.gradient(state, axis=0) + rng.normal(0, 0.001, (T, S))
    return Demo(episode_index=i, task="carry", frames=pictures, state=state.astype(np.float32),
                actions=actions.astype(np.float32), extra={"state_names": NAMES})


def _carries(frames: bool = True) -> list[Demo]:
    rng = np.random.default_rng(0)
    demos = [_carry(i, rng, frames) for i in range(N)]
    d = demos[REVERSED]
    demos[REVERSED] = Demo(REVERSED, d.task, d.frames[::-1].copy(), d.state[::-1].copy(), -d.actions[::-1].copy(),
                           extra=d.extra)
    if frames:
        demos[KNOCKED].frames[-10:] = _frame(17, 18)
    demos[DETOUR].state[:, 1] += 0.4 * np.exp(-((np.arange(T) - 40) / 8.0) ** 2)
    return demos


def _evidence(demos: list[Demo]) -> Evidence:
    ev = Evidence(episodes=pd.DataFrame({"episode_index": [d.episode_index for d in demos],
                                         "task": [d.task for d in demos]}))
    chosen = select(["start", "end", "path", "backwards", "backwards_state"])
    consumer = chosen[0].decode(ev, slice(0, len(demos)), "cpu")
    for d in demos:
        consumer.add(d)
    ev.behaviour = {"timeline": consumer.finish()}
    return compute(ev, chosen)


@pytest.fixture(scope="module")
def carried() -> Evidence:
    return _evidence(_carries())


def _top(ev: Evidence, check: str) -> int:
    return int(np.argmax(ev.scores[check]))


def test_a_demo_played_backwards_begins_where_they_end_ends_where_they_begin_and_runs_opposite(carried):
    for check in ("start", "end", "path"):
        assert _top(carried, check) == REVERSED, check
    # One block on one background: its colours side by side are the same at both ends, so the ``backwards`` check
    # cannot tell (where the block lies tells, which the start and the end read)
    assert carried.findings["backwards"][REVERSED].kind == "forwards"
    assert carried.findings["start"][REVERSED].kind == "where they end"
    assert carried.findings["end"][REVERSED].kind == "where they begin"
    assert carried.findings["path"][REVERSED].kind == "backwards"
    assert carried.reasons["end"][REVERSED] == ("ends where its task's demos begin: done backwards (a reset "
                                                "recorded as a demo?)")
    # The arm tells: it begins where its task's demos' arms end, and ends where theirs begin
    assert _top(carried, "backwards_state") == REVERSED
    found = carried.findings["backwards_state"][REVERSED]
    assert found.kind == "done backwards" and found.params["began"] > 0.9 and found.params["ended"] < 0.1


def test_a_knocked_over_object_is_an_end_unlike_its_tasks_and_says_where(carried):
    end = carried.scores["end"]
    assert end[KNOCKED] > np.delete(end, [REVERSED, KNOCKED]).max() + 2
    finding = carried.findings["end"][KNOCKED]
    assert finding.kind == "view" and finding.params["place"] == "the bottom right"
    # its start is its task's, and it went forwards
    assert carried.findings["start"][KNOCKED].kind == "like"
    assert carried.findings["backwards"][KNOCKED].kind == "forwards"
    assert carried.findings["backwards_state"][KNOCKED].kind == "forwards"


def test_a_detour_strays_in_the_joint_it_took_half_way(carried):
    path = carried.scores["path"]
    assert path[DETOUR] > np.delete(path, [REVERSED, KNOCKED, DETOUR]).max()
    finding = carried.findings["path"][DETOUR]
    assert finding.kind == "state" and finding.params["dims"].startswith("elbow")
    assert 0.4 <= finding.params["at"] <= 0.6
    assert "elbow" in carried.reasons["path"][DETOUR]


def test_clean_demos_stay_within_a_few_robust_sd():
    ev = _evidence([_carry(i, np.random.default_rng(100 + i)) for i in range(N)])
    for check in ("start", "end", "path", "backwards", "backwards_state"):
        assert np.nanmax(ev.scores[check]) < 5, (check, np.sort(ev.scores[check])[-3:])


def _place(i: int, rng: np.random.Generator) -> Demo:
    """A yellow object carried onto a white plate, both laid out anew in each demo, the arm home at both ends."""
    px, py = rng.integers(2, 22, 2)
    bx, by = rng.integers(2, 26, 2)
    while abs(bx - px) < 10 and abs(by - py) < 10:
        bx, by = rng.integers(2, 26, 2)
    frames = np.full((20, 32, 32, 3), 40, np.uint8) + rng.integers(0, 12, (20, 32, 32, 3), dtype=np.uint8)
    for t, a in enumerate(np.linspace(0, 1, 20)):
        frames[t, py:py + 8, px:px + 8] = 230
        x, y = int(round(bx + a * (px + 2 - bx))), int(round(by + a * (py + 2 - by)))
        frames[t, y:y + 3, x:x + 4] = (230, 200, 30)
    state = np.sin(np.linspace(0, np.pi, 20))[:, None] * rng.uniform(0.5, 1.0, (1, 2))
    return Demo(episode_index=i, task="place", frames=frames, state=state.astype(np.float32),
                actions=np.gradient(state, axis=0).astype(np.float32))


def test_a_reset_is_found_by_what_lies_beside_what_wherever_the_objects_lie():
    """The object and its plate lie anywhere, and the arm begins and ends at home: which colours lie side by side
    (the object on the plate, or on the table) tells a task's starts from its ends wherever they lie, and a
    reset's first picture lies nearer its mates' last ones than their first."""
    from democheck.audit.timeline import _arranged_part

    rng = np.random.default_rng(3)
    demos = [_place(i, rng) for i in range(N)]
    d = demos[REVERSED]
    demos[REVERSED] = Demo(REVERSED, d.task, d.frames[::-1].copy(), d.state[::-1].copy(), -d.actions[::-1].copy())
    ev = _evidence(demos)
    t = ev.behaviour["timeline"]
    own, cross = _arranged_part(t.first_arranged, np.zeros(N, int), t.last_arranged)
    clean = np.delete(np.arange(N), REVERSED)
    assert (own[clean] < cross[clean]).all() and cross[REVERSED] < own[REVERSED]
    for check, kind in (("start", "where they end"), ("end", "where they begin"), ("backwards", "done backwards")):
        assert _top(ev, check) == REVERSED, (check, np.round(ev.scores[check], 1))
        assert ev.findings[check][REVERSED].kind == kind
    # The arm goes out and comes home: its ends do not tell a start from an end, and the state says so
    assert np.isnan(ev.scores["backwards_state"]).all() and {f.kind for f in ev.findings["backwards_state"]} == {
        "no way"}


def test_a_task_whose_way_each_layout_draws_anew_has_no_way_to_run_backwards():
    """The arm pushes toward a goal each demo draws anew: its task's demos share no direction from start to end, so
    no demo's ends are read as crossed over, whichever way it went."""
    rng = np.random.default_rng(5)
    demos = []
    for i in range(N):
        goal = rng.uniform(-1, 1, 2)
        state = np.linspace(0, 1, T)[:, None] * np.r_[goal, 0.0] + rng.normal(0, 0.01, (T, 3))
        demos.append(Demo(i, "push", np.zeros((T, 0, 0, 3), np.uint8), state.astype(np.float32),
                          np.gradient(state, axis=0).astype(np.float32)))
    ev = _evidence(demos)
    assert {f.kind for f in ev.findings["backwards_state"]} == {"no way"}
    assert np.isnan(ev.scores["backwards_state"]).all()


def test_an_object_carried_back_by_an_arm_that_starts_at_home_is_read_from_the_objects_place():
    """A reset an operator records runs forwards: the arm starts at home and goes out as in every demo, and only the
    object goes from where its task's demos leave it to where they find it.  Read in the dimension that ran
    backwards, by name; an arm that swings to the side its task's demos do not (its last value beyond their start)
    came back to no start and went forwards."""
    rng = np.random.default_rng(3)
    names = ["arm.x", "arm.y", "object.y", "arm.side"]
    carried, swung = 4, 9

    def demo(i: int, begin: float, end: float, side: float) -> Demo:
        arm = np.linspace(0, 1, T)[:, None] * np.array([0.2, 0.5]) + rng.normal(0, 0.01, (T, 2))
        obj = np.r_[np.full(T // 2, begin), np.linspace(begin, end, T - T // 2)] + rng.normal(0, 0.005, T)
        state = np.column_stack([arm, obj, np.linspace(0, side, T) + rng.normal(0, 0.01, T)]).astype(np.float32)
        return Demo(i, "place", np.zeros((T, 0, 0, 3), np.uint8), state, np.gradient(state, axis=0),
                    extra={"state_names": names})

    demos = [demo(i, rng.normal(0.6, 0.02), rng.normal(0.85, 0.02), rng.normal(1.0, 0.05)) for i in range(N)]
    demos[carried] = demo(carried, 0.85, 0.6, 1.0)
    demos[swung] = demo(swung, 0.6, 0.85, -1.3)
    ev = _evidence(demos)
    found = ev.findings["backwards_state"]
    assert _top(ev, "backwards_state") == carried
    assert found[carried].kind == "done backwards" and found[carried].params["name"] == "object.y"
    assert found[carried].words.startswith("its object.y begins where its task's demos end and ends where they begin")
    assert found[swung].kind == "forwards"


def test_the_arm_half_way_back_is_partly_backwards_and_a_demo_without_state_says_so():
    """A demo whose arm begins most of its task's way along and ends a little short of that went partly backwards;
    a demo whose state is missing (NaN) has nothing to read, and its task-mates are read as before; a dataset with no
    state (the timeline follows its actions, which may be steps rather than places) is not read at all."""
    demos = _carries()
    d = demos[REVERSED]
    along = np.linspace(0.75, 0.6, T)[:, None] * np.array([1.0, -0.5, 0.3, 0.0])
    demos[REVERSED] = Demo(REVERSED, d.task, d.frames, along.astype(np.float32), d.actions, extra=d.extra)
    demos[KNOCKED] = Demo(KNOCKED, "carry", demos[KNOCKED].frames, np.full((T, S), np.nan, np.float32),
                          demos[KNOCKED].actions, extra=demos[KNOCKED].extra)
    ev = _evidence(demos)
    found = ev.findings["backwards_state"]
    assert found[REVERSED].kind == "toward the other end"
    assert int(np.nanargmax(ev.scores["backwards_state"])) == REVERSED
    assert found[KNOCKED].kind == "no state" and np.isnan(ev.scores["backwards_state"][KNOCKED])
    assert found[DETOUR].kind == "forwards"
    stateless = [Demo(x.episode_index, x.task, x.frames, np.zeros((T, 0), np.float32), x.actions) for x in _carries()]
    ev = _evidence(stateless)
    assert {f.kind for f in ev.findings["backwards_state"]} == {"no state"}


def test_a_dataset_without_a_camera_is_judged_by_its_path_alone():
    ev = _evidence(_carries(frames=False))
    assert _top(ev, "path") == REVERSED and ev.findings["path"][REVERSED].params["part"] == "state"
    assert ev.findings["path"][DETOUR].kind == "state"
    assert np.isnan(ev.scores["end"]).all() and {f.kind for f in ev.findings["end"]} == {"no frames"}
    assert np.isnan(ev.scores["backwards"]).all() and {f.kind for f in ev.findings["backwards"]} == {"no frames"}
    # the arm's ends still tell a reset
    assert _top(ev, "backwards_state") == REVERSED
    assert ev.findings["backwards_state"][REVERSED].kind == "done backwards"


def test_a_group_too_small_to_compare_gives_no_score():
    ev = _evidence(_carries()[:3])
    assert np.isnan(ev.scores["end"]).all() and {f.kind for f in ev.findings["end"]} == {"like"}
    assert np.isnan(ev.scores["backwards"]).all() and {f.kind for f in ev.findings["backwards"]} == {"too few demos"}
    assert np.isnan(ev.scores["backwards_state"]).all()
    assert {f.kind for f in ev.findings["backwards_state"]} == {"too few demos"}


def _resets_in_a_row(count: int, demos: int) -> list[Demo]:
    """``demos`` carries, the first ``count`` of them played backwards: an operator's resets, all alike."""
    rng = np.random.default_rng(5)
    out = [_carry(i, rng) for i in range(demos)]
    for i in range(count):
        d = out[i]
        out[i] = Demo(i, d.task, d.frames[::-1].copy(), d.state[::-1].copy(), -d.actions[::-1].copy(), extra=d.extra)
    return out


def test_a_task_of_sixty_demos_or_fewer_keeps_five_mates_and_the_median_is_numpys():
    from democheck.audit import neighbours

    assert [neighbours.mates(n - 1) for n in (4, 11, 60)] == [1, 5, 5]
    assert [neighbours.mates(n - 1) for n in (61, 93, 110, 1000)] == [7, 9, 11, 99]
    rng = np.random.default_rng(0)
    for k in (1, 4, 5, 11):
        x = rng.normal(size=(3, 7, k)).astype(np.float32)
        assert np.array_equal(neighbours._median_last(x), np.median(x, axis=-1))


def test_resets_a_twentieth_of_a_task_shares_are_not_each_others_reference(monkeypatch):
    """Four resets in 80 demos: against five mates, three of which are resets, a reset's start, end and path look
    like its mates'; against more mates than twice the resets, each is beyond every clean demo."""
    from democheck.audit import neighbours

    demos = _resets_in_a_row(4, 80)
    assert neighbours.mates(79) > 2 * 3
    ev = _evidence(demos)
    for check in ("start", "end", "path"):
        assert ev.scores[check][:4].min() > ev.scores[check][4:].max(), check
    monkeypatch.setattr(neighbours, "SHARED", 0.0)
    hidden = _evidence(demos)
    assert any(hidden.scores[check][:4].min() < hidden.scores[check][4:].max() for check in ("start", "end", "path"))

@pytest.fixture(scope="module")
def time_probes(tiny_dataset, tmp_path_factory):
    from democheck.sim.probes import make_probes

    root, _ = tiny_dataset
    out = tmp_path_factory.mktemp("time-probes") / "p"
    summary = make_probes(root, out, ["reversed", "hesitates"], per_kind=2, seed=3, workers=1)
    return root, out, summary


def _probes_of(time_probes, kind: str):
    """(probe, its source demo) of each probe of ``kind``."""
    root, out, _ = time_probes
    src, probes = open_dataset(root), open_dataset(out)
    for e in probes.episode_indices:
        if probes[e].label == kind:
            yield probes[e], src[probes[e].source_episode]


def test_reversed_probe_is_its_source_played_backwards_with_velocities_negated(time_probes):
    from democheck.data.reorder import velocities

    assert time_probes[2]["kinds"] == {"reversed": 2, "hesitates": 2}
    for d, s in _probes_of(time_probes, "reversed"):
        assert (d.frames == s.frames[::-1]).all()  # lossless video: bit for bit
        vel = velocities(s.extra["state_names"], s.state.shape[1])
        assert vel.any() and not vel.all()
        np.testing.assert_array_equal(d.state[:, ~vel], s.state[::-1][:, ~vel])
        np.testing.assert_array_equal(d.state[:, vel], -s.state[::-1][:, vel])
        # torques: time reversal keeps them, one step on (each step's action is the one that leads to the next)
        np.testing.assert_array_equal(d.actions[:-1], s.actions[::-1][1:])
        np.testing.assert_array_equal(d.actions[-1], d.actions[-2])


def test_velocities_are_told_by_their_names():
    from democheck.data.reorder import velocities

    names = ["shoulder.pos", "joint1.vel", "grip.vx", "block.wz", "dx", "gripper", "speed", "block.x", "delta_yaw"]
    assert velocities(names, len(names)).tolist() == [False, True, True, True, True, False, True, False, True]
    assert not velocities(None, 3).any() and not velocities(["a"], 2).any()


def test_a_pause_is_put_in_on_the_demos_way_not_in_its_rest():
    """A demo that does its task in its first fifth and rests after is paused within that fifth, where a share of
    its motion is done; the pause lasts as long as by its steps; one whose state never moves is paused by its
    steps, and one with no state by its actions' motion (here commanded positions)."""
    from democheck.data.reorder import motion_done, pause, replant

    t = np.arange(100)
    state = np.column_stack([np.minimum(t, 20) / 20.0, np.full(100, 0.3)])
    actions = state + 0.01  # commanded positions, one step ahead of the state
    for seed in range(20):
        at, n = pause(100, seed, motion_done(state))
        assert 5 <= at <= 15 and (at, n)[1] == pause(100, seed)[1]
        planted, where = replant("hesitates", {"state": state, "actions": actions}, {}, seed)
        assert where == {"at": at, "steps": n} and len(planted["state"]) == 100 + n
        assert (planted["state"][at:at + n + 1] == state[at]).all()
        assert replant("hesitates", {"state": None, "actions": actions}, {}, seed)[1]["at"] == at
    assert motion_done(np.ones((100, 2))) is None and pause(100, 0, None) == pause(100, 0)


def test_hesitates_probe_holds_one_frame_and_state_then_goes_on(time_probes):
    from democheck.data.reorder import motion_done, pause

    for d, s in _probes_of(time_probes, "hesitates"):
        at, n = d.sim["probe"]["pause"]["at"], d.sim["probe"]["pause"]["steps"]
        assert (at, n) == pause(len(s), d.sim["probe"]["seed"], motion_done(s.state, s.extra.get("state_names")))
        assert len(d) == len(s) + n
        assert (d.frames[at:at + n + 1] == s.frames[at]).all()
        np.testing.assert_array_equal(d.frames[at + n:], s.frames[at:])
        np.testing.assert_array_equal(d.actions[:at], s.actions[:at])
