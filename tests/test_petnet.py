import pickle
from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from democheck.cli import app
from democheck.data import open_dataset
from democheck.data.cache import build_cache
from democheck.errors import DemocheckError
from democheck.petnet.checkpoint import CheckpointError, Normalisation, load_checkpoint
from democheck.petnet.batches import Batches, augment, random_shift, task_rows, to_device
from democheck.petnet.blocks import ModelConfig, cue_input
from democheck.petnet.model import PETNet, TecNet, build_model, hinge_embedding_loss
from democheck.petnet.posterior import product_of_gaussians
from democheck.petnet.regularisers import broken_cue_loss, broken_cues
from democheck.petnet.train import TrainConfig, objective, train


def losses(model, batch, tc, sample=True, teacher=None):
    return objective(model, batch, tc, sample=sample, teacher=teacher)

FAST = dict(batch_tasks=2, timesteps=4, val_every=5, ckpt_every=5, device="cpu")


@pytest.fixture(scope="module")
def arrays(tiny_dataset, tmp_path_factory):
    root, _ = tiny_dataset
    return build_cache(open_dataset(root), tmp_path_factory.mktemp("cache"))


@pytest.mark.parametrize("model_type", ["petnet", "tecnet"])
def test_shapes_and_positivity(model_type):
    cfg = ModelConfig(model_type=model_type, image_size=32)
    model = build_model(cfg)
    cue = torch.randint(0, 256, (3, 2, 32, 32, 3), dtype=torch.uint8)
    frames = torch.randint(0, 256, (3, 5, 32, 32, 3), dtype=torch.uint8)
    act, emb, var = model(cue, frames, torch.randn(3, 5, 17))
    assert act.shape == (3, 5, 7) and torch.isfinite(act).all()
    if model_type == "petnet":
        assert emb.shape == (3, 10) and var.shape == (3, 10)
        assert (var >= cfg.var_floor).all()
        mu, var2 = model.task_posterior(cue[:, None].expand(3, 4, *cue.shape[1:]))
        assert mu.shape == (3, 10) and torch.allclose(var2, var / 4, rtol=1e-5)  # 4 identical cues: var / 4
    else:
        assert emb.shape == (3, 20) and torch.allclose(emb.norm(dim=-1), torch.ones(3))
        assert model.embed(cue[:, None]).shape == (3, 20)


def test_product_of_gaussians_closed_form_and_brute_force():
    g = torch.Generator().manual_seed(0)
    mu = torch.randn(3, 1, generator=g, dtype=torch.float64)
    var = torch.rand(3, 1, generator=g, dtype=torch.float64) + 0.2
    m, v = product_of_gaussians(mu, var)
    # Closed form, by hand for three Gaussians.
    p = (1 / var).sum()
    assert torch.allclose(v, 1 / p) and torch.allclose(m, (mu / var).sum() / p)
    # Brute force: multiply the densities on a grid and read off mean and variance.
    x = torch.linspace(-8, 8, 200_001, dtype=torch.float64)
    logd = (-(x[None] - mu) ** 2 / (2 * var)).sum(0)
    d = torch.exp(logd - logd.max())
    d /= d.sum()
    mean = (d * x).sum()
    assert abs(mean - m.item()) < 1e-6 and abs((d * (x - mean) ** 2).sum() - v.item()) < 1e-6


def test_hinge_loss_is_zero_when_tasks_are_separated():
    e = torch.eye(4)
    assert hinge_embedding_loss(e, e, margin=0.1) == 0
    assert hinge_embedding_loss(e, e.roll(1, 0), margin=0.1) > 0


def test_loss_falls_on_a_tiny_dataset(arrays, tmp_path):
    tc = TrainConfig(steps=100, lr=2e-3, seed=0, **FAST)
    torch.manual_seed(tc.seed)
    result = train(arrays, tmp_path / "m", tc)
    batches = Batches(arrays, task_rows(arrays, "train", 0), result.norm)
    batch = to_device(batches.sample(np.random.default_rng(5), 4, 12), torch.device("cpu"))
    torch.manual_seed(tc.seed)
    fresh = build_model(result.config)  # the same initialisation train() started from
    with torch.no_grad():
        before = losses(fresh, batch, tc, sample=False)["mse"].item()
        after = losses(result.model.eval(), batch, tc, sample=False)["mse"].item()
    assert after < 0.7 * before, (before, after)


