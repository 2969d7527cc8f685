"""Probes, injected defects and the detection benchmark (democheck probe, synth --defects, bench)."""

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import average_precision_score, roc_auc_score
from typer.testing import CliRunner

from democheck.cli import app
from democheck.data import open_dataset
from democheck.sim import scene
from democheck.sim.catalog import make_tasks, split_objects
from democheck.sim.env import PushEnv
from democheck.sim.variants import DEFECTS, EnvCache, make_policy, record_demo, resimulate

from tests.conftest import TINY

runner = CliRunner()


@pytest.fixture(scope="module")
def probes(tiny_dataset, tmp_path_factory):
    from democheck.sim.probes import make_probes

    root, _ = tiny_dataset
    out = tmp_path_factory.mktemp("probes") / "p"
    summary = make_probes(root, out, per_kind=2, seed=5, workers=1)
    return root, out, summary


def _pairs(src_root, probe_root):
    src, pr = open_dataset(src_root), open_dataset(probe_root)
    return [(pr[e], src[pr[e].source_episode]) for e in pr.episode_indices]


def test_probe_dataset_labels_and_links(probes):
    root, out, summary = probes
    ds = open_dataset(out)
    assert summary["kinds"] == {"no-action": 2, "random": 2, "no-objects": 2, "hidden": 2}
    eps = ds.episodes
    assert sorted(eps["label"].value_counts().items()) == [("hidden", 2), ("no-action", 2), ("no-objects", 2),
                                                          ("random", 2)]
    src = open_dataset(root)
    for e in ds.episode_indices:
        d = ds[e]
        s = src[d.source_episode]
        assert d.task == s.task and d.split == s.split and d.sim["probe"]["source_episode"] == s.episode_index


def test_each_probe_kind_differs_from_its_source_as_defined(probes):
    root, out, _ = probes
    for probe, source in _pairs(root, out):
        kind = probe.label
        arm_q = probe.state[:, :7]
        if kind == "no-action":
            assert np.abs(arm_q - arm_q[0]).max() < 1e-3  # the arm never moves
            assert np.abs(probe.actions).max() == 0
            np.testing.assert_allclose(probe.env_state, np.repeat(source.env_state[:1], len(probe), 0), atol=1e-6)
        elif kind == "random":
            assert np.abs(arm_q - arm_q[0]).max() > 0.05  # it moves, and not as the source did
            assert not np.allclose(probe.actions, source.actions)
        elif kind == "no-objects":
            assert np.isnan(probe.env_state).all()  # no objects in the scene
            np.testing.assert_array_equal(probe.actions, source.actions)  # the source's motion replayed
            np.testing.assert_array_equal(probe.state[0], source.state[0])
            # Only the objects' pixels change at the first frame: a small, non-empty region.
            diff = np.abs(probe.frames[0].astype(int) - source.frames[0].astype(int)).max(-1) > 40
            assert 0 < diff.mean() < 0.25
        elif kind == "hidden":
            squares = probe.sim["probe"]["squares"]
            covered = np.zeros(probe.frames.shape[1:3], bool)
            for r, c, side, *rgb in squares:
                covered[r:r + side, c:c + side] = True
            assert covered.mean() >= 0.5
            last = squares[-1]  # the last square drawn is on top everywhere it lies
            patch = probe.frames[:, last[0]:last[0] + last[2], last[1]:last[1] + last[2]].astype(int)
            err = np.abs(patch - np.array(last[3:]))
            assert err.mean() < 4 and err.max() <= 24  # a solid colour, up to video compression at its edges
            outside = ~covered
            if outside.any():
                err = np.abs(probe.frames[:, outside].astype(int) - source.frames[:, outside].astype(int))
                assert err.mean() < 4
        else:  # pragma: no cover
            raise AssertionError(kind)


