"""democheck clean: the flagged demos go, everything else stays as it was, re-indexed, with meta/ consistent."""

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from democheck.cli import app
from democheck.data import open_dataset

runner = CliRunner()


@pytest.fixture(scope="module")
def audited(tmp_path_factory):
    """A tiny suite (4 tasks x 6 demos) with an idle and a random demo planted, audited without a model."""
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    root = tmp_path_factory.mktemp("clean") / "data"
    generate(replace(TINY, seed=5, demos_per_task=6, steps=60, defects=(("idle", 1), ("random", 1))), root, workers=1)
    report = root.with_name("report")
    res = runner.invoke(app, ["audit", str(root), "--out", str(report), "--no-model"])
    assert res.exit_code == 0, res.output
    return root, report


def test_clean_drops_exactly_the_flagged_planted_demos_and_keeps_the_rest_bit_for_bit(audited, tmp_path):
    root, report = audited
    src = open_dataset(root)
    planted = src.episodes.index[src.episodes["label"].fillna("clean") != "clean"].tolist()
    assert len(planted) == 2
    out = tmp_path / "clean"
    res = runner.invoke(app, ["clean", str(root), "--report", str(report), "--out", str(out)])
    assert res.exit_code == 0, res.output
    got = open_dataset(out)
    kept = [e for e in src.episode_indices if e not in planted]
    assert got.episode_indices == list(range(len(kept))) and len(got) == len(src) - 2
    assert (got.episodes["label"].fillna("clean") == "clean").all()  # the sidecar came along, renumbered
    for new, old in enumerate(kept):
        a, b = src[old], got[new]
        assert a.task == b.task and np.array_equal(a.frames, b.frames)
        assert np.array_equal(a.actions, b.actions) and np.array_equal(a.state, b.state)
    # meta/: totals, the episodes table's rows, pooled statistics that match the kept data.
    info = json.loads((out / "meta/info.json").read_text())
    eps = pd.read_parquet(out / "meta/episodes/chunk-000/file-000.parquet")
    assert info["total_episodes"] == len(kept) and info["total_frames"] == int(eps["length"].sum())
    assert (eps["dataset_from_index"].to_numpy()[1:] == eps["dataset_to_index"].to_numpy()[:-1]).all()
    data = pd.concat([pd.read_parquet(f) for f in sorted((out / "data").rglob("*.parquet"))])
    assert data["index"].tolist() == list(range(len(data))) and sorted(data["episode_index"].unique()) == list(
        range(len(kept)))
    stats = json.loads((out / "meta/stats.json").read_text())
    actions = np.concatenate([got[e].actions for e in got.episode_indices]).astype(np.float64)
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(0), atol=1e-5)
    np.testing.assert_allclose(stats["action"]["std"], actions.std(0), atol=1e-4)
    assert stats["action"]["count"] == [len(actions)]
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # written atomically
    # The cleaned dataset audits like any other.
    res = runner.invoke(app, ["audit", str(out), "--out", str(tmp_path / "again"), "--no-model"])
    assert res.exit_code == 0, res.output


def test_clean_other_choices_and_refusals(audited, tmp_path):
    root, report = audited
    res = runner.invoke(app, ["clean", str(root), "--report", str(report), "--out", str(tmp_path / "t"),
                              "--drop", "top:5"])
    assert res.exit_code == 0 and len(open_dataset(tmp_path / "t")) == len(open_dataset(root)) - 5
    listed = tmp_path / "drop.json"
    listed.write_text("[0, 1, 2]")
    res = runner.invoke(app, ["clean", str(root), "--report", str(report), "--out", str(tmp_path / "l"),
                              "--drop", f"list:{listed}"])
    assert res.exit_code == 0 and open_dataset(tmp_path / "l").episodes["label"].notna().all()
    # A report made on another dataset, a drop that is not one, an existing output.
    other = tmp_path / "t"
    res = runner.invoke(app, ["clean", str(other), "--report", str(report), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "another dataset" in res.output and not (tmp_path / "x").exists()
    res = runner.invoke(app, ["clean", str(root), "--report", str(report), "--out", str(tmp_path / "x"),
                              "--drop", "worst"])
    assert res.exit_code == 2 and "one of flagged, fpr:X, top:K, list:FILE" in res.output
    # fpr:X flags what the audit would at --fpr X: more as X grows, the report's own flags at its level.
    from democheck.workflows import episodes_to_drop

    assert episodes_to_drop(report, "fpr:0.01") == episodes_to_drop(report, "flagged")
    assert len(episodes_to_drop(report, "fpr:0.5")) >= len(episodes_to_drop(report, "fpr:0.01"))
    res = runner.invoke(app, ["clean", str(root), "--report", str(report), "--out", str(tmp_path / "t")])
    assert res.exit_code == 2 and "already exists" in res.output
