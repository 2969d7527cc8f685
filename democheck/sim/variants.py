"""Every way democheck records an episode: the expert, planted bad operators, semantic defects and probes.

A *kind* names what drove the arm and what the scene held.  The same kind
names the ``policy`` in an episode's ``sim`` record, so any episode can be
re-simulated from its record alone (``make_policy`` + ``scene_options``).

- ``expert``: the scripted expert pushes the target to the goal.
- Planted bad operators (``[defects]`` in a recipe, like the defects below):
  ``idle`` (the arm never moves), ``random`` (smoothed random torques).
- Semantic defects: ``wrong-object`` (the distractor is pushed to the goal),
  ``both-objects`` (the distractor first, then the target), ``occluded`` (a
  card hides the target from the camera all episode), ``gave-up`` (the expert
  stops once the target has covered half its way).
- Probes re-simulated from a demo: ``no-action`` (as ``idle``), ``random``,
  ``no-objects`` (the demo's actions replayed in a scene without objects);
  ``hidden`` works on the frames alone (see ``democheck.sim.probes``).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from democheck.errors import DatasetError
from democheck.sim import scene
from democheck.sim.catalog import CATALOG_VERSION, OBJECTS
from democheck.sim.env import ENV_STATE_DIM, PushEnv
from democheck.sim.expert import MarkovianExpert, ScriptedExpert

BAD_OPERATORS = ("idle", "random")
DEFECTS = ("wrong-object", "both-objects", "occluded", "gave-up")
PLANT_KINDS = BAD_OPERATORS + DEFECTS
# The kinds a scripted expert drives (a recipe's ``action_noise`` perturbs these alone): every semantic defect.
PUSHING_KINDS = ("expert",) + DEFECTS
# What ``democheck probe`` makes by default; ``TIME_PROBES`` on request (``--kinds``).
PROBES = ("no-action", "random", "no-objects", "hidden")
# A demo's recording in another order: played backwards (a reset recorded as a demo), or with a pause put in.
TIME_PROBES = ("reversed", "hesitates")
# Kinds made from the frames alone, so they work on datasets without a sim record (``TIME_PROBES`` too).
IMAGE_PROBES = ("no-action", "hidden")
# The scripted experts a recipe can record with (``democheck.sim.expert``); push-v1 was made by "hysteresis".
EXPERTS = {"hysteresis": ScriptedExpert, "markovian": MarkovianExpert}


def action_noise_for(kind: str, action_noise: float) -> float:
    """The DART noise an episode of ``kind`` is recorded with: the recipe's where the expert drives, else none."""
    return float(action_noise) if kind in PUSHING_KINDS else 0.0


def make_expert(env, role: str = "target", expert: str = "hysteresis") -> ScriptedExpert:
    try:
        return EXPERTS[expert](env, role=role)
    except KeyError:
        raise ValueError(f"unknown expert {expert!r}; experts: {', '.join(EXPERTS)}") from None


class IdlePolicy:
    """A recording where the arm never moves: zero torque (the arm holds still, gravity compensated)."""

    def __init__(self, env, seed: int = 0):
        self.action_dim = env.action_space.shape[0]

    def act(self) -> np.ndarray:
        return np.zeros(self.action_dim, np.float32)


class RandomPolicy:
    """Random torques, low-pass filtered so the arm flails like a confused operator rather than vibrating."""

    def __init__(self, env, seed: int, smoothing: float = 0.85, scale: float = 0.6):
        self.rng = np.random.default_rng(seed)
        self.a = np.zeros(env.action_space.shape[0])
        self.smoothing, self.scale = smoothing, scale

    def act(self) -> np.ndarray:
        self.a = self.smoothing * self.a + (1 - self.smoothing) * self.rng.normal(0, 3 * self.scale, self.a.shape)
        return np.clip(self.a, -1.0, 1.0).astype(np.float32)