def test_rendered_probes_go_through_the_sources_encoder(probes):
    """A re-simulated probe's frames are its fresh render through the source's lossy encoder, not the render
    itself: otherwise every such probe differs from every clean demo by the encoder's traces alone."""
    from democheck.data.video import through_codec
    from democheck.sim.probes import source_codec

    root, out, summary = probes
    codec, source_fps = source_codec(open_dataset(root)), open_dataset(root).fps
    assert codec == (TINY.pix_fmt, TINY.crf)
    assert summary["rendered_frames_through"] == {"pix_fmt": TINY.pix_fmt, "crf": TINY.crf}
    envs = EnvCache(TINY.image_size)
    for probe, source in _pairs(root, out):
        if probe.label != "no-action":
            continue
        render = resimulate(envs, source.sim, "no-action", seed=probe.sim["probe"]["seed"])["frames"]
        np.testing.assert_array_equal(probe.frames, through_codec(render, round(source_fps), *codec))
        traces = np.abs(probe.frames.astype(int) - render).mean()
        assert 0 < traces < 4  # the encoder's small errors, now like the source's own
    assert source_codec(open_dataset(out)) is None  # the probes themselves are lossless


def test_resimulating_a_clean_demo_reproduces_it_exactly(tiny_dataset):
    root, _ = tiny_dataset
    ds = open_dataset(root)
    envs = EnvCache(TINY.image_size)
    for e in ds.episode_indices[:3]:
        demo = ds[e]
        rec = resimulate(envs, demo.sim)
        np.testing.assert_array_equal(rec["state"], demo.state)
        np.testing.assert_array_equal(rec["actions"], demo.actions)
        np.testing.assert_array_equal(rec["env_state"], demo.env_state)
        assert rec["success"] == demo.success


def test_image_level_probes_for_a_dataset_without_sim_records(tiny_dataset, tmp_path):
    import shutil

    from democheck.errors import DatasetError
    from democheck.sim.probes import make_probes

    root, _ = tiny_dataset
    plain = tmp_path / "plain"
    shutil.copytree(root, plain)
    (plain / "meta/democheck/episodes.parquet").unlink()  # a user's dataset: no sidecar, no sim records
    with pytest.raises(DatasetError, match="no sim records"):
        make_probes(plain, tmp_path / "p1", ["no-objects"], per_kind=1, workers=1)
    assert not (tmp_path / "p1").exists()
    summary = make_probes(plain, tmp_path / "p2", per_kind=2, workers=1)  # default: the kinds this data allows
    assert summary["kinds"] == {"no-action": 2, "hidden": 2}
    ds, source = open_dataset(tmp_path / "p2"), open_dataset(plain)
    assert ds.camera == source.camera  # the camera keeps its name
    for e in ds.episode_indices:
        d = ds[e]
        src = source[int(d.sim["probe"]["source_episode"])].frames
        if d.label == "no-action":  # the first frame held, bit for bit (the probe's video is lossless)
            assert (d.frames == src[:1]).all()
            assert (d.state == d.state[0]).all() and (d.actions == 0).all()
        else:  # hidden: the source's frames exactly, but under the squares
            covered = np.zeros(src.shape[1:3], bool)
            for r, c, side, *_ in d.sim["probe"]["squares"]:
                covered[r:r + side, c:c + side] = True
            assert (d.frames[:, ~covered] == src[:, ~covered]).all() and covered.mean() >= 0.5


