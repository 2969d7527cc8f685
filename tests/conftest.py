import os

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest  # noqa: E402

from democheck.sim.suite import Recipe  # noqa: E402

# A suite small enough for every test run: 4 tasks (2/1/1), 3 demos, 16x16 frames, 12 steps.
TINY = Recipe(name="tiny", seed=3, train_tasks=2, val_tasks=1, test_tasks=1, demos_per_task=3, steps=12, image_size=16)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    from democheck.sim.suite import generate

    out = tmp_path_factory.mktemp("ds") / "tiny"
    summary = generate(TINY, out, workers=1)
    return out, summary


@pytest.fixture(scope="session")
def tiny_model(tiny_dataset, tmp_path_factory):
    from democheck.petnet.train import TrainConfig
    from democheck.workflows import train_model

    root, _ = tiny_dataset
    out = tmp_path_factory.mktemp("model") / "m"
    train_model(root, out, TrainConfig(steps=6, batch_tasks=2, timesteps=2, val_every=3, device="cpu"),
                cache_dir=tmp_path_factory.mktemp("cache"))
    return out
