import mujoco
import pytest

from democheck.sim.catalog import COLOURS, OBJECTS, SHAPES, catalog, make_tasks, split_objects
from democheck.sim.scene import build_spec
from democheck.sim.suite import load_recipe


def test_catalog_size():
    assert len(SHAPES) >= 6 and len(COLOURS) >= 12
    assert len(catalog()) == len(SHAPES) * len(COLOURS) * 2
    assert len({o.key for o in catalog()}) == len(catalog())


@pytest.mark.parametrize("key", sorted(OBJECTS))
def test_every_object_builds(key):
    obj = OBJECTS[key]
    model = build_spec(obj, OBJECTS["cube-red-small"] if obj.colour != "red" else OBJECTS["cube-blue-small"]).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert model.body("target").id > 0 and model.nu == 7
    assert 0 < obj.half_height < 0.06 and obj.radius < 0.08


def test_split_holds_objects_out():
    train_objs, test_objs = split_objects(seed=0)
    assert not set(train_objs) & set(test_objs)
    tasks = make_tasks(400, 40, 64, seed=0)
    meta_train = {o for t in tasks if t.split in ("train", "val") for o in (t.target, t.distractor)}
    meta_test = {o for t in tasks if t.split == "test" for o in (t.target, t.distractor)}
    assert meta_test and not meta_train & meta_test
    assert len({t.name for t in tasks}) == len(tasks)  # every task string is unique
    assert all(t.target.colour != t.distractor.colour for t in tasks)


def test_default_suite_is_big_enough():
    r = load_recipe("push-v1")
    assert r.train_tasks >= 400 and r.test_tasks >= 60 and r.demos_per_task == 12 and r.steps == 100
    assert r.image_size == 64


def test_task_override_keeps_proportions():
    r = load_recipe("push-v1").with_overrides(tasks=25, demos=4)
    assert r.n_tasks == 25 and r.n_episodes == 100
    assert r.train_tasks > r.test_tasks >= 1 and r.val_tasks >= 1


def test_every_pair_is_used_in_both_orders_within_its_split():
    """The scene alone must not give the task away: (A, B) and (B, A) are both tasks, in the same split."""
    tasks = make_tasks(400, 40, 64, seed=0)
    by_split = {}
    for t in tasks:
        by_split.setdefault(t.split, set()).add((t.target.key, t.distractor.key))
    for split, pairs in by_split.items():
        assert all((b, a) in pairs for a, b in pairs), split
