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