def test_save_load_bit_identical_and_card(arrays, tmp_path):
    result = train(arrays, tmp_path / "m", TrainConfig(steps=6, seed=1, **FAST))
    ckpt = load_checkpoint(tmp_path / "m")
    assert isinstance(ckpt.model, PETNet) and ckpt.meta["data"]["fingerprint"] == arrays.fingerprint
    cue, end = torch.from_numpy(arrays.cue(np.arange(4))), torch.from_numpy(arrays.end_state(np.arange(4)))
    with torch.no_grad():
        a = result.model.eval().encoder(cue_input(cue), end)
        b = ckpt.model.encoder(cue_input(cue), end)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not (tmp_path / ".m.partial").exists()  # the resume state is gone once the model is written


def test_recipe_sets_the_task_variables_width_the_layers_and_weight_decay(arrays, tmp_path):
    from democheck.petnet.recipe import load_recipe

    tc, _ = load_recipe("paper", ["model.z_dim=16", "model.fc_units=32", "optim.weight_decay=0.01"])
    assert (tc.z_dim, tc.fc_units, tc.weight_decay) == (16, 32, 0.01)
    result = train(arrays, tmp_path / "m", replace(tc, steps=2, seed=0, **FAST))
    assert (result.config.z_dim, result.config.fc_units) == (16, 32)
    ckpt = load_checkpoint(tmp_path / "m")
    assert (ckpt.config.z_dim, ckpt.config.fc_units) == (16, 32)
    cue, end = torch.from_numpy(arrays.cue(np.arange(2))), torch.from_numpy(arrays.end_state(np.arange(2)))
    with torch.no_grad():
        assert ckpt.model.encoder(cue_input(cue), end)[0].shape == (2, 16)  # the task mean: 16 dimensions


@pytest.mark.parametrize("shift", [0, 2])
def test_resume_reproduces_uninterrupted_run(arrays, tmp_path, shift):
    tc = TrainConfig(steps=14, seed=2, shift=shift, **FAST)
    full = train(arrays, tmp_path / "full", tc)
    assert train(arrays, tmp_path / "cut", tc, stop_after=7) is None  # "killed" after its step-7 save
    assert (tmp_path / ".cut.partial").exists() and not (tmp_path / "cut").exists()
    with pytest.raises(DemocheckError, match="--resume"):
        train(arrays, tmp_path / "cut", tc)
    resumed = train(arrays, tmp_path / "cut", tc, resume=True)
    for (k, a), (_, b) in zip(full.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), k


def test_random_shift_moves_each_item_by_one_offset_with_edge_padding():
    torch.manual_seed(0)
    images = torch.randint(0, 256, (64, 2, 9, 7, 3), dtype=torch.uint8)
    moved = random_shift(images, 2)
    padded = np.pad(images.numpy(), ((0, 0), (0, 0), (2, 2), (2, 2), (0, 0)), mode="edge")
    seen = set()
    for i in range(len(images)):
        # exactly one crop of the edge-padded item (both of its frames together) gives the shifted item
        hits = [(dy, dx) for dy in range(5) for dx in range(5)
                if np.array_equal(moved[i].numpy(), padded[i, :, dy:dy + 9, dx:dx + 7])]
        assert len(hits) >= 1
        seen.add(hits[0])
    assert len(seen) > 10  # offsets vary between items, in both directions
    assert torch.equal(random_shift(images, 0), images)


def test_augment_shifts_cues_whole_and_frames_one_by_one():
    torch.manual_seed(1)
    still = torch.randint(0, 256, (1, 1, 16, 16, 3), dtype=torch.uint8)
    batch = {"cue": still.expand(6, 2, 16, 16, 3).clone(), "frames": still.expand(6, 5, 16, 16, 3).clone(),
             "state": torch.zeros(6, 5, 3)}
    out = augment(batch, 3)
    assert torch.equal(out["cue"][:, 0], out["cue"][:, 1])  # a cue's two frames move together
    assert not all(torch.equal(out["frames"][0, 0], out["frames"][0, k]) for k in range(5))  # frames apart
    assert out["state"] is batch["state"] and torch.equal(batch["cue"][:, 0], still[:, 0].expand(6, 16, 16, 3))


def test_broken_cues_splice_scenes_and_reverse_time():
    cue = torch.arange(3, dtype=torch.uint8)[:, None, None, None, None] * 10 + torch.tensor([0, 1], dtype=torch.uint8
                                                                                           )[None, :, None, None, None]
    cue = cue.expand(3, 2, 4, 4, 3)
    out = broken_cues(cue)
    assert out.shape == (6, 2, 4, 4, 3)
    assert out[:3, :, 0, 0, 0].tolist() == [[0, 11], [10, 21], [20, 1]]  # first frame of i, last frame of i + 1
    assert out[3:, :, 0, 0, 0].tolist() == [[1, 0], [11, 10], [21, 20]]  # played backwards


