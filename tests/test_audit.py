import json

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from democheck.audit.metrics import detection, precision_at_k, separation
from democheck.audit.run import score_posteriors
from democheck.audit.ocsvm import fit_ocsvm, ocsvm_margin
from democheck.audit.scores import consistency_parts, task_neighbours
from democheck.cli import app
from democheck.petnet.posterior import TaskPosterior, product_of_others

runner = CliRunner()


def _episodes(n_tasks=5, per=6):
    return pd.DataFrame({"episode_index": np.arange(n_tasks * per), "task": np.repeat([f"t{i}" for i in range(n_tasks)], per),
                         "label": "clean"})


def _post(mu, var):
    return TaskPosterior(mu, var, np.zeros_like(var))


def score_table(eps, mu, var, action_error=None):
    return score_posteriors(eps, _post(mu, var), behaviour={"action_error": action_error} if action_error is not None
                            else None)


def _posteriors(eps, rng, spread=0.05):
    centres = {t: rng.normal(0, 1, 10) for t in eps["task"].unique()}
    mu = np.stack([centres[t] + rng.normal(0, spread, 10) for t in eps["task"]])
    var = np.full_like(mu, spread**2) * rng.uniform(0.8, 1.25, mu.shape)
    return mu, var, centres


def test_planted_uncertain_demo_ranks_first():
    rng = np.random.default_rng(0)
    eps = _episodes()
    mu, var, _ = _posteriors(eps, rng)
    var[17] *= 30  # a cue that says nothing
    table = score_table(eps, mu, var)
    assert table.iloc[0]["episode_index"] == 17 and table.iloc[0]["rank"] == 1
    assert list(table["rank"]) == list(range(1, len(eps) + 1))


def test_planted_wrong_task_demo_ranks_first_by_consistency():
    rng = np.random.default_rng(1)
    eps = _episodes()
    mu, var, centres = _posteriors(eps, rng)
    mu[8] = centres["t3"] + rng.normal(0, 0.05, 10)  # a t1 demo that clearly shows task t3
    table = score_table(eps, mu, var)
    assert table.iloc[0]["episode_index"] == 8
    row = table.set_index("episode_index").loc[8]
    assert row["consistency"] > 5 * table["consistency"].median()
    # variance alone cannot see it
    assert table.sort_values("task_uncertainty", ascending=False).iloc[0]["episode_index"] != 8


def test_consistency_matches_brute_force_and_handles_singletons():
    rng = np.random.default_rng(2)
    n = 23
    mu, var = rng.normal(size=(n, 4)), rng.uniform(0.1, 1, (n, 4))
    tasks = np.array(["a"] * 20 + ["b"] * 2 + ["c"])  # b: one other demo; c: none
    c, apart = consistency_parts(_post(mu, var), tasks)
    x = mu / np.median(np.sqrt(var), axis=0)  # units: each dimension's median task SD
    for i in [0, 7, 19, 20]:
        others = np.flatnonzero((tasks == tasks[i]) & (np.arange(n) != i))
        d = np.linalg.norm(x[i] - x[others], axis=1)
        nn = others[np.argsort(d)[:5]]  # task b: its one other demo
        assert np.isclose(c[i], np.sort(d)[:5].mean()) and np.allclose(apart[i], np.abs(x[i] - x[nn].mean(0)))
    # In a small task, never more than half of the other demos: a bad minority is not every demo's neighbour.
    small = np.array(["s"] * 6 + ["a"] * 17)
    c6 = consistency_parts(_post(mu, var), small)[0]
    assert np.isclose(c6[0], np.sort(np.linalg.norm(x[0] - x[1:6], axis=1))[:2].mean())
    assert np.isnan(c[22])  # a task's only demo
    # Taken a few demos at a time, the same numbers.
    assert np.allclose(task_neighbours(x, tasks, 5, at_most_half=True, chunk=3)[0], c, equal_nan=True)


def test_consistency_against_the_k_nearest_others_matches_brute_force():
    rng = np.random.default_rng(5)
    n = 23
    mu, var = rng.normal(size=(n, 4)), rng.uniform(0.1, 1, (n, 4))
    tasks = np.array(["a"] * 20 + ["b"] * 3)
    m, v = product_of_others(mu, var, tasks, k=5, chunk=7)  # several chunks of task a
    for i in [0, 6, 7, 19, 21]:
        idx = np.flatnonzero(tasks == tasks[i])
        others = idx[idx != i]
        d = ((mu[i] - mu[others]) ** 2 / (var[i] + var[others])).mean(1)
        nn = others[np.argsort(d)[:5]]
        p = (1 / var[nn]).sum(0)
        assert np.allclose(m[i], (mu[nn] / var[nn]).sum(0) / p) and np.allclose(v[i], 1 / p)
    m_all, _ = product_of_others(mu, var, tasks)
    assert np.allclose(m[21], m_all[21])  # task b has 2 others, fewer than k: all of them