def test_probes_of_a_wide_camera_keep_its_shape_and_the_sources_names_and_invent_no_environment(tmp_path):
    """A user's recording: a 24x32 camera, named joints, no environment state, no sim records.  Its probes are
    24x32 too, name the joints as the source does, record no environment state, and a reversed probe is its
    source played backwards, frame for frame."""
    import json

    from democheck.data.demo import Demo
    from democheck.data.lerobot_write import VideoOptions, write_meta, write_shard
    from democheck.sim.probes import make_probes

    rng = np.random.default_rng(0)
    demos = [Demo(episode_index=i, task="put the banana on the plate",
                  frames=rng.integers(0, 256, (12, 24, 32, 3), dtype=np.uint8),
                  state=rng.normal(size=(12, 2)).astype(np.float32),
                  actions=rng.normal(size=(12, 3)).astype(np.float32)) for i in range(4)]
    source = tmp_path / "real"
    opts = VideoOptions(camera="observation.images.top", lossless=True)
    rows = write_shard(source, 0, demos, {"put the banana on the plate": 0}, 0, 10, opts)
    write_meta(source, rows, ["put the banana on the plate"], 10, (24, 32), ["shoulder", "elbow"],
               ["shoulder.vel", "elbow.vel", "gripper"], [], opts)
    (source / "meta/democheck/episodes.parquet").unlink()  # no sidecar, no sim records
    make_probes(source, tmp_path / "p", ["reversed", "hidden"], per_kind=2, workers=1)
    features = json.loads((tmp_path / "p/meta/info.json").read_text())["features"]
    assert features["observation.images.top"]["shape"] == [24, 32, 3]
    assert features["observation.state"]["names"] == ["shoulder", "elbow"]
    assert features["action"]["names"] == ["shoulder.vel", "elbow.vel", "gripper"]
    assert "observation.environment_state" not in features
    ds, src = open_dataset(tmp_path / "p"), open_dataset(source)
    for e in ds.episode_indices:
        d = ds[e]
        assert d.frames.shape[1:] == (24, 32, 3) and d.env_state is None
        if d.label == "reversed":
            assert (d.frames == src[int(d.sim["probe"]["source_episode"])].frames[::-1]).all()


def test_defects_behave_as_labelled():
    """Full-length episodes without rendering: each defect does what its name says."""
    task = make_tasks(3, 0, 0, seed=0)[1]
    env = PushEnv(task, render_images=False)
    ends = {}
    for kind in ("expert",) + DEFECTS:
        env.occluder = kind == "occluded"
        env.set_task(task)
        rec = record_demo(env, make_policy(kind, env, 11).act, 100, seed=11)
        to_goal = lambda xy: np.hypot(*(xy - scene.GOAL_XY))  # noqa: E731
        ends[kind] = (to_goal(rec["env_state"][0, :2]), to_goal(rec["env_state"][-1, :2]),
                      to_goal(rec["env_state"][0, 3:5]), to_goal(rec["env_state"][-1, 3:5]), rec["success"])
    t0, t1, d0, d1, ok = ends["expert"]
    assert ok and t1 < scene.GOAL_RADIUS
    t0, t1, d0, d1, ok = ends["wrong-object"]
    assert not ok and d1 < scene.GOAL_RADIUS and abs(t1 - t0) < 0.01  # the distractor pushed, the target left
    t0, t1, d0, d1, ok = ends["both-objects"]
    assert d1 < d0 - 0.05 and t1 < t0 - 0.05  # both moved towards the goal
    t0, t1, d0, d1, ok = ends["gave-up"]
    assert not ok and scene.GOAL_RADIUS < t1 < t0  # stopped on the way
    assert ends["occluded"][4]  # the expert's push, only hidden from the camera


def test_occluder_hides_the_target_from_the_camera():
    task = make_tasks(3, 0, 0, seed=0)[0]
    envs = EnvCache(64)
    frames = {}
    for kind in ("expert", "occluded"):
        env = envs.get(task.target, task.distractor, kind)
        obs, _ = env.reset(seed=4)
        frames[kind] = obs["image"].astype(int)
    # Without the target: what the camera sees where the target is.
    env = envs.get(task.target, task.distractor, "expert")
    env.reset(seed=4)
    env.data.qpos[env._obj_qadr["target"][:2]] = [0.0, 0.9]  # out of view
    import mujoco

    mujoco.mj_forward(env.model, env.data)
    no_target = env.render().astype(int)
    target_px = np.abs(frames["expert"] - no_target).max(-1) > 30
    assert target_px.sum() > 5
    # Every pixel that showed the target now shows one flat grey card instead.
    seen = frames["occluded"][target_px]
    assert np.abs(seen - seen.mean(0)).max() < 40 and np.ptp(seen.mean(0)) < 20
    assert np.abs(seen - frames["expert"][target_px]).max(-1).mean() > 30


