"""The parts of benchmarks/foreign's generators that run without LeRobot's environment: the plan of clean and
planted episodes, the occluding card, the options (the simulators and LeRobot's writer run in LeRobot's own
virtual environment, not here)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "foreign"))
import record  # noqa: E402


def test_the_plan_holds_every_task_and_kind_in_a_seeded_order():
    jobs = record.plan(["a", "b", "c"], demos=4, plant=2, seed=3, kinds=record.KINDS)
    assert [j[0] for j in jobs] == list(range(12 + 2 * len(record.KINDS)))
    kinds = [j[2] for j in jobs]
    assert kinds.count("clean") == 12 and all(kinds.count(k) == 2 for k in record.KINDS)
    assert sum(j[1] == "a" and j[2] == "clean" for j in jobs) == 4
    assert all(j[3] != j[1] and j[3] in "abc" for j in jobs)  # the other task (wrong-task) is another task
    assert jobs == record.plan(["a", "b", "c"], 4, 2, 3, record.KINDS)
    assert jobs != record.plan(["a", "b", "c"], 4, 2, 4, record.KINDS)


def test_kinds_on_the_way_are_planted_only_where_the_simulator_can_and_on_the_tasks_they_fit(tmp_path):
    plants = {"failed-place": ("b",), "detour": ("a", "b", "c")}
    jobs = record.plan(["a", "b", "c"], demos=4, plant=5, seed=3, kinds=("idle", "failed-place"), plants=plants)
    assert {j[1] for j in jobs if j[2] == "failed-place"} == {"b"}
    assert sum(j[2] == "failed-place" for j in jobs) == 5 and sum(j[2] == "idle" for j in jobs) == 5
    ap = record.parser("doc", demos=5, size="96")
    with pytest.raises(SystemExit, match="unknown kind drop-regrasp"):
        record.options(ap.parse_args([str(tmp_path / "y"), "--kinds", "detour,drop-regrasp"]), plants)
    assert record.options(ap.parse_args([str(tmp_path / "y"), "--kinds", "detour"]), plants)[0] == ("detour",)


def test_a_plan_of_one_task_plants_there_what_fits_it_and_refuses_what_does_not():
    plants = {"failed-place": ("b",), "reset": ("a", "c")}
    jobs = record.plan(["b"], demos=3, plant=2, seed=1, kinds=("failed-place", "idle"), plants=plants)
    assert {(j[1], j[3]) for j in jobs} == {("b", "b")} and len(jobs) == 7
    with pytest.raises(SystemExit, match="reset: none of the tasks"):
        record.plan(["b"], demos=3, plant=2, seed=1, kinds=("reset",), plants=plants)
    assert record.listed("--tasks", " b, a", ("a", "b", "c")) == ("b", "a")
    with pytest.raises(SystemExit, match="--tasks: unknown d; tasks: a, b, c"):
        record.listed("--tasks", "a,d", ("a", "b", "c"))
    with pytest.raises(SystemExit, match="--tasks: unknown none given"):
        record.listed("--tasks", " , ", ("a", "b", "c"))


def test_a_planted_kind_is_kept_only_where_its_rollout_did_what_it_says():
    """A detour still succeeds, a failed place fails: layouts are drawn until the rollout does so."""
    def rollout(task, scene, kind, rng, layout, stop=None):
        ok = layout % 2 == 0  # every other layout succeeds
        return {"frames": np.zeros((3, 2, 2, 3), np.uint8), "state": np.full((3, 1), layout, np.float64),
                "env_state": np.zeros((3, 1)), "actions": np.zeros((3, 1)), "success": ok,
                "first_success": 1 if ok else None}

    for kind, succeeds in (("detour", True), ("drop-regrasp", True), ("failed-place", False), ("clean", True),
                           ("reset", True)):
        for index in range(6):
            ep = record.episode((index, "a", kind, "b", 9), rollout, {"a": "do a", "b": "do b"})
            assert ep["label"] == kind and (int(ep["state"][0, 0]) % 2 == 0) == succeeds
    # a reset whose object lay where it should go (done at its first step) undoes nothing: drawn again, as a clean
    # demo done before the arm moved is
    for kind in ("reset", "clean"):
        with pytest.raises(RuntimeError, match="no usable rollout"):
            record.episode((0, "a", kind, "b", 9), rollout, {"a": "do a", "b": "do b"}, min_first=2)

    # a rollout that says its kind's deed never came (a carry that ended before the drop) is drawn again
    def undone(task, scene, kind, rng, layout, stop=None):
        return {**rollout(task, scene, kind, rng, layout, stop), "planted": layout % 3 == 0}

    for index in range(6):
        ep = record.episode((index, "a", "drop-regrasp", "b", 9), undone, {"a": "do a", "b": "do b"})
        assert int(ep["state"][0, 0]) % 6 == 0


def test_the_card_covers_35_to_55_percent_of_every_frame_alike():
    frames = np.zeros((5, 48, 64, 3), np.uint8)
    for seed in range(20):
        out = record.cover(frames, np.random.default_rng(seed))
        covered = (out != 0).any(axis=3)
        assert (covered == covered[0]).all() and 0.3 < covered[0].mean() < 0.56
    assert (frames == 0).all()  # the input is left alone


def test_options_refuse_an_existing_folder_and_an_unknown_kind(tmp_path):
    ap = record.parser("doc", demos=5, size="96")
    (tmp_path / "x").mkdir()
    with pytest.raises(SystemExit, match="exists"):
        record.options(ap.parse_args([str(tmp_path / "x")]))
    with pytest.raises(SystemExit, match="unknown kind bored"):
        record.options(ap.parse_args([str(tmp_path / "y"), "--kinds", "idle,bored"]))
    kinds, size = record.options(ap.parse_args([str(tmp_path / "x"), "--force", "--size", "480x640",
                                                "--kinds", "idle,jerky"]))
    assert kinds == ("idle", "jerky") and size == (480, 640) and not (tmp_path / "x").exists()


def test_planted_actions_are_what_each_kind_says():
    rng = np.random.default_rng(0)
    oracle = lambda: np.full(3, 0.9)  # noqa: E731
    assert (record.planted_action("idle", 0, None, rng, 0.0, 3, oracle) == 0).all()
    assert (record.planted_action("gave-up", 5, 5, rng, 0.0, 3, oracle) == 0).all()  # stopped from step 5
    assert (record.planted_action("gave-up", 4, 5, rng, 0.0, 3, oracle) == 0.9).all()
    random = np.stack([record.planted_action("random", t, None, rng, 0.0, 3, oracle) for t in range(200)])
    assert random.min() >= -1 and random.max() <= 1 and random.std() > 0.5
    jerky = np.stack([record.planted_action("jerky", t, None, rng, 0.4, 3, oracle) for t in range(200)])
    assert jerky.max() <= 1 and 0.2 < jerky.std() < 0.5 and (record.planted_action("clean", 0, None, rng, 0.0, 3,
                                                                                      oracle) == 0.9).all()


@pytest.mark.parametrize("name", ["fetch_lerobot", "kitchen_lerobot", "scene_lerobot"])
def test_each_generator_names_every_dimension_it_writes(name):
    """The generators import without their simulators, and name each state, environment-state and action
    dimension of the features they declare (the names are what an audit's reasons quote)."""
    import importlib

    gen = importlib.import_module(name)
    feats = gen.features((64, 64))
    for key in ("observation.state", "observation.environment_state", "action"):
        names = feats[key]["names"]
        assert len(names) == feats[key]["shape"][0] and len(set(names)) == len(names), key
    assert len(gen.TASKS) >= 4 and all(isinstance(words, str) for words, *_ in gen.TASKS.values())


def test_time_kinds_are_written_reordered_and_the_others_as_simulated():
    T = 20
    ep = {"label": "reversed", "frames": np.arange(T)[:, None, None, None] * np.ones((1, 2, 2, 3), np.uint8),
          "state": np.c_[np.arange(T), np.ones(T)].astype(np.float32), "env_state": np.zeros((T, 1), np.float32),
          "actions": np.arange(T, dtype=np.float32)[:, None]}
    names = {"frames": None, "state": ["x", "x.vel"], "env_state": ["z"], "actions": ["dx"]}
    back = record.reordered(ep, names, seed=1)
    assert (back["frames"][:, 0, 0, 0] == np.arange(T)[::-1]).all()
    assert (back["state"][:, 0] == np.arange(T)[::-1]).all() and (back["state"][:, 1] == -1).all()
    # a displacement per step: negated, one step on (the step from t to t + 1 undoes the recording's step before)
    assert (back["actions"][:-1, 0] == -np.arange(T)[::-1][1:]).all() and back["actions"][-1, 0] == 0
    paused = record.reordered({**ep, "label": "hesitates"}, names, seed=1)
    assert len(paused["actions"]) > T and len(paused["frames"]) == len(paused["state"]) == len(paused["actions"])
    clean = {**ep, "label": "clean"}
    assert record.reordered(clean, names, seed=1) is clean
    assert "reversed" in record.TIME_KINDS and "reversed" not in record.KINDS  # asked for, never by default