def test_a_changed_cue_is_measured_against_its_demos_task_mates_as_the_demo_is():
    """``consistency_of``: a demo's own cue standing in for it gives its own consistency; a cue moved far from its
    task gives a larger one."""
    from democheck.audit.scores import consistency, consistency_of

    rng = np.random.default_rng(8)
    n = 30
    tasks = np.array(["a"] * 18 + ["b"] * 12)
    post = _post(rng.normal(size=(n, 4)), rng.uniform(0.1, 1, (n, 4)))
    rows = np.array([0, 5, 17, 18, 29])
    same = _post(post.mu[rows], post.var[rows])
    assert np.allclose(consistency_of(same, rows, post, tasks), consistency(post, tasks)[rows])
    far = _post(post.mu[rows] + 50.0, post.var[rows])
    assert (consistency_of(far, rows, post, tasks) > 10 * consistency(post, tasks)[rows]).all()


def test_ocsvm_flags_high_uncertainty():
    rng = np.random.default_rng(3)
    train_sigma = rng.uniform(0.05, 0.07, (500, 10))
    params = fit_ocsvm(train_sigma, nu=0.01)
    json.dumps(params)  # stored in config.json: plain numbers only
    assert params["flagged_fraction_on_fit"] <= 0.05
    new = np.vstack([rng.uniform(0.05, 0.07, (50, 10)), np.full((3, 10), 0.3)])
    flags = ocsvm_margin(params, new) < 0
    assert flags[-3:].all() and flags[:-3].mean() < 0.1


def test_metrics():
    bad = np.array([1, 1, 0, 0, 0], bool)
    assert precision_at_k(bad, np.array([5, 1, 4, 0, 0])) == 0.5
    d = detection(bad, np.array([5, 4, 1, 0, 0]))
    assert d["auroc"] == 1.0 and d["p_at_k"] == 1.0 and d["n"] == 2
    # A kind's AUROC against the clean demos, and how many of it lie above every clean one (what a flag needs).
    labels = np.array(["clean"] * 4 + ["detour"] * 2 + ["drop"] * 2)
    assert separation(labels, np.array([0, 1, 2, 3, 4, 2.5, 5, 6])) == ("detour 0.875 (0.50 beyond), "
                                                                       "drop 1.000 (1.00 beyond)")


