"""The novelty density: the epistemic part of PETNet's task variance."""

import json

import numpy as np
import pytest
import torch
from sklearn.covariance import LedoitWolf
from typer.testing import CliRunner

from democheck.cli import app
from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.errors import DemocheckError
from democheck.petnet.card import model_card
from democheck.petnet.checkpoint import load_checkpoint
from democheck.petnet.blocks import ModelConfig, cue_input
from democheck.petnet.model import build_model
from democheck.petnet.novelty import QUANTILE, conv_features, fit_novelty, stack_features
from democheck.petnet.finish import nonsense_cues
from democheck.petnet.train import TrainConfig, train

FAST = dict(batch_tasks=2, timesteps=4, val_every=5, ckpt_every=5, device="cpu")
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def arrays(tiny_dataset, tmp_path_factory):
    root, _ = tiny_dataset
    return build_cache(open_dataset(root), tmp_path_factory.mktemp("cache"))


def _cues(n: int, seed: int = 0, size: int = 16) -> np.ndarray:
    """Smooth random cues: a coarse random image blown up, so they share structure like real frames do."""
    coarse = np.random.default_rng(seed).integers(60, 200, (n, 2, size // 4, size // 4, 3))
    return coarse.repeat(4, axis=2).repeat(4, axis=3).astype(np.uint8)


def _scenes(n: int, seed: int, size: int = 32) -> np.ndarray:
    """Cues of one fixed textured table with an arm (a bright bar) and a cyan block somewhere else in every
    frame, and sensor noise: like a fixed camera's demos, which share their background."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    table = np.stack([110 + 40 * np.sin(xx / 3.0), 100 + 30 * np.cos(yy / 4.0), 80 + 2 * xx], -1)
    out = np.repeat(np.repeat(table[None, None], n, 0), 2, 1) + rng.normal(0, 3, (n, 2, size, size, 3))
    for i in range(n):
        for f in range(2):
            r = rng.integers(0, size - 4)
            out[i, f, r:r + 4, :rng.integers(size // 3, size)] = 235
            r, c = rng.integers(0, size - 5, 2)
            out[i, f, r:r + 5, c:c + 5] = (20, 220, 220)
    return np.clip(out, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("autoencoder", [None, 0])
def test_novelty_adds_variance_far_from_the_training_cues_and_nothing_else(autoencoder):
    torch.manual_seed(0)
    model = build_model(ModelConfig(image_size=32)).eval()
    train_cues, held = _scenes(300, seed=1), _scenes(60, seed=2)
    with torch.no_grad():
        before = model.encoder(cue_input(torch.from_numpy(held)))
    stats = fit_novelty(model, train_cues, held, CPU, autoencoder=autoencoder)
    assert model.cfg.novelty and stats["train_cues"] == 300 and stats["held_out_cues"] == 60
    # Forty passes over the training cues by default (300 cues, batches of 64: 188 steps), or none.
    assert model.cfg.novelty_autoencoder == (autoencoder is None)
    assert stats["autoencoder"]["steps"] == (188 if autoencoder is None else 0)
    black = np.zeros_like(held)
    with torch.no_grad():
        mu, var_task, var_novel = model.encoder.parts(cue_input(torch.from_numpy(held)))
        _, var_b = model.encoder(cue_input(torch.from_numpy(black)))
        _, _, novel_b = model.encoder.parts(cue_input(torch.from_numpy(black)))
    # The paper's head is untouched; the total is the head's variance plus the novelty part.
    assert torch.equal(mu, before[0]) and torch.equal(var_task, before[1])
    assert torch.equal(model.encoder(cue_input(torch.from_numpy(held)))[1], var_task + var_novel)
    # A held-out cue at the reference distance gets one prior's worth: 90% of them (QUANTILE) get less.
    ratio = (var_novel / model.encoder.prior_var).mean(1)
    assert (ratio <= 1 + 1e-5).float().mean().item() == pytest.approx(QUANTILE, abs=0.02)
    # A black cue is far from anything seen: many times the novelty of any held-out cue.
    assert (novel_b / model.encoder.prior_var).mean(1).min() > 5 * ratio.max()
    assert torch.equal(var_b, model.encoder.parts(cue_input(torch.from_numpy(black)))[1] + novel_b)
    assert var_b.sqrt().mean() > 2 * (var_task + var_novel).sqrt().mean()


@pytest.mark.parametrize("autoencoder,view", [(20, "last"), (20, "cue"), (0, "last"), (0, "cue")])
def test_distance_is_sklearn_mahalanobis_and_prior_is_the_variance_of_z(autoencoder, view):
    torch.manual_seed(1)
    model = build_model(ModelConfig(image_size=16)).eval()
    train_cues, held = _cues(200, seed=3), _cues(40, seed=4)
    stats = fit_novelty(model, train_cues, held, CPU, autoencoder=autoencoder, view=view)
    assert model.cfg.novelty_view == view and stats["view"] == view
    # The density is over the autoencoder's features where there is one, else the task encoder's own; of the
    # last frame in both places ("last") or of the cue as it is ("cue").
    own, mus, var_task = conv_features(model.encoder, train_cues, CPU)
    assert hasattr(model.encoder, "novelty_conv") == (autoencoder != 0)
    conv = model.encoder.novelty_conv if autoencoder else model.encoder.conv
    read = train_cues[:, [1, 1]] if view == "last" else train_cues
    feats = stack_features(conv, read, CPU)
    np.testing.assert_array_equal(feats, stack_features(conv, train_cues, CPU, view=view))
    assert np.array_equal(feats, own) == (autoencoder == 0 and view == "cue")
    lw = LedoitWolf().fit(feats.astype(np.float64))
    held_feats = stack_features(conv, held[:, [1, 1]] if view == "last" else held, CPU)
    want = lw.mahalanobis(held_feats.astype(np.float64))
    got = model.encoder.distance2(torch.from_numpy(held_feats)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-3)
    assert stats["d2_ref"] == pytest.approx(float(np.quantile(want, QUANTILE)))
    # The encoder reads the same view at scoring time: a cue's novelty part is its d2 over the reference.
    with torch.no_grad():
        _, _, var_novel = model.encoder.parts(cue_input(torch.from_numpy(held)))
    np.testing.assert_allclose((var_novel / model.encoder.prior_var).mean(1).numpy(), want / stats["d2_ref"],
                               rtol=1e-3)
    # The prior is z's variance over the training cues: the spread of their means plus their mean variance.
    np.testing.assert_allclose(model.encoder.prior_var.numpy(), mus.var(0) + var_task.mean(0), rtol=1e-5)


def test_the_last_view_reads_the_end_alone_and_old_models_the_cue():
    torch.manual_seed(2)
    model = build_model(ModelConfig(image_size=16)).eval()
    train_cues = _cues(120, seed=5)
    fit_novelty(model, train_cues, _cues(30, seed=6), CPU, autoencoder=10)
    cues = _cues(8, seed=7)
    other_start = cues.copy()
    other_start[:, 0] = _cues(8, seed=8)[:, 0]
    with torch.no_grad():
        novel = lambda c: model.encoder.parts(cue_input(torch.from_numpy(c)))[2]  # noqa: E731
        assert torch.equal(novel(cues), novel(other_start))  # the first frame does not count
        model.cfg.novelty_view = "cue"  # a model fitted before the view was a choice reads the whole cue
        assert not torch.equal(novel(cues), novel(other_start))
    assert ModelConfig().novelty_view == "cue"  # what a config.json without the field means
    with pytest.raises(ValueError, match="unknown novelty view"):  # a checkpoint's loader says which file
        ModelConfig(novelty_view="first")
    with pytest.raises(DemocheckError, match="unknown novelty view"):
        fit_novelty(model, train_cues, train_cues, CPU, autoencoder=0, view="first")


def test_the_end_state_counts_where_the_arm_ended_and_nothing_else():
    """With end states the density is one Gaussian over the image features and the standardised last state: a
    demo whose frames look ordinary but whose arm ended far from where every training demo's did is unfamiliar
    (an arm flung out of view leaves an ordinary-looking last frame), and one that ended where they did is not."""
    torch.manual_seed(3)
    cfg = ModelConfig(image_size=16, state_dim=3)
    model = build_model(cfg).eval()
    rng = np.random.default_rng(9)
    train_cues, held = _cues(200, seed=10), _cues(40, seed=11)
    ends = lambda n: rng.normal([0.2, -0.1, 5.0], [0.05, 0.05, 0.5], (n, 3)).astype(np.float32)  # noqa: E731
    train_ends, held_ends = ends(200), ends(40)
    stats = fit_novelty(model, train_cues, held, CPU, autoencoder=10, train_states=train_ends,
                        held_out_states=held_ends)
    assert model.cfg.novelty_state and stats["end_state"]
    np.testing.assert_allclose(model.encoder.end_state_mean.numpy(), train_ends.mean(0), rtol=1e-5)
    np.testing.assert_allclose(model.encoder.end_state_scale.numpy(), train_ends.std(0), rtol=1e-4)
    # The d2 is sklearn's over both parts.
    feats = stack_features(model.encoder.novelty_conv, train_cues, CPU, view="last").astype(np.float64)
    both = lambda f, e: np.concatenate([f, (e - train_ends.mean(0)) / train_ends.std(0)], 1)  # noqa: E731
    lw = LedoitWolf().fit(both(feats, train_ends.astype(np.float64)))
    held_feats = stack_features(model.encoder.novelty_conv, held, CPU, view="last").astype(np.float64)
    want = lw.mahalanobis(both(held_feats, held_ends.astype(np.float64)))
    assert stats["d2_ref"] == pytest.approx(float(np.quantile(want, QUANTILE)), rel=1e-3)
    flung = held_ends.copy()
    flung[:, 0] += 1.0  # 20 training SDs away, the frames the same
    with torch.no_grad():
        novel = lambda e: (model.encoder.parts(cue_input(torch.from_numpy(held)), torch.from_numpy(e))[2]  # noqa: E731
                           / model.encoder.prior_var).mean(1).numpy()
        np.testing.assert_allclose(novel(held_ends), want / stats["d2_ref"], rtol=1e-3)
        assert novel(flung).min() > 10 * novel(held_ends).max()
        with pytest.raises(ValueError, match="end_state"):  # such a model cannot be read without them
            model.encoder.parts(cue_input(torch.from_numpy(held)))
    assert not ModelConfig().novelty_state  # what a config.json without the field means
    # Refitted without end states, the density is the image features' alone again, of their size.
    fit_novelty(model, train_cues, held, CPU, autoencoder=10)
    assert not model.cfg.novelty_state and model.encoder.feature_mean.shape == (feats.shape[1],)
    assert not hasattr(model.encoder, "end_state_mean")
    # A dataset with no state dimensions (a robomimic file without state keys) keeps the frame alone.
    fit_novelty(model, train_cues, held, CPU, autoencoder=10, train_states=np.zeros((200, 0), np.float32),
                held_out_states=np.zeros((40, 0), np.float32))
    assert not model.cfg.novelty_state
    with pytest.raises(DemocheckError, match="both"):
        fit_novelty(model, train_cues, held, CPU, autoencoder=0, train_states=train_ends)


def test_fit_refuses_a_tecnet_and_too_few_cues():
    with pytest.raises(DemocheckError, match="PETNet"):
        fit_novelty(build_model(ModelConfig(model_type="tecnet", image_size=16)), _cues(5), _cues(2), CPU)
    with pytest.raises(DemocheckError, match="at least 2"):
        fit_novelty(build_model(ModelConfig(image_size=16)), _cues(1), _cues(2), CPU)


def test_training_fits_it_and_the_checkpoint_keeps_it_bit_for_bit(arrays, tmp_path):
    card = lambda meta: model_card("m", meta)  # noqa: E731
    result = train(arrays, tmp_path / "m", TrainConfig(steps=4, seed=0, **FAST), card=card)
    ckpt = load_checkpoint(tmp_path / "m")
    assert ckpt.config.novelty and ckpt.meta["novelty"]["train_cues"] > 0
    assert ckpt.config.novelty_state and ckpt.meta["novelty"]["end_state"]  # the density reads where demos ended
    cue, end = torch.from_numpy(arrays.cue(np.arange(6))), torch.from_numpy(arrays.end_state(np.arange(6)))
    with torch.no_grad():
        a, b = result.model.eval().encoder.parts(cue_input(cue), end), ckpt.model.encoder.parts(cue_input(cue), end)
    assert all(torch.equal(x, y) for x, y in zip(a, b)) and (a[2] > 0).all()
    assert "novelty density" in (tmp_path / "m" / "README.md").read_text()
    # The card's nonsense table is measured with both parts: a black cue is more uncertain than real ones.
    sig = ckpt.meta["metrics"]["task_sigma"]
    real = sig.get("val demos", sig.get("train demos"))
    assert sig["black"] > real and sig["grey"] > real

    plain = train(arrays, tmp_path / "plain", TrainConfig(steps=4, seed=0, novelty=False, **FAST), card=card)
    assert not plain.config.novelty and "novelty" not in load_checkpoint(tmp_path / "plain").meta
    assert "the paper's head alone" in (tmp_path / "plain" / "README.md").read_text()
    # Fine-tuning drops the starting model's density (its weights change) and fits a new one.
    tuned = train(arrays, tmp_path / "ft", TrainConfig(steps=2, seed=0, init=str(tmp_path / "m"), **FAST))
    assert tuned.config.novelty


def test_fit_novelty_cli_adds_it_to_a_trained_model(tiny_dataset, tmp_path):
    root, _ = tiny_dataset
    arrays = build_cache(open_dataset(root), tmp_path / "cache")
    train(arrays, tmp_path / "plain", TrainConfig(steps=3, seed=0, novelty=False, **FAST))
    args = ["fit-novelty", str(tmp_path / "plain"), "--data", str(root), "--out", str(tmp_path / "nov"),
            "--device", "cpu", "--cache-dir", str(tmp_path / "cache")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "reference d2" in res.output and "mean sigma: black" in res.output
    before, after = load_checkpoint(tmp_path / "plain"), load_checkpoint(tmp_path / "nov")
    assert after.config.novelty and not before.config.novelty
    for k, v in before.model.state_dict().items():  # the weights are the same; only the density is new
        assert torch.equal(v, after.model.state_dict()[k]), k
    doc = json.loads((tmp_path / "nov" / "config.json").read_text())
    assert doc["novelty"]["command"] and doc["reference"]["ocsvm"]  # how it was made, and the audit refitted
    real, end = arrays.cue(np.arange(8)), torch.from_numpy(arrays.end_state(np.arange(8)))
    with torch.no_grad():
        _, var_real = after.model.encoder(cue_input(torch.from_numpy(real)), end)
        for name, cues in nonsense_cues(real, np.random.default_rng(0)).items():
            if name in ("black", "white", "grey", "noise"):
                _, var = after.model.encoder(cue_input(torch.from_numpy(cues)), end)
                assert var.sqrt().mean() > var_real.sqrt().mean(), name
    assert after.config.novelty_state  # where each demo ended is read too, unless asked not to
    frame_only = [str(tmp_path / "frame") if a == str(tmp_path / "nov") else a for a in args]
    res = CliRunner().invoke(app, frame_only + ["--no-end-state"])
    assert res.exit_code == 0, res.output
    assert not load_checkpoint(tmp_path / "frame").config.novelty_state
    # The same folder again needs --force; a TecNets model and the wrong data are refused in one line.
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "already exists" in res.output
    train(arrays, tmp_path / "tec", TrainConfig(model_type="tecnet", steps=2, seed=0, **FAST))
    res = CliRunner().invoke(app, ["fit-novelty", str(tmp_path / "tec"), *args[2:4], "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "PETNet" in res.output