def test_broken_cue_loss_ranks_broken_cues_above_real_ones_by_the_margin():
    real = torch.full((4,), 0.3, requires_grad=True)
    broken = torch.tensor([0.3, 0.9], requires_grad=True)  # one as sure as a real cue, one 3x less sure
    loss = broken_cue_loss(real, broken)
    loss.backward()
    assert loss.item() == pytest.approx(np.log(2) / 2)
    assert broken.grad[0] < 0 and broken.grad[1] == 0  # only the too-sure broken cue is pushed up...
    assert torch.all(real.grad > 0)  # ...and the real cues down
    assert broken_cue_loss(real * 10, broken * 10).item() == pytest.approx(loss.item())  # no scale of its own


def test_broken_cue_weight_adds_its_loss(arrays):
    cfg = ModelConfig(image_size=arrays.frames.shape[1], state_dim=arrays.state.shape[1],
                      action_dim=arrays.actions.shape[1])
    norm = Normalisation.fit(arrays.state, arrays.actions)
    batch = to_device(Batches(arrays, task_rows(arrays, "train", 0), norm).sample(np.random.default_rng(0), 2, 3),
                      torch.device("cpu"))
    out = losses(build_model(cfg), batch, TrainConfig(regularisers={"broken_cue": 2.0}))
    assert out["broken_cue"] > 0
    assert out["loss"].item() == pytest.approx((out["mse"] + 2.0 * out["broken_cue"]).item(), rel=1e-5)


def test_tecnet_trains(arrays, tmp_path):
    result = train(arrays, tmp_path / "t", TrainConfig(model_type="tecnet", steps=5, seed=0, **FAST))
    assert isinstance(load_checkpoint(tmp_path / "t").model, TecNet)
    assert "val_tecnet_hinge" in result.history[-1]


def test_loading_untrusted_files_fails_cleanly(arrays, tmp_path):
    train(arrays, tmp_path / "m", TrainConfig(steps=2, seed=0, **FAST))
    weights = tmp_path / "m" / "model.safetensors"
    good = weights.read_bytes()
    weights.write_bytes(pickle.dumps({"w": torch.zeros(3)}))
    with pytest.raises(CheckpointError, match="not a safetensors file"):
        load_checkpoint(tmp_path / "m")
    weights.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(CheckpointError, match="not a safetensors file"):
        load_checkpoint(tmp_path / "m")
    weights.write_bytes(good)
    cfg = tmp_path / "m" / "config.json"
    cfg.write_text(cfg.read_text().replace('"fc_units": 200', '"fc_units": 100'))
    with pytest.raises(CheckpointError, match="do not match config.json"):
        load_checkpoint(tmp_path / "m")
    cfg.write_bytes(b"\x80\x04garbage")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_checkpoint(tmp_path / "m")
    with pytest.raises(CheckpointError, match="no such model folder"):
        load_checkpoint(tmp_path / "nope")