def test_a_markovian_suite_with_dart_noise_records_and_resimulates_exactly(tmp_path):
    """push-v2's recipe: the Markovian expert, noise on the executed torques; the sim record names both, and a
    re-simulation from it reproduces every demo bit for bit (the noise is drawn from the episode's seed)."""
    from democheck.errors import RecipeError
    from democheck.sim.suite import generate, load_recipe

    v2 = load_recipe("push-v2")
    assert (v2.expert, v2.action_noise) == ("markovian", 0.1) and load_recipe("push-v1").expert == "hysteresis"
    with pytest.raises(RecipeError, match="an expert among"):
        replace(v2, expert="telepathic").validate()
    root = tmp_path / "v2"
    generate(replace(TINY, seed=4, expert="markovian", action_noise=0.1), root, workers=1)
    ds = open_dataset(root)
    envs = EnvCache(TINY.image_size)
    for e in ds.episode_indices[:3]:
        demo = ds[e]
        assert (demo.sim["expert"], demo.sim["action_noise"]) == ("markovian", 0.1)
        rec = resimulate(envs, demo.sim)
        np.testing.assert_array_equal(rec["state"], demo.state)
        np.testing.assert_array_equal(rec["actions"], demo.actions)
    # A record made before the expert was named replays with push-v1's expert and no noise.
    old = {k: v for k, v in ds[0].sim.items() if k not in ("expert", "action_noise")}
    assert not np.array_equal(resimulate(envs, old)["state"], ds[0].state)


def test_recipe_defects_and_rate(tmp_path):
    from democheck.sim.suite import load_recipe, planted_episodes

    r = load_recipe("push-mini").with_overrides(defect_rate=0.25, defects={"idle": 3})
    counts = r.defect_counts()
    assert counts["idle"] == 3 and sum(counts[k] for k in DEFECTS) == round(0.25 * r.n_episodes)
    assert max(counts[k] for k in DEFECTS) - min(counts[k] for k in DEFECTS) <= 1
    assert len(planted_episodes(r)) == sum(counts.values())
    toml = tmp_path / "r.toml"
    toml.write_text('name = "x"\n[defects]\nrate = 0.1\nwrong-object = 2\n')
    r2 = load_recipe(str(toml))
    assert r2.defect_rate == 0.1 and dict(r2.defects) == {"wrong-object": 2}
    from democheck.errors import RecipeError

    with pytest.raises(RecipeError, match="defect kinds"):
        load_recipe("push-mini").with_overrides(defects={"sneeze": 1})


def test_fresh_meta_test_recipe_keeps_push_v1_held_out_objects():
    from democheck.sim.suite import load_recipe

    test = load_recipe("push-v1-test")
    v1 = load_recipe("push-v1")
    _, held = split_objects(v1.seed, v1.test_object_fraction)
    held = {o.key for o in held}
    tasks = test.tasks()
    assert tasks and all(t.split == "test" for t in tasks)
    assert all(t.target.key in held and t.distractor.key in held for t in tasks)
    v1_pairs = {(t.target.key, t.distractor.key) for t in v1.tasks() if t.split == "test"}
    new_pairs = {(t.target.key, t.distractor.key) for t in tasks}
    assert len(new_pairs - v1_pairs) > len(new_pairs) // 2  # mostly new tasks


@pytest.fixture(scope="module")
def defect_dataset(tmp_path_factory):
    from democheck.sim.suite import generate

    out = tmp_path_factory.mktemp("defects") / "d"
    recipe = replace(TINY, seed=9, defects=(("idle", 1), ("random", 1), ("wrong-object", 1)))
    generate(recipe, out, workers=1)
    return out