def _read_rrd(path):
    import rerun.chunk as rc

    out = {}
    for chunk in rc.RrdReader(str(path)).store().stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def test_audit_cli_lerobot_writes_report_and_recording(tiny_dataset, tiny_model, tmp_path):
    root, _ = tiny_dataset
    res = runner.invoke(app, ["audit", str(root), "--out", str(tmp_path / "r"), "--model", str(tiny_model),
                              "--top", "3", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    for col in ("episode_index", "task", "task_uncertainty", "consistency", "suspicion", "reason", "rank", "is_anomaly",
                "sigma", "mu", "label"):
        assert col in table
    assert len(table) == 12 and list(table["rank"]) == list(range(1, 13))
    assert "score" not in table  # the name before the registry is gone
    assert table["action_error"].notna().all()  # on by default
    assert (np.diff(table["suspicion"].to_numpy()) <= 1e-12).all()  # ranked by suspicion
    assert len(table["sigma"][0]) == 10 and (np.stack(table["sigma"]) > 0).all()
    # The model has a novelty density: each demo's d2 / d2_ref, which scales the novelty part of its variance.
    from democheck.data import open_dataset
    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.petnet.novelty import stack_features

    enc = load_checkpoint(tiny_model).model.encoder
    ds = open_dataset(root)
    assert enc.cfg.novelty_autoencoder  # democheck train's default: the density is over its autoencoder's features
    eps = table["episode_index"].tolist()
    feats = stack_features(enc.novelty_conv, ds.cue_frames_many(eps), torch.device("cpu"), view=enc.cfg.novelty_view)
    assert enc.cfg.novelty_state  # ... and where each demo ended, standardised by the training demos' ends
    ends = (torch.from_numpy(ds.end_states(eps)) - enc.end_state_mean) / enc.end_state_scale
    want = (enc.distance2(torch.cat([torch.from_numpy(feats), ends], 1)) / enc.novelty_ref).numpy()
    np.testing.assert_allclose(table["novelty"].to_numpy(), want, rtol=1e-4)
    csv = pd.read_csv(tmp_path / "r" / "scores.csv")
    assert list(csv["episode_index"]) == list(table["episode_index"])
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["demos"] == 12 and summary["model_trained_on_this_dataset"] is True
    suspects = (tmp_path / "r" / "suspects.txt").read_text().split()
    assert [int(e) for e in suspects] == table[table["is_anomaly"]]["episode_index"].tolist()

    rrd = _read_rrd(tmp_path / "r" / "report.rrd")
    text = rrd["/suspects"][0].column("TextDocument:text").to_pylist()[0][0]
    top = table.iloc[0]
    assert f"| 1 | {top['episode_index']} |" in text
    base = f"/suspects/001_ep{top['episode_index']}"
    blobs = [b for b in rrd[f"{base}/video"] if "AssetVideo:blob" in b.schema.names]
    refs = sum(b.num_rows for b in rrd[f"{base}/video"] if "VideoFrameReference:timestamp" in b.schema.names)
    assert len(blobs) == 1 and refs == 12  # one video frame reference per step of the suspect's episode
    import io

    import av

    from democheck.data import open_dataset

    blob = bytes(blobs[0].column("AssetVideo:blob").to_pylist()[0][0])
    with av.open(io.BytesIO(blob)) as c:
        logged = np.stack([f.to_ndarray(format="rgb24") for f in c.decode(video=0)])
    truth = open_dataset(root)[int(top["episode_index"])].frames
    assert logged.shape == truth.shape
    assert np.abs(logged.astype(int) - truth.astype(int)).mean() < 12  # the suspect's own frames, re-encoded
    sigma = rrd[f"{base}/sigma"][0].column("BarChart:values").to_pylist()[0]
    bars = sigma[0]  # the suspect's task sigma per dimension over the unflagged demos' median
    typical = np.median(np.stack(table["sigma"][~table["is_anomaly"]]), axis=0)
    assert bars["shape"] == [10] and np.allclose(bars["buffer"], table["sigma"].iloc[0] / typical, rtol=1e-5)
    actions = [b for b in rrd[f"{base}/actions"] if "Scalars:scalars" in b.schema.names][0]
    assert actions.num_rows == 12 and len(actions.column("Scalars:scalars").to_pylist()[0]) == 7
    pts = rrd["/map/demos"][0].column("Points2D:positions").to_pylist()[0]
    assert len(pts) == 12
    # What a reviewer decides from: each suspect's reason beside its video, the list's short form of it, the
    # dataset's own names for its action series, histograms whose bars are as wide as their bins.
    from democheck.viz.report import short_reason

    about = rrd[f"{base}/about"][0].column("TextDocument:text").to_pylist()[0][0]
    assert top["reason"].split("; also ")[0] in about and ("FLAGGED" in about) == bool(top["is_anomaly"])
    assert f"| {short_reason(top['reason']).replace('|', chr(92) + '|')} |" in text
    series = [b for b in rrd[f"{base}/actions"] if "SeriesLines:names" in b.schema.names][0]
    assert series.column("SeriesLines:names").to_pylist()[0] == ds.names("action")
    assert ds.names("action")[0] == "shoulder_pan.torque"  # as the dataset's info.json names it
    # Every flagged demo has a tab (at least --top), each beside a clean demo of its task; the flag level is
    # drawn on the suspicion histogram.
    abouts = [k for k in rrd if k.startswith("/suspects/") and k.endswith("/about")]
    assert len(abouts) == max(3, int(table["is_anomaly"].sum()))
    typical = [k for k in rrd if k.startswith("/typical/") and k.endswith("/actions")]
    assert len(typical) == table.head(len(abouts))["task"].nunique()
    assert "Beside it: episode" in about
    beside = int(about.split("Beside it: episode ")[1].split(",")[0])
    assert not table.set_index("episode_index").loc[beside, "is_anomaly"]
    assert "/scores/suspicion/level" in rrd or not table["is_anomaly"].any()
    for name in ("suspicion", "task_uncertainty", "action_error"):
        bars = rrd[f"/scores/{name}/all"][0]
        centres = np.asarray(bars.column("BarChart:abscissa").to_pylist()[0][0]["buffer"])
        widths = np.asarray(bars.column("BarChart:widths").to_pylist()[0])
        np.testing.assert_allclose(widths, 0.95 * np.diff(centres).mean(), rtol=1e-4)
        counts = np.asarray(bars.column("BarChart:values").to_pylist()[0][0]["buffer"])
        assert counts.sum() == 12


def _write_robomimic(path, n=6, T=8, size=16, joints=14):
    import h5py

    rng = np.random.default_rng(0)
    push = np.random.default_rng(1).normal(size=10)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "PushTiny", "env_kwargs": {"control_freq": 20}})
        for i in range(n):
            g = data.create_group(f"demo_{i}")
            g.create_dataset("actions", data=rng.uniform(-1, 1, (T, 7)).astype(np.float32))
            g.create_dataset("obs/agentview_image", data=rng.integers(0, 255, (T, size, size, 3), dtype=np.uint8))
            g.create_dataset("obs/robot0_eef_pos", data=rng.normal(size=(T, 3)))
            g.create_dataset("obs/robot0_joint_pos", data=rng.normal(size=(T, joints)))
            # the objects' poses, moved alike by every demo
            g.create_dataset("obs/object", data=rng.normal(0, 0.01, 10) + np.linspace(0, 1, T)[:, None] * push)
            if i == 5:
                g.attrs["task"] = "another task"
        f.create_dataset("mask/train", data=np.array([b"demo_0", b"demo_1", b"demo_2", b"demo_5"]))
        f.create_dataset("mask/valid", data=np.array([b"demo_3", b"demo_4"]))


