"""An interrupted audit continues with ``--resume`` from the shards it finished: the same table as a run that never
stopped, without decoding those shards again."""

from __future__ import annotations

import json
from dataclasses import replace

import pandas as pd
import pytest

from democheck.errors import DemocheckError


class Stop(Exception):
    """What a Ctrl-C or a kill is to the audit: it stops where it is."""


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from democheck.sim.suite import generate
    from tests.conftest import TINY

    root = tmp_path_factory.mktemp("resume") / "d"
    generate(replace(TINY, seed=6, demos_per_task=6, steps=16, defects=(("idle", 1),)), root, workers=1)
    return root


@pytest.mark.parametrize("with_model", [False, True])
def test_an_audit_stopped_half_way_resumes_to_the_same_table(data, tmp_path, monkeypatch, tiny_model, with_model):
    from democheck.audit import shards
    from democheck.data import video
    from democheck.workflows import audit_dataset

    monkeypatch.setattr(shards, "SHARD", 4)  # 24 demos: six shards of the decoding pass
    monkeypatch.setattr(shards, "CUE_SHARD", 8)  # and three of the cue pass
    options = {"model": tiny_model, "device": "cpu"} if with_model else {"no_model": True}
    whole = tmp_path / "whole"
    before = video.frames_decoded
    audit_dataset(data, whole, **options)
    every = video.frames_decoded - before
    stage = "actions" if with_model else "decoding"

    def stop_half_way(at: str, done: int, total: int, info: str = "") -> None:
        if at.startswith(stage) and done >= total // 2:
            raise Stop

    out = tmp_path / "r"
    with pytest.raises(Stop):
        audit_dataset(data, out, on_progress=stop_half_way, **options)
    work = tmp_path / ".r.partial"
    kept = sorted(p.name for p in work.glob("*.pkl"))
    # the two shards done before it stopped (the third was on its last demo), after the cue pass's
    cues = [f"cues-0-0000{i}.pkl" for i in range(3)] if with_model else []
    assert not out.exists() and kept == cues + ["decode-0-00000.pkl", "decode-0-00001.pkl"], kept
    with pytest.raises(DemocheckError, match="--resume"):  # an interrupted audit is not silently discarded
        audit_dataset(data, out, **options)
    before = video.frames_decoded
    audit_dataset(data, out, resume=True, **options)
    saved = every - (video.frames_decoded - before)
    # the two shards' frames; with a model, also the first and last frames of the 24 cues (a seek each)
    assert saved == 2 * 4 * 16 if not with_model else saved >= 2 * 4 * 16 + 2 * 24
    a, b = pd.read_parquet(whole / "scores.parquet"), pd.read_parquet(out / "scores.parquet")
    assert a.columns.equals(b.columns)
    for col in a.columns:
        assert a[col].equals(b[col]), col
    assert not work.exists()  # written: nothing left to resume


def test_resume_refuses_the_work_of_another_audit(data, tmp_path, tiny_dataset):
    from democheck.workflows import audit_dataset

    out = tmp_path / "r"
    with pytest.raises(Stop):
        audit_dataset(data, out, no_model=True, on_progress=lambda *a: (_ for _ in ()).throw(Stop))
    journal = json.loads((tmp_path / ".r.partial" / "journal.json").read_text())
    assert journal["actions"] is True and journal["model"] is None
    with pytest.raises(DemocheckError, match="other data or options"):
        audit_dataset(tiny_dataset[0], out, no_model=True, resume=True)
    audit_dataset(data, out, no_model=True, force=True)  # --force starts over
    assert (out / "scores.parquet").exists()


def test_a_shard_file_names_no_other_code_to_run(data, tmp_path):
    """The shards are unpickled into numpy's and democheck's classes alone: a planted file that would run a command
    is refused with one line."""
    import os
    import pickle

    from democheck.workflows import audit_dataset

    out = tmp_path / "r"
    with pytest.raises(Stop):
        audit_dataset(data, out, no_model=True, on_progress=lambda *a: (_ for _ in ()).throw(Stop))

    class Run:
        def __reduce__(self):
            return os.system, ("touch planted",)

    (tmp_path / ".r.partial" / "decode-0-00000.pkl").write_bytes(pickle.dumps([Run()]))
    with pytest.raises(DemocheckError, match="not a shard this audit wrote"):
        audit_dataset(data, out, no_model=True, resume=True)
    assert not (tmp_path / "planted").exists() and not os.path.exists("planted")