def test_bench_cli_schema_and_auroc_against_sklearn(defect_dataset, probes, tiny_model, tmp_path):
    from democheck.petnet.train import TrainConfig
    from democheck.workflows import train_model

    _, probe_root, _ = probes
    tec = tmp_path / "tec"
    train_model(defect_dataset, tec, TrainConfig(model_type="tecnet", steps=4, batch_tasks=2, timesteps=2, val_every=2,
                                                 device="cpu"), cache_dir=tmp_path / "cache")
    out = tmp_path / "bench"
    res = runner.invoke(app, ["bench", str(defect_dataset), str(probe_root), "--out", str(out), "--model",
                              str(tiny_model), "--tecnet", str(tec)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "bench.json").read_text())
    kinds = {"idle", "random", "wrong-object", "no-action", "no-objects", "hidden"}
    assert kinds <= set(doc["kinds"])
    assert list(doc["scorers"]) == ["task_uncertainty", "task_uncertainty_head", "novelty", "consistency",
                                    "action_error", "motion", "idle", "pause", "grasps", "broken", "jerk", "saturation",
                                    "duplicate",
                                    "dynamics", "lag", "timing", "frozen_video", "frame_jump", "state_jump",
                                    "frozen_state", "view", "colours",
                                    "outcome", "moved", "start", "end", "path", "backwards", "backwards_state",
                                    "coupling",
                                    "suspicion",
                                    "model_free",
                                    "ocsvm_flag", "tecnet_knn", "heuristic", "random"]
    for name, per in doc["scorers"].items():
        for kind in kinds:
            assert set(per[kind]) == {"auroc", "auprc", "p_at_k", "n"}
    # Every figure is what scikit-learn says on the pooled scores.
    table = pd.read_parquet(out / "scores.parquet")
    assert len(table) == len(open_dataset(defect_dataset)) + len(open_dataset(probe_root))
    # The paper's sigma (the head alone) is the total without the novelty part: never larger, larger somewhere.
    head, total = table["task_uncertainty_head"], table["task_uncertainty"]
    assert (head <= total * (1 + 1e-6)).all() and (head < total).any()
    for name in ("task_uncertainty", "heuristic", "tecnet_knn"):
        for kind in ("idle", "hidden"):
            keep = table["label"].isin([kind, "clean"])
            y, s = (table["label"][keep] == kind).to_numpy(), table[name][keep].to_numpy()
            s = np.nan_to_num(s, nan=np.nanmin(s))
            assert doc["scorers"][name][kind]["auroc"] == pytest.approx(roc_auc_score(y, s))
            assert doc["scorers"][name][kind]["auprc"] == pytest.approx(average_precision_score(y, s))
    curve = [c["mean_sigma"] for c in doc["figure_5b"]]
    assert all(b < a for a, b in zip(curve, curve[1:]))  # more cues, less uncertainty
    assert set(doc["figure_5a"]) >= kinds | {"clean"}
    md = (out / "bench.md").read_text()
    assert "AUROC" in md and "Figure 5A" in md and "Figure 5B" in md
    from tests.test_audit import _read_rrd

    ents = _read_rrd(out / "bench.rrd")
    # One named bar per kind (the legend says which), at its own place, as high as the kind's mean sigma.
    assert {"/bench", "/figure_5b/mean_sigma"} <= set(ents)
    for i, kind in enumerate(doc["figure_5a"]):
        bar = ents[f"/figure_5a/mean/{kind}"][0]
        assert bar.column("BarChart:abscissa").to_pylist()[0][0]["buffer"] == [float(i)]
        assert np.isclose(bar.column("BarChart:values").to_pylist()[0][0]["buffer"][0], doc["figure_5a"][kind]["mean"])
        assert f"/figure_5a/std/{kind}" in ents


def test_heuristic_scorer_catches_an_idle_demo():
    from democheck.audit.baselines import heuristic_score, heuristic_table
    from democheck.data.demo import Demo

    rng = np.random.default_rng(0)
    demos = []
    for i in range(10):
        state = np.cumsum(rng.normal(0, 0.05, (20, 4)), 0).astype(np.float32)
        demos.append(Demo(i, "t", np.zeros((20, 2, 2, 3), np.uint8), state, rng.normal(0, 0.3, (20, 3)).astype(np.float32)))
    demos[4].state[:] = demos[4].state[0]
    demos[4].actions[:] = 0
    score = heuristic_score(heuristic_table(demos))
    assert int(np.argmax(score)) == 4


def test_bench_refuses_unlabelled_data(tiny_model, tmp_path, tiny_dataset):
    import shutil

    root, _ = tiny_dataset
    plain = tmp_path / "plain"
    shutil.copytree(root, plain)
    (plain / "meta/democheck/episodes.parquet").unlink()
    res = runner.invoke(app, ["bench", str(plain), "--out", str(tmp_path / "b"), "--model", str(tiny_model)])
    assert res.exit_code == 2 and "no labels" in res.output
    assert not (tmp_path / "b").exists()
