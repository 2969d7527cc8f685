import numpy as np
import pytest

from democheck.sim import scene
from democheck.sim.catalog import OBJECTS, make_tasks
from democheck.sim.env import EPISODE_STEPS, SUCCESS_STEPS, PushEnv
from democheck.sim.expert import ScriptedExpert

PAIR = (OBJECTS["cylinder-green-large"], OBJECTS["cross-orange-small"])


@pytest.mark.parametrize("with_objects", [True, False], ids=["scene", "no-objects"])
def test_reset_step_shapes(with_objects):
    env = PushEnv(PAIR, image_size=16, with_objects=with_objects)
    obs, info = env.reset(seed=1)
    assert obs["image"].shape == (16, 16, 3) and obs["image"].dtype == np.uint8
    assert obs["state"].shape == (17,) and obs["state"].dtype == np.float32
    assert env.observation_space.contains(obs)
    rng = np.random.default_rng(0)
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 7))
        assert np.isfinite(obs["state"]).all() and np.isfinite(reward)
        assert isinstance(info["success"], bool)
    assert obs["image"].std() > 0  # something was rendered
    env.close()


def test_layouts_inside_workspace_and_seeded():
    env = PushEnv(PAIR, image_size=16, render_images=False)
    seen = []
    for seed in range(20):
        env.reset(seed=seed)
        t, d = np.array(env.layout.target[:2]), np.array(env.layout.distractor[:2])
        for p in (t, d):
            assert (scene.WORKSPACE[:, 0] <= p).all() and (p <= scene.WORKSPACE[:, 1]).all()
        assert np.linalg.norm(t - scene.GOAL_XY) > scene.GOAL_RADIUS
        seen.append(env.layout)
    env.reset(seed=3)
    assert env.layout == seen[3]
    assert len(set(seen)) == 20


def test_success_rule_counts_steps_in_goal():
    env = PushEnv(PAIR, image_size=16, render_images=False)
    env.reset(seed=0)
    qadr = env._obj_qadr["target"]
    env.data.qpos[qadr[:2]] = scene.GOAL_XY  # place the target in the goal
    for k in range(SUCCESS_STEPS):
        _, _, _, _, info = env.step(np.zeros(7))
        assert info["success"] == (k + 1 >= SUCCESS_STEPS)
    assert info["steps_in_goal"] == SUCCESS_STEPS


def test_actions_are_scaled_and_clipped():
    env = PushEnv(PAIR, image_size=16, render_images=False)
    env.reset(seed=0)
    env.step(np.full(7, 5.0))
    assert np.allclose(env.data.ctrl, scene.TORQUE_LIMIT)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_expert_succeeds(seed):
    tasks = make_tasks(4, 0, 2, seed=0)
    task = tasks[seed] if seed < 2 else tasks[-1]  # includes a meta-test task
    env = PushEnv(task, image_size=16, render_images=False)
    env.reset(seed=seed)
    expert = ScriptedExpert(env)
    for _ in range(EPISODE_STEPS):
        _, _, _, truncated, info = env.step(expert.act())
    assert truncated and info["success"], info


def _copy_of(env: PushEnv) -> PushEnv:
    import mujoco

    twin = PushEnv((env.target, env.distractor), image_size=16, render_images=False)
    twin.reset(seed=0)
    mujoco.mj_copyData(twin.data, env.model, env.data)
    return twin


def test_the_markovian_experts_action_is_a_function_of_the_state_alone():
    """Handed a copy of the simulator's state mid-episode, a new MarkovianExpert acts exactly as the one that
    drove the episode there; the hysteresis expert, which remembers its phase, does not always."""
    from democheck.sim.expert import MarkovianExpert

    for kind, same_everywhere in ((MarkovianExpert, True), (ScriptedExpert, False)):
        env = PushEnv(PAIR, image_size=16, render_images=False)
        env.reset(seed=3)
        expert, differ = kind(env), 0
        for t in range(EPISODE_STEPS):
            a = expert.act()
            if t % 5 == 0:
                differ += int(np.abs(kind(_copy_of(env)).act() - a).max() > 1e-9)
            env.step(a)
        assert (differ == 0) == same_everywhere, (kind.__name__, differ)


def test_the_markovian_expert_recovers_from_a_thrown_arm_and_a_moved_target():
    import mujoco

    from democheck.sim.expert import MarkovianExpert

    tasks = make_tasks(4, 0, 0, seed=0)
    rng = np.random.default_rng(5)
    for k, task in enumerate(tasks):
        env = PushEnv(task, image_size=16, render_images=False)
        env.reset(seed=k)
        expert = MarkovianExpert(env)
        for _ in range(30):
            env.step(expert.act())
        env.data.qpos[env._arm_qadr] = scene.ARM_HOME + np.array([0.4, 0.3, -0.3, -0.4, 0.3, -0.3, 0.2]) * (-1) ** k
        env.data.qvel[:] = 0.0
        env.data.qpos[env._obj_qadr["target"][:2]] += rng.uniform(-0.03, 0.03, 2)
        mujoco.mj_forward(env.model, env.data)
        env.steps_in_goal = 0
        for _ in range(EPISODE_STEPS):
            _, _, _, _, info = env.step(expert.act())
        assert info["success"], (k, info)


def test_dart_noise_moves_the_arm_off_the_experts_path_and_records_the_experts_action():
    from democheck.sim.expert import MarkovianExpert
    from democheck.sim.variants import record_demo

    env = PushEnv(PAIR, image_size=16, render_images=False)
    clean = record_demo(env, MarkovianExpert(env).act, 40, seed=2)
    labels = []

    def expert_then_check():
        labels.append(expert.act())
        return labels[-1]

    expert = MarkovianExpert(env)
    noisy = record_demo(env, expert_then_check, 40, seed=2, action_noise=0.1)
    np.testing.assert_array_equal(noisy["actions"], np.stack(labels))  # the label is the expert's own action
    assert np.abs(noisy["state"][-1] - clean["state"][-1]).max() > 1e-3  # the noise moved the arm
    again = record_demo(env, MarkovianExpert(env).act, 40, seed=2, action_noise=0.1)
    np.testing.assert_array_equal(again["state"], noisy["state"])  # the same seed, the same noise


def test_dart_noise_leaves_a_stopped_arm_still():
    from democheck.sim.variants import GaveUpPolicy, record_demo

    env = PushEnv(PAIR, image_size=16, render_images=False)
    policy = GaveUpPolicy(env, expert="markovian")
    rec = record_demo(env, policy.act, EPISODE_STEPS, seed=1, action_noise=0.2)
    stopped = np.flatnonzero(~rec["actions"].any(axis=1))
    assert len(stopped) > 10 and (np.diff(stopped) == 1).all()  # it gave up, and stayed given up
    assert np.abs(env.data.ctrl).max() == 0.0  # what the arm executed at the end: nothing, no noise
