"""The closed-loop meta-test (democheck eval)."""

import json
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from democheck.cli import app
from democheck.evaluate.meta_test import sigma_quartiles, wilson
from democheck.evaluate.rollout import ControllerPolicy
from democheck.petnet.checkpoint import Normalisation
from democheck.sim import scene
from democheck.sim.catalog import make_tasks
from democheck.sim.env import SUCCESS_STEPS, Layout, PushEnv
from democheck.sim.variants import record_demo

runner = CliRunner()


class _StubController:
    """Returns a constant normalised action whatever it sees; records what it was given."""

    def __init__(self, value):
        self.value = value
        self.seen = []

    def act(self, frames, state, z):
        self.seen.append((tuple(frames.shape), tuple(state.shape), tuple(z.shape), frames.dtype))
        return torch.full((frames.shape[0], frames.shape[1], 7), self.value)


def _identity_norm():
    return Normalisation([0.0] * 17, [1.0] * 17, [0.0] * 7, [2.0] * 7)


def test_rollout_with_a_stub_controller_shapes_and_success_rule():
    task = make_tasks(2, 0, 0, seed=0)[0]
    env = PushEnv(task, image_size=16)
    stub = _StubController(0.8)
    policy = ControllerPolicy(env, SimpleNamespace(controller=stub), _identity_norm(), np.zeros(10))
    rec = record_demo(env, policy.act, 12, seed=1)
    assert rec["frames"].shape == (12, 16, 16, 3) and rec["state"].shape == (12, 17) and rec["actions"].shape == (12, 7)
    # The controller saw one uint8 frame, the state and z each step; its output was un-normalised and clipped.
    assert stub.seen[0] == ((1, 1, 16, 16, 3), (1, 1, 17), (1, 10), torch.uint8) and len(stub.seen) == 12
    np.testing.assert_allclose(rec["actions"], 1.0)  # 0.8 * std 2 = 1.6, clipped to the torque limit
    assert not rec["success"]  # nothing was pushed
    # The success rule: the target inside the goal on SUCCESS_STEPS steps.
    home = Layout((float(scene.GOAL_XY[0]), 0.0, 0.0), (0.45, 0.2, 0.0), tuple(scene.ARM_HOME))
    still = ControllerPolicy(env, SimpleNamespace(controller=_StubController(0.0)), _identity_norm(), np.zeros(10))
    assert not record_demo(env, still.act, SUCCESS_STEPS - 1, layout=home)["success"]
    assert record_demo(env, still.act, SUCCESS_STEPS, layout=home)["success"]


def test_wilson_interval_and_quartiles():
    lo, hi = wilson(72, 100)
    assert lo == pytest.approx(0.6251, abs=1e-3) and hi == pytest.approx(0.7986, abs=1e-3)  # by hand: centre 0.7119, half 0.0867
    assert wilson(0, 10)[0] == pytest.approx(0.0, abs=1e-12)
    sigma = np.arange(8.0)
    success = np.array([1, 1, 1, 0, 1, 0, 0, 0], bool)
    q = sigma_quartiles(sigma, success)
    assert [r["n"] for r in q] == [2, 2, 2, 2]
    assert [r["success_rate"] for r in q] == [1.0, 0.5, 0.5, 0.0]


