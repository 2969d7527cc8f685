"""The model-free audit holds its false-flag rate on clean data of any shape: randomly generated clean datasets
whose world record holds a quaternion (its sign flipping between demos), a wrapped angle near +-pi, a switch that
ends on or off, a drawer that ends open or closed, a fixed part constant to float noise, a dimension that is
always zero, a slide that most demos push against its stop and the rest leave short of it at any point, and
episodes whose length varies by task and by demo."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from democheck.audit.run import score_table
from democheck.audit.evidence import Evidence
from democheck.audit.scorers import SCORERS, compute, select
from democheck.data.demo import Demo, no_frames

NAMES = ["cube.x", "cube.y", "lid.qw", "lid.qx", "lid.qy", "lid.qz", "knob.angle", "switch", "drawer", "fixture.z",
         "spare", "slide"]


def _smooth(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    t = np.arange(n)[:, None]
    return np.sin(2 * np.pi * t / n * rng.uniform(0.5, 2, d) + rng.uniform(0, 2 * np.pi, d)) \
        + rng.normal(0, 0.05, (n, d))


def clean_dataset(seed: int, tasks: int = 4, demos: int = 50) -> list[Demo]:
    rng = np.random.default_rng(seed)
    out = []
    for t in range(tasks):
        goal = rng.uniform(-0.3, 0.3, 2)
        p_switch, p_open = rng.uniform(0.3, 0.7, 2)
        p_stop = rng.uniform(0.5, 0.7)
        length = int(rng.integers(30, 90))
        for _ in range(demos):
            n = length + int(rng.integers(-5, 6))
            s = np.linspace(0, 1, n)[:, None]
            ease = s * s * (3 - 2 * s)
            actions = _smooth(rng, n, 4).astype(np.float32)
            state = np.concatenate([np.cumsum(actions, 0) * 0.05, _smooth(rng, n, 2) * 0.1], 1)
            start = rng.uniform(-0.3, 0.3, 2)
            cube = start + ease * (goal + rng.normal(0, 0.005, 2) - start)
            yaw = rng.uniform(-np.pi, np.pi) + ease[:, 0] * rng.normal(0, 0.2)
            lid = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], 1) * rng.choice([-1, 1])
            knob = np.angle(np.exp(1j * (np.pi + rng.normal(0, 0.05) + 0.02 * ease[:, 0])))
            switch = (s[:, 0] > rng.uniform(0.3, 0.7)) * float(rng.random() < p_switch)
            drawer = 0.15 * ease[:, 0] * float(rng.random() < p_open) + rng.normal(0, 0.002, n)
            fixture = 0.000462 + rng.normal(0, 1e-7, n)
            reach = 0.44 if rng.random() < p_stop else rng.uniform(0.2, 0.43)
            slide = reach * ease[:, 0] + rng.normal(0, 1e-5, n)
            env = np.column_stack([cube, lid, knob, switch, drawer, fixture, np.zeros(n), slide]).astype(np.float32)
            out.append(Demo(episode_index=len(out), task=f"task {t}", frames=no_frames(n),
                            state=state.astype(np.float32), actions=actions, env_state=env,
                            extra={"env_state_names": NAMES, "timestamp": np.arange(n) / 20.0, "fps": 20.0}))
    return out


def _audit(demos: list[Demo]) -> pd.DataFrame:
    eps = pd.DataFrame({"episode_index": [d.episode_index for d in demos], "task": [d.task for d in demos]})
    ev = Evidence(episodes=eps, frames=False)
    names = [n for n, s in SCORERS.items() if s.model_free and s.in_audit and "frames" not in s.needs]
    chosen = select(names)
    consumers = {}
    for s in chosen:
        if s.decode is not None:
            consumers.setdefault(s.source, s.decode(ev, slice(0, len(demos)), "cpu"))
    for d in demos:
        for c in consumers.values():
            c.add(d)
    ev.behaviour = {k: c.finish() for k, c in consumers.items()}
    return score_table(compute(ev, chosen))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clean_data_of_any_shape_is_flagged_at_the_rate_asked_for(seed):
    table = _audit(clean_dataset(seed))
    n = len(table)
    assert table["is_anomaly"].sum() <= stats.binom.interval(0.99, n, 0.01)[1], \
        table.loc[table["is_anomaly"], "reason"].tolist()
    # No check reads float noise, a sign flip or a wrap at pi as an extreme outcome.
    assert np.nanmax(table["outcome"]) < 30, table.loc[table["outcome"].idxmax(), "reason"]


def test_a_planted_outcome_still_ranks_first_among_those_shapes():
    demos = clean_dataset(5)
    bad = demos[17]
    bad.env_state = bad.env_state.copy()
    bad.env_state[len(bad) // 2:, :2] = bad.env_state[len(bad) // 2, :2]  # the cube left half way
    table = _audit(demos).set_index("episode_index")
    assert table["outcome"].idxmax() == 17 and table.loc[17, "is_anomaly"]
    assert "cube." in table.loc[17, "reason"]


def test_the_shapes_benchmark_adds_dimensions_that_change_nothing_of_the_ranking(tmp_path):
    """benchmarks/shapes.py on a tiny suite with an idle and a random demo planted: the copy opens with the extra
    dimensions named, and audited without a model its planted demos rank as in the original."""
    import importlib.util
    from dataclasses import replace
    from pathlib import Path

    from democheck.sim.suite import generate
    from tests.conftest import TINY

    from typer.testing import CliRunner

    from democheck.cli import app
    from democheck.data import open_dataset

    path = Path(__file__).resolve().parent.parent / "benchmarks" / "shapes.py"
    spec = importlib.util.spec_from_file_location("shapes", path)
    shapes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(shapes)
    root = tmp_path / "data"
    generate(replace(TINY, seed=5, demos_per_task=6, steps=60, defects=(("idle", 1), ("random", 1))), root, workers=1)
    copy = tmp_path / "shapes"
    shapes.write_copy(root, copy, seed=3)
    demo = open_dataset(copy)[0]
    assert demo.env_state.shape[1] == open_dataset(root)[0].env_state.shape[1] + len(shapes.EXTRA)
    assert demo.extra["env_state_names"][-len(shapes.EXTRA):] == shapes.EXTRA
    ranks = []
    for ds in (root, copy):
        res = CliRunner().invoke(app, ["audit", str(ds), "--out", str(tmp_path / f"r-{ds.name}"), "--no-model"])
        assert res.exit_code == 0, res.output
        table = pd.read_parquet(tmp_path / f"r-{ds.name}" / "scores.parquet")
        ranks.append(table.loc[table["label"].fillna("clean") != "clean", "rank"].sort_values().tolist())
    assert len(ranks[0]) == 2 and ranks[0] == ranks[1]
    # The ranking's sweep re-ranks the saved audit as the audit did (it checks), and under a variant.
    spec = importlib.util.spec_from_file_location("sweep", path.parent / "ranking" / "sweep.py")
    sweep = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sweep)
    got = sweep.main([str(tmp_path / "r-data"), "--variants", "shipped,no-floors,without-outcome"])
    assert got[("r-data", "shipped")]["idle"] == 1.0 and got[("r-data", "shipped")]["random"] == 1.0
    assert set(got) == {("r-data", v) for v in ("shipped", "no-floors", "without-outcome")}
    # ... and the reasons benchmark reads it: the planted idle and random demos' reasons name their cause first.
    spec = importlib.util.spec_from_file_location("reasons", path.parent / "reasons.py")
    reasons = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reasons)
    said = reasons.main([str(tmp_path / "r-data")])
    assert said["idle"]["lead names the cause"] == 1.0 and said["random"]["lead names the cause"] == 1.0
    assert said["reasons"]["clean demos called beyond every clean demo"] == 0
    assert said["reasons"]["latent dimension"] == 0 and said["reasons"]["probability under 1e-12"] == 0


def test_a_spread_beside_a_pile_is_an_outcome_and_a_few_failures_beside_it_are_not():
    """Half a task's kettles rest where they stood (a pile), the rest were pushed up onto the grate at any height:
    the pushed ones are an outcome of their own.  Three failures of twelve beside a pile of successes are not, and a
    pile of a few demos that happen to agree is no pile."""
    from democheck.audit.outcome_modes import modes

    rng = np.random.default_rng(0)
    pile = 1.619 + rng.normal(0, 2e-4, 27)
    pushed = 1.62 + rng.uniform(0.005, 0.1, 25)
    label = modes(np.r_[pile, pushed], floor=2.5e-4)
    assert len(set(label[:27])) == 1 and len(set(label[27:])) == 1 and label[0] != label[-1]
    assert not modes(np.r_[pile, pushed], floor=2.5e-4, piles=False).any()  # no gap: no switch either
    successes, failures = 0.44 + rng.normal(0, 1e-5, 40), rng.uniform(0.1, 0.4, 3)
    assert not modes(np.r_[successes, failures], floor=2e-3).any()
    assert not modes(np.r_[successes[:6], rng.uniform(0.1, 0.4, 6)], floor=2e-3).any()  # six agreeing: no pile


def test_the_clean_shapes_benchmark_runs_and_reports_the_rate(capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "clean_shapes.py"
    spec = importlib.util.spec_from_file_location("clean_shapes", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = bench.main(["--seeds", "3-3"])
    assert result["of"] == 200 and result["flagged"] <= stats.binom.interval(0.99, 200, 0.01)[1]
    assert "clean demos flagged" in capsys.readouterr().out


def test_a_part_left_short_of_where_its_task_piles_is_a_job_done_in_part_not_far_out():
    """A slide most of its task's demos push to the stop at 0.44 and a few leave 0.24-0.38 open: those are a few
    units of the task's own job out, not the pile's spread of nothing.  A demo that never moved it, and one of
    another task that opened it, stay far out."""
    from democheck.audit.outcome import OutcomeStats, outcome

    rng = np.random.default_rng(0)
    stats, tasks = OutcomeStats(), []

    def add(task: str, slide: float, kettle: float) -> None:
        first, last = np.array([0.0, 0.0]), np.array([slide, kettle])
        stats.ends.append(np.stack([first, last]))
        stats.sources.append("environment state")
        stats.names.append(["slide_cabinet", "kettle_x"])
        stats.moves.append(np.stack([np.abs(last - first), np.zeros(2)]))
        tasks.append(task)

    for _ in range(34):
        add("slide", 0.44 + rng.normal(0, 1e-5), 0.0)
    short = rng.uniform(0.24, 0.38, 6)
    for v in short:
        add("slide", v, 0.0)
    add("slide", 0.0, 0.0)  # never opened it
    for _ in range(40):
        add("kettle", 0.0, 0.2 + rng.normal(0, 0.01))
    add("kettle", 0.2, 0.0)  # opened the slide instead
    score, found = outcome(stats, np.array(tasks))
    assert score[34:40].max() < 5  # a few tenths short: a few units of the job
    assert score[40] > 5 and score[-1] > 15  # never opened it; the other task opened it
    assert "slide_cabinet" in found[-1].params["name"]


def test_the_outcome_says_whether_the_world_differed_from_the_start_and_what_never_changed():
    """A demo from another scene (its object elsewhere from the first step, never moved) differs at the start and
    its reason says the part held one value; one that pushed its object elsewhere differs by what it did."""
    from democheck.audit.outcome import OutcomeStats, outcome

    rng = np.random.default_rng(1)
    stats, tasks = OutcomeStats(), []

    def add(start: float, end: float) -> None:
        first, last = np.array([start]), np.array([end])
        stats.ends.append(np.stack([first, last]))
        stats.sources.append("state")
        stats.names.append(None)
        stats.moves.append(np.stack([np.abs(last - first), np.full(1, 1e-6)]))
        tasks.append("push")

    for _ in range(30):
        s = rng.normal(0.3, 0.01)
        add(s, s + 0.2 + rng.normal(0, 0.01))
    add(0.9, 0.9)  # another scene: its object elsewhere, never moved
    add(0.3, 0.8)  # pushed it too far
    _, found = outcome(stats, np.array(tasks))
    assert found[30].kind == "another scene" and found[31].kind == "another job"
    assert found[30].params["columns"] == [0] and found[30].params["held"]
    assert "state[0] holds one value through the demo (0.9)" in found[30].words, found[30].words
    assert "holds one value" not in found[31].words


def test_a_joint_the_robot_turned_once_counts_as_one_far_feature_not_hundreds_of_units():
    """The robot's own state as the record: 40 demos leave the wrist where it began, two turn it 0.7 rad.  Against
    the pile's spread of nothing that is hundreds of units; in the score it counts ``ROBOT_CLIP`` (the words keep
    the distance).  The same turn of an object in the environment state stays as far as it is."""
    from democheck.audit.outcome import ROBOT_CLIP, OutcomeStats, outcome

    rng = np.random.default_rng(2)
    scores = {}
    for source in ("state", "environment state"):
        stats = OutcomeStats()
        for i in range(42):
            first = np.array([0.0, 0.0, 0.0])
            last = np.array([rng.normal(1.0, 0.05), rng.normal(-0.5, 0.05), 0.7 if i >= 40 else 0.0])
            stats.ends.append(np.stack([first, last]))
            stats.sources.append(source)
            stats.names.append(["shoulder", "elbow", "wrist"])
            stats.moves.append(np.stack([np.abs(last - first), np.full(3, 1e-6)]))
        scores[source], found = outcome(stats, np.array(["pick"] * 42))
        assert found[41].params["name"] == "wrist" and found[41].params["z"] > 100
    assert scores["state"][40:].max() <= ROBOT_CLIP
    assert scores["environment state"][40:].min() > 100


def test_how_fast_a_joint_moved_at_the_last_step_is_no_outcome():
    """Two of 30 demos stop recording with the wrist still turning (its velocity -1.8 where the others' is 0): the
    outcome reads where the record was left, not how fast a part moved then; a wrist left elsewhere still counts."""
    from democheck.audit.outcome import OutcomeStats, outcome

    rng = np.random.default_rng(4)
    stats = OutcomeStats()
    for i in range(30):
        first = np.zeros(2)
        last = np.array([rng.normal(1.0, 0.05) + (0.8 if i == 29 else 0.0), -1.8 if i in (27, 28) else 0.0])
        stats.ends.append(np.stack([first, last]))
        stats.sources.append("state")
        stats.names.append(["wrist.pos", "wrist.vel"])
        stats.moves.append(np.stack([np.abs(last - first) + 0.5, np.full(2, 1e-6)]))
    score, found = outcome(stats, np.array(["pick"] * 30))
    assert score[27:29].max() < 1 and score[29] > 3 * np.delete(score, 29).max()
    assert {f.params["name"] for f in found} == {"wrist.pos"}


def test_a_job_undone_is_told_from_another_scene():
    """Twenty demos push a block from 0 to 0.3.  One begins with it at 0.3, where they leave it, and pushes it back
    to 0 (a reset recorded as a demo): its job undone.  One begins with it at 0.3 and leaves it there: another
    scene."""
    from democheck.audit.outcome import OutcomeStats, outcome

    rng = np.random.default_rng(5)
    stats = OutcomeStats()
    for start, end in [(0.0, 0.3)] * 20 + [(0.3, 0.0), (0.3, 0.3)]:
        first, last = np.array([start + rng.normal(0, 0.005)]), np.array([end + rng.normal(0, 0.005)])
        stats.ends.append(np.stack([first, last]))
        stats.sources.append("environment state")
        stats.names.append(["block.x"])
        stats.moves.append(np.stack([np.abs(last - first), np.full(1, 1e-6)]))
    _, found = outcome(stats, np.array(["push"] * 22))
    assert found[20].kind == "undone"
    assert "undid its task's job" in found[20].words and "done backwards" in found[20].words
    assert found[21].kind == "another scene"


def test_a_fault_a_few_of_one_tasks_demos_share_is_no_outcome_of_the_task_but_a_toggle_is():
    """Three of a task's twelve demos pushed the other object to the goal too (it began where the others' did):
    in a dataset of several tasks they are far out, not an outcome of their own.  A button that ends on where it
    began off, and off where it began on, ends two ways because it began two ways: both are outcomes."""
    from democheck.audit.outcome import OutcomeStats, outcome
    from democheck.audit.outcome_modes import explained

    rng = np.random.default_rng(4)
    stats, tasks = OutcomeStats(), []

    def add(task: str, first: list[float], last: list[float]) -> None:
        first, last = np.array(first), np.array(last)
        stats.ends.append(np.stack([first, last]))
        stats.sources.append("environment state")
        stats.names.append(["target.x", "distractor.x", "button"])
        stats.moves.append(np.stack([np.abs(last - first) + 1e-9, np.full(3, 1e-6)]))
        tasks.append(task)

    for task in ("a", "b", "c"):
        for i in range(12):
            t0, d0, on = rng.uniform(0.3, 0.5), rng.uniform(0.3, 0.5), float(rng.random() < 0.5)
            both = task == "a" and i < 3
            add(task, [t0, d0, on], [0.7 + rng.normal(0, 0.003), 0.62 if both else d0, 1 - on])
    score, found = outcome(stats, np.array(tasks))
    assert score[:3].min() > 10 * np.median(score[3:]), score[:12]
    assert all(f.params["name"] == "distractor.x" for f in found[:3])
    assert score[3:].max() < 5, np.sort(score)[-5:]  # the button ends two ways in every task: no demo far out
    began = np.array([0.0] * 6 + [1.0] * 6)
    toggled = (1 - began).astype(int)
    assert (explained(toggled, began, 0.01) == toggled).all()
    assert not explained(began.astype(int), rng.uniform(0, 1, 12), 0.01).any()
    # Two demos never pressed it, one that began on and one off: each joins the toggle of the demos that began as
    # it began, and is measured against them.
    label, began = np.r_[toggled, 2, 2], np.r_[began, 0.0, 1.0]
    assert (explained(label, began, 0.01) == np.r_[toggled, 1, 0]).all()


def test_a_body_recorded_by_roll_pitch_and_yaw_is_compared_as_its_quaternion_would_be():
    """One orientation, two records: a body's roll, pitch and yaw (``box.roll`` ...) and its quaternion give the
    same outcome scores.  Its task's demos turn it about the vertical by a wide spread and one tips it onto its
    side: as three angles, a roll no clean demo has would read as far out as a knocked-over object beside a
    turn; as one rotation it is one more orientation, measured as the quaternion record measures it."""
    from scipy.spatial.transform import Rotation

    from democheck.audit.outcome import OutcomeStats, outcome
    from democheck.audit.world_record import features_of

    rng = np.random.default_rng(4)
    rpy = []
    for i in range(40):
        yaw = rng.uniform(-np.pi, np.pi)
        tip = np.pi / 2 if i == 0 else rng.normal(0, 0.02)
        rpy.append(np.array([[0.0, 0.0, yaw], [tip, 0.0, yaw + rng.normal(0, 0.5)]]))

    def scored(euler: bool):
        stats = OutcomeStats()
        for ends in rpy:
            names = ["box.roll", "box.pitch", "box.yaw"] if euler else ["box.qw", "box.qx", "box.qy", "box.qz"]
            x = ends if euler else Rotation.from_euler("xyz", ends).as_quat()[:, [3, 0, 1, 2]]
            stats.ends.append(x)
            stats.sources.append("environment state")
            stats.names.append(names)
            stats.moves.append(np.stack([np.abs(x[1] - x[0]), np.zeros(x.shape[1])]))
        return outcome(stats, np.zeros(len(rpy), int))

    (as_angles, found), (as_quaternion, _) = scored(True), scored(False)
    [feature] = features_of(["box.roll", "box.pitch", "box.yaw"], rpy[0][:1], rpy[0][1:])
    assert feature.kind == "rotation" and feature.columns == [0, 1, 2]
    np.testing.assert_allclose(as_angles, as_quaternion, rtol=1e-6)
    assert np.argmax(as_angles) == 0 and found[0].params["name"] == "the orientation of box"


def test_an_unnamed_quaternion_is_one_rotation_where_some_tasks_leave_its_slot_at_zero():
    """Meta-World's record names no dimension and fills an object's orientation only in the tasks that have a free
    object (a drawer's task leaves the four at zero): the four are still one rotation, not four values."""
    from scipy.spatial.transform import Rotation

    from democheck.audit.world_record import features_of

    rng = np.random.default_rng(2)
    turned = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi, (20, 1))).as_quat()
    first = np.concatenate([np.c_[rng.normal(0, 1, (20, 2)), turned], np.zeros((10, 6))])
    last = first + np.c_[rng.normal(0, 0.1, (30, 2)), np.zeros((30, 4))]
    assert [(f.kind, f.columns) for f in features_of(None, first, last)] == [
        ("value", [0]), ("value", [1]), ("rotation", [2, 3, 4, 5])]
    assert [f.kind for f in features_of(None, first[20:], last[20:])] == ["value"] * 6  # never filled: no rotation