def test_robomimic_reader_and_audit(tiny_model, tmp_path):
    from democheck.data import open_dataset

    path = tmp_path / "demo.hdf5"
    _write_robomimic(path)
    ds = open_dataset(path)
    assert ds.format == "robomimic" and len(ds) == 6 and ds.state_dim == 17 and ds.action_dim == 7
    assert ds.by_task() == {"PushTiny": [0, 1, 2, 3, 4], "another task": [5]}
    assert ds.split("val") == [3, 4]
    demo = ds[2]
    assert demo.frames.shape == (8, 16, 16, 3) and demo.env_state.shape == (8, 10)  # obs/object, not the state
    np.testing.assert_array_equal(ds.cue_frames(2), demo.frames[[0, -1]])
    np.testing.assert_array_equal(ds.end_states([2, 5]), np.stack([demo.state[-1], ds[5].state[-1]]))
    np.testing.assert_array_equal(ds.end_states([2, 5], at=0.0), np.stack([demo.state[0], ds[5].state[0]]))
    import shutil

    import h5py

    broken = shutil.copy(path, tmp_path / "broken.hdf5")
    with h5py.File(broken, "a") as f:  # a sensor that dropped out at the last step: a broken demo, not NaN scores
        f["data/demo_4/obs/robot0_eef_pos"][-1, 0] = np.nan
    ends = open_dataset(broken).end_states([3, 4])
    demo = open_dataset(broken)[4]
    np.testing.assert_array_equal(ends[1], demo.state[-1])
    assert ends[1][0] == demo.state[-2, 0] and demo.damaged[0][0] == 1  # the last finite value carried on
    res = runner.invoke(app, ["audit", str(broken), "--out", str(tmp_path / "b"), "--model", str(tiny_model),
                              "--device", "cpu"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "b" / "scores.parquet")
    first = table.iloc[0]
    assert first["episode_index"] == 4 and first["is_anomaly"] and np.isinf(first["suspicion"])
    assert first["reason"] == "broken: NaN or infinite values in 'obs (state keys)' at 1 of 8 frames, 7", first["reason"]
    assert table["is_anomaly"].sum() == 1 + (table["duplicate"] == np.inf).sum()
    assert open_dataset(path, task="lift").tasks == ["another task", "lift"]
    lost = shutil.copy(path, tmp_path / "lost.hdf5")
    with h5py.File(lost, "a") as f:  # the first demo's images lost: a broken demo, not a crash or a camera-less file
        del f["data/demo_0/obs/agentview_image"]
    assert open_dataset(lost).camera == "agentview_image"
    demo = open_dataset(lost)[0]
    assert not demo.frames.any() and demo.frames.shape == (8, 16, 16, 3) and "unreadable frames" in demo.damaged[0][1]
    assert not open_dataset(lost).cue_frames(0).any()
    res = runner.invoke(app, ["audit", str(lost), "--out", str(tmp_path / "l"), "--no-model"])
    assert res.exit_code == 0, res.output
    first = pd.read_parquet(tmp_path / "l" / "scores.parquet").iloc[0]
    assert first["episode_index"] == 0 and first["is_anomaly"] and "unreadable frames" in first["reason"]
    res = runner.invoke(app, ["audit", str(path), "--out", str(tmp_path / "r"), "--model", str(tiny_model),
                              "--device", "cpu", "--json"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    assert np.isnan(table.set_index("episode_index").loc[5, "consistency"])  # a task with one demo
    assert np.isfinite(table["outcome"]).sum() == 5  # the objects' ends compared within the task of five


def test_a_missing_video_file_breaks_its_episodes_and_the_audit_goes_on(tiny_dataset, tiny_model, tmp_path):
    """Four episodes' frames in a video file that is not there (a partial download): they rank first as broken
    recordings, flagged, and the others are audited."""
    import shutil

    import pyarrow.parquet as pq

    src, _ = tiny_dataset
    ds = tmp_path / "partial"
    shutil.copytree(src, ds)
    meta = next((ds / "meta" / "episodes").rglob("*.parquet"))
    eps = pq.read_table(meta).to_pandas()
    lost = eps["episode_index"].isin([1, 4, 6, 9])
    eps.loc[lost, "videos/observation.images.main/file_index"] = 1  # file-001.mp4: never written
    eps.to_parquet(meta, index=False)
    res = runner.invoke(app, ["audit", str(ds), "--out", str(tmp_path / "r"), "--model", str(tiny_model),
                              "--device", "cpu"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    assert set(table["episode_index"][:4]) == {1, 4, 6, 9} and table["is_anomaly"][:4].all()
    assert (table["broken"][:4] == 1.0).all() and (table["broken"][4:] == 0).all()
    assert table["reason"][:4].str.startswith("broken: unreadable frames (").all(), table["reason"][:4].tolist()
    assert "file-001.mp4" in table["reason"][0] and not table["reference"][:4].any()
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["flag"]["broken_recordings"] == 4
    # One line for the file, naming the episodes it takes down, in the summary and in the terminal; the count line
    # tells the broken recordings from the demos flagged by their scores.
    lines = [w for w in summary["warnings"] if "file-001.mp4" in w]
    assert len(lines) == 1 and "4 episodes (1, 4, 6, 9) flagged as broken recordings" in lines[0], lines
    said = " ".join(res.output.split())
    assert "file-001.mp4 cannot be read" in said and "4 broken recordings" in said, res.output


def test_runs_of_episodes_read_as_ranges():
    from democheck.audit.modelfree import BROKEN
    from democheck.audit.summary import spans, unreadable_files

    assert spans([9, 3, 7, 8, 12, 13]) == "3, 7-9, 12-13" and spans([5]) == "5"
    found = [BROKEN("intact"), BROKEN("damaged", what="", files=[("v/a.mp4", "frame 9 is missing")]),
             BROKEN("damaged", what="", files=[("v/a.mp4", "bad packet")]),
             BROKEN("damaged", what="", files=[("v/b.mp4", "bad")])]
    assert unreadable_files(np.array([0, 10, 11, 12]), found) == [
        "v/a.mp4 cannot be read (frame 9 is missing): 2 episodes (10-11) flagged as broken recordings",
        "v/b.mp4 cannot be read (bad): 1 episode (12) flagged as broken recordings"]


def test_nan_in_a_lerobot_episode_is_repaired_reported_and_refused_where_nothing_would_report_it(
        tiny_dataset, tiny_model, tmp_path):
    """Three NaN actions in episode 2 of a LeRobot dataset: the reader carries the last finite value over them
    and says where; the audit ranks the demo first as broken; an audit of the cues alone (--no-actions), which
    decodes no demo and so could not report it, refuses the dataset with the same words."""
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    from democheck.data import open_dataset
    from democheck.errors import DatasetError

    src, _ = tiny_dataset
    ds = tmp_path / "nan"
    shutil.copytree(src, ds)
    data = next((ds / "data").rglob("*.parquet"))
    table = pq.read_table(data)
    actions = np.stack(table.column("action").to_pylist()).astype(np.float32)
    rows = np.flatnonzero(table.column("episode_index").to_numpy() == 2)
    actions[rows[3:6], 1] = np.nan
    column = pa.FixedSizeListArray.from_arrays(pa.array(actions.reshape(-1)), actions.shape[1])
    pq.write_table(table.set_column(table.column_names.index("action"), "action", column), data)
    demo = open_dataset(ds)[2]
    assert np.isfinite(demo.actions).all() and (demo.actions[3:6, 1] == actions[rows[2], 1]).all()
    assert [d.what for d in demo.damaged] == [f"NaN or infinite values in 'action' at 3 of {len(rows)} frames, 3-5"]
    assert demo.damaged[0].frames == 3 and not demo.damaged[0].file
    assert not open_dataset(ds)[1].damaged
    res = runner.invoke(app, ["audit", str(ds), "--out", str(tmp_path / "r"), "--model", str(tiny_model),
                              "--device", "cpu"])
    assert res.exit_code == 0, res.output
    scores = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    assert scores["episode_index"][0] == 2 and scores["is_anomaly"][0] and scores["reason"][0].startswith("broken: ")
    res = runner.invoke(app, ["audit", str(ds), "--out", str(tmp_path / "c"), "--model", str(tiny_model),
                              "--device", "cpu", "--no-actions"])
    assert res.exit_code == 2 and "episode 2 holds NaN or infinite values in 'action'" in res.output, res.output
    with pytest.raises(DatasetError, match="episode 2 holds NaN"):
        open_dataset(ds).strict()[2]


def test_audit_mismatch_and_fail_on(tiny_dataset, tiny_model, tmp_path):
    # Another image size is read at the model's, as its training read its own data.
    path = tmp_path / "big.hdf5"
    _write_robomimic(path, size=32)
    res = runner.invoke(app, ["audit", str(path), "--out", str(tmp_path / "big"), "--model", str(tiny_model),
                              "--device", "cpu"])
    assert res.exit_code == 0, res.output
    frames = json.loads((tmp_path / "big" / "summary.json").read_text())["frames"]
    assert frames == {"camera": [32, 32, 3], "model": [16, 16, 3], "resized": True, "count": 48}
    # Only the model reads the resized frames: the model-free checks score the camera's own, as without a model.
    res = runner.invoke(app, ["audit", str(path), "--out", str(tmp_path / "bare"), "--no-model"])
    assert res.exit_code == 0, res.output
    with_model, bare = (pd.read_parquet(tmp_path / r / "scores.parquet").set_index("episode_index").sort_index()
                        for r in ("big", "bare"))
    for check in ("view", "colours", "frame_jump", "frozen_video", "start", "end", "path"):
        assert np.allclose(with_model[check], bare[check], equal_nan=True), check
    path = tmp_path / "narrow.hdf5"
    _write_robomimic(path, joints=10)
    res = runner.invoke(app, ["audit", str(path), "--out", str(tmp_path / "r"), "--model", str(tiny_model)])
    assert res.exit_code == 2 and "states have 13 dimensions" in res.output and "democheck train" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "r").exists()
    res = runner.invoke(app, ["audit", str(tiny_dataset[0]), "--out", str(tmp_path / "r"), "--model",
                              str(tmp_path / "nope")])
    assert res.exit_code == 2 and "no such model folder" in res.output
    root, _ = tiny_dataset
    # --fail-on: status 3 when more demos are flagged than allowed, 0 otherwise.
    res = runner.invoke(app, ["audit", str(root), "--out", str(tmp_path / "a"), "--model", str(tiny_model),
                              "--fail-on", "12", "--device", "cpu", "--no-actions"])
    assert res.exit_code == 0, res.output
    assert "action_error" not in pd.read_parquet(tmp_path / "a" / "scores.parquet")  # the cue-only pass
    flagged = json.loads((tmp_path / "a" / "summary.json").read_text())["flagged"]
    if flagged:
        res = runner.invoke(app, ["audit", str(root), "--out", str(tmp_path / "b"), "--model", str(tiny_model),
                                  "--fail-on", str(flagged - 1), "--device", "cpu", "--no-actions"])
        assert res.exit_code == 3


def test_fail_on_trips_and_fpr_sets_the_flags(tiny_dataset, tiny_model, tmp_path):
    """A looser --fpr flags more demos; the CI gate trips on them; the lists hold the flagged and the rest."""
    root, _ = tiny_dataset
    counts = {}
    for fpr in ("0.01", "0.9"):
        out = tmp_path / fpr
        res = runner.invoke(app, ["audit", str(root), "--out", str(out), "--model", str(tiny_model), "--fpr", fpr,
                                  "--device", "cpu", "--drop-list", str(out.with_suffix(".drop")),
                                  "--keep-list", str(out.with_suffix(".keep"))])
        assert res.exit_code == 0, res.output
        summary = json.loads((out / "summary.json").read_text())
        counts[fpr] = summary["flagged"]
        table = pd.read_parquet(out / "scores.parquet")
        assert summary["flag"]["fpr"] == float(fpr)
        # fpr times the reference's size: what the flags cost were the unflagged demos clean
        assert summary["flag"]["expected_false_flags"] == pytest.approx(float(fpr) * table["reference"].sum(), abs=0.01)
        drop = json.loads(out.with_suffix(".drop").read_text())
        keep = json.loads(out.with_suffix(".keep").read_text())
        assert len(drop) == summary["flagged"] and sorted(drop + keep) == list(range(12)) and drop == sorted(drop)
        assert sorted(int(e) for e in (out / "suspects.txt").read_text().split()) == drop
    assert counts["0.9"] > counts["0.01"]
    res = runner.invoke(app, ["audit", str(root), "--out", str(tmp_path / "r"), "--model", str(tiny_model),
                              "--fpr", "0.9", "--fail-on", str(counts["0.9"] - 1), "--device", "cpu"])
    assert res.exit_code == 3 and f"{counts['0.9']} demos flagged" in res.output
    res = runner.invoke(app, ["audit", str(root), "--out", str(tmp_path / "x"), "--fpr", "1.5"])
    assert res.exit_code == 2 and "between 0 and 1" in res.output


class _ZeroController:
    """A controller that always predicts the normalised action 0."""

    def act(self, frames, state, z):
        return torch.zeros(*frames.shape[:2], 7)


def test_action_error_is_the_controllers_mse_and_ranks_a_planted_flailing_demo_first():
    from types import SimpleNamespace

    from democheck.audit.action_error import action_errors, controller_z
    from democheck.petnet.checkpoint import Normalisation

    rng = np.random.default_rng(3)
    eps = _episodes(n_tasks=3, per=5)
    demos = [SimpleNamespace(frames=np.zeros((40, 8, 8, 3), np.uint8), state=rng.normal(0, 1, (40, 17)).astype(np.float32),
                             actions=rng.normal(0, 0.1, (40, 7)).astype(np.float32)) for _ in range(len(eps))]
    demos[6].actions = rng.normal(0, 3.0, (40, 7)).astype(np.float32)  # flails
    norm = Normalisation(state_mean=[0.0] * 17, state_std=[1.0] * 17, action_mean=[0.0] * 7, action_std=[1.0] * 7)
    ckpt = SimpleNamespace(model=SimpleNamespace(controller=_ZeroController()), norm=norm,
                           config=SimpleNamespace(image_size=8))
    mu, var, _ = _posteriors(eps, rng)
    err = action_errors(iter(demos), ckpt, controller_z(_post(mu, var), eps["task"].to_numpy()), "cpu", steps=10, batch=4)
    t = np.linspace(0, 39, 10).round().astype(int)
    assert np.allclose(err, [np.mean(d.actions[t] ** 2) for d in demos], rtol=1e-5)
    table = score_table(eps, mu, var, err)
    assert table.iloc[0]["episode_index"] == 6 and "action_error" in table
    # No OCSVM here: the flag is the suspicion threshold alone, and only the flailing demo crosses it.
    assert table.loc[table["is_anomaly"], "episode_index"].tolist() == [6]


def test_controller_z_is_the_other_demos_posterior_or_the_demos_own():
    from democheck.audit.action_error import controller_z

    mu = np.array([[0.0], [2.0], [4.0], [9.0]])
    var = np.array([[1.0], [1.0], [1.0], [1.0]])
    z = controller_z(_post(mu, var), np.array(["a", "a", "a", "b"]))
    assert np.allclose(z[:, 0], [3.0, 2.0, 1.0, 9.0])  # leave-one-out means; b's lone demo keeps its own


def test_view_says_what_the_viewer_needs(tmp_path, monkeypatch):
    """No display: the commands for another machine and for a browser here, bound to this machine only; no ffmpeg:
    that the videos will not play, and how to get it."""
    import shutil as sh

    rrd = tmp_path / "report.rrd"
    rrd.write_bytes(b"")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    real = sh.which
    monkeypatch.setattr(sh, "which", lambda name, *a, **k: None if name == "ffmpeg" else real(name, *a, **k))
    res = runner.invoke(app, ["view", str(tmp_path)])
    assert res.exit_code == 0, res.output
    out = " ".join(res.output.split())
    assert "rerun --web-viewer --bind 127.0.0.1" in out and "no ffmpeg" in out and "apt-get install ffmpeg" in out
    res = runner.invoke(app, ["view", str(tmp_path / "nothing")])
    assert res.exit_code == 2 and "run democheck audit first" in res.output


def test_view_binds_the_viewer_to_this_machine_and_keeps_its_log_out_of_the_terminal(tmp_path, monkeypatch):
    import subprocess as sp

    rrd = tmp_path / "report.rrd"
    rrd.write_bytes(b"")
    monkeypatch.setenv("DISPLAY", ":99")
    started = []

    class Fake:
        def __init__(self, args, **kw):
            started.append((args, kw))

    monkeypatch.setattr(sp, "Popen", Fake)
    res = runner.invoke(app, ["view", str(tmp_path)])
    assert res.exit_code == 0, res.output
    (args, kw), = started
    assert args[1:] == ["--bind", "127.0.0.1", str(rrd)]
    assert kw["stdout"] is kw["stderr"] and kw["stdout"] not in (None, sp.PIPE) and kw["start_new_session"]
    assert "listening on 127.0.0.1" in " ".join(res.output.split())
    runner.invoke(app, ["view", str(tmp_path), "--bind", "0.0.0.0"])
    assert started[-1][0][1:3] == ["--bind", "0.0.0.0"]


def test_a_model_score_that_failed_its_test_is_reported_not_ranked(tiny_dataset, tiny_model, tmp_path):
    """A controller that explains held-out actions no better than their average: its action error stays in the
    table, leaves the ranking, and the audit says why.  Task uncertainty ranks only where the model is at least
    twice as unsure of the demos whose arm hardly moves as of the others (else of cues cut short, else by its
    training record)."""
    import shutil

    from democheck.audit.trust import untrusted
    from democheck.petnet.checkpoint import load_checkpoint

    assert untrusted(load_checkpoint().meta) == {}  # the shipped model passes both
    meta = {"metrics": {"final": {"val_mse": 0.3}, "task_sigma": {"val demos": 1.0, "still": 1.5}}}
    real = np.linspace(1.0, 2.0, 51)  # median 1.5
    assert "task_uncertainty" in untrusted(meta)  # by the means recorded at training: 1.5 < 2 x 1.0
    assert untrusted(meta, still=(np.full(8, 3.5), real)) == {}  # cut cues over twice as uncertain: it ranks
    why = untrusted(meta, still=(np.full(8, 2.5), real))["task_uncertainty"]
    assert "demos cut 10% of the way in: median task uncertainty 2.5, the same demos whole 1.5" in why
    assert "reported, not ranked" in why
    # Where the data holds demos whose arm hardly moves, they decide, whatever the cut cues say.
    assert "task_uncertainty" in untrusted(meta, (np.full(8, 3.5), real), idle=(np.full(3, 2.0), real))
    assert untrusted(meta, (np.full(8, 2.5), real), idle=(np.full(3, 3.1), real)) == {}
    assert "task_uncertainty" in untrusted(meta, (np.full(8, 2.5), real), idle=(np.full(1, 9.0), real))
    # The novelty and the consistency rank where the model reads demos played backwards as at least twice as
    # unusual as the same demos (median); unmeasured, they rank as the recipe says.
    left_out = untrusted(meta, backwards={"novelty": (np.full(8, 3.1), real), "consistency": (np.full(8, 2.9), real)})
    assert "novelty" not in left_out and "median consistency 2.9 backwards, 1.5 as recorded" in left_out["consistency"]
    assert not {"novelty", "consistency"} & set(untrusted(meta))
    src, _ = tiny_dataset
    model = tmp_path / "weak"
    shutil.copytree(tiny_model, model)
    config = json.loads((model / "config.json").read_text())
    config["metrics"]["final"]["val_mse"] = 1.09
    (model / "config.json").write_text(json.dumps(config))
    res = runner.invoke(app, ["audit", str(src), "--out", str(tmp_path / "r"), "--model", str(model),
                              "--device", "cpu"])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    ranked = summary["flag"]["scores"]
    assert "action_error" not in ranked
    for name in ("novelty", "consistency"):  # tested on the data, each ranks or the audit says why not
        assert (name in ranked) != any(f"its {name} is reported, not ranked" in w for w in summary["warnings"])
        test = summary["model_tests"][name]  # what the test read, whichever way it went
        assert test["demos"] > 0 and test["votes"] == (name in ranked) and test["backwards"] >= 0
    table = pd.read_parquet(tmp_path / "r" / "scores.parquet")
    assert np.isfinite(table["action_error"]).all()
    said = [w for w in summary["warnings"] if "error is reported, not ranked" in w]
    assert len(said) == 1 and "normalised error 1.1" in said[0], summary["warnings"]


def test_a_reference_too_small_for_the_rate_asked_for_is_said():
    """With n reference demos a conformal share is never under 1 / (n + 1): at --fpr 0.01 a reference of 40
    cannot calibrate the flag, and the audit says so; one of 200 can."""
    from democheck.audit.summary import warnings

    def table(n_ref):
        return pd.DataFrame({"task": ["push"] * 250, "reference": np.arange(250) < n_ref})

    said = [w for w in warnings(table(40), None, fpr=0.01) if "the reference holds 40 demos" in w]
    assert len(said) == 1 and "0.39 or more above" in said[0] and "--fpr 0.024 flags" in said[0], said
    assert "99 demos or more" in said[0]
    # ... and what it says is so: 0.39 above the most suspect reference demo is flagged at 0.01, 0.38 is not.
    from democheck.audit.flagging import conformal_p

    suspicion = np.r_[np.linspace(0, 2, 40), 2.39, 2.38]
    core = np.r_[np.ones(40, bool), False, False]
    assert (conformal_p(suspicion, core)[40:] <= 0.01).tolist() == [True, False]
    assert not [w for w in warnings(table(200), None, fpr=0.01) if "reference holds" in w]
    assert not [w for w in warnings(table(40), None, fpr=0.05) if "reference holds" in w]


def test_the_reports_suspects_read_ahead_give_the_demos_in_order(tiny_dataset):
    """The report reads the next suspect in a thread while it writes this one: the same demos, in order."""
    from democheck.data import open_dataset
    from democheck.viz.report import fit_frames
    from democheck.viz.suspects import Suspects

    ds = open_dataset(tiny_dataset[0])
    episodes = ds.episode_indices[::-1][:5]
    suspects = Suspects(ds, episodes)
    read = list(suspects)
    assert [d.episode_index for d in read] == episodes
    for demo, e in zip(read, episodes):  # shrunk to the recording's size as they are read
        assert np.array_equal(demo.frames, fit_frames(ds[e].frames)) and np.array_equal(demo.actions, ds[e].actions)
    assert list(Suspects(ds, [])) == []
    first = next(iter(suspects))  # a report that stops early leaves no reader behind
    assert first.episode_index == episodes[0]