def test_eval_cli_end_to_end_on_a_tiny_suite(tiny_dataset, tiny_model, tmp_path):
    root, summary = tiny_dataset
    out = tmp_path / "eval"
    res = runner.invoke(app, ["eval", str(tiny_model), "--data", str(root), "--out", str(out), "--split", "train",
                              "--trials", "2", "--workers", "1", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "eval.json").read_text())
    n_tasks = summary["tasks"]["train"]
    assert doc["n_trials"] == 2 * n_tasks and doc["tasks"] == n_tasks
    for key in ("success_rate", "ci95", "per_task", "flagged", "unflagged", "expert", "sigma_quartiles"):
        assert key in doc
    assert doc["flagged"]["n"] + doc["unflagged"]["n"] == doc["n_trials"]
    trials = pd.read_parquet(out / "trials.parquet")
    assert len(trials) == doc["n_trials"] and trials["task_uncertainty"].gt(0).all()
    assert doc["success_rate"] == pytest.approx(trials["success"].mean())
    assert "democheck eval" in (out / "eval.md").read_text()
    from tests.test_audit import _read_rrd

    ents = _read_rrd(out / "eval.rrd")
    kept = [e for e in ents if e.startswith("/rollouts/")]
    assert "/eval" in ents and any(e.endswith("/video") for e in kept) and any(e.endswith("/actions") for e in kept)
    # Same seed, same trials: the cues and layouts are drawn from the seed.
    out2 = tmp_path / "eval2"
    runner.invoke(app, ["eval", str(tiny_model), "--data", str(root), "--out", str(out2), "--split", "train",
                        "--trials", "2", "--workers", "1", "--device", "cpu"])
    t2 = pd.read_parquet(out2 / "trials.parquet")
    assert trials["cues"].map(list).tolist() == t2["cues"].map(list).tolist()
    assert trials["final_distance"].tolist() == t2["final_distance"].tolist()


def test_eval_refuses_a_split_without_demos(tiny_dataset, tiny_model, tmp_path):
    root, _ = tiny_dataset
    res = runner.invoke(app, ["eval", str(tiny_model), "--data", str(root), "--out", str(tmp_path / "e"),
                              "--split", "nope", "--workers", "1"])
    assert res.exit_code == 2 and "no clean demos" in res.output


def test_eval_gate_reports_executed_refused_and_after_asking(tiny_dataset, tiny_model, tmp_path):
    from democheck.data import open_dataset
    from democheck.evaluate.meta_test import meta_test
    from democheck.petnet.checkpoint import load_checkpoint
    from democheck.petnet.gate import Gate

    root, _ = tiny_dataset
    out = tmp_path / "eval"
    res = runner.invoke(app, ["eval", str(tiny_model), "--data", str(root), "--out", str(out), "--split", "train",
                              "--trials", "3", "--workers", "1", "--device", "cpu", "--gate", "--gate-cues", "3"])
    assert res.exit_code == 0, res.output
    assert "run-time gate" in (out / "eval.md").read_text()
    cli = json.loads((out / "eval.json").read_text())["gate"]
    assert cli["false_refusal"] == 0.05 and cli["max_cues"] == 3 and cli["reference_cues"] > 0
    # A gate just below every single cue's uncertainty refuses each first cue; two or three cues narrow the
    # posterior by up to 1/sqrt(3), so some trials are acted on after asking and rolled out again.
    ckpt, ds = load_checkpoint(tiny_model), open_dataset(root)
    first = pd.read_parquet(out / "trials.parquet")["task_uncertainty"].min()
    gate = Gate(threshold=0.9 * first, false_refusal=0.05, reference_cues=1, max_cues=3)
    result = meta_test(ckpt, ds, split="train", trials=3, workers=1, gate=gate)
    trials, g = result.trials, result.summary["gate"]
    refused, acted = trials["refused"].to_numpy(bool), trials["gate_acted"].to_numpy(bool)
    assert refused.all() and g["refused_share"] == 1.0 and g["executed"]["n"] == 0
    assert g["refused_would_have"]["n"] == len(trials)
    assert g["after_asking"]["n"] == acted.sum() > 0 and g["still_refused"] == (~acted).sum()
    assert (trials["asked"] >= 1).all() and (trials["asked"] <= 2).all()
    assert trials.loc[acted, "success_after_asking"].notna().all()
    assert (trials.loc[acted, "gate_uncertainty"] <= gate.threshold).all()
    assert (trials.loc[~acted, "gate_uncertainty"] > gate.threshold).all()


def test_the_gate_example_runs(tiny_dataset, tiny_model):
    import subprocess
    import sys
    from pathlib import Path

    root, _ = tiny_dataset
    example = Path(__file__).resolve().parent.parent / "examples" / "gate_a_cue.py"
    res = subprocess.run([sys.executable, str(example), str(root), "--model", str(tiny_model), "--false-refusal",
                          "0.5"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "a covered camera's cue" in res.stdout and "pushed on a new layout" in res.stdout
