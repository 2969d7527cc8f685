import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from democheck.cli import app
from democheck.errors import DemocheckError
from democheck.petnet.checkpoint import load_checkpoint
from democheck.evaluate.dagger import DaggerConfig, MixedPolicy, dagger

FAST = dict(rounds=2, steps=3, batch_tasks=2, timesteps=2, workers=1, device="cpu")


class Counter:
    def __init__(self, value):
        self.value, self.calls = value, 0

    def act(self):
        self.calls += 1
        return np.full(2, self.value, np.float32)


def test_mixed_policy_labels_every_step_with_the_expert():
    expert, learner = Counter(1.0), Counter(-1.0)
    policy = MixedPolicy(learner.act, expert, beta=0.25, seed=0)
    acted = np.array([policy.act()[0] for _ in range(400)])
    assert expert.calls == 400 and len(policy.labels) == 400 and all(l[0] == 1.0 for l in policy.labels)
    assert 0.15 < (acted == 1.0).mean() < 0.35  # the expert's share of the executed steps is about beta
    assert np.array_equal(MixedPolicy(learner.act, expert, 0.0, 0).act(), [-1.0, -1.0])


def test_dagger_trains_only_the_controller_and_keeps_the_audit(tiny_dataset, tiny_model, tmp_path):
    root, _ = tiny_dataset
    base = load_checkpoint(tiny_model)
    s = dagger(tiny_model, root, tmp_path / "d", DaggerConfig(**FAST))
    new = load_checkpoint(tmp_path / "d")
    enc = base.model.encoder.state_dict()
    assert all(torch.equal(v, enc[k]) for k, v in new.model.encoder.state_dict().items())
    ctl = base.model.controller.state_dict()
    assert any(not torch.equal(v, ctl[k]) for k, v in new.model.controller.state_dict().items())
    assert new.meta["reference"] == base.meta["reference"]  # the stored score scales and OCSVM still hold
    assert [h["round"] for h in s["history"]] == [1, 2]
    assert all(h["rollouts"] == 2 and np.isfinite(h["recovery_mse"]) for h in s["history"])  # 2 training tasks
    assert new.meta["recovery"]["history"] == s["history"]
    assert "## Recovery training" in (tmp_path / "d" / "README.md").read_text()
    assert not (tmp_path / ".d.partial").exists()


def test_dagger_resume_reaches_the_uninterrupted_weights(tiny_dataset, tiny_model, tmp_path):
    root, _ = tiny_dataset
    cfg = DaggerConfig(**FAST)
    dagger(tiny_model, root, tmp_path / "full", cfg)

    def killed_in_round_two(text):
        if text.startswith("round 2/"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        dagger(tiny_model, root, tmp_path / "cut", cfg, on_stage=killed_in_round_two)
    with pytest.raises(DemocheckError, match="--resume"):
        dagger(tiny_model, root, tmp_path / "cut", cfg)
    dagger(tiny_model, root, tmp_path / "cut", cfg, resume=True)
    a, b = load_checkpoint(tmp_path / "full").model.state_dict(), load_checkpoint(tmp_path / "cut").model.state_dict()
    assert all(torch.equal(v, b[k]) for k, v in a.items())


def test_dagger_cli_and_its_errors(tiny_dataset, tiny_model, tmp_path):
    root, _ = tiny_dataset
    args = ["dagger", str(tiny_model), "--data", str(root), "--set", "rounds=1", "--set", "steps=2", "--set",
            "batch_tasks=2", "--set", "timesteps=2", "--workers", "1", "--device", "cpu"]
    res = CliRunner().invoke(app, args + ["--out", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    recovery = json.loads((tmp_path / "d" / "config.json").read_text())["recovery"]
    assert recovery["config"]["rounds"] == 1 and recovery["config"]["beta"] == 0.3  # the shipped recipe's
    assert recovery["recipe"]["source"] == "dagger" and "rounds=1" in recovery["recipe"]["set"]
    res = CliRunner().invoke(app, args + ["--out", str(tmp_path / "e"), "--set", "beta=1.5"])
    assert res.exit_code == 2 and "probability" in res.output
    for bad, words in (("betta=0.5", "unknown key betta"), ("rounds=two", "rounds must be int"),
                       ("rounds", "key=value")):
        res = CliRunner().invoke(app, args + ["--out", str(tmp_path / "e"), "--set", bad])
        assert res.exit_code == 2 and words in res.output and "Traceback" not in res.output, res.output
    res = CliRunner().invoke(app, args + ["--out", str(tmp_path / "e"), "--recipe", "nonesuch"])
    assert res.exit_code == 2 and "no recovery recipe 'nonesuch'; known: dagger" in res.output
    res = CliRunner().invoke(app, args + ["--out", str(tmp_path / "e"), "--data", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "nowhere" in res.output and "Traceback" not in res.output


def test_dagger_trains_a_tecnets_controller_too(tiny_dataset, tmp_path):
    from democheck.petnet.model import TecNet
    from democheck.petnet.train import TrainConfig
    from democheck.workflows import train_model

    root, _ = tiny_dataset
    train_model(root, tmp_path / "tec", TrainConfig(model_type="tecnet", steps=2, batch_tasks=2, timesteps=2,
                                                    device="cpu"), cache_dir=tmp_path / "cache")
    s = dagger(tmp_path / "tec", root, tmp_path / "d", DaggerConfig(**{**FAST, "rounds": 1}))
    assert isinstance(load_checkpoint(tmp_path / "d").model, TecNet) and np.isfinite(s["history"][0]["demo_mse"])