class ReplayPolicy:
    """Plays back recorded actions open-loop (zero torque once they run out)."""

    def __init__(self, actions: np.ndarray):
        self.actions = np.asarray(actions, np.float32)
        self.t = 0

    def act(self) -> np.ndarray:
        a = self.actions[self.t] if self.t < len(self.actions) else np.zeros(self.actions.shape[1], np.float32)
        self.t += 1
        return a


def _to_goal(env, role: str) -> float:
    x, y = env.data.qpos[env._obj_qadr[role][:2]]
    return float(np.hypot(x - scene.GOAL_XY[0], y - scene.GOAL_XY[1]))


class GaveUpPolicy:
    """The expert, until the target has covered half its way to the goal; then hands off the controls."""

    def __init__(self, env, seed: int = 0, expert: str = "hysteresis"):
        self.env, self.expert = env, make_expert(env, expert=expert)
        self.start: float | None = None
        self.stopped = False

    def act(self) -> np.ndarray:
        d = _to_goal(self.env, "target")
        if self.start is None:
            self.start = d
        self.stopped = self.stopped or d <= 0.5 * self.start
        return np.zeros(self.env.action_space.shape[0], np.float32) if self.stopped else self.expert.act()


class BothObjectsPolicy:
    """Pushes the distractor towards the goal first, then the target (both objects end up moved)."""

    def __init__(self, env, seed: int = 0, switch_step: int = 50, expert: str = "hysteresis"):
        self.env, self.switch_step = env, switch_step
        self.first, self.second = make_expert(env, "distractor", expert), make_expert(env, "target", expert)
        self.t, self.switched = 0, False

    def act(self) -> np.ndarray:
        if not self.switched and (_to_goal(self.env, "distractor") < 1.5 * scene.GOAL_RADIUS
                                  or self.t >= self.switch_step):
            self.switched = True
        self.t += 1
        return (self.second if self.switched else self.first).act()


def scene_options(kind: str) -> dict[str, bool]:
    """PushEnv keyword arguments for a kind: which scene it is recorded in (an occluder only ever with objects)."""
    return {"with_objects": kind != "no-objects", "occluder": kind == "occluded"}


def make_policy(kind: str, env, seed: int, actions: np.ndarray | None = None, expert: str = "hysteresis") -> Any:
    """The policy that records ``kind`` in ``env`` (freshly reset); ``actions`` are replayed by ``no-objects``;
    ``expert`` names the scripted expert (``EXPERTS``) of the kinds that push."""
    if kind in ("expert", "occluded"):
        return make_expert(env, expert=expert)
    if kind == "wrong-object":
        return make_expert(env, "distractor", expert)
    if kind in ("idle", "no-action"):
        return IdlePolicy(env, seed)
    if kind == "random":
        return RandomPolicy(env, seed)
    if kind == "gave-up":
        return GaveUpPolicy(env, seed, expert=expert)
    if kind == "both-objects":
        return BothObjectsPolicy(env, seed, expert=expert)
    if kind == "no-objects":
        if actions is None:
            raise ValueError("no-objects replays a demo's actions; none given")
        return ReplayPolicy(actions)
    raise ValueError(f"unknown episode kind {kind!r}")


class EnvCache:
    """One PushEnv per process, rebuilt only when the objects or the scene change (the GL context is kept)."""

    def __init__(self, image_size: int):
        self.image_size = image_size
        self.env = None

    def get(self, target, distractor, kind: str = "expert"):
        opts = scene_options(kind)
        env = self.env
        if env is None:
            self.env = PushEnv((target, distractor), image_size=self.image_size, **opts)
        elif (env.target, env.distractor, env.with_objects, env.occluder) != (
                target, distractor, opts["with_objects"], opts["occluder"]):
            env.with_objects, env.occluder = opts["with_objects"], opts["occluder"]
            env.set_task((target, distractor))
        return self.env

    def for_record(self, sim: dict[str, Any], kind: str | None = None):
        """The env an episode's sim record was recorded in (or ``kind``'s scene for it), checking versions."""
        if sim.get("scene_version") != scene.SCENE_VERSION or sim.get("catalog_version") != CATALOG_VERSION:
            raise DatasetError(f"sim record from scene v{sim.get('scene_version')}/catalog v{sim.get('catalog_version')};"
                               f" this democheck simulates scene v{scene.SCENE_VERSION}/catalog v{CATALOG_VERSION}")
        if int(sim["image_size"]) != self.image_size:
            raise DatasetError(f"sim record at {sim['image_size']} px, simulator set up for {self.image_size} px")
        return self.get(OBJECTS[sim["target"]], OBJECTS[sim["distractor"]], kind or sim.get("policy", "expert"))