def test_train_cli(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.setenv("DEMOCHECK_CACHE", str(tmp_path / "cache"))
    root, _ = tiny_dataset
    res = CliRunner().invoke(app, ["train", str(root), "--out", str(tmp_path / "m"), "--steps", "4", "--set",
                                   "optim.batch_tasks=2", "--set", "timesteps=2", "--set", "schedule.val_every=2",
                                   "--device", "cpu", "--cache-dir", str(tmp_path / "cache")])
    assert res.exit_code == 0, res.output
    card = (tmp_path / "m" / "README.md").read_text()
    assert "democheck" in card and "Intended use" in card and "fingerprint" in card
    assert 'name = "paper"' in card and "batch_tasks = 2" in card  # the resolved recipe, overrides included
    cfg = load_checkpoint(tmp_path / "m").meta
    assert cfg["recipe"]["set"] == ["optim.batch_tasks=2", "timesteps=2", "schedule.val_every=2"]
    assert cfg["recipe"]["config"]["steps"] == 4 and cfg["training"]["batch_tasks"] == 2
    for args, msg in ((["--set", "model_type=mlp"], "petnet or tecnet"), (["--set", "lr"], "key=value"),
                      (["--set", "optim.nope=1"], "unknown key"), (["--set", "regularisers.nope=1"], "unknown regulariser"),
                      (["--set", "steps=many"], "steps must be int"), (["--recipe", "nope"], "no training recipe"),
                      (["--set", "regularisers.kl_prior=1", "--set", "regularisers.kl_np=1"], "one of them")):
        res = CliRunner().invoke(app, ["train", str(root), "--out", str(tmp_path / "m2"), *args])
        assert res.exit_code == 2 and msg in res.output and "Traceback" not in res.output, (args, res.output)


def test_hard_negative_batches_hold_both_orders_of_an_object_pair(tiny_dataset, arrays):
    from democheck.workflows import object_pair_groups

    root, _ = tiny_dataset
    groups = object_pair_groups(open_dataset(root))
    assert groups and all(len(v.split("|")) == 2 for v in groups.values())
    rows = task_rows(arrays, "train", 0)
    batches = Batches(arrays, rows, None, groups)
    assert batches.groups  # the tiny suite's two train tasks are one pair in both orders
    rng = np.random.default_rng(0)
    for _ in range(5):
        picks = batches._pick_tasks(rng, 2)
        assert len(set(groups[batches.tasks[i]] for i in picks)) == 1 and len(set(picks)) == 2
    plain = Batches(arrays, rows, None)
    assert not plain.groups and len(plain._pick_tasks(rng, 2)) == 2


def test_partial_cues_cut_the_cue_demo_short_and_train(arrays, tmp_path):
    rows = task_rows(arrays, "train", 0)
    cue_rows = np.array([r[0] for r in rows.values()])
    start = arrays.cue(cue_rows, end=np.zeros(len(cue_rows), np.int64))
    assert np.array_equal(start[:, 1], start[:, 0])  # cut at t=0: the last frame is the first
    assert np.array_equal(arrays.cue(cue_rows, end=arrays.lengths[cue_rows] + 5), arrays.cue(cue_rows))
    norm = Normalisation.fit(arrays.state, arrays.actions)
    batch = Batches(arrays, rows, norm).sample(np.random.default_rng(0), 2, 4, partial=True)
    assert batch["partial_cue"].shape == batch["cue"].shape
    assert np.array_equal(batch["partial_cue"][:, 0], batch["cue"][:, 0])  # same demo, same first frame
    result = train(arrays, tmp_path / "m", TrainConfig(steps=5, seed=0, regularisers={"partial_cue": 1.0}, **FAST))
    assert np.isfinite(result.history[-1]["train_partial_cue"]) and "val_partial_cue" in result.history[-1]


def test_partial_kl_covers_the_starting_encoders_whole_cue_posterior(arrays, tmp_path):
    import copy

    from democheck.petnet.model import kl_diag

    rows = task_rows(arrays, "train", 0)
    norm = Normalisation.fit(arrays.state, arrays.actions)
    batches = Batches(arrays, rows, norm)
    cue_rows, traj_rows = batches.pick_rows(np.random.default_rng(0), 2)
    steps = np.zeros((2, 3), np.int64)
    model = build_model(ModelConfig(image_size=arrays.frames.shape[1], state_dim=arrays.state.shape[1],
                                    action_dim=arrays.actions.shape[1]))
    torch.manual_seed(0)
    with torch.no_grad():  # large random weights, so that a cut cue's posterior differs from the whole one's
        for p in model.encoder.parameters():
            p.normal_(0.0, 0.3)
    teacher = copy.deepcopy(model.encoder).requires_grad_(False)
    tc = TrainConfig(regularisers={"partial_kl": 1.0})
    cut = to_device(batches.gather(cue_rows, traj_rows, steps, np.zeros(2, np.int64)), torch.device("cpu"))
    with pytest.raises(ValueError, match="starting encoder"):
        losses(model, cut, tc)
    out = losses(model, cut, tc, sample=False, teacher=teacher)
    with torch.no_grad():
        mu, var = teacher(cue_input(cut["cue"]))
        mu_p, var_p = model.encoder(cue_input(cut["partial_cue"]))
    assert torch.allclose(out["partial_kl"], kl_diag(mu, var, mu_p, var_p).mean(), rtol=1e-5)
    assert out["partial_kl"].item() > 1e-3
    # Cut at the last frame the cue is whole: while the model is still its starting point, nothing to cover.
    whole = to_device(batches.gather(cue_rows, traj_rows, steps, arrays.lengths[cue_rows] - 1), torch.device("cpu"))
    assert losses(model, whole, tc, sample=False, teacher=teacher)["partial_kl"].item() == pytest.approx(0.0, abs=1e-6)
    # The target is fixed: the teacher gets no gradient.
    out["partial_kl"].backward()
    assert all(p.grad is None for p in teacher.parameters())


def test_init_starts_from_a_model_and_the_partial_kl_needs_it(arrays, tmp_path):
    base = train(arrays, tmp_path / "base", TrainConfig(steps=3, seed=0, **FAST))
    with pytest.raises(DemocheckError, match="needs a starting model"):
        train(arrays, tmp_path / "x", TrainConfig(steps=1, seed=0, regularisers={"partial_kl": 1.0}, **FAST))
    with pytest.raises(DemocheckError, match="architecture differs"):
        train(arrays, tmp_path / "x", TrainConfig(steps=1, seed=0, init=str(tmp_path / "base"), keypoints=True, **FAST))
    # A step at learning rate 0 keeps the starting model exactly, normalisation included.
    same = train(arrays, tmp_path / "same", TrainConfig(steps=1, lr=0.0, seed=0, init=str(tmp_path / "base"), **FAST))
    assert same.norm == base.norm
    for (k, a), b in zip(base.model.state_dict().items(), same.model.state_dict().values()):
        assert torch.equal(a, b), k
    tuned = train(arrays, tmp_path / "ft", TrainConfig(steps=5, seed=0, init=str(tmp_path / "base"),
                                                       regularisers={"partial_kl": 1.0}, **FAST))
    assert np.isfinite(tuned.history[-1]["train_partial_kl"]) and "val_partial_sigma" in tuned.history[-1]


def test_no_task_is_left_out_of_training_unless_the_data_names_a_split():
    from types import SimpleNamespace

    import pandas as pd

    from democheck.petnet.batches import held_out_demos

    tasks = np.repeat([f"task {i}" for i in range(12)], 10)
    eps = pd.DataFrame({"episode_index": np.arange(len(tasks)), "task": tasks})
    arrays = SimpleNamespace(episodes=eps)
    train_rows, val_rows = task_rows(arrays, "train", 0), task_rows(arrays, "val", 0)
    assert sorted(train_rows) == sorted(set(tasks))  # every task trained on
    assert sorted(val_rows) == sorted(set(tasks)) and all(len(r) == 2 for r in val_rows.values())
    every = np.sort(np.concatenate([*train_rows.values(), *val_rows.values()]))
    assert np.array_equal(every, np.arange(len(tasks)))  # a partition of the demos
    assert not held_out_demos(eps.iloc[:5], 0).any()  # a task of 5 demos keeps them all for training
    one = eps[eps["task"] == "task 0"]  # a single-task dataset still validates on held-out demos
    assert held_out_demos(one, 0).sum() == 2
    # A dataset that names its split is split as it says (the user's choice).
    named = eps.assign(split=np.where(eps["task"] == "task 3", "val", "train"))
    assert "task 3" not in task_rows(SimpleNamespace(episodes=named), "train", 0)


def test_the_model_records_the_tasks_it_learnt(arrays, tmp_path):
    train(arrays, tmp_path / "m", TrainConfig(steps=2, seed=0, **FAST))
    tasks = load_checkpoint(tmp_path / "m").meta["data"]["task_split"]
    assert tasks["trained"] == sorted(task_rows(arrays, "train", 0))
    assert set(tasks["left_out"]) == set(arrays.episodes["task"]) - set(tasks["trained"])  # the suite's val/test
    assert tasks["validation"] == "the data's val split"


def test_train_at_another_image_size_and_audit_reads_the_same_way(tiny_dataset, tmp_path):
    from democheck.data.demo import resize_frames

    root, _ = tiny_dataset
    res = CliRunner().invoke(app, ["train", str(root), "--out", str(tmp_path / "m"), "--steps", "2", "--image-size",
                                   "8", "--set", "batch_tasks=2", "--set", "timesteps=2", "--device", "cpu",
                                   "--cache-dir", str(tmp_path / "cache")])
    assert res.exit_code == 0, res.output
    ckpt = load_checkpoint(tmp_path / "m")
    assert ckpt.config.image_size == 8 and ckpt.meta["training"]["image_size"] == 8
    assert ckpt.meta["data"]["camera_shape"] == [16, 16, 3]
    ds = open_dataset(root, image_size=8)
    assert ds.image_shape == (8, 8, 3) and ds[0].frames.shape[1:] == (8, 8, 3)
    np.testing.assert_array_equal(ds.cue_frames(0), resize_frames(open_dataset(root).cue_frames(0), 8))
    res = CliRunner().invoke(app, ["audit", str(root), "--out", str(tmp_path / "r"), "--model", str(tmp_path / "m"),
                                   "--device", "cpu", "--json"])
    assert res.exit_code == 0, res.output
    import json

    frames = json.loads((tmp_path / "r" / "summary.json").read_text())["frames"]
    assert frames == {"camera": [16, 16, 3], "model": [8, 8, 3], "resized": True, "count": frames["count"]}


def test_resize_frames_averages_areas():
    from democheck.data.demo import resize_frames

    img = np.zeros((2, 4, 4, 3), np.uint8)
    img[:, :2, :2] = 200  # one quadrant bright
    out = resize_frames(img, 2)
    assert out.shape == (2, 2, 2, 3) and out[0, 0, 0, 0] == 200 and out[0, 1, 1, 0] == 0
    assert resize_frames(img, 4) is img
    assert resize_frames(np.zeros((3, 6, 8, 3), np.uint8), 4).shape == (3, 4, 4, 3)  # a wide camera, squeezed


def test_the_final_phase_learns_the_validation_demos_too(tmp_path):
    from dataclasses import replace

    from democheck.sim.suite import generate
    from tests.conftest import TINY

    root = tmp_path / "plain"
    generate(replace(TINY, demos_per_task=6), root, workers=1)
    (root / "meta/democheck/episodes.parquet").unlink()  # a user's dataset: no named split
    arrays = build_cache(open_dataset(root), tmp_path / "cache")
    assert task_rows(arrays, "val", 0)  # two held-out demos of every task
    result = train(arrays, tmp_path / "m", TrainConfig(steps=6, seed=0, final_all_share=1 / 3, **FAST))
    meta = load_checkpoint(tmp_path / "m").meta
    assert meta["data"]["task_split"]["validation"].endswith("learnt too in the last 2 steps")
    assert result.history[-1]["step"] == 4  # validation stops where every demo is trained on
    assert meta["novelty"]["train_cues"] == len(arrays.episodes)  # the density (and the OCSVM) see every demo
    assert meta["novelty"]["held_out_cues"] == len(arrays.episodes)  # ... and its reference is theirs
    # fit-novelty refits it as training fitted it, not on the training split with the held-out demos as reference.
    res = CliRunner().invoke(app, ["fit-novelty", str(tmp_path / "m"), "--data", str(root), "--out",
                                   str(tmp_path / "refit"), "--device", "cpu", "--cache-dir", str(tmp_path / "cache")])
    assert res.exit_code == 0, res.output
    refit = load_checkpoint(tmp_path / "refit").meta["novelty"]
    assert refit["train_cues"] == refit["held_out_cues"] == len(arrays.episodes)
    assert refit["d2_ref"] == pytest.approx(meta["novelty"]["d2_ref"], rel=1e-6)  # the same fit, from its seed


@pytest.mark.parametrize("fusion", ["shift", "tile"])
def test_early_fusion_makes_the_first_convolution_depend_on_the_task(fusion):
    cfg = ModelConfig(image_size=32, task_fusion=fusion, keypoints=True)
    ctrl = build_model(cfg).controller
    frame = torch.rand(2, 3, 32, 32) - 0.5
    z = torch.randn(2, cfg.embed_dim)
    h1, h2 = ctrl.features(frame, z), ctrl.features(frame, z + 1.0)
    assert not torch.allclose(h1, h2)  # the feature points move with the task variable
    assert ctrl.head[0].in_features == 2 * cfg.conv_channels + cfg.state_dim  # z does not also join late
    late = build_model(ModelConfig(image_size=32, keypoints=True)).controller
    assert torch.equal(late.features(frame, z), late.features(frame, z + 1.0))


def test_a_checkpoint_made_before_task_fusion_loads_as_late_fusion(arrays, tmp_path):
    import json

    res = train(arrays, tmp_path / "m", TrainConfig(steps=2, **FAST))
    doc = json.loads((tmp_path / "m" / "config.json").read_text())
    doc["model"].pop("task_fusion")  # as config.json files written before the option
    (tmp_path / "m" / "config.json").write_text(json.dumps(doc))
    ck = load_checkpoint(tmp_path / "m")
    assert ck.config.task_fusion == "late"
    x = torch.rand(1, 3, 16, 16) - 0.5
    s, z = torch.zeros(1, ck.config.state_dim), torch.zeros(1, ck.config.embed_dim)
    assert torch.equal(ck.model.controller(x, s, z), res.model.controller(x, s, z))


@pytest.mark.parametrize("model_type", ["petnet", "tecnet"])
def test_early_fusion_trains_and_the_gate_reference_is_stored(arrays, tmp_path, model_type):
    tc = TrainConfig(model_type=model_type, steps=4, task_fusion="shift", conv_channels=8, lr_schedule="cosine",
                     **FAST)
    train(arrays, tmp_path / "m", tc)
    ck = load_checkpoint(tmp_path / "m")
    assert ck.config.task_fusion == "shift" and ck.config.conv_channels == 8
    if model_type == "petnet":
        ref = ck.meta["gate"]["cue_uncertainty"]
        assert len(ref) == ck.meta["gate"]["cues"] > 0 and ref == sorted(ref) and ref[0] > 0


def test_cosine_schedule_warms_up_then_decays_to_zero():
    from democheck.petnet.train import learning_rate

    tc = TrainConfig(steps=1000, lr=1e-3, lr_schedule="cosine")
    lrs = [learning_rate(tc, s) for s in range(1000)]
    assert lrs[0] == pytest.approx(1e-3 / 20) and max(lrs) == pytest.approx(1e-3)
    assert lrs[19] == pytest.approx(1e-3) and lrs[-1] < 1e-8 and all(np.diff(lrs[19:]) <= 0)
    assert learning_rate(TrainConfig(lr=2e-4), 123) == 2e-4


def test_gate_refuses_the_stated_share_and_more_cues_narrow_it():
    from democheck.petnet.gate import Gate
    from democheck.petnet.posterior import TaskPosterior

    rng = np.random.default_rng(0)
    ref = rng.lognormal(0, 0.3, 999)
    gate = Gate.fit(ref, false_refusal=0.05)
    assert gate.threshold == pytest.approx(np.sort(ref)[949])  # ceil(1000 * 0.95) = 950th smallest
    # Over draws of the reference, a fresh cue is refused 5% of the time: uniform cues, 99 per reference.
    refusals = [1.0 - Gate.fit(rng.random(99), 0.05).threshold for _ in range(2000)]
    assert np.mean(refusals) == pytest.approx(0.05, abs=0.003)
    wide = TaskPosterior(np.zeros((1, 4)), np.full((1, 4), (1.5 * gate.threshold) ** 2), np.zeros((1, 4)))
    assert not gate.decide(wide).act
    three = TaskPosterior(np.zeros((3, 4)), np.full((3, 4), (1.5 * gate.threshold) ** 2), np.zeros((3, 4)))
    d = gate.decide(three)  # sigma / sqrt(3) = 0.87 of the threshold
    assert d.act and d.uncertainty == pytest.approx(1.5 * gate.threshold / np.sqrt(3))
    assert Gate.fit(ref[:5], 0.05).threshold == np.inf  # too few cues to promise 5%
    with pytest.raises(DemocheckError):
        Gate.fit(ref, 1.5)


def test_batches_gathered_on_the_device_train_the_same_weights(arrays, tmp_path):
    # The GPU path (the data held on the training device) runs here on the CPU: same batches, same weights.
    tc = TrainConfig(steps=3, task_fusion="shift", regularisers={"broken_cue": 1.0, "partial_cue": 1.0},
                     keypoints=True, object_readout=1.0, **FAST)
    a = train(arrays, tmp_path / "host", tc, resident=False).model.state_dict()
    b = train(arrays, tmp_path / "dev", tc, resident=True).model.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("model_type", ["petnet", "tecnet"])
def test_the_object_readout_learns_the_recorded_object_poses(arrays, tmp_path, model_type):
    assert arrays.env_state is not None and arrays.env_state.shape[1] == 6  # target, distractor (x, y, yaw)
    tc = TrainConfig(model_type=model_type, steps=40, task_fusion="shift", keypoints=True, object_readout=1.0,
                     lr=3e-3, **{**FAST, "val_every": 40})
    res = train(arrays, tmp_path / "m", tc)
    assert res.config.readout_dim == 6
    last = res.history[-1]
    assert "train_readout" in last and np.isfinite(last["val_readout"])
    ck = load_checkpoint(tmp_path / "m")
    assert ck.model.controller.readout.out_features == 6  # saved and loaded with the weights
    with pytest.raises(DemocheckError, match="environment state"):
        import dataclasses
        train(dataclasses.replace(arrays, env_state=None), tmp_path / "n", tc)


def test_posed_frames_keep_the_layout_and_move_the_arm(tiny_dataset):
    import json

    from democheck.data import open_dataset
    from democheck.sim.posed import render_posed

    ds = open_dataset(tiny_dataset[0])
    sims = [json.loads(s) for s in ds.episodes["sim"].iloc[:2]]
    arms = np.stack([sims[0]["layout"]["arm_qpos"], np.array(sims[0]["layout"]["arm_qpos"]) + 0.8])
    frames, poses = render_posed(sims, arms, per_demo=6, seed=1)
    assert frames.shape == (2, 6, 16, 16, 3) and frames.dtype == np.uint8 and poses.shape == (2, 6, 6)
    for n, sim in enumerate(sims):  # the objects where the demo's began, in the environment state's order
        np.testing.assert_allclose(poses[n], np.tile(sim["layout"]["target"] + sim["layout"]["distractor"], (6, 1)),
                                   atol=1e-6)
    assert len({f.tobytes() for f in frames[0]}) == 2  # two arm poses, two pictures of one layout
    np.testing.assert_array_equal(render_posed(sims, arms, per_demo=6, seed=1)[0], frames)  # the seed's frames
    with pytest.raises(ValueError, match="joint positions"):
        render_posed(sims, arms[:, :3], per_demo=1, seed=1)


def test_the_read_out_learns_on_posed_frames_with_the_trajectory_demos_task_variable(tiny_dataset, arrays, tmp_path):
    from democheck.petnet.batches import POSED_PER_TASK, Batches, PosedFrames, task_rows
    from democheck.workflows import posed_renderer

    tc = TrainConfig(steps=4, task_fusion="tile", keypoints=True, object_readout=1.0, posed_frames=3,
                     **{**FAST, "val_every": 4})
    seen = []

    def posed(rows):
        seen.append(rows)
        return posed_renderer(open_dataset(tiny_dataset[0]), arrays, 3, 0, None)(rows)

    res = train(arrays, tmp_path / "m", tc, posed=posed)
    train_rows = np.concatenate(list(task_rows(arrays, "train", 0).values()))
    np.testing.assert_array_equal(np.sort(seen[0]), np.sort(train_rows))  # rendered once, for the training demos
    assert np.isfinite(res.history[-1]["train_posed_readout"]) and "val_posed_readout" not in res.history[-1]
    # A batch reads the posed frames of its trajectory demos (not its cues': z could carry their layout).
    frames, poses = posed(train_rows)
    rows = task_rows(arrays, "train", 0)
    b = Batches(arrays, rows, res.norm, env_norm=(np.zeros(6, np.float32), np.ones(6, np.float32)),
                posed=PosedFrames(train_rows, frames, poses))
    batch = b.sample(np.random.default_rng(0), 2, 2)
    assert batch["posed_frames"].shape == (2, POSED_PER_TASK, 16, 16, 3)
    cue_rows, traj_rows = b.pick_rows(np.random.default_rng(0), 2)
    slots = [list(train_rows).index(r) for r in traj_rows]
    assert all(any((batch["posed_env"][i] == poses[s][0]).all(axis=-1)) for i, s in enumerate(slots))
    with pytest.raises(DemocheckError, match="pushing suite"):
        train(arrays, tmp_path / "n", tc)
    with pytest.raises(DemocheckError, match="object_readout"):
        TrainConfig(posed_frames=2).check()


def test_fine_points_read_a_map_half_the_images_side():
    cfg = ModelConfig(image_size=32, keypoints=True, fine_points=True, task_fusion="tile", conv_channels=8)
    ctrl = build_model(cfg).controller
    convs = [m for m in ctrl.conv if isinstance(m, torch.nn.Conv2d)]
    assert [c.stride[0] for c in convs] == [2, 1, 1, 1] and [c.kernel_size[0] for c in convs] == [5, 3, 3, 3]
    h = ctrl.conv[:-1](torch.zeros(1, 3 + cfg.embed_dim, 32, 32))
    assert h.shape[-2:] == (16, 16)
    assert ctrl.features(torch.zeros(2, 3, 32, 32), torch.zeros(2, cfg.embed_dim)).shape == (2, 16)
    with pytest.raises(ValueError, match="keypoints"):
        ModelConfig(fine_points=True)


def test_the_controller_speed_benchmark_runs_every_controller():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "benchmarks" / "controller_speed.py"
    spec = importlib.util.spec_from_file_location("controller_speed", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    for kw in bench.CONTROLLERS.values():
        assert bench.samples_per_s(1, 2, steps=1, warmup=0, **kw) > 0


def test_the_cores_a_process_may_use_read_a_containers_quota(tmp_path):
    """Training sets torch's threads to the cores it may use: a container's CPU quota of 1.5 cores is 1, no quota
    is the CPU affinity's count."""
    import os

    from democheck.pool import usable_cores

    quota = tmp_path / "cpu.max"
    quota.write_text("150000 100000\n")
    assert usable_cores(str(quota)) == 1
    quota.write_text("max 100000\n")
    assert usable_cores(str(quota)) == len(os.sched_getaffinity(0))
    assert usable_cores(str(tmp_path / "none")) == len(os.sched_getaffinity(0))