def record_demo(env, policy: Callable[[], np.ndarray], steps: int, seed: int | None = None,
                layout: Any = None, action_noise: float = 0.0) -> dict[str, Any]:
    """Roll one episode out: observation t, then action t, for ``steps`` steps.

    ``action_noise`` (DART, Laskey et al. 2017): the arm executes the policy's action plus Gaussian noise of
    this standard deviation (normalised torque units, drawn from ``seed``) while the policy's own action is
    recorded, so the demo shows the way back from where the noise pushed it.  A zero action (nobody driving:
    a gave-up demo after it stops) is executed as it is."""

    obs, info = env.reset(seed=seed, options={"layout": layout} if layout is not None else None)
    noise = np.random.default_rng([0 if seed is None else seed, 0xDA27]) if action_noise > 0 else None
    frames = np.empty((steps, env.image_size, env.image_size, 3), np.uint8)
    state = np.empty((steps, obs["state"].shape[0]), np.float32)
    env_state = np.empty((steps, ENV_STATE_DIM), np.float32)
    actions = np.empty((steps, env.action_space.shape[0]), np.float32)
    for t in range(steps):
        frames[t], state[t], env_state[t] = obs["image"], obs["state"], env.object_state()
        actions[t] = policy()
        executed = actions[t]
        if noise is not None:
            jitter = noise.normal(0.0, action_noise, actions.shape[1])  # drawn every step: the same stream
            executed = executed + jitter if executed.any() else executed
        obs, _, _, _, info = env.step(executed)
    return {"frames": frames, "state": state, "env_state": env_state, "actions": actions,
            "success": bool(info["success"]), "layout": env.layout}


def sim_record(suite: str, task, kind: str, seed: int, layout, image_size: int, steps: int,
               attempt: int = 0, expert: str = "hysteresis", action_noise: float = 0.0) -> dict[str, Any]:
    """What an episode's ``sim`` column holds: enough to re-simulate it (``resimulate``).  Records made before
    ``expert`` and ``action_noise`` were kept mean the hysteresis expert without noise."""

    return {"suite": suite, "catalog_version": CATALOG_VERSION, "scene_version": scene.SCENE_VERSION,
            "target": task.target.key, "distractor": task.distractor.key, "seed": int(seed), "attempt": attempt,
            "image_size": int(image_size), "steps": int(steps), "policy": kind, "layout": layout.to_dict(),
            "expert": expert, "action_noise": float(action_noise)}


def resimulate(envs: EnvCache, sim: dict[str, Any], kind: str | None = None, actions: np.ndarray | None = None,
               seed: int | None = None) -> dict[str, Any]:
    """Record an episode again from its sim record: as it was (``kind=None``) or as another kind, same layout.

    With ``actions``, they are replayed open-loop instead of running a policy (``no-objects`` needs them).
    """
    kind = kind or sim.get("policy", "expert")
    env = envs.for_record(sim, kind)
    seed = int(sim["seed"]) if seed is None else seed
    expert = sim.get("expert", "hysteresis")
    policy = ReplayPolicy(actions) if actions is not None else make_policy(kind, env, seed, expert=expert)
    # Noise only where the expert drives: a probe's still or random arm, or a replay, is what it is.
    noise = action_noise_for(kind, sim.get("action_noise", 0.0)) if actions is None else 0.0
    return record_demo(env, policy.act, int(sim["steps"]), seed=seed, layout=sim["layout"], action_noise=noise)
